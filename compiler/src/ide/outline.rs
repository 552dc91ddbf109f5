//! The document outline: declarations and the lets inside blocks.

use super::Analysis;
use crate::front::ast::*;

impl Analysis<'_> {
    /// Document outline: `(name, kind word, whole span, name span, children)`.
    pub fn symbols(&self) -> Vec<Symbol> {
        let Some(script) = &self.script else {
            return self
                .lexical_decls()
                .into_iter()
                .map(|(name, kind, span)| Symbol {
                    name,
                    kind,
                    span,
                    name_span: span,
                    children: Vec::new(),
                })
                .collect();
        };
        let mut out = Vec::new();
        for item in &script.items {
            let leaf = |name: &Ident, kind: &'static str| Symbol {
                name: name.name.clone(),
                kind,
                span: item.span,
                name_span: name.span,
                children: Vec::new(),
            };
            let lets = |stmts: &[Stmt]| -> Vec<Symbol> {
                stmts
                    .iter()
                    .filter_map(|s| match &s.kind {
                        StmtKind::Let(l) => Some(Symbol {
                            name: l.name.name.clone(),
                            kind: "let",
                            span: s.span,
                            name_span: l.name.span,
                            children: Vec::new(),
                        }),
                        _ => None,
                    })
                    .collect()
            };
            let block = |name: &str, kind: &'static str, children: Vec<Symbol>| Symbol {
                name: name.to_string(),
                kind,
                span: item.span,
                name_span: Span::new(item.span.start, item.span.start + kind.len()),
                children,
            };
            out.push(match &item.kind {
                ItemKind::Decl { kind, name, .. } => leaf(name, kind.keyword()),
                ItemKind::Material(m) => {
                    let mut s = leaf(&m.name, "material");
                    if let MaterialBody::Block(b) = &m.body {
                        s.children = lets(b);
                    }
                    s
                }
                ItemKind::Param(p) => leaf(&p.name, "param"),
                ItemKind::Input(i) => leaf(&i.name, "input"),
                ItemKind::Let(l) => leaf(&l.name, "let"),
                ItemKind::Fn(f) => leaf(&f.name, if f.is_controller { "controller" } else { "fn" }),
                ItemKind::Sim(stmts) => block("sim", "sim", lets(stmts)),
                ItemKind::Loss(_) => block("loss", "loss", Vec::new()),
                ItemKind::Optimize(o) => {
                    let names: Vec<&str> = o.targets.iter().map(|t| t.name.as_str()).collect();
                    block(
                        &format!("optimize {}", names.join(", ")),
                        "optimize",
                        Vec::new(),
                    )
                }
            });
        }
        out
    }
}

/// One entry of the document outline.
#[derive(Clone, Debug, PartialEq)]
pub struct Symbol {
    pub name: String,
    /// The declaration keyword (`param`, `chamber`, `sim`, …).
    pub kind: &'static str,
    pub span: Span,
    pub name_span: Span,
    pub children: Vec<Symbol>,
}
