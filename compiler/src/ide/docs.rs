//! Documentation texts of the keywords, built-in functions, constants, reserved names and settings.

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
        "the simulation block: settings, `fix`, `pressure`, `contact`, `use`, `output`",
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
    (
        "with",
        "`optimize … with OPTIMIZER`; `contact BODY with OBSTACLE`",
    ),
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
    (
        "obstacle",
        "declares a rigid obstacle: `obstacle NAME = plane(point: …, normal: …)` or \
         `sphere(center: …, radius: …)`",
    ),
    (
        "contact",
        "`contact BODY with OBSTACLE (gap: …, stiffness: …, friction: …)` in `sim`: barrier \
         contact of the mesh (or a node set's surface nodes) with an obstacle, with Coulomb \
         friction in dynamic runs",
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

/// Every function of [`crate::sema::FUNCTIONS`], documented (a test checks the two agree).
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
        "stretch",
        "stretch(element) -> dimensionless",
        ["element"],
        "The largest principal stretch of an element bound by a reduction over an element set, \
         at the state the loss reads (√ of the largest eigenvalue of FᵀF): a strain limit as a \
         loss term, `sum(e in walls) max(stretch(e) - 1.3, 0)^2`."
    ),
    b!(
        "force",
        "force(obstacle, on: node set) -> force[3]",
        ["obstacle", "on"],
        "The total force (N) the obstacle exerts on the bodies in contact with it at the state \
         the loss reads, summed over their contact nodes: a loss term (`force(table).z`). \
         `on:` (optional) sums over the contact nodes of one node set only (one finger's grip: \
         `force(object, on: left).x`)."
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
        "Index ⌊t / width⌋ of the current window (windowed parameters); a t on a boundary is in the window it starts."
    ),
    b!(
        "step",
        "step(t: time, at: time) -> dimensionless",
        ["t", "at"],
        "0 before `at`, 1 from `at` on."
    ),
    b!(
        "load",
        "load(path: string, unit?: length, order?: int) -> mesh",
        ["path", "unit", "order"],
        "Reads a mesh file (.msh, .vtk, .vtu, tetgen, .inp); `unit` is the length of one file unit (default 1 mm); `order: 2` simulates quadratic (10-node) tetrahedra, adding a straight-sided mid-edge node on every edge of a linear mesh."
    ),
    b!(
        "box",
        "box(min: length[3], max: length[3]) -> region | obstacle",
        ["min", "max"],
        "Axis-aligned box: a region; in an `obstacle` declaration a rigid box the body stays outside of (its arguments may then follow `t` or params)."
    ),
    b!(
        "sphere",
        "sphere(center: length[3], radius: length) -> region | obstacle",
        ["center", "radius"],
        "Ball: a region; in an `obstacle` declaration a rigid ball the body stays outside of (its arguments may then follow `t` or params)."
    ),
    b!(
        "cylinder",
        "cylinder(start: length[3], end: length[3], radius: length) -> region | obstacle",
        ["start", "end", "radius"],
        "Capped cylinder between two points: a region; in an `obstacle` declaration a rigid one the body stays outside of (its arguments may then follow `t` or params)."
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

/// The shapes of an `obstacle` declaration that are not also built-in functions (`sphere` is
/// one: [`BUILTIN_DOCS`] documents both of its uses). Their arguments may follow `t` or params.
pub const OBSTACLE_SHAPE_DOCS: &[BuiltinDoc] = &[b!(
    "plane",
    "plane(point: length[3], normal: 1[3]) -> obstacle",
    ["point", "normal"],
    "A rigid plane through `point`; the half-space behind `normal` (normalized) is solid, the \
     body stays on the side the normal points to. Only in an `obstacle` declaration."
)];

/// The arguments of the sim statement `contact BODY with OBSTACLE (…)`.
pub const CONTACT_DOC: BuiltinDoc = b!(
    "contact",
    "contact BODY with OBSTACLE (gap: length, stiffness?: pressure, friction?: 1)",
    ["gap", "stiffness", "friction"],
    "Barrier contact: each boundary node of BODY within `gap` (a positive constant) of the \
     obstacle is pushed away by a log barrier that grows without bound at the obstacle; \
     `stiffness` (a positive constant, default about the body's Young's modulus) scales it. In \
     every integrator (explicit steps solve it implicitly per node). `friction`: Coulomb's \
     coefficient (a constant ≥ 0; dynamic runs only for now), frictionless without it."
);

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
        "implicit_euler",
        "`integrator`: backward Euler, a Newton solve per step (steps far above the explicit limit)",
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
pub const REDUCTIONS: &[&str] = &["sum", "mean", "area_mean", "max", "min"];

/// Settings with a one-line description.
pub(super) fn setting_doc(name: &str) -> &'static str {
    match name {
        "dt" => "time step: a time, `auto` or `auto(safety: S)`",
        "steps" => "number of time steps (integer)",
        "duration" => "simulated time",
        "integrator" => "`semi_implicit_euler`, `implicit_euler` or `quasi_static`",
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
