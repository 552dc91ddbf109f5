//! Checks against the mesh itself: the chamber surfaces, tags and named sets a script refers to
//! must exist in the mesh file, and every node set, element set and fixed region must select
//! something. The compiler does not read meshes; the caller (the runtime) provides a
//! [`MeshProbe`] that does.

use super::Checker;
use super::types::Value;
use crate::diag::{Diagnostic, did_you_mean};
use crate::front::ast::*;
use std::collections::BTreeMap;
use std::path::Path;

/// What the checker needs to know about a mesh, in SI units.
#[derive(Debug, Clone, Default)]
pub struct MeshSummary {
    pub nodes: Vec<[f64; 3]>,
    /// Centroid of every tet (for element selections).
    pub centroids: Vec<[f64; 3]>,
    /// Surface (triangle) tags with their physical names.
    pub surfaces: Vec<(i32, Option<String>)>,
    /// Region (tet) tags with their physical names.
    pub regions: Vec<(i32, Option<String>)>,
    pub node_sets: Vec<String>,
    pub element_sets: Vec<String>,
}

impl MeshSummary {
    fn names(&self) -> Vec<&str> {
        let mut v: Vec<&str> = self
            .surfaces
            .iter()
            .chain(&self.regions)
            .filter_map(|(_, n)| n.as_deref())
            .chain(self.node_sets.iter().map(String::as_str))
            .chain(self.element_sets.iter().map(String::as_str))
            .collect();
        v.sort();
        v.dedup();
        v
    }

    fn bbox(&self) -> Option<([f64; 3], [f64; 3])> {
        let first = *self.nodes.first()?;
        let mut lo = first;
        let mut hi = first;
        for p in &self.nodes {
            for k in 0..3 {
                lo[k] = lo[k].min(p[k]);
                hi[k] = hi[k].max(p[k]);
            }
        }
        Some((lo, hi))
    }

    fn bbox_text(&self) -> String {
        match self.bbox() {
            Some((lo, hi)) => format!(
                "the mesh spans x ∈ [{}, {}] mm, y ∈ [{}, {}] mm, z ∈ [{}, {}] mm",
                mm(lo[0]),
                mm(hi[0]),
                mm(lo[1]),
                mm(hi[1]),
                mm(lo[2]),
                mm(hi[2])
            ),
            None => "the mesh has no nodes".into(),
        }
    }
}

fn mm(v: f64) -> String {
    let x = v * 1e3;
    let r = (x * 1e6).round() / 1e6;
    format!("{r}")
}

/// Reads a mesh file for the checker. `unit` is the length of one file unit in metres.
pub trait MeshProbe: Send + Sync {
    fn probe(&self, path: &Path, unit: f64) -> Result<MeshSummary, String>;
}

/// A region's geometry, in metres: what the checker tests selections with and what binding a
/// scene to its mesh selects with (one definition of containment).
#[derive(Debug, Clone)]
pub(crate) enum Shape {
    Box([f64; 3], [f64; 3]),
    Sphere([f64; 3], f64),
    Cylinder([f64; 3], [f64; 3], f64),
}

/// The surface a chamber declaration names: by physical name or by tag.
#[derive(Debug, Clone, PartialEq)]
pub(crate) enum SurfaceRef {
    Name(String),
    Tag(i32),
}

/// What a node or element set selects by.
#[derive(Debug, Clone, PartialEq)]
pub(crate) enum Selector {
    /// `select(mesh, condition)`: the condition at each point (lowered by binding).
    Condition,
    /// `inside(mesh, region)`.
    Inside(String),
    /// `tagged(mesh, tag)`: the elements of a region tag (or their nodes).
    Tagged(i32),
    /// `named(mesh, "name")`: a physical name or named set of the mesh.
    Named(String),
}

/// What a script refers to in its mesh, as the checker evaluated it: binding a scene to its
/// mesh reads this, not the syntax.
#[derive(Debug, Clone, Default)]
pub(crate) struct MeshRefs {
    /// Each region declaration's geometry.
    pub regions: BTreeMap<String, Shape>,
    /// Each chamber declaration's surface, by name or tag.
    pub surfaces: BTreeMap<String, SurfaceRef>,
    /// Each node or element set declaration, in source order, with what it selects by.
    pub sets: Vec<DeclaredSet>,
    /// What the sim block fixes, in order: declared regions and node sets (a `let` naming
    /// one resolved to it).
    pub fixed: Vec<FixTarget>,
    /// The sim block's `use MATERIAL [in SET]` lines, in order.
    pub uses: Vec<(String, Option<String>)>,
}

/// A declaration the sim block fixes the nodes of.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct FixTarget {
    /// The region or node set declaration.
    pub name: String,
    /// A region (its nodes inside) rather than a node set.
    pub region: bool,
}

/// A declared node or element set.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct DeclaredSet {
    pub name: String,
    /// Elements (centroids) rather than nodes.
    pub elements: bool,
    pub selector: Selector,
}

impl Shape {
    pub(crate) fn contains(&self, p: [f64; 3]) -> bool {
        // A tolerance of a nanometre keeps nodes exactly on a face inside.
        const EPS: f64 = 1e-9;
        match self {
            Shape::Box(lo, hi) => (0..3).all(|k| p[k] >= lo[k] - EPS && p[k] <= hi[k] + EPS),
            Shape::Sphere(c, r) => dist2(p, *c) <= (r + EPS) * (r + EPS),
            Shape::Cylinder(a, b, r) => {
                let ab = sub(*b, *a);
                let ap = sub(p, *a);
                let len2 = dot(ab, ab);
                if len2 == 0.0 {
                    return false;
                }
                let s = dot(ap, ab) / len2;
                // The distance from the axis: |ap - s·ab|.
                let off = [ap[0] - s * ab[0], ap[1] - s * ab[1], ap[2] - s * ab[2]];
                (-EPS..=1.0 + EPS).contains(&s) && dot(off, off) <= (r + EPS) * (r + EPS)
            }
        }
    }

    pub(super) fn from_call(name: &str, values: &[Option<Value>]) -> Option<Shape> {
        let v3 = |v: &Option<Value>| -> Option<[f64; 3]> {
            match v {
                Some(Value::Array(a)) if a.len() == 3 => {
                    Some([a[0].as_f64()?, a[1].as_f64()?, a[2].as_f64()?])
                }
                _ => None,
            }
        };
        let s = |v: &Option<Value>| v.as_ref().and_then(Value::as_f64);
        Some(match name {
            "box" => Shape::Box(v3(values.first()?)?, v3(values.get(1)?)?),
            "sphere" => Shape::Sphere(v3(values.first()?)?, s(values.get(1)?)?),
            "cylinder" => Shape::Cylinder(
                v3(values.first()?)?,
                v3(values.get(1)?)?,
                s(values.get(2)?)?,
            ),
            _ => return None,
        })
    }
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
fn dist2(a: [f64; 3], b: [f64; 3]) -> f64 {
    let d = sub(a, b);
    dot(d, d)
}

impl Checker {
    /// Read the mesh through the probe, if there is one.
    pub(super) fn probe_mesh(&mut self, path: &str, unit: f64, span: Span) {
        let (Some(probe), Some(base)) = (self.options.mesh_probe.clone(), &self.options.base_dir)
        else {
            return;
        };
        match probe.probe(&base.join(path), unit) {
            Ok(summary) => self.mesh = Some(summary),
            Err(msg) => {
                let d =
                    Diagnostic::error("E0319", span, format!("the mesh `{path}` cannot be used"))
                        .with_hint(msg);
                self.err(d);
            }
        }
    }

    /// `surface(mesh, "name")` / `surface(mesh, tag: n)`: the surface must exist.
    pub(super) fn check_surface_exists(&mut self, arg: &Expr, value: &Value) {
        let Some(mesh) = &self.mesh else { return };
        let list = |m: &super::mesh_probe::MeshSummary| {
            m.surfaces
                .iter()
                .map(|(t, n)| match n {
                    Some(n) => format!("\"{n}\" (tag {t})"),
                    None => format!("tag {t}"),
                })
                .collect::<Vec<_>>()
                .join(", ")
        };
        let d = match value {
            Value::Str(name) => {
                if mesh
                    .surfaces
                    .iter()
                    .any(|(_, n)| n.as_deref() == Some(name))
                {
                    return;
                }
                let names: Vec<&str> = mesh
                    .surfaces
                    .iter()
                    .filter_map(|(_, n)| n.as_deref())
                    .collect();
                let mut d = Diagnostic::error(
                    "E0323",
                    arg.span,
                    format!("the mesh has no surface named \"{name}\""),
                );
                d = match did_you_mean(name, names) {
                    Some(s) => d.with_hint(format!("did you mean \"{s}\"? The surfaces are {}", list(mesh))),
                    None if mesh.surfaces.is_empty() => d.with_hint("the mesh has no tagged surfaces: tag the chamber walls as a physical surface"),
                    None => d.with_hint(format!("the surfaces are {}", list(mesh))),
                };
                d
            }
            Value::Num(t) => {
                if mesh.surfaces.iter().any(|(tag, _)| f64::from(*tag) == *t) {
                    return;
                }
                Diagnostic::error(
                    "E0323",
                    arg.span,
                    format!("the mesh has no surface with tag {t}"),
                )
                .with_hint(if mesh.surfaces.is_empty() {
                    "the mesh has no tagged surfaces: tag the chamber walls as a physical surface"
                        .to_string()
                } else {
                    format!("the surfaces are {}", list(mesh))
                })
            }
            _ => return,
        };
        self.err(d);
    }

    /// `named(mesh, "name")`: some physical name or set of the mesh.
    pub(super) fn check_name_exists(&mut self, arg: &Expr, name: &str) {
        let Some(mesh) = &self.mesh else { return };
        let names = mesh.names();
        if names.contains(&name) {
            return;
        }
        let mut d = Diagnostic::error(
            "E0323",
            arg.span,
            format!("the mesh has no part named \"{name}\""),
        );
        d = match did_you_mean(name, names.iter().copied()) {
            Some(s) => d.with_hint(format!("did you mean \"{s}\"?")),
            None if names.is_empty() => d.with_hint("the mesh has no named parts"),
            None => d.with_hint(format!(
                "the named parts are {}",
                names
                    .iter()
                    .map(|n| format!("\"{n}\""))
                    .collect::<Vec<_>>()
                    .join(", ")
            )),
        };
        self.err(d);
    }

    /// `tagged(mesh, n)`: a region tag of the mesh.
    pub(super) fn check_region_tag_exists(&mut self, arg: &Expr, tag: f64) {
        let Some(mesh) = &self.mesh else { return };
        if mesh.regions.iter().any(|(t, _)| f64::from(*t) == tag) {
            return;
        }
        let tags = mesh.regions.iter().map(|(t, n)| match n {
            Some(n) => format!("{t} (\"{n}\")"),
            None => t.to_string(),
        });
        let d = Diagnostic::error(
            "E0323",
            arg.span,
            format!("the mesh has no region with tag {tag}"),
        )
        .with_hint(format!(
            "the region tags are {}",
            tags.collect::<Vec<_>>().join(", ")
        ));
        self.err(d);
    }

    /// A node or element set declared with `select(mesh, condition)` or `inside(mesh, region)`
    /// must select at least one node (element centroid).
    pub(super) fn check_selection_nonempty(&mut self, name: &Ident, kind: DeclKind, value: &Expr) {
        let Some(mesh) = self.mesh.clone() else {
            return;
        };
        let ExprKind::Call { callee, args } = &value.kind else {
            return;
        };
        let ExprKind::Name(f) = &callee.kind else {
            return;
        };
        let points = if kind == DeclKind::Nodes {
            &mesh.nodes
        } else {
            &mesh.centroids
        };
        let what = if kind == DeclKind::Nodes {
            "node"
        } else {
            "element"
        };
        let Some(arg) = args.get(1).map(|a| &a.value) else {
            return;
        };
        let count = match f.name.as_str() {
            "select" => {
                let mut n = 0;
                for p in points {
                    match self.eval_at(arg, *p) {
                        Some(Value::Bool(true)) => n += 1,
                        Some(Value::Bool(false)) => {}
                        _ => return, // not evaluable here: leave it to the runtime
                    }
                }
                n
            }
            "inside" => {
                let ExprKind::Name(r) = &arg.kind else { return };
                let Some(shape) = self.out.mesh_refs.regions.get(&r.name).cloned() else {
                    return;
                };
                points.iter().filter(|p| shape.contains(**p)).count()
            }
            _ => return,
        };
        if count == 0 {
            let d = Diagnostic::error(
                "E0324",
                value.span,
                format!("`{}` selects no {what} of the mesh", name.name),
            )
            .with_hint(mesh.bbox_text());
            self.err(d);
        }
    }

    /// A fixed region must contain at least one node.
    pub(super) fn check_region_nonempty(&mut self, id: &Ident) {
        let Some(mesh) = &self.mesh else { return };
        let Some(shape) = self.out.mesh_refs.regions.get(&id.name) else {
            return;
        };
        if mesh.nodes.iter().any(|p| shape.contains(*p)) {
            return;
        }
        let d = Diagnostic::error(
            "E0324",
            id.span,
            format!("the region `{}` contains no node of the mesh", id.name),
        )
        .with_hint(format!("{}; move or enlarge the region", mesh.bbox_text()));
        self.err(d);
    }

    /// Evaluate a selection condition at one point (`x`, `y`, `z` in metres). Only constant
    /// arithmetic, comparisons, logic and a few functions; `None` when something else appears.
    fn eval_at(&mut self, e: &Expr, p: [f64; 3]) -> Option<Value> {
        Some(match &e.kind {
            ExprKind::Number { value, unit, .. } => {
                let factor = match unit {
                    Some(u) => {
                        let mut f = 1.0;
                        for fac in &u.factors {
                            f *= super::units::unit(&fac.name)?.0.powi(fac.power);
                        }
                        f
                    }
                    None => 1.0,
                };
                Value::Num(value * factor)
            }
            ExprKind::Bool(b) => Value::Bool(*b),
            ExprKind::Paren(inner) => self.eval_at(inner, p)?,
            ExprKind::Name(id) => match id.name.as_str() {
                "x" => Value::Num(p[0]),
                "y" => Value::Num(p[1]),
                "z" => Value::Num(p[2]),
                _ => {
                    let g = *self.globals.get(&id.name)?;
                    match &self.syms[g].state {
                        super::GState::Done(t) => t.value.clone()?,
                        _ => return None,
                    }
                }
            },
            ExprKind::Unary { op, operand } => match (op, self.eval_at(operand, p)?) {
                (UnaryOp::Neg, Value::Num(v)) => Value::Num(-v),
                (UnaryOp::Not, Value::Bool(b)) => Value::Bool(!b),
                _ => return None,
            },
            ExprKind::Binary { op, lhs, rhs } => {
                let a = self.eval_at(lhs, p)?;
                let b = self.eval_at(rhs, p)?;
                match (a, b) {
                    (Value::Num(a), Value::Num(b)) => match op {
                        BinOp::Add => Value::Num(a + b),
                        BinOp::Sub => Value::Num(a - b),
                        BinOp::Mul => Value::Num(a * b),
                        BinOp::Div => Value::Num(a / b),
                        BinOp::Pow => Value::Num(a.powf(b)),
                        BinOp::Lt => Value::Bool(a < b),
                        BinOp::Le => Value::Bool(a <= b),
                        BinOp::Gt => Value::Bool(a > b),
                        BinOp::Ge => Value::Bool(a >= b),
                        BinOp::Eq => Value::Bool(a == b),
                        BinOp::Ne => Value::Bool(a != b),
                        _ => return None,
                    },
                    (Value::Bool(a), Value::Bool(b)) => match op {
                        BinOp::And => Value::Bool(a && b),
                        BinOp::Or => Value::Bool(a || b),
                        _ => return None,
                    },
                    _ => return None,
                }
            }
            ExprKind::Call { callee, args } => {
                let ExprKind::Name(f) = &callee.kind else {
                    return None;
                };
                if self.globals.contains_key(&f.name) {
                    return None;
                }
                let vals: Vec<f64> = args
                    .iter()
                    .map(|a| self.eval_at(&a.value, p).and_then(|v| v.as_f64()))
                    .collect::<Option<_>>()?;
                Value::Num(match (f.name.as_str(), vals.as_slice()) {
                    ("abs", [v]) => v.abs(),
                    ("sqrt", [v]) => v.sqrt(),
                    ("min", [a, b]) => a.min(*b),
                    ("max", [a, b]) => a.max(*b),
                    ("sin", [v]) => v.sin(),
                    ("cos", [v]) => v.cos(),
                    _ => return None,
                })
            }
            ExprKind::If {
                cond,
                then,
                otherwise,
            } => match self.eval_at(cond, p)? {
                Value::Bool(true) => self.eval_at(then, p)?,
                Value::Bool(false) => self.eval_at(otherwise, p)?,
                _ => return None,
            },
            _ => return None,
        })
    }
}
