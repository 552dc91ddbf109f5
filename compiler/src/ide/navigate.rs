//! Go to definition and find references.

use super::{Analysis, TokKind};
use crate::front::ast::Span;

impl Analysis<'_> {
    /// Where the name at `offset` is declared (in this script).
    pub fn definition(&self, offset: usize) -> Option<Span> {
        if self.script.is_some() {
            return self.resolved.def_at(offset).map(|d| d.span);
        }
        let tok = self.token_at(offset)?;
        if tok.kind != TokKind::Ident {
            return None;
        }
        let word = &self.text[tok.span.start..tok.span.end];
        self.lexical_decls()
            .into_iter()
            .find(|(n, _, _)| n == word)
            .map(|(_, _, s)| s)
    }

    /// All references to the declaration at `offset` (including the declaration).
    pub fn references(&self, offset: usize) -> Vec<Span> {
        let Some(def) = self.resolved.def_at(offset) else {
            return Vec::new();
        };
        let idx = self
            .resolved
            .defs
            .iter()
            .position(|d| std::ptr::eq(d, def))
            .unwrap_or(usize::MAX);
        let mut out = vec![def.span];
        out.extend(
            self.resolved
                .refs
                .iter()
                .filter(|(_, d)| *d == idx)
                .map(|(s, _)| *s),
        );
        out
    }
}
