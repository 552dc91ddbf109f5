//! A variant of a script, as a compile option (a rewrite of its text, so a front-end matter): another mesh file and other `sim` settings
//! (`bench --tradeoff` runs one script at several resolutions, precisions, models and
//! time-step safeties). The compiler applies it to the text at the spans it parsed, so the
//! variant is checked and compiled like any script, and its text can be saved to reproduce it.

use super::ast::{DeclKind, ExprKind, ItemKind, StmtKind};
use std::path::PathBuf;

/// What a variant changes.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Variant {
    /// The mesh file to load instead of the script's (same unit). A relative path is taken
    /// relative to the working folder.
    pub mesh: Option<PathBuf>,
    /// `sim` settings as source text, `("dt", "auto(safety: 0.5)")`: replaced where the
    /// script sets them, added at the top of the sim block where it does not.
    pub sim_settings: Vec<(String, String)>,
    /// The element order to load the mesh with (`load(…, order: N)`), replacing the script's.
    pub order: Option<u32>,
}

impl Variant {
    pub fn is_empty(&self) -> bool {
        self.mesh.is_none() && self.sim_settings.is_empty() && self.order.is_none()
    }

    /// The script's text with the variant applied.
    pub fn apply(&self, source: &str) -> Result<String, String> {
        let ast = super::parse(source).map_err(|d| d.message)?;
        // Edits as (start, end, replacement), applied back to front.
        let mut edits: Vec<(usize, usize, String)> = Vec::new();
        if let Some(order) = self.order {
            let (call, args) = mesh_call(&ast)?;
            match args
                .iter()
                .find(|a| a.name.as_ref().is_some_and(|n| n.name == "order"))
            {
                Some(a) => edits.push((a.value.span.start, a.value.span.end, order.to_string())),
                None => {
                    // Before the call's closing parenthesis.
                    let close = source[..call.end]
                        .rfind(')')
                        .ok_or("the mesh's `load(…)` has no `)`")?;
                    edits.push((close, close, format!(", order: {order}")));
                }
            }
        }
        if let Some(mesh) = &self.mesh {
            let absolute = std::path::absolute(mesh).unwrap_or_else(|_| mesh.clone());
            let span = mesh_call(&ast)?
                .1
                .first()
                .filter(|a| matches!(a.value.kind, ExprKind::Str(_)))
                .map(|a| a.value.span)
                .ok_or("the script's mesh is not `load(\"FILE\")`")?;
            edits.push((
                span.start,
                span.end,
                format!("{:?}", absolute.display().to_string()),
            ));
        }
        if !self.sim_settings.is_empty() {
            let (sim_span, stmts) = ast
                .items
                .iter()
                .find_map(|i| match &i.kind {
                    ItemKind::Sim(stmts) => Some((i.span, stmts)),
                    _ => None,
                })
                .ok_or("the script has no sim block")?;
            for (name, value) in &self.sim_settings {
                let existing = stmts.iter().find_map(|s| match &s.kind {
                    StmtKind::Assign { name: n, .. } if n.name == *name => Some(s.span),
                    _ => None,
                });
                let line = format!("{name} = {value}");
                match existing {
                    Some(span) => edits.push((span.start, span.end, line)),
                    None => {
                        let open = source[sim_span.start..]
                            .find('{')
                            .map(|i| sim_span.start + i + 1)
                            .ok_or("the sim block has no `{`")?;
                        edits.push((open, open, format!("\n  {line}")));
                    }
                }
            }
        }
        edits.sort_by_key(|e| std::cmp::Reverse(e.0));
        let mut text = source.to_string();
        for (start, end, with) in edits {
            text.replace_range(start..end, &with);
        }
        Ok(text)
    }
}

/// The script's mesh declaration's call: its span and arguments.
fn mesh_call(ast: &super::ast::Script) -> Result<(super::ast::Span, &[super::ast::Arg]), String> {
    ast.items
        .iter()
        .find_map(|item| match &item.kind {
            ItemKind::Decl {
                kind: DeclKind::Mesh,
                value,
                ..
            } => match &value.kind {
                ExprKind::Call { args, .. } => Some((value.span, args.as_slice())),
                _ => None,
            },
            _ => None,
        })
        .ok_or_else(|| "the script's mesh is not `load(\"FILE\")`".to_string())
}

#[cfg(test)]
mod tests {
    use super::*;

    const SCRIPT: &str = "mesh body = load(\"m.msh\")\nsim { dt = 1 us; steps = 1 }\n";

    #[test]
    fn a_variant_sets_the_element_order_and_replaces_a_given_one() {
        let v = Variant {
            order: Some(2),
            sim_settings: vec![("precision".into(), "f64".into())],
            ..Variant::default()
        };
        let text = v.apply(SCRIPT).unwrap();
        assert!(text.contains("load(\"m.msh\", order: 2)"), "{text}");
        assert!(text.contains("precision = f64"), "{text}");
        let v1 = Variant {
            order: Some(1),
            ..Variant::default()
        };
        let again = v1.apply(&text).unwrap();
        assert!(again.contains("load(\"m.msh\", order: 1)"), "{again}");
        assert!(!again.contains("order: 2"), "{again}");
        assert!(!v1.is_empty() && Variant::default().is_empty());
    }
}
