//! Editor support: what is under the cursor, where it was declared, what may be typed next.
//!
//! The language server (`softc lsp`, in the runtime crate) speaks the protocol; this module
//! answers its questions from the same front end and checker as `softc check`. Everything works
//! on byte offsets into the script; the server converts to editor positions.
//!
//! Hover, go-to-definition and references use the checker's resolution table
//! ([`crate::sema::Resolution`]: every declaration and every use with what it resolved to) when
//! the script parses — the checker goes on past semantic errors, so a script with mistakes is
//! resolved too — and a token scan otherwise (while the user types, most states of the
//! document do not parse). The editor has no resolver of its own. Completion always works from
//! tokens before the cursor, so it is useful in the middle of an unfinished statement.

mod complete;
mod docs;
#[cfg(test)]
mod grammar_sync;
mod hover;
mod lex;
mod navigate;
mod outline;
#[cfg(test)]
mod tests;

pub use crate::sema::{Def, DefKind, Resolution};
pub use complete::{Completion, CompletionKind};
pub use docs::{
    BUILTIN_DOCS, BuiltinDoc, CONSTANT_DOCS, CONTACT_DOC, CONTEXTUAL_KEYWORDS, KEYWORDS,
    OBSTACLE_SHAPE_DOCS, REDUCTIONS, RESERVED_DOCS,
};
pub use hover::{builtin_hover, eval_dim, prelude_signatures};
pub use lex::{Tok, TokKind, is_keyword, tokenize};
pub use outline::Symbol;

use crate::front::ast::*;
use crate::sema::{CheckOptions, CheckedScript, GlobalInfo};

/// The callee name under which [`Analysis::params_of`] knows the arguments of the sim statement
/// `contact BODY with OBSTACLE (…)`: not an identifier, so no function of the script has it.
pub(crate) const CONTACT_ARGS: &str = "contact BODY with OBSTACLE";

/// Whether a `(` right after these words (the nearest last) opens the arguments of
/// `contact BODY with OBSTACLE (…)`.
pub(crate) fn opens_contact_args(words: &[&str]) -> bool {
    let name =
        |w: &str| w.starts_with(|c: char| c.is_ascii_alphabetic() || c == '_') && !is_keyword(w);
    matches!(words, [.., "contact", body, "with", obstacle] if name(body) && name(obstacle))
}

/// A script parsed, resolved and checked, ready to answer editor questions.
pub struct Analysis<'a> {
    pub text: &'a str,
    pub script: Option<Script>,
    /// The checker's resolution table (empty when the script does not parse).
    pub resolved: Resolution,
    /// The checker's view of the script's globals (types, values); empty when not checked.
    pub globals: Vec<GlobalInfo>,
    pub tokens: Vec<Tok>,
}

impl<'a> Analysis<'a> {
    /// Parse and check the text (no files read: paths and the mesh are not checked).
    pub fn new(text: &'a str) -> Self {
        let script = crate::front::parse(text).ok();
        let checked = script
            .as_ref()
            .map(|s| crate::sema::check(s, &CheckOptions::default()).0);
        Analysis::from_parsed(text, script, checked)
    }

    /// Analyze with the results of a check made before (`softc lsp` checks with the mesh).
    pub fn with_check(text: &'a str, checked: Option<CheckedScript>) -> Self {
        let script = crate::front::parse(text).ok();
        Analysis::from_parsed(text, script, checked)
    }

    /// Analyze a script parsed and checked before (`script` must be `front::parse(text).ok()`
    /// and `checked` its check).
    pub fn from_parsed(
        text: &'a str,
        script: Option<Script>,
        checked: Option<CheckedScript>,
    ) -> Self {
        let (resolved, globals) = match (script.is_some(), checked) {
            (true, Some(c)) => (c.resolution, c.globals),
            _ => Default::default(),
        };
        Analysis {
            text,
            script,
            resolved,
            globals,
            tokens: tokenize(text),
        }
    }

    fn global_info(&self, name: &str, span: Span) -> Option<&GlobalInfo> {
        self.globals
            .iter()
            .find(|g| g.name == name && g.span == span)
    }

    fn token_at(&self, offset: usize) -> Option<Tok> {
        self.tokens
            .iter()
            .find(|t| {
                t.span.start <= offset
                    && offset <= t.span.end
                    && matches!(t.kind, TokKind::Ident | TokKind::Unit)
            })
            .or_else(|| {
                self.tokens
                    .iter()
                    .find(|t| t.span.start <= offset && offset < t.span.end)
            })
            .copied()
    }

    /// Declarations found by scanning tokens (`KEYWORD NAME`), for unparsable documents.
    fn lexical_decls(&self) -> Vec<(String, &'static str, Span)> {
        let mut out = Vec::new();
        let words: Vec<(&str, Tok)> = self
            .tokens
            .iter()
            .filter(|t| t.kind != TokKind::Comment)
            .map(|t| (&self.text[t.span.start..t.span.end], *t))
            .collect();
        for w in words.windows(2) {
            let kind = match w[0].0 {
                "mesh" => "mesh",
                "material" => "material",
                "region" => "region",
                "chamber" => "chamber",
                "nodes" => "nodes",
                "elements" => "elements",
                "obstacle" => "obstacle",
                "param" => "param",
                "input" => "input",
                "let" => "let",
                "fn" => "fn",
                "controller" => "controller",
                _ => continue,
            };
            if w[1].1.kind == TokKind::Ident && !is_keyword(w[1].0) {
                out.push((w[1].0.to_string(), kind, w[1].1.span));
            }
        }
        out
    }
}
