//! The abstract syntax tree of a `.soft` script. Every node carries its source span (byte
//! offsets into the script); literals keep their source text so `softc fmt` reproduces them.

use std::fmt;

/// A half-open byte range `start..end` in the source text.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Default)]
pub struct Span {
    pub start: usize,
    pub end: usize,
}

impl Span {
    pub fn new(start: usize, end: usize) -> Self {
        Span { start, end }
    }
    pub fn to(self, other: Span) -> Span {
        Span::new(self.start.min(other.start), self.end.max(other.end))
    }
}

#[derive(Clone, Debug, PartialEq)]
pub struct Ident {
    pub name: String,
    pub span: Span,
}

#[derive(Clone, Debug, PartialEq)]
pub struct Script {
    pub items: Vec<Item>,
}

impl Script {
    /// The statements of the `sim` block (empty without one).
    pub fn sim_block(&self) -> &[Stmt] {
        self.items
            .iter()
            .find_map(|i| match &i.kind {
                ItemKind::Sim(s) => Some(s.as_slice()),
                _ => None,
            })
            .unwrap_or(&[])
    }

    /// The value of a `name = value` setting of the `sim` block.
    /// A setting of the `optimize` block (`gradient_scale = 1e-3`).
    pub fn optimize_setting(&self, name: &str) -> Option<&Expr> {
        self.items.iter().find_map(|i| match &i.kind {
            ItemKind::Optimize(o) => o.body.iter().flatten().find_map(|s| match &s.kind {
                StmtKind::Assign { name: n, value } if n.name == name => Some(value),
                _ => None,
            }),
            _ => None,
        })
    }

    pub fn sim_setting(&self, name: &str) -> Option<&Expr> {
        self.sim_block().iter().find_map(|s| match &s.kind {
            StmtKind::Assign { name: n, value } if n.name == name => Some(value),
            _ => None,
        })
    }
}

#[derive(Clone, Debug, PartialEq)]
pub struct Item {
    pub kind: ItemKind,
    pub span: Span,
}

/// The declaration keyword of the simple `KIND NAME = EXPR` declarations.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum DeclKind {
    Mesh,
    Region,
    Chamber,
    Nodes,
    Elements,
    /// `obstacle NAME = plane(…)` or `sphere(…)`: a rigid body the mesh may touch.
    Obstacle,
}

impl DeclKind {
    /// What the declaration declares, for messages.
    pub fn noun(self) -> &'static str {
        match self {
            DeclKind::Mesh => "mesh",
            DeclKind::Region => "region",
            DeclKind::Chamber => "chamber",
            DeclKind::Nodes => "node set",
            DeclKind::Elements => "element set",
            DeclKind::Obstacle => "obstacle",
        }
    }

    pub fn keyword(self) -> &'static str {
        match self {
            DeclKind::Mesh => "mesh",
            DeclKind::Region => "region",
            DeclKind::Chamber => "chamber",
            DeclKind::Nodes => "nodes",
            DeclKind::Elements => "elements",
            DeclKind::Obstacle => "obstacle",
        }
    }
}

#[derive(Clone, Debug, PartialEq)]
pub enum ItemKind {
    Decl {
        kind: DeclKind,
        name: Ident,
        value: Expr,
    },
    Material(MaterialDecl),
    Param(ParamDecl),
    Input(InputDecl),
    Let(LetDecl),
    Fn(FnDecl),
    Sim(Vec<Stmt>),
    Loss(LossDecl),
    Optimize(OptimizeDecl),
}

#[derive(Clone, Debug, PartialEq)]
pub struct MaterialDecl {
    pub name: Ident,
    /// Present for material templates (`material yeoh(c10: pressure, …) { … }`).
    pub params: Option<Vec<FnParam>>,
    pub body: MaterialBody,
}

#[derive(Clone, Debug, PartialEq)]
pub enum MaterialBody {
    /// `material silicone = yeoh(…)`
    Expr(Expr),
    /// `material gel { density = …; W(I1bar, J) = … }`
    Block(Vec<Stmt>),
}

#[derive(Clone, Debug, PartialEq)]
pub struct ParamDecl {
    pub name: Ident,
    pub ty: TypeExpr,
    pub init: Expr,
    pub bounds: Option<Bounds>,
}

#[derive(Clone, Debug, PartialEq)]
pub struct Bounds {
    /// `None` for an open end (`..`).
    pub lower: Option<Expr>,
    pub upper: Option<Expr>,
    pub span: Span,
}

#[derive(Clone, Debug, PartialEq)]
pub struct InputDecl {
    pub name: Ident,
    pub ty: TypeExpr,
    pub source: Expr,
}

#[derive(Clone, Debug, PartialEq)]
pub struct LetDecl {
    pub name: Ident,
    pub ty: Option<TypeExpr>,
    pub value: Expr,
}

#[derive(Clone, Debug, PartialEq)]
pub struct FnDecl {
    /// `controller` functions may read the simulation state; plain `fn`s are pure.
    pub is_controller: bool,
    pub name: Ident,
    pub params: Vec<FnParam>,
    pub ret: Option<TypeExpr>,
    pub body: Expr,
}

#[derive(Clone, Debug, PartialEq)]
pub struct FnParam {
    pub name: Ident,
    pub ty: TypeExpr,
    pub default: Option<Expr>,
}

#[derive(Clone, Debug, PartialEq)]
pub struct LossDecl {
    pub value: Expr,
    pub when: LossWhen,
}

#[derive(Clone, Debug, PartialEq)]
pub enum LossWhen {
    /// No clause: evaluated at the final step.
    Default,
    /// `at end`
    AtEnd(Span),
    /// `over [t0, t1]`: summed over every step whose time lies in the range (thesis eq. 7.1).
    Over { from: Expr, to: Expr, span: Span },
}

#[derive(Clone, Debug, PartialEq)]
pub struct OptimizeDecl {
    pub targets: Vec<Ident>,
    pub optimizer: Expr,
    pub iterations: Option<Expr>,
    pub body: Option<Vec<Stmt>>,
}

/// A type: a physical dimension and an optional shape (`pressure`, `1/length[3, 4]`).
#[derive(Clone, Debug, PartialEq)]
pub struct TypeExpr {
    pub dim: DimExpr,
    pub shape: Vec<ShapeItem>,
    pub span: Span,
}

#[derive(Clone, Debug, PartialEq)]
pub struct DimExpr {
    /// The first factor, then `(op, factor)` pairs.
    pub first: DimFactor,
    pub rest: Vec<(DimOp, DimFactor)>,
    pub span: Span,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum DimOp {
    Mul,
    Div,
}

#[derive(Clone, Debug, PartialEq)]
pub struct DimFactor {
    pub base: DimBase,
    pub power: Option<(String, Span)>,
    pub span: Span,
}

#[derive(Clone, Debug, PartialEq)]
pub enum DimBase {
    One,
    Named(Ident),
    Group(Box<DimExpr>),
}

#[derive(Clone, Debug, PartialEq)]
pub enum ShapeItem {
    /// `*`: any length (template parameters only).
    Any(Span),
    Len(String, Span),
    /// An element set: one value per element of the set.
    Set(Ident),
}

#[derive(Clone, Debug, PartialEq)]
pub struct Stmt {
    pub kind: StmtKind,
    pub span: Span,
}

#[derive(Clone, Debug, PartialEq)]
pub enum StmtKind {
    Let(LetDecl),
    /// `setting = value`
    Assign {
        name: Ident,
        value: Expr,
    },
    /// `W(I1bar, I2bar, J) = expr` inside a material body.
    Energy {
        name: Ident,
        args: Vec<Ident>,
        body: Expr,
    },
    Fix(Vec<Ident>),
    Pressure {
        chamber: Ident,
        value: Expr,
    },
    Use {
        material: Ident,
        set: Option<Ident>,
    },
    /// `contact BODY with OBSTACLE (gap: …, stiffness: …)`: BODY the mesh or a node set.
    Contact {
        body: Ident,
        obstacle: Ident,
        args: Vec<Arg>,
    },
    Output {
        what: Expr,
        every: Expr,
        steps: bool,
    },
    Stop(Expr),
    Validate {
        input: Ident,
        source: Expr,
    },
}

#[derive(Clone, Debug, PartialEq)]
pub struct Expr {
    pub kind: ExprKind,
    pub span: Span,
}

#[derive(Clone, Debug, PartialEq)]
pub enum ExprKind {
    /// A number with an optional unit. `value` is the number as written (before the unit).
    Number {
        text: String,
        value: f64,
        is_int: bool,
        unit: Option<Unit>,
    },
    Array {
        items: Vec<Expr>,
        unit: Option<Unit>,
    },
    Str(String),
    Bool(bool),
    Name(Ident),
    Paren(Box<Expr>),
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
        callee: Box<Expr>,
        args: Vec<Arg>,
    },
    Index {
        base: Box<Expr>,
        indices: Vec<Expr>,
    },
    Field {
        base: Box<Expr>,
        field: Ident,
    },
    Reduce {
        op: ReduceOp,
        var: Ident,
        domain: Box<Expr>,
        body: Box<Expr>,
    },
    If {
        cond: Box<Expr>,
        then: Box<Expr>,
        otherwise: Box<Expr>,
    },
}

#[derive(Clone, Debug, PartialEq)]
pub struct Arg {
    pub name: Option<Ident>,
    pub value: Expr,
}

/// A unit as written after a number: `kg/m^3` is `[(kg, 1), (m, -3)]`.
#[derive(Clone, Debug, PartialEq)]
pub struct Unit {
    pub factors: Vec<UnitFactor>,
    pub span: Span,
}

#[derive(Clone, Debug, PartialEq)]
pub struct UnitFactor {
    pub name: String,
    /// Signed: factors after `/` are negative.
    pub power: i32,
    /// The power as written after `^` (kept for formatting), if any.
    pub written_power: Option<i32>,
    pub divides: bool,
    pub span: Span,
}

impl fmt::Display for Unit {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for (i, factor) in self.factors.iter().enumerate() {
            if factor.divides {
                f.write_str("/")?;
            } else if i > 0 {
                f.write_str("*")?;
            }
            f.write_str(&factor.name)?;
            if let Some(p) = factor.written_power {
                write!(f, "^{p}")?;
            }
        }
        Ok(())
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum UnaryOp {
    Neg,
    Not,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BinOp {
    Or,
    And,
    Eq,
    Ne,
    Lt,
    Le,
    Gt,
    Ge,
    Range,
    Add,
    Sub,
    Mul,
    Div,
    MatMul,
    Pow,
}

impl BinOp {
    pub fn symbol(self) -> &'static str {
        match self {
            BinOp::Or => "or",
            BinOp::And => "and",
            BinOp::Eq => "==",
            BinOp::Ne => "!=",
            BinOp::Lt => "<",
            BinOp::Le => "<=",
            BinOp::Gt => ">",
            BinOp::Ge => ">=",
            BinOp::Range => "..",
            BinOp::Add => "+",
            BinOp::Sub => "-",
            BinOp::Mul => "*",
            BinOp::Div => "/",
            BinOp::MatMul => "@",
            BinOp::Pow => "^",
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ReduceOp {
    Sum,
    Mean,
    /// The mean over the boundary surface a node set covers, each node weighted by the
    /// integral of its shape function over the set's boundary triangles.
    AreaMean,
    Max,
    Min,
}

impl ReduceOp {
    pub fn name(self) -> &'static str {
        match self {
            ReduceOp::Sum => "sum",
            ReduceOp::Mean => "mean",
            ReduceOp::AreaMean => "area_mean",
            ReduceOp::Max => "max",
            ReduceOp::Min => "min",
        }
    }
}

impl Expr {
    /// Nesting depth of the expression tree (1 for a leaf). Iterative: the parser bounds depth,
    /// but this must stay safe on any tree.
    pub fn depth(&self) -> usize {
        let mut max = 0;
        let mut stack = vec![(self, 1usize)];
        while let Some((e, d)) = stack.pop() {
            max = max.max(d);
            e.for_each_child(|c| stack.push((c, d + 1)));
        }
        max
    }

    pub fn for_each_child<'a>(&'a self, mut f: impl FnMut(&'a Expr)) {
        match &self.kind {
            ExprKind::Number { .. } | ExprKind::Str(_) | ExprKind::Bool(_) | ExprKind::Name(_) => {}
            ExprKind::Array { items, .. } => items.iter().for_each(f),
            ExprKind::Paren(e) => f(e),
            ExprKind::Unary { operand, .. } => f(operand),
            ExprKind::Binary { lhs, rhs, .. } => {
                f(lhs);
                f(rhs)
            }
            ExprKind::Call { callee, args } => {
                f(callee);
                args.iter().for_each(|a| f(&a.value));
            }
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
}
