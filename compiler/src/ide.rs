//! Editor support: what is under the cursor, where it was declared, what may be typed next.
//!
//! The language server (`softc lsp`, in the runtime crate) speaks the protocol; this module
//! answers its questions from the same front end and checker as `softc check`. Everything works
//! on byte offsets into the script; the server converts to editor positions.
//!
//! Hover and go-to-definition use the AST when the script parses, and a token scan otherwise
//! (while the user types, most states of the document do not parse). Completion always works
//! from tokens before the cursor, so it is useful in the middle of an unfinished statement.

use crate::front::ast::*;
use crate::sema::types::Ty;
use crate::sema::units::{self, Dim};
use crate::sema::{self, CheckedScript, GlobalInfo, SymKind};
use std::collections::HashMap;

// ------------------------------------------------------------------------------------------
// Static knowledge: keywords, built-ins, reserved names

/// Reserved keywords with a one-line description (SPEC section 2.3).
pub const KEYWORDS: &[(&str, &str)] = &[
    (
        "mesh",
        "declares the tetrahedral mesh: `mesh NAME = load(PATH)`",
    ),
    ("material", "declares a material or a material template"),
    (
        "region",
        "declares a region of space: `region NAME = box(…)`",
    ),
    (
        "chamber",
        "declares a pressure chamber: `chamber NAME = surface(mesh, \"name\")`",
    ),
    (
        "nodes",
        "declares a node set: `nodes NAME = select(mesh, …)`",
    ),
    ("elements", "declares an element set"),
    (
        "param",
        "declares a trainable parameter: `param NAME: TYPE = INIT in [LO, HI]`",
    ),
    (
        "input",
        "declares a batch input: `input NAME: TYPE from SOURCE`",
    ),
    ("let", "binds a name to a value"),
    ("fn", "declares a pure function"),
    (
        "controller",
        "declares a function that may read the simulation state and time",
    ),
    (
        "sim",
        "the simulation block: settings, `fix`, `pressure`, `use`, `output`",
    ),
    (
        "optimize",
        "what to optimize: `optimize P, … with OPTIMIZER [for N iterations] { … }`",
    ),
    (
        "fix",
        "fixes the nodes of regions or node sets: `fix NAME, …`",
    ),
    ("use", "assigns a material: `use MATERIAL [in ELEMENTSET]`"),
    ("output", "writes results: `output vtk every N steps`"),
    ("every", "output interval: `every N steps` or `every TIME`"),
    ("steps", "`every N steps`"),
    ("stop", "`stop when CONDITION` ends the optimization"),
    ("when", "`stop when CONDITION`"),
    ("validate", "`validate INPUT from SOURCE`"),
    ("with", "`optimize … with OPTIMIZER`"),
    ("for", "`for N iterations`"),
    ("iterations", "`for N iterations`"),
    ("from", "`input NAME: TYPE from SOURCE`"),
    (
        "in",
        "bounds `in [LO, HI]`, `use M in SET`, reductions `sum(n in SET)`",
    ),
    ("at", "`loss = … at end`"),
    ("end", "`loss = … at end`: the loss at the final step"),
    (
        "over",
        "`loss = … over [T0, T1]`: summed over the steps in the window",
    ),
    ("if", "`if COND then A else B`"),
    ("then", "`if COND then A else B`"),
    ("else", "`if COND then A else B`"),
    ("and", "logical and"),
    ("or", "logical or"),
    ("not", "logical not"),
    ("true", "the boolean true"),
    ("false", "the boolean false"),
];

/// Contextual keywords: they start a statement but stay usable as names.
pub const CONTEXTUAL_KEYWORDS: &[(&str, &str)] = &[
    (
        "loss",
        "the loss: `loss = EXPR [at end | over [T0, T1]]`; inside `stop when`, its value",
    ),
    (
        "pressure",
        "`pressure CHAMBER = EXPR` in `sim`; in types, the dimension of pressure",
    ),
];

/// Documentation of a built-in function: its signature (parameter names and units) and meaning.
pub struct BuiltinDoc {
    pub name: &'static str,
    pub signature: &'static str,
    /// Parameter names in order (`?` marks optional ones in the signature, not here).
    pub params: &'static [&'static str],
    pub doc: &'static str,
}

macro_rules! b {
    ($name:literal, $sig:literal, [$($p:literal),*], $doc:literal) => {
        BuiltinDoc { name: $name, signature: $sig, params: &[$($p),*], doc: $doc }
    };
}

/// Every function of [`sema::FUNCTIONS`], documented (a test checks the two agree).
pub const BUILTIN_DOCS: &[BuiltinDoc] = &[
    b!(
        "sqrt",
        "sqrt(x: any) -> dimension of x / 2",
        ["x"],
        "Square root; a constant argument must be ≥ 0."
    ),
    b!(
        "abs",
        "abs(x: any) -> same dimension",
        ["x"],
        "Absolute value (elementwise)."
    ),
    b!(
        "exp",
        "exp(x: dimensionless) -> dimensionless",
        ["x"],
        "Exponential."
    ),
    b!(
        "ln",
        "ln(x: dimensionless) -> dimensionless",
        ["x"],
        "Natural logarithm; a constant argument must be > 0."
    ),
    b!(
        "log10",
        "log10(x: dimensionless) -> dimensionless",
        ["x"],
        "Base-10 logarithm; a constant argument must be > 0."
    ),
    b!(
        "sin",
        "sin(x: dimensionless) -> dimensionless",
        ["x"],
        "Sine (angles in rad; `30 deg` converts)."
    ),
    b!(
        "cos",
        "cos(x: dimensionless) -> dimensionless",
        ["x"],
        "Cosine."
    ),
    b!(
        "tan",
        "tan(x: dimensionless) -> dimensionless",
        ["x"],
        "Tangent."
    ),
    b!(
        "tanh",
        "tanh(x: dimensionless) -> dimensionless",
        ["x"],
        "Hyperbolic tangent."
    ),
    b!(
        "sigmoid",
        "sigmoid(x: dimensionless) -> dimensionless",
        ["x"],
        "Logistic function 1/(1+e⁻ˣ)."
    ),
    b!(
        "floor",
        "floor(x: dimensionless) -> integer",
        ["x"],
        "Round down to an integer."
    ),
    b!(
        "ceil",
        "ceil(x: dimensionless) -> integer",
        ["x"],
        "Round up to an integer."
    ),
    b!(
        "min",
        "min(a, b) -> that dimension",
        ["a", "b"],
        "Smaller of two values of one dimension (elementwise)."
    ),
    b!(
        "max",
        "max(a, b) -> that dimension",
        ["a", "b"],
        "Larger of two values of one dimension (elementwise)."
    ),
    b!(
        "clamp",
        "clamp(x, lo, hi) -> that dimension",
        ["x", "lo", "hi"],
        "`x` limited to [lo, hi]; all of one dimension."
    ),
    b!(
        "norm",
        "norm(v: array) -> scalar of v's dimension",
        ["v"],
        "Euclidean norm of all entries."
    ),
    b!(
        "len",
        "len(v: array) -> integer",
        ["v"],
        "Length of the first axis."
    ),
    b!(
        "dot",
        "dot(a: vector, b: vector) -> dim(a)·dim(b)",
        ["a", "b"],
        "Dot product of two vectors of one length."
    ),
    b!(
        "cross",
        "cross(a: 3-vector, b: 3-vector) -> 3-vector, dim(a)·dim(b)",
        ["a", "b"],
        "Cross product."
    ),
    b!(
        "ramp",
        "ramp(t: time, duration: time) -> dimensionless",
        ["t", "duration"],
        "Rises linearly from 0 at t = 0 to 1 at t = duration, then stays 1."
    ),
    b!(
        "window",
        "window(t: time, width: time) -> integer",
        ["t", "width"],
        "Index ⌊t / width⌋ of the current window (windowed parameters)."
    ),
    b!(
        "step",
        "step(t: time, at: time) -> dimensionless",
        ["t", "at"],
        "0 before `at`, 1 from `at` on."
    ),
    b!(
        "load",
        "load(path: string, unit?: length) -> mesh",
        ["path", "unit"],
        "Reads a mesh file (.msh, .vtk, .vtu, tetgen, .inp); `unit` is the length of one file unit (default 1 mm)."
    ),
    b!(
        "box",
        "box(min: length[3], max: length[3]) -> region",
        ["min", "max"],
        "Axis-aligned box."
    ),
    b!(
        "sphere",
        "sphere(center: length[3], radius: length) -> region",
        ["center", "radius"],
        "Ball."
    ),
    b!(
        "cylinder",
        "cylinder(start: length[3], end: length[3], radius: length) -> region",
        ["start", "end", "radius"],
        "Capped cylinder between two points."
    ),
    b!(
        "surface",
        "surface(mesh: mesh, name: string | tag: integer) -> chamber surface",
        ["mesh", "name", "tag"],
        "A named or tagged surface of the mesh (a chamber's walls)."
    ),
    b!(
        "select",
        "select(mesh: mesh, where: bool in x, y, z) -> selection",
        ["mesh", "where"],
        "Nodes or elements whose coordinates satisfy the condition."
    ),
    b!(
        "named",
        "named(mesh: mesh, name: string) -> selection",
        ["mesh", "name"],
        "A named node/element set or physical group of the mesh."
    ),
    b!(
        "tagged",
        "tagged(mesh: mesh, tag: integer) -> selection",
        ["mesh", "tag"],
        "Elements of a region tag of the mesh."
    ),
    b!(
        "inside",
        "inside(mesh: mesh, region: region) -> selection",
        ["mesh", "region"],
        "Nodes inside a region."
    ),
    b!(
        "auto",
        "auto(safety: dimensionless in (0, 1]) -> time step",
        ["safety"],
        "The largest stable time step (CFL), scaled by `safety`."
    ),
    b!(
        "springs",
        "springs(volume_stiffness: force/volume) -> force model",
        ["volume_stiffness"],
        "Spring-mesh forces with a volume-conservation term (thesis eq. 2.3–2.7, 2.16)."
    ),
    b!(
        "csv",
        "csv(set: node set) -> output kind",
        ["set"],
        "Writes the positions of a node set as CSV."
    ),
    b!(
        "gd",
        "gd(lr: dimensionless) -> optimizer",
        ["lr"],
        "Gradient descent."
    ),
    b!(
        "sgd",
        "sgd(lr: dimensionless, momentum?: dimensionless in [0, 1)) -> optimizer",
        ["lr", "momentum"],
        "Stochastic gradient descent with momentum."
    ),
    b!(
        "adam",
        "adam(lr: dimensionless, beta1?: [0, 1), beta2?: [0, 1), eps?: > 0) -> optimizer",
        ["lr", "beta1", "beta2", "eps"],
        "Adam."
    ),
    b!(
        "nadam",
        "nadam(lr: dimensionless, beta1?: [0, 1), beta2?: [0, 1), eps?: > 0) -> optimizer",
        ["lr", "beta1", "beta2", "eps"],
        "Nesterov-accelerated Adam."
    ),
    b!(
        "magnitude",
        "magnitude(m: dimensionless > 0) -> normalization",
        ["m"],
        "Thesis eq. 5.5: the gradient scaled to one order of magnitude below the parameter."
    ),
    b!(
        "exponential",
        "exponential(gamma: dimensionless in (0, 1]) -> schedule",
        ["gamma"],
        "Learning rate × gamma each iteration."
    ),
    b!(
        "step_decay",
        "step_decay(every: integer ≥ 1, gamma: (0, 1]) -> schedule",
        ["every", "gamma"],
        "Learning rate × gamma every N iterations."
    ),
    b!(
        "cosine",
        "cosine(floor?: dimensionless in [0, 1)) -> schedule",
        ["floor"],
        "Cosine decay to `floor` × the learning rate."
    ),
    b!(
        "periodic",
        "periodic(steps: integer ≥ 1) -> checkpoint schedule",
        ["steps"],
        "Store every k-th state, recompute the segments."
    ),
    b!(
        "revolve",
        "revolve(snapshots: integer ≥ 1) -> checkpoint schedule",
        ["snapshots"],
        "Binomial (revolve) checkpointing with n snapshots."
    ),
    b!(
        "circle_quadrants",
        "circle_quadrants(radius: length, plane?, center?: length[3], seed?: integer) -> batch source",
        ["radius", "plane", "center", "seed"],
        "Targets on a circle, one per quadrant per batch (thesis §6)."
    ),
];

/// Built-in constants (SPEC 9.6).
pub const CONSTANT_DOCS: &[(&str, &str)] = &[
    (
        "auto",
        "automatic choice: `dt = auto`, `normalize = auto`, `checkpoint = auto`",
    ),
    ("none", "`normalize = none`: the raw gradient"),
    (
        "fem",
        "`model = fem`: tetrahedral FEM forces from the strain energy W",
    ),
    (
        "semi_implicit_euler",
        "`integrator`: v += dt·F/m; x += dt·v (thesis eq. 2.2)",
    ),
    (
        "quasi_static",
        "`integrator`: the steady state by a static equilibrium solve",
    ),
    ("f32", "`precision`: 32-bit floats"),
    ("f64", "`precision`: 64-bit floats"),
    ("vtk", "`output vtk every …`: VTK files of the mesh"),
    ("store_all", "`checkpoint`: the adjoint stores every state"),
    ("constant", "`lr_schedule`: a constant learning rate"),
];

/// Reserved built-in names (SPEC 2.4).
pub const RESERVED_DOCS: &[(&str, &str)] = &[
    ("t", "the simulation time (time)"),
    ("t_end", "the simulated duration (time, a constant)"),
    ("dt", "the time step (time, a constant)"),
    (
        "x",
        "current node positions `x[n]` (length[3]); a coordinate inside `select`",
    ),
    ("y", "a coordinate (length) inside `select`"),
    ("z", "a coordinate (length) inside `select`"),
    ("x0", "initial node positions `x0[n]` (length[3])"),
    ("v", "node velocities `v[n]` (velocity[3])"),
    (
        "I1bar",
        "first isochoric invariant of the deformation (thesis eq. 2.11)",
    ),
    ("I2bar", "second isochoric invariant (thesis eq. 2.12)"),
    ("J", "volume ratio det F (thesis eq. 2.13)"),
    (
        "I1",
        "first invariant tr(FᵀF), not isochoric: W(I1, J) is evaluated without J^(-2/3) (inversion-safe laws)",
    ),
    ("loss", "the current loss, inside `stop when`"),
    (
        "grad_norm",
        "the gradient norm (dimensionless), inside `stop when`",
    ),
    (
        "iteration",
        "the optimization iteration (integer), inside `stop when`",
    ),
    ("pi", "π (dimensionless)"),
];

/// Reduction operators (`sum(i in D) body`).
pub const REDUCTIONS: &[&str] = &["sum", "mean", "max", "min"];

/// Settings with a one-line description.
fn setting_doc(name: &str) -> &'static str {
    match name {
        "dt" => "time step: a time, `auto` or `auto(safety: S)`",
        "steps" => "number of time steps (integer)",
        "duration" => "simulated time",
        "integrator" => "`semi_implicit_euler` or `quasi_static`",
        "damping" => "mass-proportional damping (rate, e.g. `20 /s`)",
        "model" => "`fem` or `springs(volume_stiffness: …)`",
        "gravity" => "acceleration 3-vector, e.g. `[0, 0, -9.81] m/s^2`",
        "mass_scaling" => "node mass multiplier ≥ 1",
        "precision" => "`f32` or `f64`",
        "batch" => "scenes per iteration (integer ≥ 1)",
        "seed" => "seed for batch sampling (integer)",
        "gradient_scale" => "thesis eq. 5.4 factor in (0, 1]",
        "normalize" => "`magnitude(m: …)`, `auto` or `none`",
        "clip" => "clip the gradient norm (positive)",
        "lr_schedule" => "`constant`, `exponential(…)`, `step_decay(…)`, `cosine(…)`",
        "memory_budget" => "memory for adjoint states (`2 GiB`)",
        "checkpoint" => "`auto`, `store_all`, `periodic(steps: k)`, `revolve(snapshots: n)`",
        "truncate" => "differentiate through at most this many steps",
        _ => "",
    }
}

// ------------------------------------------------------------------------------------------
// Tokens (robust against any text)

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
fn is_ident_char(c: char) -> bool {
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

// ------------------------------------------------------------------------------------------
// Name resolution over the AST

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
#[derive(Debug, Default)]
pub struct Resolved {
    pub defs: Vec<Def>,
    /// `(use, def index)`.
    pub refs: Vec<(Span, usize)>,
    /// Names used but not declared in the script (built-ins, prelude names, or errors).
    pub free: Vec<Ident>,
    /// Dimension names in types.
    pub dims: Vec<Ident>,
}

struct Resolver {
    r: Resolved,
    globals: HashMap<String, usize>,
    scopes: Vec<HashMap<String, usize>>,
}

/// Resolve the names of a parsed script.
pub fn resolve(script: &Script) -> Resolved {
    let mut rs = Resolver {
        r: Resolved::default(),
        globals: HashMap::new(),
        scopes: Vec::new(),
    };
    for item in &script.items {
        let Some((name, kind)) = SymKind::of_item(item) else {
            continue;
        };
        let ty = match &item.kind {
            ItemKind::Param(p) => Some(p.ty.clone()),
            ItemKind::Input(i) => Some(i.ty.clone()),
            ItemKind::Let(l) => l.ty.clone(),
            ItemKind::Fn(f) => f.ret.clone(),
            _ => None,
        };
        let id = rs.def(name, DefKind::Global(kind), item.span, ty);
        rs.globals.entry(name.name.clone()).or_insert(id);
    }
    for item in &script.items {
        rs.item(item);
    }
    rs.r
}

impl Resolver {
    fn def(&mut self, name: &Ident, kind: DefKind, decl: Span, ty: Option<TypeExpr>) -> usize {
        self.r.defs.push(Def {
            name: name.name.clone(),
            kind,
            span: name.span,
            decl,
            ty,
        });
        self.r.defs.len() - 1
    }

    fn bind(&mut self, name: &Ident, kind: DefKind, decl: Span, ty: Option<TypeExpr>) {
        let id = self.def(name, kind, decl, ty);
        if let Some(s) = self.scopes.last_mut() {
            s.insert(name.name.clone(), id);
        }
    }

    fn use_name(&mut self, id: &Ident) {
        let found = self
            .scopes
            .iter()
            .rev()
            .find_map(|s| s.get(&id.name))
            .or_else(|| self.globals.get(&id.name))
            .copied();
        match found {
            Some(d) => self.r.refs.push((id.span, d)),
            None => self.r.free.push(id.clone()),
        }
    }

    fn ty(&mut self, t: &TypeExpr) {
        self.dim(&t.dim);
        for s in &t.shape {
            if let ShapeItem::Set(id) = s {
                self.use_name(id);
            }
        }
    }

    fn dim(&mut self, d: &DimExpr) {
        for f in std::iter::once(&d.first).chain(d.rest.iter().map(|(_, f)| f)) {
            match &f.base {
                DimBase::One => {}
                DimBase::Named(id) => self.r.dims.push(id.clone()),
                DimBase::Group(g) => self.dim(g),
            }
        }
    }

    fn params(&mut self, owner: &Ident, params: &[FnParam]) {
        for p in params {
            self.ty(&p.ty);
            if let Some(d) = &p.default {
                self.expr(d);
            }
            let decl = p.default.as_ref().map_or(p.ty.span, |d| d.span);
            self.bind(
                &p.name,
                DefKind::Param {
                    owner: owner.name.clone(),
                },
                p.name.span.to(decl),
                Some(p.ty.clone()),
            );
        }
    }

    fn item(&mut self, item: &Item) {
        match &item.kind {
            ItemKind::Decl { value, .. } => self.expr(value),
            ItemKind::Material(m) => {
                self.scopes.push(HashMap::new());
                if let Some(ps) = &m.params {
                    self.params(&m.name, ps);
                }
                match &m.body {
                    MaterialBody::Expr(e) => self.expr(e),
                    MaterialBody::Block(stmts) => self.stmts(stmts),
                }
                self.scopes.pop();
            }
            ItemKind::Param(p) => {
                self.ty(&p.ty);
                self.expr(&p.init);
                if let Some(b) = &p.bounds {
                    for e in b.lower.iter().chain(b.upper.iter()) {
                        self.expr(e);
                    }
                }
            }
            ItemKind::Input(i) => {
                self.ty(&i.ty);
                self.expr(&i.source);
            }
            ItemKind::Let(l) => {
                if let Some(t) = &l.ty {
                    self.ty(t);
                }
                self.expr(&l.value);
            }
            ItemKind::Fn(f) => {
                self.scopes.push(HashMap::new());
                self.params(&f.name, &f.params);
                if let Some(r) = &f.ret {
                    self.ty(r);
                }
                self.expr(&f.body);
                self.scopes.pop();
            }
            ItemKind::Sim(stmts) => {
                self.scopes.push(HashMap::new());
                self.stmts(stmts);
                self.scopes.pop();
            }
            ItemKind::Loss(l) => {
                self.expr(&l.value);
                if let LossWhen::Over { from, to, .. } = &l.when {
                    self.expr(from);
                    self.expr(to);
                }
            }
            ItemKind::Optimize(o) => {
                for t in &o.targets {
                    self.use_name(t);
                }
                self.expr(&o.optimizer);
                if let Some(n) = &o.iterations {
                    self.expr(n);
                }
                if let Some(b) = &o.body {
                    self.stmts(b);
                }
            }
        }
    }

    fn stmts(&mut self, stmts: &[Stmt]) {
        for s in stmts {
            match &s.kind {
                StmtKind::Let(l) => {
                    if let Some(t) = &l.ty {
                        self.ty(t);
                    }
                    self.expr(&l.value);
                    self.bind(&l.name, DefKind::LocalLet, s.span, l.ty.clone());
                }
                StmtKind::Assign { value, .. } => self.expr(value),
                StmtKind::Energy { body, .. } => self.expr(body),
                StmtKind::Fix(names) => names.iter().for_each(|n| self.use_name(n)),
                StmtKind::Pressure { chamber, value } => {
                    self.use_name(chamber);
                    self.expr(value);
                }
                StmtKind::Use { material, set } => {
                    self.use_name(material);
                    if let Some(s) = set {
                        self.use_name(s);
                    }
                }
                StmtKind::Output { what, every, .. } => {
                    self.expr(what);
                    self.expr(every);
                }
                StmtKind::Stop(e) => self.expr(e),
                StmtKind::Validate { input, source } => {
                    self.use_name(input);
                    self.expr(source);
                }
            }
        }
    }

    fn expr(&mut self, e: &Expr) {
        // Iterative over everything but reductions (which open a scope): expressions may be
        // deep, and the parser bounds their depth, so recursion on reductions is fine.
        match &e.kind {
            ExprKind::Name(id) => self.use_name(id),
            ExprKind::Field { base, .. } => self.expr(base),
            ExprKind::Reduce {
                var, domain, body, ..
            } => {
                self.expr(domain);
                self.scopes.push(HashMap::new());
                self.bind(var, DefKind::ReduceVar, e.span, None);
                self.expr(body);
                self.scopes.pop();
            }
            _ => e.for_each_child(|c| self.expr(c)),
        }
    }
}

impl Resolved {
    /// The definition at or referenced at `offset`.
    pub fn def_at(&self, offset: usize) -> Option<&Def> {
        let inside = |s: &Span| s.start <= offset && offset <= s.end;
        if let Some((_, d)) = self.refs.iter().find(|(s, _)| inside(s)) {
            return self.defs.get(*d);
        }
        self.defs.iter().find(|d| inside(&d.span))
    }
}

// ------------------------------------------------------------------------------------------
// Analysis of one document

/// A script parsed, resolved and checked, ready to answer editor questions.
pub struct Analysis<'a> {
    pub text: &'a str,
    pub script: Option<Script>,
    pub resolved: Resolved,
    /// The checker's view of the script's globals (types, values); empty when not checked.
    pub globals: Vec<GlobalInfo>,
    pub tokens: Vec<Tok>,
}

impl<'a> Analysis<'a> {
    /// Analyze without running the checker (hover then shows declared, not inferred, types).
    pub fn new(text: &'a str) -> Self {
        let script = crate::front::parse(text).ok();
        let resolved = script.as_ref().map(resolve).unwrap_or_default();
        Analysis {
            text,
            script,
            resolved,
            globals: Vec::new(),
            tokens: tokenize(text),
        }
    }

    /// Analyze and keep the checker's results (types of globals).
    pub fn with_check(text: &'a str, checked: Option<CheckedScript>) -> Self {
        let mut a = Analysis::new(text);
        a.globals = checked.map(|c| c.globals).unwrap_or_default();
        a
    }

    /// Analyze a script parsed before (`script` must be `front::parse(text).ok()`).
    pub fn from_parsed(text: &'a str, script: Option<Script>, globals: Vec<GlobalInfo>) -> Self {
        let resolved = script.as_ref().map(resolve).unwrap_or_default();
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

    /// Markdown describing what is at `offset`, and the span it describes.
    pub fn hover(&self, offset: usize) -> Option<(String, Span)> {
        let tok = self.token_at(offset)?;
        let word = &self.text[tok.span.start..tok.span.end];
        match tok.kind {
            TokKind::Unit => return unit_hover(word).map(|h| (h, tok.span)),
            TokKind::Ident => {}
            _ => return None,
        }
        if self.script.is_some() {
            if let Some(def) = self.resolved.def_at(offset) {
                return Some((self.def_hover(def), tok.span));
            }
            if self.resolved.dims.iter().any(|d| d.span == tok.span) {
                return dim_hover(word).map(|h| (h, tok.span));
            }
        } else if let Some((_, kind, span)) =
            self.lexical_decls().into_iter().find(|(n, _, _)| n == word)
        {
            let line_end = self.text[span.start..]
                .find('\n')
                .map_or(self.text.len(), |e| span.start + e);
            let line_start = self.text[..span.start].rfind('\n').map_or(0, |s| s + 1);
            let _ = kind;
            let code = truncate(self.text[line_start..line_end].trim());
            return Some((format!("```soft\n{code}\n```"), tok.span));
        }
        if let Some(h) = self.argument_hover(tok, word) {
            return Some((h, tok.span));
        }
        builtin_hover(word, self.is_call(tok)).map(|h| (h, tok.span))
    }

    /// An argument name (`radius` in `sphere(center: c, radius: 2 mm)`): the callee's parameter.
    fn argument_hover(&self, tok: Tok, word: &str) -> Option<String> {
        let rest = self.text[tok.span.end..].trim_start_matches([' ', '\t']);
        if !rest.starts_with(':') || rest.starts_with("::") {
            return None;
        }
        let callee = self.enclosing_callee(tok.span.start)?;
        if !self.params_of(&callee).iter().any(|p| p == word) {
            return None;
        }
        let sig = BUILTIN_DOCS
            .iter()
            .find(|b| b.name == callee)
            .map(|b| b.signature.to_string())
            .or_else(|| {
                let item = self
                    .script
                    .as_ref()
                    .and_then(|s| {
                        s.items.iter().find(|i| match &i.kind {
                            ItemKind::Fn(f) => f.name.name == callee,
                            ItemKind::Material(m) => m.name.name == callee,
                            _ => false,
                        })
                    })
                    .map(|i| (self.text, i))
                    .or_else(|| prelude_item(&callee).map(|i| (sema::PRELUDE, i)))?;
                let (text, item) = item;
                Some(match &item.kind {
                    ItemKind::Fn(f) => signature_text(text, item.span, f.body.span),
                    _ => {
                        let t = &text[item.span.start..item.span.end];
                        t[..t.find(['{', '=']).unwrap_or(t.len())]
                            .trim()
                            .to_string()
                    }
                })
            })?;
        Some(format!(
            "argument `{word}` of `{callee}`\n\n```soft\n{}\n```",
            truncate(&sig)
        ))
    }

    /// The name called by the innermost unclosed `(` before `offset`.
    fn enclosing_callee(&self, offset: usize) -> Option<String> {
        let mut depth = 0usize;
        let toks: Vec<&Tok> = self
            .tokens
            .iter()
            .filter(|t| t.span.end <= offset && t.kind != TokKind::Comment)
            .collect();
        for (i, t) in toks.iter().enumerate().rev() {
            if t.kind != TokKind::Punct {
                continue;
            }
            match &self.text[t.span.start..t.span.end] {
                ")" | "]" | "}" => depth += 1,
                "[" | "{" => {
                    if depth == 0 {
                        return None;
                    }
                    depth -= 1;
                }
                "(" => {
                    if depth == 0 {
                        let prev = toks.get(i.checked_sub(1)?)?;
                        return (prev.kind == TokKind::Ident)
                            .then(|| self.text[prev.span.start..prev.span.end].to_string());
                    }
                    depth -= 1;
                }
                _ => {}
            }
        }
        None
    }

    fn is_call(&self, tok: Tok) -> bool {
        self.text[tok.span.end..].trim_start().starts_with('(')
    }

    fn def_hover(&self, def: &Def) -> String {
        let text = self.text;
        let src = |s: Span| text.get(s.start..s.end).unwrap_or("");
        let mut code;
        let mut extra = String::new();
        match &def.kind {
            DefKind::Global(kind) => {
                let info = self.global_info(&def.name, def.span);
                let ty_unit = |written: Option<&TypeExpr>| -> String {
                    let ty = info.and_then(|i| i.ty.clone());
                    type_with_unit(ty.as_ref(), written, text)
                };
                let item = self
                    .script
                    .as_ref()
                    .and_then(|s| s.items.iter().find(|i| i.span == def.decl));
                code = match item.map(|i| &i.kind) {
                    Some(ItemKind::Param(p)) => {
                        let mut c = format!(
                            "param {}: {} = {}",
                            def.name,
                            ty_unit(Some(&p.ty)),
                            src(p.init.span)
                        );
                        if let Some(b) = &p.bounds {
                            c.push(' ');
                            c.push_str(src(b.span));
                        }
                        c
                    }
                    Some(ItemKind::Input(i)) => format!(
                        "input {}: {} from {}",
                        def.name,
                        ty_unit(Some(&i.ty)),
                        src(i.source.span)
                    ),
                    Some(ItemKind::Let(l)) => format!(
                        "let {}: {} = {}",
                        def.name,
                        ty_unit(l.ty.as_ref()),
                        src(l.value.span)
                    ),
                    Some(ItemKind::Decl { kind, value, .. }) => {
                        format!("{} {} = {}", kind.keyword(), def.name, src(value.span))
                    }
                    Some(ItemKind::Fn(f)) => signature_text(text, def.decl, f.body.span),
                    Some(ItemKind::Material(m)) => match &m.body {
                        MaterialBody::Expr(e) => {
                            format!("material {} = {}", def.name, src(e.span))
                        }
                        MaterialBody::Block(_) => {
                            let head_end = text[def.decl.start..def.decl.end]
                                .find('{')
                                .map_or(def.decl.end, |i| def.decl.start + i);
                            text[def.decl.start..head_end].trim().to_string()
                        }
                    },
                    _ => format!("{} {}", kind_word(*kind), def.name),
                };
                if let Some(info) = info {
                    if let (Some(v), Some(ty)) = (info.value, &info.ty) {
                        let unit = ty.dim().map(|d| d.si_unit()).unwrap_or_default();
                        let unit = if unit == "1" {
                            String::new()
                        } else {
                            format!(" {unit}")
                        };
                        if !matches!(kind, SymKind::Param) {
                            extra = format!("value: {}{unit} (SI)", fmt_num(v));
                        }
                    } else if let Some(ty) = &info.ty
                        && matches!(ty, Ty::Obj(_))
                    {
                        extra = ty.to_string();
                    }
                }
                let doc = leading_comment(text, def.decl.start);
                if !doc.is_empty() {
                    extra = if extra.is_empty() {
                        doc
                    } else {
                        format!("{extra}\n\n{doc}")
                    };
                }
            }
            DefKind::Param { owner } => {
                code = format!(
                    "{}: {}",
                    def.name,
                    type_with_unit(None, def.ty.as_ref(), text)
                );
                let decl = src(def.decl);
                if let Some(eq) = decl.find('=') {
                    code.push_str(" = ");
                    code.push_str(decl[eq + 1..].trim());
                }
                extra = format!("parameter of `{owner}`");
            }
            DefKind::LocalLet => {
                code = src(def.decl).to_string();
                if let Some(t) = &def.ty {
                    extra = format!("type: {}", type_with_unit(None, Some(t), text));
                }
            }
            DefKind::ReduceVar => {
                let decl = src(def.decl);
                let head = decl.find(')').map_or(decl, |i| &decl[..=i]);
                code = head.to_string();
                extra = format!("`{}`: the variable of this reduction", def.name);
            }
        }
        let code = truncate(&code);
        if extra.is_empty() {
            format!("```soft\n{code}\n```")
        } else {
            format!("```soft\n{code}\n```\n\n{extra}")
        }
    }

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
                for p in params {
                    push(
                        &p,
                        CompletionKind::Argument,
                        format!("argument of `{callee}`"),
                        Some(format!("{p}: ")),
                    );
                }
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
                        &["let", "fix", "pressure", "use", "output"],
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

    /// Parameter names of a callee: a built-in, a prelude template/function, or the script's.
    fn params_of(&self, callee: &str) -> Vec<String> {
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
    /// Inside the argument list of a call to the named function.
    Args(String),
    /// A name of one of these kinds: `pressure CHAMBER`, `fix REGION`, `use MATERIAL`, …
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

/// In a statement that names declarations (`pressure CHAMBER`, `fix A, B`, `use M in SET`,
/// `optimize P, Q with`, `validate INPUT`): the kinds of names that fit at the cursor.
fn statement_names(text: &str, before: &[&Tok]) -> Option<&'static [SymKind]> {
    let word = |t: &Tok| &text[t.span.start..t.span.end];
    // The tokens of the current statement: back to a line start, `{` or `;`.
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

// ------------------------------------------------------------------------------------------
// Hover texts

fn kind_word(k: SymKind) -> &'static str {
    match k {
        SymKind::Mesh => "mesh",
        SymKind::Material | SymKind::MaterialTemplate => "material",
        SymKind::Region => "region",
        SymKind::Chamber => "chamber",
        SymKind::Nodes => "nodes",
        SymKind::Elements => "elements",
        SymKind::Param => "param",
        SymKind::Input => "input",
        SymKind::Let => "let",
        SymKind::Fn => "fn",
        SymKind::Controller => "controller",
    }
}

fn truncate(s: &str) -> String {
    const MAX: usize = 400;
    if s.len() <= MAX {
        return s.to_string();
    }
    let mut end = MAX;
    while !s.is_char_boundary(end) {
        end -= 1;
    }
    format!("{} …", &s[..end])
}

fn fmt_num(v: f64) -> String {
    if v != 0.0 && (v.abs() >= 1e15 || v.abs() < 1e-4) {
        format!("{v:e}")
    } else {
        format!("{v}")
    }
}

/// The dimension of a written type (`pressure`, `length/time^2`), when it names only known
/// dimensions.
pub fn eval_dim(d: &DimExpr) -> Option<Dim> {
    fn factor(f: &DimFactor) -> Option<Dim> {
        let base = match &f.base {
            DimBase::One => Dim::NONE,
            DimBase::Named(id) => units::named_dim(&id.name)?,
            DimBase::Group(g) => eval_dim(g)?,
        };
        match &f.power {
            Some((p, _)) => base.powi(p.parse().ok()?),
            None => Some(base),
        }
    }
    let mut acc = factor(&d.first)?;
    for (op, f) in &d.rest {
        let v = factor(f)?;
        acc = match op {
            DimOp::Mul => acc.times(v),
            DimOp::Div => acc.per(v),
        };
    }
    Some(acc)
}

/// `pressure [Pa]`, `length[3] [m]`: a type with its SI unit.
fn type_with_unit(checked: Option<&Ty>, written: Option<&TypeExpr>, text: &str) -> String {
    let written_text =
        written.map(|w| text.get(w.span.start..w.span.end).unwrap_or("").to_string());
    let (name, dim) = match (checked, written) {
        (Some(ty), w) => (
            written_text.clone().unwrap_or_else(|| ty.to_string()),
            ty.dim().or_else(|| w.and_then(|w| eval_dim(&w.dim))),
        ),
        (None, Some(w)) => (written_text.clone().unwrap_or_default(), eval_dim(&w.dim)),
        (None, None) => return "(type not known)".into(),
    };
    match dim {
        Some(d) if !d.is_none() => format!("{name} [{}]", d.si_unit()),
        _ => name,
    }
}

/// The text of a declaration up to its body's `=`: `fn lame_mu(E: pressure, nu: 1) -> pressure`.
fn signature_text(text: &str, decl: Span, body: Span) -> String {
    let head = text.get(decl.start..body.start).unwrap_or("");
    let head = head.trim_end();
    head.strip_suffix('=')
        .unwrap_or(head)
        .trim_end()
        .to_string()
}

/// The `#` comment lines right above `offset`'s line.
fn leading_comment(text: &str, offset: usize) -> String {
    let line_start = text[..offset.min(text.len())]
        .rfind('\n')
        .map_or(0, |i| i + 1);
    let mut lines = Vec::new();
    let mut end = line_start;
    while end > 0 {
        let prev_start = text[..end - 1].rfind('\n').map_or(0, |i| i + 1);
        let line = text[prev_start..end - 1].trim();
        match line.strip_prefix('#') {
            Some(c) => lines.push(c.trim().to_string()),
            None => break,
        }
        end = prev_start;
    }
    lines.reverse();
    lines.join("\n")
}

fn unit_hover(name: &str) -> Option<String> {
    let (factor, dim) = units::unit(name)?;
    let si = dim.si_unit();
    Some(format!(
        "**{name}** — unit of {}\n\n1 {name} = {} {si} (SI)",
        if dim.is_none() {
            "a dimensionless quantity (angle)".to_string()
        } else {
            dim.name()
        },
        fmt_num(factor)
    ))
}

fn dim_hover(name: &str) -> Option<String> {
    let d = units::named_dim(name)?;
    Some(format!("**{name}** — dimension; SI unit `{}`", d.si_unit()))
}

fn prelude() -> Option<&'static Script> {
    static P: std::sync::OnceLock<Option<Script>> = std::sync::OnceLock::new();
    P.get_or_init(|| crate::front::parse(sema::PRELUDE).ok())
        .as_ref()
}

fn prelude_item(name: &str) -> Option<&'static Item> {
    prelude()?.items.iter().find(|i| match &i.kind {
        ItemKind::Material(m) => m.name.name == name,
        ItemKind::Fn(f) => f.name.name == name,
        _ => false,
    })
}

/// Names and signatures of the prelude's materials and functions.
pub fn prelude_signatures() -> Vec<(String, String)> {
    let Some(p) = prelude() else {
        return Vec::new();
    };
    p.items
        .iter()
        .filter_map(|i| {
            let (name, body) = match &i.kind {
                ItemKind::Material(m) => (&m.name, None),
                ItemKind::Fn(f) => (&f.name, Some(f.body.span)),
                _ => return None,
            };
            let sig = match body {
                Some(b) => signature_text(sema::PRELUDE, i.span, b),
                None => {
                    let t = &sema::PRELUDE[i.span.start..i.span.end];
                    t[..t.find('{').unwrap_or(t.len())].trim().to_string()
                }
            };
            Some((name.name.clone(), sig))
        })
        .collect()
}

/// Hover text of a built-in name (keyword, function, constant, reserved name, prelude item,
/// dimension, unit).
pub fn builtin_hover(word: &str, called: bool) -> Option<String> {
    if let Some(item) = prelude_item(word) {
        let (sig, what) = match &item.kind {
            ItemKind::Fn(f) => (
                signature_text(sema::PRELUDE, item.span, f.body.span),
                "prelude function",
            ),
            _ => {
                let t = &sema::PRELUDE[item.span.start..item.span.end];
                (t.trim_end().to_string(), "prelude material template")
            }
        };
        let doc = leading_comment(sema::PRELUDE, item.span.start);
        return Some(format!("```soft\n{sig}\n```\n\n{what}. {doc}"));
    }
    let other_meaning = RESERVED_DOCS.iter().any(|(n, _)| *n == word)
        || CONSTANT_DOCS.iter().any(|(n, _)| *n == word);
    if (called || !other_meaning)
        && let Some(b) = BUILTIN_DOCS.iter().find(|b| b.name == word)
    {
        return Some(format!(
            "```soft\n{}\n```\n\nbuilt-in function. {}",
            b.signature, b.doc
        ));
    }
    if let Some((_, d)) = RESERVED_DOCS.iter().find(|(n, _)| *n == word) {
        return Some(format!("**{word}** — built-in name: {d}"));
    }
    if let Some((_, d)) = CONSTANT_DOCS.iter().find(|(n, _)| *n == word) {
        return Some(format!("**{word}** — built-in constant: {d}"));
    }
    if let Some((_, d)) = KEYWORDS
        .iter()
        .chain(CONTEXTUAL_KEYWORDS)
        .find(|(n, _)| *n == word)
    {
        return Some(format!("**{word}** — keyword: {d}"));
    }
    if let Some(h) = dim_hover(word) {
        return Some(h);
    }
    if REDUCTIONS.contains(&word) {
        return Some(format!(
            "**{word}** — reduction: `{word}(i in DOMAIN) BODY`"
        ));
    }
    if !setting_doc(word).is_empty() {
        return Some(format!("**{word}** — setting: {}", setting_doc(word)));
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    fn at(text: &str, needle: &str) -> usize {
        text.find(needle).expect("needle") + 1
    }

    #[test]
    fn every_builtin_function_is_documented() {
        for f in sema::FUNCTIONS {
            assert!(
                BUILTIN_DOCS.iter().any(|b| b.name == *f),
                "built-in `{f}` has no entry in ide::BUILTIN_DOCS"
            );
        }
        for b in BUILTIN_DOCS {
            assert!(
                sema::FUNCTIONS.contains(&b.name),
                "`{}` is not a built-in",
                b.name
            );
        }
        for (c, _) in sema::CONSTANTS {
            assert!(CONSTANT_DOCS.iter().any(|(n, _)| n == c), "constant `{c}`");
        }
        for r in sema::RESERVED_NAMES {
            assert!(RESERVED_DOCS.iter().any(|(n, _)| n == r), "reserved `{r}`");
        }
    }

    /// The documented parameter names are the checker's: calling with them by name never
    /// gives "unknown argument" (E0105).
    #[test]
    fn documented_parameter_names_are_accepted() {
        for b in BUILTIN_DOCS {
            for p in b.params {
                let src = format!("let _a = {}({p}: 1)\n", b.name);
                let checked = crate::check_source(&src, &Default::default());
                assert!(
                    !checked.diagnostics.iter().any(|d| d.code == "E0105"),
                    "`{}` rejects its documented parameter `{p}`: {:?}",
                    b.name,
                    checked.diagnostics
                );
            }
        }
    }

    #[test]
    fn units_after_numbers_and_arrays_are_tokens() {
        let text = "let rho = 1070 kg/m^3\nlet g = [0, 0, -9.81] m/s^2 + 8 /s\nlet a = x[1] and 2";
        let toks = tokenize(text);
        let units: Vec<&str> = toks
            .iter()
            .filter(|t| t.kind == TokKind::Unit)
            .map(|t| &text[t.span.start..t.span.end])
            .collect();
        assert_eq!(units, ["kg", "m", "m", "s", "s"]);
    }

    #[test]
    fn hover_shows_param_type_unit_and_bounds() {
        let text = "param p_max: pressure = 1 kPa in [0 kPa, 50 kPa]\nlet q = p_max * 2\n";
        let checked = crate::check_source(text, &Default::default());
        let a = Analysis::with_check(text, checked.script);
        let (h, _) = a.hover(text.rfind("p_max").unwrap() + 1).unwrap();
        assert!(
            h.contains("param p_max: pressure [Pa] = 1 kPa in [0 kPa, 50 kPa]"),
            "{h}"
        );
        let (h, _) = a.hover(at(text, "kPa")).unwrap();
        assert!(h.contains("1 kPa = 1000 Pa"), "{h}");
        let (h, _) = a.hover(at(text, "q =")).unwrap();
        assert!(h.contains("let q: pressure [Pa]"), "{h}");
        let text = "let s = sphere(center: [0, 0, 0] mm, radius: 2 mm)\nsim { dt = auto }\n";
        let a = Analysis::new(text);
        let (h, _) = a.hover(at(text, "radius")).unwrap();
        assert!(h.contains("argument `radius` of `sphere`"), "{h}");
        let (h, _) = a.hover(at(text, "auto")).unwrap();
        assert!(h.contains("built-in constant"), "{h}");
        let text = "let m = yeoh(c10: 1 kPa, d1: 1 /MPa, density: 1 kg/m^3)\n";
        let (h, _) = Analysis::new(text).hover(at(text, "d1")).unwrap();
        assert!(h.contains("material yeoh(c10: pressure"), "{h}");
    }

    #[test]
    fn definition_of_chamber_in_pressure_statement() {
        let text = "chamber cavity = surface(body, \"c\")\nsim {\n  pressure cavity = 1 kPa\n}\n";
        let a = Analysis::new(text);
        let use_at = text.rfind("cavity").unwrap() + 2;
        let def = a.definition(use_at).unwrap();
        assert_eq!(&text[def.start..def.end], "cavity");
        assert_eq!(def.start, text.find("cavity").unwrap());
    }

    #[test]
    fn definitions_of_locals_and_the_outline() {
        let text = "fn f(a: length, b: length = 1 mm) -> length = a + b\n\
                    let s = sum(i in 0..3) i * 1 mm\n\
                    region r = box(min: [0, 0, 0] mm, max: [1, 1, 1] mm)\n\
                    sim {\n  let k = 2\n  damping = k * 1 /s\n  fix r\n}\n";
        let a = Analysis::new(text);
        let def_of = |needle: &str, skip: usize| {
            let at = text.match_indices(needle).nth(skip).unwrap().0;
            let d = a.definition(at).expect(needle);
            (d.start, &text[d.start..d.end])
        };
        // The fn parameter `a` in the body, the reduction variable, the sim let, the region.
        assert_eq!(def_of("a + b", 0), (text.find("a:").unwrap(), "a"));
        assert_eq!(def_of("b\n", 0), (text.find("b:").unwrap(), "b"));
        assert_eq!(def_of("i * 1", 0), (text.find("i in").unwrap(), "i"));
        assert_eq!(def_of("k * 1", 0), (text.find("k = 2").unwrap(), "k"));
        assert_eq!(def_of("r\n}", 0), (text.find("r = box").unwrap(), "r"));
        let h = a.hover(text.find("a + b").unwrap()).unwrap().0;
        assert!(
            h.contains("a: length [m]") && h.contains("parameter of `f`"),
            "{h}"
        );
        let outline: Vec<(String, &str, usize)> = a
            .symbols()
            .into_iter()
            .map(|s| (s.name, s.kind, s.children.len()))
            .collect();
        assert_eq!(
            outline,
            [
                ("f".to_string(), "fn", 0),
                ("s".to_string(), "let", 0),
                ("r".to_string(), "region", 0),
                ("sim".to_string(), "sim", 1)
            ]
        );
        // While the script does not parse, declarations are still found.
        let broken = format!("{text}let oops = (\n");
        let b = Analysis::new(&broken);
        assert!(b.script.is_none());
        let r_use = broken.find("fix r").unwrap() + 4;
        assert_eq!(
            b.definition(r_use),
            Some(Span::new(
                broken.find("r = box").unwrap(),
                broken.find("r = box").unwrap() + 1
            ))
        );
        assert!(b.symbols().iter().any(|s| s.name == "oops"));
        assert!(b.hover(r_use).unwrap().0.contains("region r = box"));
    }

    #[test]
    fn completion_contexts() {
        let kw = |text: &str| -> Vec<String> {
            Analysis::new(text)
                .completions(text.len())
                .into_iter()
                .map(|c| c.label)
                .collect()
        };
        assert!(kw("mat").contains(&"material".to_string()));
        assert!(kw("let a = 3 k").contains(&"kPa".to_string()));
        assert!(kw("let a = [1, 2] m").contains(&"mm".to_string()));
        assert!(!kw("let a = x[1] m").contains(&"mm".to_string()));
        assert!(kw("let a = 8 /").contains(&"s".to_string()));
        assert!(kw("let a = 1070 kg/m").contains(&"mm".to_string()));
        assert!(!kw("let a = 8 / s").contains(&"ms".to_string()));
        assert!(!kw("let a = 8\n  m").contains(&"mm".to_string()));
        assert!(kw("sim {\n  da").contains(&"damping".to_string()));
        assert!(kw("optimize p with adam(lr: 0.1) {\n  ").contains(&"gradient_scale".to_string()));
        assert!(kw("param p: pre").contains(&"pressure".to_string()));
        assert!(kw("let a = adam(").contains(&"beta1".to_string()));
        assert!(kw("let a = yeoh(c10: 1 kPa, ").contains(&"density".to_string()));
        let names = kw("param pmax: pressure = 1 kPa\nlet b = 2 * pm");
        assert!(names.contains(&"pmax".to_string()), "{names:?}");
        assert!(kw("let b = sq").contains(&"sqrt".to_string()));
        let decls = "chamber ch = surface(b, \"c\")\nregion r = box(min: [0, 0, 0] mm, max: [1, 1, 1] mm)\nparam p: pressure = 1 kPa\nmaterial m = neo_hookean(mu: 1 kPa, kappa: 1 MPa, density: 1 kg/m^3)\nelements e = tagged(b, 1)\n";
        let names = |tail: &str| kw(&format!("{decls}{tail}"));
        assert_eq!(names("sim {\n  pressure "), ["ch"]);
        assert_eq!(names("sim {\n  fix "), ["r"]);
        assert_eq!(names("sim {\n  fix r, "), ["r"]);
        assert_eq!(names("sim {\n  use "), ["m"]);
        assert_eq!(names("sim {\n  use m in "), ["e"]);
        assert_eq!(names("optimize "), ["p"]);
        assert!(names("sim {\n  pressure ch = ").contains(&"p".to_string()));
    }

    #[test]
    fn never_panics_on_odd_text() {
        for text in [
            "",
            "\"",
            "3 /",
            "[",
            "]] m",
            "µ",
            "1 µm",
            "let x = 3 kPa ^",
            "fn f(",
            "sim { let",
            "\u{feff}",
            "1e",
            "..",
            "3 m^-",
        ] {
            let a = Analysis::new(text);
            for o in 0..=text.len() + 1 {
                let _ = a.hover(o);
                let _ = a.definition(o);
                let _ = a.completions(o);
                let _ = a.references(o);
            }
            let _ = a.symbols();
        }
    }
}

/// The editor files in lang-spec/editors must know every name the compiler knows.
#[cfg(test)]
mod grammar_sync {
    use super::*;
    use std::collections::HashSet;

    fn read(rel: &str) -> String {
        let path = format!("{}/../{rel}", env!("CARGO_MANIFEST_DIR"));
        std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{path}: {e}"))
    }

    /// Words of every `(a|b|c)` alternation in the grammar's regexes.
    fn grammar_words() -> HashSet<String> {
        let g: serde_json::Value = serde_json::from_str(&read(
            "lang-spec/editors/vscode/syntaxes/soft.tmLanguage.json",
        ))
        .expect("the grammar is JSON");
        let mut regexes = Vec::new();
        let mut stack = vec![&g];
        while let Some(v) = stack.pop() {
            match v {
                serde_json::Value::Object(m) => {
                    for (k, v) in m {
                        if (k == "match" || k == "begin") && v.is_string() {
                            regexes.push(v.as_str().unwrap().to_string());
                        }
                        stack.push(v);
                    }
                }
                serde_json::Value::Array(a) => stack.extend(a),
                _ => {}
            }
        }
        let mut words = HashSet::new();
        for r in regexes {
            for part in r.split('(').skip(1) {
                let Some(inner) = part.split(')').next() else {
                    continue;
                };
                if inner.contains('|')
                    && inner
                        .chars()
                        .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '|')
                {
                    words.extend(inner.split('|').map(str::to_string));
                }
            }
        }
        words
    }

    #[test]
    fn keywords_match_the_pest_grammar() {
        let pest = read("compiler/src/front/soft.pest");
        let start = pest.find("keyword = @{").unwrap();
        let block = &pest[start..start + pest[start..].find("~ !ident_char").unwrap()];
        let mut from_pest: Vec<&str> = block.split('"').skip(1).step_by(2).collect();
        let mut ours: Vec<&str> = KEYWORDS.iter().map(|(k, _)| *k).collect();
        from_pest.sort();
        ours.sort();
        assert_eq!(ours, from_pest);
    }

    #[test]
    fn the_textmate_grammar_knows_every_built_in_name() {
        let words = grammar_words();
        let mut names: Vec<String> = Vec::new();
        names.extend(sema::FUNCTIONS.iter().map(|s| s.to_string()));
        names.extend(sema::CONSTANTS.iter().map(|(s, _)| s.to_string()));
        names.extend(sema::RESERVED_NAMES.iter().map(|s| s.to_string()));
        names.extend(units::NAMED_DIMS.iter().map(|(s, _)| s.to_string()));
        names.extend(KEYWORDS.iter().map(|(s, _)| s.to_string()));
        names.extend(prelude_signatures().into_iter().map(|(n, _)| n));
        names.extend(REDUCTIONS.iter().map(|s| s.to_string()));
        let missing: Vec<&String> = names.iter().filter(|n| !words.contains(*n)).collect();
        assert!(
            missing.is_empty(),
            "lang-spec/editors/vscode/syntaxes/soft.tmLanguage.json lacks {missing:?}"
        );
    }
}
