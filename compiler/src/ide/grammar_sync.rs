//! The editor files in lang-spec/editors must know every name the compiler knows.

use super::*;
use crate::sema::{self, units};
use std::collections::HashSet;

fn read(rel: &str) -> String {
    let path = format!("{}/../{rel}", env!("CARGO_MANIFEST_DIR"));
    std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{path}: {e}"))
}

/// Words of every `(a|b|c)` alternation and `(word)` group in the grammar's regexes.
fn grammar_words() -> HashSet<String> {
    let g: serde_json::Value = serde_json::from_str(&read(
        "lang-spec/editors/vscode/syntaxes/soft.tmLanguage.json",
    ))
    .expect("the grammar is JSON");
    let mut regexes = Vec::new();
    let mut stack = vec![&g];
    while let Some(v) = stack.pop() {
        match v {
            serde_json::Value::Object(m) => {
                for (k, v) in m {
                    if (k == "match" || k == "begin") && v.is_string() {
                        regexes.push(v.as_str().unwrap().to_string());
                    }
                    stack.push(v);
                }
            }
            serde_json::Value::Array(a) => stack.extend(a),
            _ => {}
        }
    }
    let mut words = HashSet::new();
    for r in regexes {
        for part in r.split('(').skip(1) {
            let Some(inner) = part.split(')').next() else {
                continue;
            };
            if !inner.is_empty()
                && inner
                    .chars()
                    .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '|')
            {
                words.extend(inner.split('|').map(str::to_string));
            }
        }
    }
    words
}

#[test]
fn keywords_match_the_pest_grammar() {
    let pest = read("compiler/src/front/soft.pest");
    let start = pest.find("keyword = @{").unwrap();
    let block = &pest[start..start + pest[start..].find("~ !ident_char").unwrap()];
    let mut from_pest: Vec<&str> = block.split('"').skip(1).step_by(2).collect();
    let mut ours: Vec<&str> = KEYWORDS.iter().map(|(k, _)| *k).collect();
    from_pest.sort();
    ours.sort();
    assert_eq!(ours, from_pest);
}

/// Every keyword rule of the grammar (`kw_obstacle = @{ "obstacle" … }`) is a reserved keyword
/// or a documented contextual one.
#[test]
fn every_keyword_rule_is_documented() {
    let pest = read("compiler/src/front/soft.pest");
    let mut rules: Vec<&str> = pest
        .lines()
        .filter(|l| l.starts_with("kw_"))
        .filter_map(|l| l.split('"').nth(1))
        .collect();
    let mut ours: Vec<&str> = KEYWORDS
        .iter()
        .chain(CONTEXTUAL_KEYWORDS)
        .map(|(k, _)| *k)
        .collect();
    rules.sort();
    ours.sort();
    assert_eq!(ours, rules);
}

#[test]
fn the_textmate_grammar_knows_every_built_in_name() {
    let words = grammar_words();
    let mut names: Vec<String> = Vec::new();
    names.extend(sema::FUNCTIONS.iter().map(|s| s.to_string()));
    names.extend(sema::CONSTANTS.iter().map(|(s, _)| s.to_string()));
    names.extend(sema::RESERVED_NAMES.iter().map(|s| s.to_string()));
    names.extend(units::NAMED_DIMS.iter().map(|(s, _)| s.to_string()));
    names.extend(KEYWORDS.iter().map(|(s, _)| s.to_string()));
    names.extend(CONTEXTUAL_KEYWORDS.iter().map(|(s, _)| s.to_string()));
    names.extend(OBSTACLE_SHAPE_DOCS.iter().map(|b| b.name.to_string()));
    names.extend(prelude_signatures().into_iter().map(|(n, _)| n));
    names.extend(REDUCTIONS.iter().map(|s| s.to_string()));
    let missing: Vec<&String> = names.iter().filter(|n| !words.contains(*n)).collect();
    assert!(
        missing.is_empty(),
        "lang-spec/editors/vscode/syntaxes/soft.tmLanguage.json lacks {missing:?}"
    );
}
