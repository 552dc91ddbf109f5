//! Sema's resolution table: every declaration of the user's script (globals, parameters of
//! functions, controllers and material templates, local lets, reduction variables) and every
//! use of a name with the declaration it resolved to. Recorded while checking, so it is the
//! checker's own resolution; editors answer hover, definition and references from it. A script
//! with errors still gets its table: the checker goes on past a mistake.

use super::SymKind;
use crate::front::ast::{Ident, Span, TypeExpr};

/// What a name refers to.
#[derive(Clone, Debug, PartialEq)]
pub enum DefKind {
    /// A top-level declaration.
    Global(SymKind),
    /// A parameter of a `fn`, `controller` or material template (named by the owner).
    Param { owner: String },
    /// A `let` inside `sim` or a material body.
    LocalLet,
    /// The variable of a reduction (`sum(i in …)`).
    ReduceVar,
}

#[derive(Clone, Debug)]
pub struct Def {
    pub name: String,
    pub kind: DefKind,
    /// The declared name.
    pub span: Span,
    /// The whole declaration (for its text).
    pub decl: Span,
    /// Type as written, if any.
    pub ty: Option<TypeExpr>,
}

/// The declarations and references of one script.
#[derive(Debug, Default, Clone)]
pub struct Resolution {
    pub defs: Vec<Def>,
    /// `(use, def index)`, in the order the checker met them.
    pub refs: Vec<(Span, usize)>,
    /// Names used but not declared in the script: built-ins, prelude names, implicit names
    /// (`t`, `x`, `I1bar`, `loss`), or mistakes.
    pub free: Vec<Ident>,
    /// Dimension names in types.
    pub dims: Vec<Ident>,
}

impl Resolution {
    /// The definition at or referenced at `offset`.
    pub fn def_at(&self, offset: usize) -> Option<&Def> {
        let inside = |s: &Span| s.start <= offset && offset <= s.end;
        if let Some((_, d)) = self.refs.iter().find(|(s, _)| inside(s)) {
            return self.defs.get(*d);
        }
        self.defs.iter().find(|d| inside(&d.span))
    }
}
