//! Completion: the context at the cursor (from tokens before it) and the candidates that fit.

use super::docs::setting_doc;
use super::hover::{fmt_num, kind_word, prelude_item};
use super::lex::is_ident_char;
use super::{
    Analysis, BUILTIN_DOCS, CONSTANT_DOCS, CONTACT_ARGS, CONTACT_DOC, CONTEXTUAL_KEYWORDS, DefKind,
    KEYWORDS, OBSTACLE_SHAPE_DOCS, REDUCTIONS, RESERVED_DOCS, Tok, TokKind, is_keyword,
    opens_contact_args, prelude_signatures,
};
use crate::front::ast::*;
use crate::sema::units::{self, Dim};
use crate::sema::{self, SymKind};

impl Analysis<'_> {
    /// Completion candidates at `offset`, filtered by the word being typed.
    pub fn completions(&self, offset: usize) -> Vec<Completion> {
        let offset = clamp_to_char(self.text, offset);
        let before = &self.text[..offset];
        let word_start = before
            .char_indices()
            .rev()
            .take_while(|(_, c)| is_ident_char(*c) || *c == 'µ' || *c == 'μ')
            .last()
            .map_or(offset, |(i, _)| i);
        let prefix = &before[word_start..];
        let ctx = context_at(self.text, &self.tokens, word_start);
        let mut out = Vec::new();
        let mut seen = std::collections::HashSet::new();
        let mut push =
            |label: &str, kind: CompletionKind, detail: String, insert: Option<String>| {
                if label.starts_with(prefix) && seen.insert(label.to_string()) {
                    out.push(Completion {
                        label: label.to_string(),
                        kind,
                        detail,
                        insert_text: insert,
                    });
                }
            };
        match ctx {
            Ctx::Unit => {
                for u in units::UNIT_NAMES {
                    if let Some((f, d)) = units::unit(u) {
                        push(
                            u,
                            CompletionKind::Unit,
                            format!("{} · 1 {u} = {} {}", d.name(), fmt_num(f), d.si_unit()),
                            None,
                        );
                    }
                }
                return out;
            }
            Ctx::Type => {
                for (n, _) in units::NAMED_DIMS {
                    let d = units::named_dim(n).unwrap_or(Dim::NONE);
                    push(
                        n,
                        CompletionKind::Type,
                        format!("dimension, SI unit {}", d.si_unit()),
                        None,
                    );
                }
                return out;
            }
            Ctx::Args(callee) => {
                let params = self.params_of(&callee);
                let callee = if callee == CONTACT_ARGS {
                    "contact"
                } else {
                    &callee
                };
                for p in params {
                    push(
                        &p,
                        CompletionKind::Argument,
                        format!("argument of `{callee}`"),
                        Some(format!("{p}: ")),
                    );
                }
            }
            Ctx::ObstacleShape => {
                for b in OBSTACLE_SHAPE_DOCS.iter().chain(
                    BUILTIN_DOCS
                        .iter()
                        .filter(|b| matches!(b.name, "sphere" | "box" | "cylinder")),
                ) {
                    push(
                        b.name,
                        CompletionKind::Function,
                        b.signature.to_string(),
                        None,
                    );
                }
                return out;
            }
            Ctx::TopLevel => {
                for (k, d) in KEYWORDS.iter().chain(CONTEXTUAL_KEYWORDS) {
                    if matches!(
                        *k,
                        "mesh"
                            | "material"
                            | "region"
                            | "chamber"
                            | "nodes"
                            | "elements"
                            | "obstacle"
                            | "param"
                            | "input"
                            | "let"
                            | "fn"
                            | "controller"
                            | "sim"
                            | "optimize"
                            | "loss"
                    ) {
                        push(k, CompletionKind::Keyword, d.to_string(), None);
                    }
                }
                return out;
            }
            Ctx::Sim | Ctx::Optimize | Ctx::Material => {
                let (settings, kws): (&[&str], &[&str]) = match ctx {
                    Ctx::Sim => (
                        sema::SIM_SETTINGS,
                        &["let", "fix", "pressure", "contact", "use", "output"],
                    ),
                    Ctx::Optimize => (sema::OPTIMIZE_SETTINGS, &["stop", "validate"]),
                    _ => (&["density"], &["let"]),
                };
                for s in settings {
                    push(
                        s,
                        CompletionKind::Setting,
                        setting_doc(s).to_string(),
                        Some(format!("{s} = ")),
                    );
                }
                for k in kws {
                    let d = KEYWORDS
                        .iter()
                        .chain(CONTEXTUAL_KEYWORDS)
                        .find(|(n, _)| n == k)
                        .map_or("", |(_, d)| d);
                    push(k, CompletionKind::Keyword, d.to_string(), None);
                }
                if ctx == Ctx::Material {
                    push(
                        "W",
                        CompletionKind::Setting,
                        "strain-energy density W(I1bar, I2bar, J)".into(),
                        None,
                    );
                }
                return out;
            }
            Ctx::Names(kinds) => {
                for (name, kind, detail) in self.names_of_kinds(kinds) {
                    push(&name, kind, detail, None);
                }
                return out;
            }
            Ctx::Expr => {}
        }
        // Expressions: names in scope, built-ins, expression keywords.
        for (name, kind, detail) in self.names_in_scope(offset) {
            push(&name, kind, detail, None);
        }
        for b in BUILTIN_DOCS {
            push(
                b.name,
                CompletionKind::Function,
                b.signature.to_string(),
                None,
            );
        }
        for (c, d) in CONSTANT_DOCS {
            push(c, CompletionKind::Constant, d.to_string(), None);
        }
        for (n, d) in RESERVED_DOCS {
            push(n, CompletionKind::Variable, d.to_string(), None);
        }
        for r in REDUCTIONS {
            push(
                r,
                CompletionKind::Function,
                format!("reduction: {r}(i in DOMAIN) BODY"),
                None,
            );
        }
        for (name, sig) in prelude_signatures() {
            let kind = if sig.starts_with("material") {
                CompletionKind::Material
            } else {
                CompletionKind::Function
            };
            push(&name, kind, sig, None);
        }
        for k in [
            "if",
            "then",
            "else",
            "and",
            "or",
            "not",
            "true",
            "false",
            "in",
            "at",
            "end",
            "over",
            "with",
            "for",
            "iterations",
            "every",
            "steps",
            "when",
            "from",
        ] {
            push(k, CompletionKind::Keyword, String::new(), None);
        }
        out
    }

    /// Parameter names of a callee: a built-in, a prelude template/function, or the script's
    /// (or [`CONTACT_ARGS`]: those of a `contact` statement).
    pub(super) fn params_of(&self, callee: &str) -> Vec<String> {
        if callee == CONTACT_ARGS {
            return CONTACT_DOC.params.iter().map(|p| p.to_string()).collect();
        }
        if let Some(script) = &self.script {
            for item in &script.items {
                match &item.kind {
                    ItemKind::Fn(f) if f.name.name == callee => {
                        return f.params.iter().map(|p| p.name.name.clone()).collect();
                    }
                    ItemKind::Material(m) if m.name.name == callee => {
                        return m
                            .params
                            .iter()
                            .flatten()
                            .map(|p| p.name.name.clone())
                            .collect();
                    }
                    _ => {}
                }
            }
        }
        if let Some(item) = prelude_item(callee) {
            match &item.kind {
                ItemKind::Fn(f) => return f.params.iter().map(|p| p.name.name.clone()).collect(),
                ItemKind::Material(m) => {
                    return m
                        .params
                        .iter()
                        .flatten()
                        .map(|p| p.name.name.clone())
                        .collect();
                }
                _ => {}
            }
        }
        BUILTIN_DOCS
            .iter()
            .chain(OBSTACLE_SHAPE_DOCS)
            .find(|b| b.name == callee)
            .map(|b| b.params.iter().map(|p| p.to_string()).collect())
            .unwrap_or_default()
    }

    /// Global declarations of the given kinds.
    fn names_of_kinds(&self, kinds: &[SymKind]) -> Vec<(String, CompletionKind, String)> {
        if self.script.is_some() {
            return self
                .resolved
                .defs
                .iter()
                .filter_map(|d| match d.kind {
                    DefKind::Global(k) if kinds.contains(&k) => Some((
                        d.name.clone(),
                        CompletionKind::Variable,
                        kind_word(k).to_string(),
                    )),
                    _ => None,
                })
                .collect();
        }
        self.lexical_decls()
            .into_iter()
            .filter(|(_, kw, _)| kinds.iter().any(|k| kind_word(*k) == *kw))
            .map(|(n, kw, _)| (n, CompletionKind::Variable, kw.to_string()))
            .collect()
    }

    /// Declared names visible at `offset`: globals, plus locals of the enclosing item.
    fn names_in_scope(&self, offset: usize) -> Vec<(String, CompletionKind, String)> {
        let mut out = Vec::new();
        if let Some(script) = &self.script {
            let item = script
                .items
                .iter()
                .find(|i| i.span.start <= offset && offset <= i.span.end);
            for d in &self.resolved.defs {
                let visible = match d.kind {
                    DefKind::Global(_) => true,
                    // Locals: declared in the enclosing item (lets before the cursor).
                    _ => item.is_some_and(|i| {
                        d.decl.start >= i.span.start
                            && d.decl.end <= i.span.end
                            && (d.kind != DefKind::LocalLet || d.decl.end <= offset)
                            && (d.kind != DefKind::ReduceVar
                                || (d.decl.start <= offset && offset <= d.decl.end))
                    }),
                };
                if visible {
                    let kind = match d.kind {
                        DefKind::Global(SymKind::Fn | SymKind::Controller) => {
                            CompletionKind::Function
                        }
                        DefKind::Global(SymKind::Material | SymKind::MaterialTemplate) => {
                            CompletionKind::Material
                        }
                        _ => CompletionKind::Variable,
                    };
                    let detail = match &d.kind {
                        DefKind::Global(k) => kind_word(*k).to_string(),
                        DefKind::Param { owner } => format!("parameter of {owner}"),
                        DefKind::LocalLet => "let".into(),
                        DefKind::ReduceVar => "reduction variable".into(),
                    };
                    out.push((d.name.clone(), kind, detail));
                }
            }
        } else {
            for (name, kind, _) in self.lexical_decls() {
                out.push((name, CompletionKind::Variable, kind.to_string()));
            }
        }
        out
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CompletionKind {
    Keyword,
    Variable,
    Function,
    Constant,
    Unit,
    Setting,
    Argument,
    Type,
    Material,
}

#[derive(Clone, Debug, PartialEq)]
pub struct Completion {
    pub label: String,
    pub kind: CompletionKind,
    pub detail: String,
    /// Text to insert instead of the label (`dt = `, `lr: `).
    pub insert_text: Option<String>,
}

#[derive(Clone, Debug, PartialEq, Eq)]
enum Ctx {
    /// Where a declaration starts.
    TopLevel,
    /// At the start of a statement in `sim { }`.
    Sim,
    Optimize,
    Material,
    /// Right after a number or array: a unit.
    Unit,
    /// After `:` in a declaration: a dimension name.
    Type,
    /// Inside the argument list of a call to the named function (or of a `contact` statement:
    /// [`CONTACT_ARGS`]).
    Args(String),
    /// After `obstacle NAME =`: the shapes an obstacle can have.
    ObstacleShape,
    /// A name of one of these kinds: `pressure CHAMBER`, `fix REGION`, `use MATERIAL`,
    /// `contact BODY with OBSTACLE`, …
    Names(&'static [SymKind]),
    Expr,
}

/// Where the cursor is, from the tokens before it.
fn context_at(text: &str, tokens: &[Tok], offset: usize) -> Ctx {
    let before: Vec<&Tok> = tokens
        .iter()
        .filter(|t| t.span.end <= offset && t.kind != TokKind::Comment)
        .collect();
    let word = |t: &Tok| &text[t.span.start..t.span.end];
    // A unit: after a number or an array literal, on the same line (spaces or tabs between), or
    // right after `/`, `*` or `·` in a unit (`8 /`, `kg/`).
    let head = &text[..offset];
    let (head, in_unit) = match head.strip_suffix(['/', '*', '·']) {
        Some(h) => (h, true),
        None => (head, false),
    };
    let head = head.trim_end_matches([' ', '\t']);
    if let Some(last) = before.iter().rev().find(|t| t.span.end <= head.len())
        && last.span.end == head.len()
        && (last.kind == TokKind::Number
            || (in_unit && last.kind == TokKind::Unit)
            || (word(last) == "]" && is_array_close(text, tokens, last)))
    {
        return Ctx::Unit;
    }
    // Enclosing brackets.
    let mut stack: Vec<usize> = Vec::new();
    for (i, t) in before.iter().enumerate() {
        if t.kind != TokKind::Punct {
            continue;
        }
        match word(t) {
            "(" | "[" | "{" => stack.push(i),
            ")" | "]" | "}" => {
                stack.pop();
            }
            _ => {}
        }
    }
    let last = before.last().map(|t| word(t));
    if let Some(kinds) = statement_names(text, &before) {
        return Ctx::Names(kinds);
    }
    // `obstacle NAME = `: a shape.
    if stack.is_empty()
        && let [.., kw, name, eq] = before.as_slice()
        && word(kw) == "obstacle"
        && name.kind == TokKind::Ident
        && word(eq) == "="
        && before.len() - 3 == statement_start(text, &before)
    {
        return Ctx::ObstacleShape;
    }
    if let Some(&open) = stack.last() {
        let o = word(before[open]);
        let prev = |k: usize| open.checked_sub(k).map(|j| word(before[j]));
        if o == "(" {
            // Declaration parameter lists: `fn f(`, `controller c(`, `material m(`.
            let is_decl = matches!(prev(2), Some("fn" | "controller" | "material"));
            if is_decl {
                if last == Some(":") {
                    return Ctx::Type;
                }
                return Ctx::Expr;
            }
            // `contact BODY with OBSTACLE (`: the statement's arguments.
            let words: Vec<&str> = before[open.saturating_sub(4)..open]
                .iter()
                .map(|t| word(t))
                .collect();
            if opens_contact_args(&words) {
                if matches!(last, Some("(" | ",")) {
                    return Ctx::Args(CONTACT_ARGS.to_string());
                }
                return Ctx::Expr;
            }
            if let Some(callee) = prev(1)
                && before[open - 1].kind == TokKind::Ident
            {
                // Argument names after `(` or `,`.
                if matches!(last, Some("(" | ",")) {
                    return Ctx::Args(callee.to_string());
                }
            }
            return Ctx::Expr;
        }
        if o == "{" {
            let at_stmt_start = match before.last() {
                None => true,
                Some(t) => {
                    let w = word(t);
                    w == "{" || w == ";" || text[t.span.end..offset].contains('\n')
                }
            };
            // The keyword that opened the block.
            let head = before[..open]
                .iter()
                .rev()
                .map(|t| word(t))
                .find(|w| matches!(*w, "sim" | "optimize" | "material"));
            if at_stmt_start && !ends_in_operator(last) {
                return match head {
                    Some("sim") => Ctx::Sim,
                    Some("optimize") => Ctx::Optimize,
                    Some("material") => Ctx::Material,
                    _ => Ctx::Expr,
                };
            }
        }
    } else {
        // Top level: a type after `param x:`/`input x:`/`let x:`; a new declaration at the
        // start of a line when the previous line ended a complete thing.
        if last == Some(":") && before.len() >= 3 {
            let kw = word(before[before.len() - 3]);
            if matches!(kw, "param" | "input" | "let") {
                return Ctx::Type;
            }
        }
        let at_line_start = before
            .last()
            .is_none_or(|t| text[t.span.end..offset].contains('\n'));
        if at_line_start && !ends_in_operator(last) {
            return Ctx::TopLevel;
        }
    }
    // Type positions inside sim lets: `let x: `.
    if last == Some(":") && before.len() >= 3 && word(before[before.len() - 3]) == "let" {
        return Ctx::Type;
    }
    if let Some(t) = before.last()
        && word(t) == "->"
    {
        return Ctx::Type;
    }
    Ctx::Expr
}

/// Where the current statement starts in `before`: back to a line start, `{` or `;`.
fn statement_start(text: &str, before: &[&Tok]) -> usize {
    let word = |t: &Tok| &text[t.span.start..t.span.end];
    let mut start = before.len();
    while start > 0 {
        let t = before[start - 1];
        let w = word(t);
        if w == "{" || w == ";" || w == "}" {
            break;
        }
        start -= 1;
        let line_start = text[..t.span.start].rfind('\n').map_or(0, |i| i + 1);
        if text[line_start..t.span.start].trim().is_empty() {
            break;
        }
    }
    start
}

/// In a statement that names declarations (`pressure CHAMBER`, `fix A, B`, `use M in SET`,
/// `contact BODY with OBSTACLE`, `optimize P, Q with`, `validate INPUT`): the kinds of names
/// that fit at the cursor.
fn statement_names(text: &str, before: &[&Tok]) -> Option<&'static [SymKind]> {
    let word = |t: &Tok| &text[t.span.start..t.span.end];
    // The tokens of the current statement.
    let start = statement_start(text, before);
    let stmt: Vec<&str> = before[start..].iter().map(|t| word(t)).collect();
    let list = |rest: &[&str]| {
        // `A, B, ` — names separated by commas, ending with a comma.
        rest.is_empty()
            || (rest.last() == Some(&",")
                && rest
                    .iter()
                    .enumerate()
                    .all(|(i, w)| (i % 2 == 1) == (*w == ",") && (*w == "," || !is_keyword(w))))
    };
    match stmt.as_slice() {
        ["pressure"] => Some(&[SymKind::Chamber]),
        ["fix", rest @ ..] if list(rest) => Some(&[SymKind::Region, SymKind::Nodes]),
        ["use"] => Some(&[SymKind::Material]),
        ["use", _, "in"] => Some(&[SymKind::Elements]),
        ["contact"] => Some(&[SymKind::Mesh, SymKind::Nodes]),
        ["contact", body, "with"] if !is_keyword(body) => Some(&[SymKind::Obstacle]),
        ["optimize", rest @ ..] if list(rest) => Some(&[SymKind::Param]),
        ["validate"] => Some(&[SymKind::Input]),
        _ => None,
    }
}

fn ends_in_operator(last: Option<&str>) -> bool {
    matches!(
        last,
        Some(
            "=" | "+"
                | "-"
                | "*"
                | "/"
                | "^"
                | "@"
                | ","
                | "("
                | "["
                | ":"
                | "=="
                | "!="
                | "<"
                | ">"
                | "<="
                | ">="
                | ".."
                | "->"
                | "and"
                | "or"
                | "not"
                | "if"
                | "then"
                | "else"
                | "in"
                | "with"
                | "for"
                | "every"
                | "when"
                | "from"
                | "fix"
                | "use"
                | "pressure"
                | "contact"
                | "output"
                | "over"
        )
    )
}

/// Is this `]` the end of an array literal (not of an index `a[i]` or a type shape)?
fn is_array_close(text: &str, tokens: &[Tok], close: &Tok) -> bool {
    let idx = tokens
        .iter()
        .position(|t| t.span == close.span)
        .unwrap_or(0);
    let mut depth = 0i32;
    for j in (0..=idx).rev() {
        let t = &tokens[j];
        if t.kind != TokKind::Punct {
            continue;
        }
        match &text[t.span.start..t.span.end] {
            "]" | ")" | "}" => depth += 1,
            "[" | "(" | "{" => {
                depth -= 1;
                if depth == 0 {
                    // An index or shape follows a name or a closing bracket.
                    return j == 0
                        || !matches!(tokens[j - 1].kind, TokKind::Ident | TokKind::Unit)
                            && !matches!(
                                &text[tokens[j - 1].span.start..tokens[j - 1].span.end],
                                ")" | "]"
                            );
                }
            }
            _ => {}
        }
    }
    false
}

fn clamp_to_char(text: &str, offset: usize) -> usize {
    let mut o = offset.min(text.len());
    while !text.is_char_boundary(o) {
        o -= 1;
    }
    o
}
