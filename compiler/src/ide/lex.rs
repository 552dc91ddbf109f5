//! The editor's own lexer: tokens of any text, complete or not, with units after numbers.

use super::KEYWORDS;
use crate::front::ast::Span;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TokKind {
    Ident,
    /// A word in a unit after a number or array (`kPa`, `kg`, `m` in `kg/m^3`).
    Unit,
    Number,
    Str,
    Comment,
    Punct,
}

#[derive(Clone, Copy, Debug)]
pub struct Tok {
    pub kind: TokKind,
    pub span: Span,
}

fn is_ident_start(c: char) -> bool {
    c.is_ascii_alphabetic() || c == '_'
}
pub(super) fn is_ident_char(c: char) -> bool {
    c.is_ascii_alphanumeric() || c == '_'
}
fn is_unit_start(c: char) -> bool {
    c.is_ascii_alphabetic() || c == 'µ' || c == 'μ'
}

pub fn is_keyword(word: &str) -> bool {
    KEYWORDS.iter().any(|(k, _)| *k == word)
}

/// Split a script into tokens. Never fails; unknown characters become punctuation.
pub fn tokenize(text: &str) -> Vec<Tok> {
    let chars: Vec<(usize, char)> = text.char_indices().collect();
    let end_of = |i: usize| chars.get(i).map(|c| c.0).unwrap_or(text.len());
    let mut toks = Vec::new();
    let mut i = 0;
    // After a number or `]`: the next word on the line may be a unit.
    let mut unit_ok = false;
    while i < chars.len() {
        let (start, c) = chars[i];
        let tok = |kind, j: usize| Tok {
            kind,
            span: Span::new(start, end_of(j)),
        };
        if c == '\n' {
            unit_ok = false;
            i += 1;
            continue;
        }
        if c == ' ' || c == '\t' || c == '\r' || c == '\u{feff}' {
            i += 1;
            continue;
        }
        if unit_ok
            && (is_unit_start(c)
                || (c == '/' && chars.get(i + 1).is_some_and(|n| is_unit_start(n.1))))
        {
            // A unit: [/] atom ((*|·|/) atom)*, atom = name [^ [-] digits].
            let mut j = i;
            let mut any = false;
            loop {
                let save = j;
                if j > i || chars[j].1 == '/' {
                    match chars.get(j).map(|c| c.1) {
                        Some('/') | Some('*') | Some('·') if j > i || chars[j].1 == '/' => {
                            toks.push(Tok {
                                kind: TokKind::Punct,
                                span: Span::new(chars[j].0, end_of(j + 1)),
                            });
                            j += 1;
                        }
                        _ => break,
                    }
                }
                let ws = j;
                if !chars.get(j).is_some_and(|c| is_unit_start(c.1)) {
                    if save < ws {
                        toks.pop();
                    }
                    j = save;
                    break;
                }
                while chars
                    .get(j)
                    .is_some_and(|c| is_ident_char(c.1) || c.1 == 'µ' || c.1 == 'μ')
                {
                    j += 1;
                }
                let word = &text[chars[ws].0..end_of(j)];
                if is_keyword(word) {
                    if save < ws {
                        toks.pop();
                    }
                    j = save;
                    break;
                }
                any = true;
                toks.push(Tok {
                    kind: TokKind::Unit,
                    span: Span::new(chars[ws].0, end_of(j)),
                });
                if chars.get(j).is_some_and(|c| c.1 == '^') {
                    let p = j;
                    j += 1;
                    if chars.get(j).is_some_and(|c| c.1 == '-') {
                        j += 1;
                    }
                    let d = j;
                    while chars.get(j).is_some_and(|c| c.1.is_ascii_digit()) {
                        j += 1;
                    }
                    if j == d {
                        j = p;
                    } else {
                        toks.push(Tok {
                            kind: TokKind::Punct,
                            span: Span::new(chars[p].0, chars[p].0 + 1),
                        });
                        toks.push(Tok {
                            kind: TokKind::Number,
                            span: Span::new(chars[p + 1].0, end_of(j)),
                        });
                    }
                }
            }
            unit_ok = false;
            if any {
                i = j;
                continue;
            }
        }
        unit_ok = false;
        if c == '#' {
            let mut j = i;
            while j < chars.len() && chars[j].1 != '\n' {
                j += 1;
            }
            toks.push(tok(TokKind::Comment, j));
            i = j;
        } else if c == '"' {
            let mut j = i + 1;
            while j < chars.len() && chars[j].1 != '"' && chars[j].1 != '\n' {
                if chars[j].1 == '\\' {
                    j += 1;
                }
                j += 1;
            }
            let j = (j + 1).min(chars.len());
            toks.push(tok(TokKind::Str, j));
            i = j;
        } else if c.is_ascii_digit()
            || (c == '.' && chars.get(i + 1).is_some_and(|n| n.1.is_ascii_digit()))
        {
            let mut j = i;
            while chars.get(j).is_some_and(|c| c.1.is_ascii_digit()) {
                j += 1;
            }
            if chars.get(j).is_some_and(|c| c.1 == '.')
                && chars.get(j + 1).is_none_or(|c| c.1 != '.')
            {
                j += 1;
                while chars.get(j).is_some_and(|c| c.1.is_ascii_digit()) {
                    j += 1;
                }
            }
            if chars.get(j).is_some_and(|c| c.1 == 'e' || c.1 == 'E') {
                let mut k = j + 1;
                if chars.get(k).is_some_and(|c| c.1 == '+' || c.1 == '-') {
                    k += 1;
                }
                if chars.get(k).is_some_and(|c| c.1.is_ascii_digit()) {
                    while chars.get(k).is_some_and(|c| c.1.is_ascii_digit()) {
                        k += 1;
                    }
                    j = k;
                }
            }
            toks.push(tok(TokKind::Number, j));
            i = j;
            unit_ok = true;
        } else if is_ident_start(c) {
            let mut j = i;
            while chars.get(j).is_some_and(|c| is_ident_char(c.1)) {
                j += 1;
            }
            toks.push(tok(TokKind::Ident, j));
            i = j;
        } else {
            let two = chars.get(i + 1).map(|n| n.1);
            let len = match (c, two) {
                ('=', Some('=')) | ('!', Some('=')) | ('<', Some('=')) | ('>', Some('=')) => 2,
                ('-', Some('>')) | ('.', Some('.')) => 2,
                _ => 1,
            };
            toks.push(tok(TokKind::Punct, i + len));
            i += len;
            unit_ok = c == ']';
        }
    }
    toks
}
