//! The checked program: what sema hands to lowering and to the driver instead of the syntax
//! tree. Declarations are numbered (a [`DeclId`] is the checker's index of the global, the
//! prelude's first), every name is resolved once — by the checker, while it checked — to a
//! declaration, a local binding or an implicit name, every expression carries the type (with
//! its unit's dimension) the checker gave it, and numbers are SI values. Parentheses, unit
//! spellings and the source text are gone; spans stay for messages.
//!
//! Operators and spans are the syntax's own small vocabulary types, re-exported here so that
//! the stages after sema never name the syntax tree.

pub use crate::front::ast::{BinOp, ReduceOp, Span, UnaryOp};

use super::types::{Len, Ty};
use super::{Checker, GState, SymKind, units};
use crate::front::ast as syn;
use std::collections::HashMap;

/// A global declaration: the checker's index (prelude declarations first).
pub type DeclId = usize;

/// What a name written in an expression refers to.
#[derive(Clone, Debug, PartialEq)]
pub enum Name {
    /// A top-level declaration (the user's or the prelude's).
    Global(DeclId),
    /// A binding of an enclosing scope: a parameter of a function, controller or material
    /// template, a `let` of the sim block or of a material body, an energy's invariant, a
    /// reduction's variable. Lowering binds these by name as it inlines.
    Local(String),
    /// A name the language defines: `t`, `dt`, `t_end`, `pi`, the node state `x`, `x0`, `v`,
    /// coordinates inside `select`, `loss` in a stop condition, and the built-in constants
    /// (`quasi_static`, `auto`, `vtk`, …).
    Implicit(String),
}

impl Name {
    /// The implicit name, if it is one.
    pub fn implicit(&self) -> Option<&str> {
        match self {
            Name::Implicit(n) => Some(n),
            _ => None,
        }
    }
}

/// A typed, resolved expression.
#[derive(Clone, Debug, PartialEq)]
pub struct Expr {
    pub kind: ExprKind,
    pub span: Span,
    /// The checker's type: its dimension (the unit) and shape; `Ty::Error` where the checker
    /// gave none (an expression it skipped after an error).
    pub ty: Ty,
}

#[derive(Clone, Debug, PartialEq)]
pub enum ExprKind {
    /// A number in SI units (the written number times its unit's factor).
    Num(f64),
    /// `[a, b, c] unit`: each item times `scale` (the unit's factor, 1 without one).
    Array {
        items: Vec<Expr>,
        scale: f64,
    },
    Str(String),
    Bool(bool),
    Name(Name),
    Unary {
        op: UnaryOp,
        operand: Box<Expr>,
    },
    Binary {
        op: BinOp,
        lhs: Box<Expr>,
        rhs: Box<Expr>,
    },
    Call {
        callee: Callee,
        args: Vec<Arg>,
    },
    Index {
        base: Box<Expr>,
        indices: Vec<Expr>,
    },
    /// `.x`, `.y`, `.z`: component 0, 1, 2.
    Field {
        base: Box<Expr>,
        axis: usize,
    },
    Reduce {
        op: ReduceOp,
        var: String,
        domain: Box<Expr>,
        body: Box<Expr>,
    },
    If {
        cond: Box<Expr>,
        then: Box<Expr>,
        otherwise: Box<Expr>,
    },
}

/// What a call calls.
#[derive(Clone, Debug, PartialEq)]
pub enum Callee {
    /// A `fn`, `controller` or material template.
    Decl(DeclId),
    /// A built-in function (`sqrt`, `ramp`, `load`, `adam`, …).
    Builtin(String),
}

#[derive(Clone, Debug, PartialEq)]
pub struct Arg {
    pub name: Option<String>,
    pub value: Expr,
}

impl Expr {
    pub fn for_each_child<'a>(&'a self, mut f: impl FnMut(&'a Expr)) {
        match &self.kind {
            ExprKind::Num(_) | ExprKind::Str(_) | ExprKind::Bool(_) | ExprKind::Name(_) => {}
            ExprKind::Array { items, .. } => items.iter().for_each(f),
            ExprKind::Unary { operand, .. } => f(operand),
            ExprKind::Binary { lhs, rhs, .. } => {
                f(lhs);
                f(rhs)
            }
            ExprKind::Call { args, .. } => args.iter().for_each(|a| f(&a.value)),
            ExprKind::Index { base, indices } => {
                f(base);
                indices.iter().for_each(f);
            }
            ExprKind::Field { base, .. } => f(base),
            ExprKind::Reduce { domain, body, .. } => {
                f(domain);
                f(body)
            }
            ExprKind::If {
                cond,
                then,
                otherwise,
            } => {
                f(cond);
                f(then);
                f(otherwise)
            }
        }
    }

    /// The implicit name this expression is (`quasi_static`, `auto`, `vtk`), if it is one.
    pub fn implicit_name(&self) -> Option<&str> {
        match &self.kind {
            ExprKind::Name(n) => n.implicit(),
            _ => None,
        }
    }

    /// A call's built-in function and arguments, or a bare implicit name with none
    /// (`auto` and `auto(safety: 0.5)` alike).
    pub fn builtin_call(&self) -> Option<(&str, &[Arg])> {
        match &self.kind {
            ExprKind::Call {
                callee: Callee::Builtin(f),
                args,
            } => Some((f.as_str(), args.as_slice())),
            ExprKind::Name(Name::Implicit(n)) => Some((n.as_str(), &[])),
            _ => None,
        }
    }
}

/// A call's argument given by `name`, else the one at position `pos`.
pub fn arg<'a>(args: &'a [Arg], name: &str, pos: usize) -> Option<&'a Expr> {
    args.iter()
        .find(|a| a.name.as_deref() == Some(name))
        .or_else(|| args.get(pos).filter(|a| a.name.is_none()))
        .map(|a| &a.value)
}

/// A call's argument given by `name`.
pub fn named_arg<'a>(args: &'a [Arg], name: &str) -> Option<&'a Expr> {
    args.iter()
        .find(|a| a.name.as_deref() == Some(name))
        .map(|a| &a.value)
}

#[derive(Clone, Debug, PartialEq)]
pub struct Decl {
    pub name: String,
    /// The declared name.
    pub span: Span,
    pub prelude: bool,
    pub kind: DeclKind,
}

#[derive(Clone, Debug, PartialEq)]
pub enum DeclKind {
    /// `mesh NAME = load(…)`, `region`, `chamber`, `nodes`, `elements`: the declaring call.
    Mesh(Expr),
    Region(Expr),
    Chamber(Expr),
    Nodes(Expr),
    Elements(Expr),
    /// `obstacle NAME = plane(point: …, normal: …)` or `sphere(center: …, radius: …)`.
    Obstacle(Expr),
    Material(Material),
    Param(Param),
    Input(Input),
    Let(Expr),
    Fn(Function),
}

impl DeclKind {
    /// What the declaration declares, for messages.
    pub fn noun(&self) -> &'static str {
        match self {
            DeclKind::Mesh(_) => "mesh",
            DeclKind::Region(_) => "region",
            DeclKind::Chamber(_) => "chamber",
            DeclKind::Nodes(_) => "node set",
            DeclKind::Elements(_) => "element set",
            DeclKind::Obstacle(_) => "obstacle",
            DeclKind::Material(_) => "material",
            DeclKind::Param(_) => "param",
            DeclKind::Input(_) => "input",
            DeclKind::Let(_) => "let binding",
            DeclKind::Fn(_) => "function",
        }
    }
}

#[derive(Clone, Debug, PartialEq)]
pub struct Material {
    /// A template's parameters (`material yeoh(c10: pressure, …) { … }`).
    pub params: Option<Vec<FnParam>>,
    pub body: MaterialBody,
}

#[derive(Clone, Debug, PartialEq)]
pub enum MaterialBody {
    /// `material silicone = yeoh(…)`
    Instance(Expr),
    /// `material gel { density = …; W(I1bar, J) = … }`
    Block(Vec<Stmt>),
}

#[derive(Clone, Debug, PartialEq)]
pub struct Param {
    /// The declared type (dimension and shape; a per-element param's one axis is its set).
    pub ty: Ty,
    pub init: Expr,
}

impl Param {
    /// The element set of a per-element param (a field).
    pub fn field_set(&self) -> Option<&str> {
        self.ty.shape().iter().find_map(|l| match l {
            Len::PerElement(s) => Some(s.as_str()),
            _ => None,
        })
    }
}

#[derive(Clone, Debug, PartialEq)]
pub struct Input {
    pub ty: Ty,
    pub source: Expr,
}

#[derive(Clone, Debug, PartialEq)]
pub struct Function {
    pub is_controller: bool,
    pub params: Vec<FnParam>,
    pub body: Expr,
}

#[derive(Clone, Debug, PartialEq)]
pub struct FnParam {
    pub name: String,
    pub default: Option<Expr>,
}

#[derive(Clone, Debug, PartialEq)]
pub struct Stmt {
    pub kind: StmtKind,
    pub span: Span,
}

#[derive(Clone, Debug, PartialEq)]
pub enum StmtKind {
    Let {
        name: String,
        value: Expr,
    },
    /// `setting = value`
    Assign {
        name: String,
        value: Expr,
    },
    /// `W(I1bar, I2bar, J) = expr`: the invariants it reads, and its body.
    Energy {
        args: Vec<String>,
        body: Expr,
    },
    /// `fix a, b`: the regions or node sets (directly or through a sim `let`).
    Fix(Vec<String>),
    Pressure {
        chamber: String,
        value: Expr,
    },
    Use {
        material: String,
        set: Option<String>,
    },
    /// `contact BODY with OBSTACLE (gap: …, stiffness: …)`: BODY the mesh or a node set.
    Contact {
        body: String,
        obstacle: String,
        args: Vec<Arg>,
    },
    Output {
        what: Expr,
        every: Expr,
        steps: bool,
    },
    Stop(Expr),
    Validate {
        input: String,
        source: Expr,
    },
}

#[derive(Clone, Debug, PartialEq)]
pub enum LossWhen {
    /// No clause, or `at end`: evaluated at the final step.
    AtEnd,
    /// `over [t0, t1]`: summed over every step whose time lies in the range.
    Over { from: Box<Expr>, to: Box<Expr> },
}

#[derive(Clone, Debug, PartialEq)]
pub struct Loss {
    pub value: Expr,
    pub when: LossWhen,
}

#[derive(Clone, Debug, PartialEq)]
pub struct Optimize {
    pub targets: Vec<String>,
    pub optimizer: Expr,
    pub iterations: Option<Expr>,
    pub body: Vec<Stmt>,
}

/// The checked program: the prelude's and the script's declarations by id, and the script's
/// sim block, loss and optimize block (the first of each; a second is an error).
#[derive(Clone, Debug, Default)]
pub struct Program {
    pub decls: Vec<Decl>,
    by_name: HashMap<String, DeclId>,
    pub sim: Vec<Stmt>,
    pub has_sim: bool,
    pub loss: Option<Loss>,
    pub optimize: Option<Optimize>,
}

impl Program {
    pub fn decl(&self, id: DeclId) -> &Decl {
        &self.decls[id]
    }

    /// The declaration a top-level name refers to.
    pub fn find(&self, name: &str) -> Option<(DeclId, &Decl)> {
        let id = *self.by_name.get(name)?;
        Some((id, &self.decls[id]))
    }

    /// The script's own declarations, in source order.
    pub fn user_decls(&self) -> impl Iterator<Item = &Decl> {
        self.decls.iter().filter(|d| !d.prelude)
    }

    /// The declared node sets (`false`) and element sets (`true`), by name.
    pub fn sets(&self) -> Vec<(&str, bool)> {
        let mut sets: Vec<_> = (self.decls.iter())
            .filter_map(|d| match d.kind {
                DeclKind::Nodes(_) => Some((d.name.as_str(), false)),
                DeclKind::Elements(_) => Some((d.name.as_str(), true)),
                _ => None,
            })
            .collect();
        sets.sort();
        sets
    }

    /// The set a reduction runs over, when it is a declared node or element set.
    pub fn set_reduction(&self, e: &Expr) -> Option<&str> {
        let ExprKind::Reduce { domain, .. } = &e.kind else {
            return None;
        };
        let ExprKind::Name(Name::Global(id)) = domain.kind else {
            return None;
        };
        let d = &self.decls[id];
        matches!(d.kind, DeclKind::Nodes(_) | DeclKind::Elements(_)).then_some(d.name.as_str())
    }

    /// The element set of the per-element param `name`, if it is one.
    pub fn field_set(&self, name: &str) -> Option<&str> {
        match &self.find(name)?.1.kind {
            DeclKind::Param(p) => p.field_set(),
            _ => None,
        }
    }

    /// The value of a `name = value` setting of the sim block.
    pub fn sim_setting(&self, name: &str) -> Option<&Expr> {
        setting(&self.sim, name)
    }

    /// A setting of the `optimize` block (`gradient_scale = 1e-3`).
    pub fn optimize_setting(&self, name: &str) -> Option<&Expr> {
        setting(&self.optimize.as_ref()?.body, name)
    }

    /// The sim block's `let`s by name (visible in its expressions).
    pub fn sim_lets(&self) -> HashMap<String, Expr> {
        (self.sim.iter())
            .filter_map(|s| match &s.kind {
                StmtKind::Let { name, value } => Some((name.clone(), value.clone())),
                _ => None,
            })
            .collect()
    }

    /// The mesh declaration's call.
    pub fn mesh(&self) -> Option<&Expr> {
        self.user_decls().find_map(|d| match &d.kind {
            DeclKind::Mesh(e) => Some(e),
            _ => None,
        })
    }
}

fn setting<'a>(stmts: &'a [Stmt], name: &str) -> Option<&'a Expr> {
    stmts.iter().find_map(|s| match &s.kind {
        StmtKind::Assign { name: n, value } if n == name => Some(value),
        _ => None,
    })
}

/// Where an expression or name was written: in the prelude or the script, and its span.
pub(super) type Key = (bool, usize, usize);

/// What the checker recorded while checking, for building the [`Program`].
#[derive(Default)]
pub(super) struct Tables {
    pub names: HashMap<Key, Name>,
    pub types: HashMap<Key, Ty>,
}

/// A unit's factor to SI, computed as lowering always has (the same product, so the same
/// bits).
pub fn unit_factor(u: &syn::Unit) -> f64 {
    let mut f = 1.0;
    for fac in &u.factors {
        match units::unit(&fac.name) {
            Some((k, _)) => f *= k.powi(fac.power),
            None => return f64::NAN,
        }
    }
    f
}

impl Checker {
    /// The checked program of the prelude and `script`, from the checker's tables.
    pub(super) fn build_program(&self, prelude: &syn::Script, script: &syn::Script) -> Program {
        let mut p = Program::default();
        for g in &self.syms {
            let items = if g.prelude { prelude } else { script };
            let item = &items.items[g.item];
            let b = Builder {
                checker: self,
                prelude: g.prelude,
            };
            let ty = match &g.state {
                GState::Done(t) => t.ty.clone(),
                _ => Ty::Error,
            };
            let kind = match &item.kind {
                syn::ItemKind::Decl { kind, value, .. } => {
                    let v = b.expr(value);
                    match kind {
                        syn::DeclKind::Mesh => DeclKind::Mesh(v),
                        syn::DeclKind::Region => DeclKind::Region(v),
                        syn::DeclKind::Chamber => DeclKind::Chamber(v),
                        syn::DeclKind::Nodes => DeclKind::Nodes(v),
                        syn::DeclKind::Elements => DeclKind::Elements(v),
                        syn::DeclKind::Obstacle => DeclKind::Obstacle(v),
                    }
                }
                syn::ItemKind::Material(m) => DeclKind::Material(Material {
                    params: m.params.as_ref().map(|ps| b.params(ps)),
                    body: match &m.body {
                        syn::MaterialBody::Expr(e) => MaterialBody::Instance(b.expr(e)),
                        syn::MaterialBody::Block(s) => MaterialBody::Block(b.stmts(s)),
                    },
                }),
                syn::ItemKind::Param(d) => DeclKind::Param(Param {
                    ty,
                    init: b.expr(&d.init),
                }),
                syn::ItemKind::Input(d) => DeclKind::Input(Input {
                    ty,
                    source: b.expr(&d.source),
                }),
                syn::ItemKind::Let(l) => DeclKind::Let(b.expr(&l.value)),
                syn::ItemKind::Fn(f) => DeclKind::Fn(Function {
                    is_controller: f.is_controller,
                    params: b.params(&f.params),
                    body: b.expr(&f.body),
                }),
                syn::ItemKind::Sim(_) | syn::ItemKind::Loss(_) | syn::ItemKind::Optimize(_) => {
                    unreachable!("blocks declare no name")
                }
            };
            debug_assert_eq!(
                SymKind::of_item(item).map(|(n, _)| n.name.as_str()),
                Some(g.name.as_str())
            );
            p.decls.push(Decl {
                name: g.name.clone(),
                span: g.span,
                prelude: g.prelude,
                kind,
            });
        }
        p.by_name = self.globals.clone();
        let b = Builder {
            checker: self,
            prelude: false,
        };
        for item in &script.items {
            match &item.kind {
                syn::ItemKind::Sim(s) if !p.has_sim => {
                    p.has_sim = true;
                    p.sim = b.stmts(s);
                }
                syn::ItemKind::Loss(l) if p.loss.is_none() => {
                    p.loss = Some(Loss {
                        value: b.expr(&l.value),
                        when: match &l.when {
                            syn::LossWhen::Default | syn::LossWhen::AtEnd(_) => LossWhen::AtEnd,
                            syn::LossWhen::Over { from, to, .. } => LossWhen::Over {
                                from: Box::new(b.expr(from)),
                                to: Box::new(b.expr(to)),
                            },
                        },
                    });
                }
                syn::ItemKind::Optimize(o) if p.optimize.is_none() => {
                    p.optimize = Some(Optimize {
                        targets: o.targets.iter().map(|t| t.name.clone()).collect(),
                        optimizer: b.expr(&o.optimizer),
                        iterations: o.iterations.as_ref().map(|e| b.expr(e)),
                        body: o.body.as_deref().map(|s| b.stmts(s)).unwrap_or_default(),
                    });
                }
                _ => {}
            }
        }
        p
    }
}

/// Turns the syntax of one source (the prelude or the script) into the checked program's
/// terms, reading the checker's tables.
struct Builder<'c> {
    checker: &'c Checker,
    prelude: bool,
}

impl Builder<'_> {
    fn key(&self, s: Span) -> Key {
        (self.prelude, s.start, s.end)
    }

    /// The checker's resolution of the name written at `id`. Names the checker reads as
    /// keywords without resolving them (a setting's `quasi_static`) are what a top-level name
    /// means: a global, else an implicit name.
    fn name(&self, id: &syn::Ident) -> Name {
        if let Some(n) = self.checker.hir.names.get(&self.key(id.span)) {
            return n.clone();
        }
        match self.checker.globals.get(&id.name) {
            Some(&g) => Name::Global(g),
            None => Name::Implicit(id.name.clone()),
        }
    }

    fn params(&self, ps: &[syn::FnParam]) -> Vec<FnParam> {
        ps.iter()
            .map(|p| FnParam {
                name: p.name.name.clone(),
                default: p.default.as_ref().map(|d| self.expr(d)),
            })
            .collect()
    }

    fn args(&self, args: &[syn::Arg]) -> Vec<Arg> {
        args.iter()
            .map(|a| Arg {
                name: a.name.as_ref().map(|n| n.name.clone()),
                value: self.expr(&a.value),
            })
            .collect()
    }

    fn stmts(&self, stmts: &[syn::Stmt]) -> Vec<Stmt> {
        stmts
            .iter()
            .map(|s| Stmt {
                span: s.span,
                kind: match &s.kind {
                    syn::StmtKind::Let(l) => StmtKind::Let {
                        name: l.name.name.clone(),
                        value: self.expr(&l.value),
                    },
                    syn::StmtKind::Assign { name, value } => StmtKind::Assign {
                        name: name.name.clone(),
                        value: self.expr(value),
                    },
                    syn::StmtKind::Energy { args, body, .. } => StmtKind::Energy {
                        args: args.iter().map(|a| a.name.clone()).collect(),
                        body: self.expr(body),
                    },
                    syn::StmtKind::Fix(names) => {
                        StmtKind::Fix(names.iter().map(|n| n.name.clone()).collect())
                    }
                    syn::StmtKind::Pressure { chamber, value } => StmtKind::Pressure {
                        chamber: chamber.name.clone(),
                        value: self.expr(value),
                    },
                    syn::StmtKind::Use { material, set } => StmtKind::Use {
                        material: material.name.clone(),
                        set: set.as_ref().map(|s| s.name.clone()),
                    },
                    syn::StmtKind::Contact {
                        body,
                        obstacle,
                        args,
                    } => StmtKind::Contact {
                        body: body.name.clone(),
                        obstacle: obstacle.name.clone(),
                        args: self.args(args),
                    },
                    syn::StmtKind::Output { what, every, steps } => StmtKind::Output {
                        what: self.expr(what),
                        every: self.expr(every),
                        steps: *steps,
                    },
                    syn::StmtKind::Stop(e) => StmtKind::Stop(self.expr(e)),
                    syn::StmtKind::Validate { input, source } => StmtKind::Validate {
                        input: input.name.clone(),
                        source: self.expr(source),
                    },
                },
            })
            .collect()
    }

    fn expr(&self, e: &syn::Expr) -> Expr {
        // Parentheses only group: the inner expression stands for them.
        if let syn::ExprKind::Paren(inner) = &e.kind {
            return self.expr(inner);
        }
        let boxed = |x: &syn::Expr| Box::new(self.expr(x));
        let kind = match &e.kind {
            syn::ExprKind::Number { value, unit, .. } => ExprKind::Num(match unit {
                Some(u) => value * unit_factor(u),
                None => *value,
            }),
            syn::ExprKind::Array { items, unit } => ExprKind::Array {
                items: items.iter().map(|i| self.expr(i)).collect(),
                scale: unit.as_ref().map_or(1.0, unit_factor),
            },
            syn::ExprKind::Str(s) => ExprKind::Str(s.clone()),
            syn::ExprKind::Bool(b) => ExprKind::Bool(*b),
            syn::ExprKind::Name(id) => ExprKind::Name(self.name(id)),
            syn::ExprKind::Paren(_) => unreachable!("unwrapped above"),
            syn::ExprKind::Unary { op, operand } => ExprKind::Unary {
                op: *op,
                operand: boxed(operand),
            },
            syn::ExprKind::Binary { op, lhs, rhs } => ExprKind::Binary {
                op: *op,
                lhs: boxed(lhs),
                rhs: boxed(rhs),
            },
            syn::ExprKind::Call { callee, args } => {
                let callee = match &callee.kind {
                    syn::ExprKind::Name(id) => match self.name(id) {
                        Name::Global(g) => Callee::Decl(g),
                        Name::Local(n) | Name::Implicit(n) => Callee::Builtin(n),
                    },
                    // The checker refuses any other callee.
                    _ => Callee::Builtin(String::new()),
                };
                ExprKind::Call {
                    callee,
                    args: self.args(args),
                }
            }
            syn::ExprKind::Index { base, indices } => ExprKind::Index {
                base: boxed(base),
                indices: indices.iter().map(|i| self.expr(i)).collect(),
            },
            syn::ExprKind::Field { base, field } => ExprKind::Field {
                base: boxed(base),
                axis: match field.name.as_str() {
                    "x" => 0,
                    "y" => 1,
                    _ => 2,
                },
            },
            syn::ExprKind::Reduce {
                op,
                var,
                domain,
                body,
            } => ExprKind::Reduce {
                op: *op,
                var: var.name.clone(),
                domain: boxed(domain),
                body: boxed(body),
            },
            syn::ExprKind::If {
                cond,
                then,
                otherwise,
            } => ExprKind::If {
                cond: boxed(cond),
                then: boxed(then),
                otherwise: boxed(otherwise),
            },
        };
        Expr {
            kind,
            span: e.span,
            ty: (self.checker.hir.types.get(&self.key(e.span)))
                .cloned()
                .unwrap_or(Ty::Error),
        }
    }
}

#[cfg(test)]
#[path = "hir_tests.rs"]
mod tests;
