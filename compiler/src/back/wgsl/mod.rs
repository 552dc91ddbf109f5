//! The WGSL backend: a module's kernels as one WGSL compute module, run by wgpu on any GPU
//! (Vulkan, Metal, DX12) or on Mesa's software Vulkan driver (lavapipe).
//!
//! One WGSL module per IR module, one `@compute` entry point per kernel (named after it). One
//! module rather than one per kernel because the kernels of a scene share their buffers: each
//! buffer is declared once, under its own name, with one binding number, so the generated file
//! reads like the scene's data flow and is a single golden file per example. Each entry point
//! statically uses only its own bindings, so a pipeline's (automatically derived) layout holds
//! just what that kernel touches; [`WgslKernel::bindings`] lists them for the runtime.
//!
//! Layout, all in bind group 0:
//! - binding `b` for buffer `b` of the module ([`BufferId`] order): `array<real>` holding
//!   `len(domain) × width` values, entity-major. Buffers some kernel stores to are
//!   `read_write`, the others `read`.
//! - then the connectivity as `array<u32>`: `elem_conn` (4 nodes per element), `tri_conn` (3 per
//!   triangle), and the node CSR lists `node_elem_offsets`/`node_elem_slots` and
//!   `node_tri_offsets`/`node_tri_slots` (each incidence `(entity, corner)` as the one index
//!   `entity · corners + corner`, [`crate::back::NodeCsr::slots`]), as
//!   [`crate::back::Topology`] builds them. A gather of per-corner values then reads
//!   `buffer[stride · slot + component]`: one index load per incidence, no multiply chain.
//! - then one uniform block per kernel, `launch_<kernel>`: the first entity `begin`, the entity
//!   `count` of the launch, and the kernel's uniforms (`t`, `dt`, params, …) in the order of
//!   [`WgslKernel::uniforms`], as `real` fields. The runtime binds it with a dynamic offset, so
//!   many launches with different uniforms are recorded into one submission.
//!
//! Entity `i` of a launch is `begin + i`, with `i` from the global invocation id (x, plus y
//! rows of `num_workgroups.x × softc_wg` when a launch needs more than 65,535
//! workgroups). Gathers loop over the node's CSR range in list order, one accumulator per
//! gathered value starting at 0: the same order as the interpreter, no atomics.
//!
//! Precision: `alias real = f32;` (default) or `f64` (needs wgpu's `SHADER_F64`, naga's
//! `FLOAT64`). In f32, constants are rounded to f32. SPIR-V's GLSL.std.450 `exp`, `log`, `pow`,
//! `sin`, `cos`, `tan`, `tanh` take only 16/32-bit floats, so in f64 these are software
//! functions emitted into the module (`softc_exp`, …: range reduction and polynomials,
//! within a few ulps for arguments of moderate size: trigonometric reduction is accurate for
//! `|x| < 2^20`). `pow` follows Rust's `powf` for negative bases with integral exponents and
//! for zero bases in both precisions.
//!
//! ```
//! use softc_compiler::back::{Precision, wgsl};
//! use softc_compiler::ir::{ArgSource, Domain, KernelBuilder, Module};
//!
//! let mut m = Module::default();
//! let x = m.buffer("x", Domain::Node, 1, "");
//! let y = m.buffer("y", Domain::Element, 1, "");
//! let mut k = KernelBuilder::new("demo", Domain::Element, "doc example");
//! let a = k.load(ArgSource::Corner { buffer: x, corner: 0, component: 0 });
//! let s = k.uniform("scale");
//! let v = k.b.mul(s, a);
//! k.store(y, 0, v);
//! m.push_kernel(k.finish());
//!
//! let w = wgsl::emit(&m, Precision::F32).unwrap();
//! assert!(w.source.contains("@compute @workgroup_size(softc_wg)\nfn demo("));
//! assert_eq!(w.kernels[0].uniforms, [m.uniform_named("scale").unwrap()]);
//! wgsl::validate(&w.source, Precision::F32).unwrap();
//! ```

mod math;
mod rows;

pub use rows::RowLayout;

pub use crate::back::Precision;
use crate::ir::{
    ArgSource, BinOp, BufferId, CmpOp, Domain, Inst, Kernel, Module, UnOp, UniformId, V,
};
use std::collections::BTreeSet;
use std::fmt::Write as _;

/// Invocations per workgroup of every entry point unless the runtime sets the
/// pipeline-overridable constant [`WORKGROUP_OVERRIDE`] when it makes a kernel's pipeline.
pub const WORKGROUP_SIZE: u32 = 128;

/// The name of the override (WGSL `override`) that sizes every entry point's workgroup: one
/// module serves any size, chosen per pipeline.
pub const WORKGROUP_OVERRIDE: &str = "softc_wg";

/// The component letter of lane `l` of a `vec4`.
fn lane_name(l: u32) -> &'static str {
    ["x", "y", "z", "w"][l as usize & 3]
}

/// Connectivity arrays a kernel may read.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum TopoArray {
    ElemConn,
    TriConn,
    NodeElemOffsets,
    NodeElemSlots,
    NodeTriOffsets,
    NodeTriSlots,
}

impl TopoArray {
    pub const ALL: [TopoArray; 6] = [
        TopoArray::ElemConn,
        TopoArray::TriConn,
        TopoArray::NodeElemOffsets,
        TopoArray::NodeElemSlots,
        TopoArray::NodeTriOffsets,
        TopoArray::NodeTriSlots,
    ];

    /// Its name in the generated code.
    pub fn name(self) -> &'static str {
        match self {
            TopoArray::ElemConn => "elem_conn",
            TopoArray::TriConn => "tri_conn",
            TopoArray::NodeElemOffsets => "node_elem_offsets",
            TopoArray::NodeElemSlots => "node_elem_slots",
            TopoArray::NodeTriOffsets => "node_tri_offsets",
            TopoArray::NodeTriSlots => "node_tri_slots",
        }
    }

    fn index(self) -> u32 {
        TopoArray::ALL.iter().position(|t| *t == self).unwrap_or(0) as u32
    }
}

/// What a binding of bind group 0 holds.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Binding {
    /// A buffer of the module (`array<real>`), `read_write` when some kernel stores to it.
    Buffer { id: BufferId, writable: bool },
    /// A connectivity array (`array<u32>`).
    Topo(TopoArray),
    /// The kernel's launch block (uniform, bound with a dynamic offset).
    Launch,
    /// The launch-block table ([`LaunchMode::Table`]): a read-only storage array of launch
    /// blocks, the row in the immediate `softc_row`.
    LaunchTable,
}

/// Where a kernel finds its launch block.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum LaunchMode {
    /// A uniform block bound at a dynamic offset per dispatch: any adapter.
    Uniform,
    /// A row of a read-only storage array of launch blocks (`array<Launch_k>`), its index in
    /// an immediate (push constant) set per dispatch: a dispatch changes no binding, so a time
    /// loop binds each kernel's group once. Needs wgpu's `IMMEDIATES` (4 bytes).
    Table,
}

/// Bytes of the immediate data a [`LaunchMode::Table`] module reads (the row, a `u32`).
pub const IMMEDIATE_BYTES: u32 = 4;

/// One kernel's entry point.
#[derive(Clone, Debug, PartialEq)]
pub struct WgslKernel {
    pub name: String,
    /// The entry point's name in the module.
    pub entry: String,
    pub domain: Domain,
    /// The uniforms of the launch block, in its field order (after `begin` and `count`).
    pub uniforms: Vec<UniformId>,
    /// `(binding number, what it holds)` for every binding the entry point uses.
    pub bindings: Vec<(u32, Binding)>,
    /// Bytes of the launch block (`begin`, `count`, in a batch `scene` and the three entity
    /// counts, then one `real` per uniform).
    pub launch_size: u64,
    /// Byte offset of the first uniform in the launch block.
    pub uniform_offset: u64,
    /// Storage buffers the entry point binds (buffers, connectivity and, in
    /// [`LaunchMode::Table`], the launch table).
    pub storage_buffers: u32,
    /// Buffers the kernel stores to.
    pub stores: Vec<BufferId>,
    /// The module's kernels this entry point runs: itself, or the parts of a fused entry
    /// ([`emit_fused`]), one after another over the invocations, each with its own launch
    /// block.
    pub parts: Vec<usize>,
}

impl WgslKernel {
    /// Bytes between consecutive launch blocks of this kernel: a batch's scenes, and rows of a
    /// [`LaunchMode::Table`] (whose struct is 16-byte aligned, so its array stride is this).
    pub fn launch_stride(&self) -> u64 {
        self.launch_size.div_ceil(16) * 16
    }
}

/// A module's kernels as WGSL.
#[derive(Clone, Debug, PartialEq)]
pub struct WgslModule {
    pub precision: Precision,
    /// Scenes per launch of a batched module ([`emit_batched`]), `None` for one scene.
    pub batch: Option<u32>,
    /// Where the kernels find their launch blocks.
    pub launch: LaunchMode,
    pub source: String,
    pub kernels: Vec<WgslKernel>,
}

impl WgslModule {
    pub fn kernel_index(&self, name: &str) -> Option<usize> {
        self.kernels.iter().position(|k| k.name == name)
    }
}

/// Identifiers WGSL reserves or defines (keywords, reserved words, predeclared types and
/// functions a name could shadow); a script name equal to one of them gets a `_` suffix.
const RESERVED: &[&str] = &[
    "alias",
    "array",
    "atomic",
    "bitcast",
    "bool",
    "break",
    "case",
    "const",
    "const_assert",
    "continue",
    "continuing",
    "default",
    "diagnostic",
    "discard",
    "else",
    "enable",
    "f16",
    "f32",
    "f64",
    "false",
    "fn",
    "for",
    "if",
    "i32",
    "let",
    "loop",
    "mat2x2",
    "mat3x3",
    "mat4x4",
    "override",
    "ptr",
    "requires",
    "return",
    "sampler",
    "struct",
    "switch",
    "true",
    "u32",
    "var",
    "vec2",
    "vec3",
    "vec4",
    "while",
    "NULL",
    "Self",
    "abstract",
    "active",
    "alignas",
    "alignof",
    "as",
    "asm",
    "asm_fragment",
    "async",
    "attribute",
    "auto",
    "await",
    "become",
    "binding_array",
    "cast",
    "catch",
    "class",
    "co_await",
    "co_return",
    "co_yield",
    "coherent",
    "column_major",
    "common",
    "compile",
    "compile_fragment",
    "concept",
    "const_cast",
    "consteval",
    "constexpr",
    "constinit",
    "crate",
    "debugger",
    "decltype",
    "delete",
    "demote",
    "demote_to_helper",
    "do",
    "dynamic_cast",
    "enum",
    "explicit",
    "export",
    "extends",
    "extern",
    "external",
    "fallthrough",
    "filter",
    "final",
    "finally",
    "friend",
    "from",
    "fxgroup",
    "get",
    "goto",
    "groupshared",
    "highp",
    "impl",
    "implements",
    "import",
    "inline",
    "instanceof",
    "interface",
    "layout",
    "lowp",
    "macro",
    "macro_rules",
    "match",
    "mediump",
    "meta",
    "mod",
    "module",
    "move",
    "mut",
    "mutable",
    "namespace",
    "new",
    "nil",
    "noexcept",
    "noinline",
    "nointerpolation",
    "noperspective",
    "null",
    "nullptr",
    "of",
    "operator",
    "package",
    "packoffset",
    "partition",
    "pass",
    "patch",
    "pixelfragment",
    "precise",
    "precision",
    "premerge",
    "priv",
    "protected",
    "pub",
    "public",
    "readonly",
    "ref",
    "regardless",
    "register",
    "reinterpret_cast",
    "require",
    "resource",
    "restrict",
    "self",
    "set",
    "shared",
    "sizeof",
    "smooth",
    "snorm",
    "static",
    "static_assert",
    "static_cast",
    "std",
    "subroutine",
    "super",
    "target",
    "template",
    "this",
    "thread_local",
    "throw",
    "trait",
    "try",
    "type",
    "typedef",
    "typeid",
    "typename",
    "typeof",
    "union",
    "unless",
    "unorm",
    "unsafe",
    "unsized",
    "use",
    "using",
    "varying",
    "virtual",
    "volatile",
    "wgsl",
    "where",
    "with",
    "writeonly",
    "yield",
    "real",
    "main",
    "abs",
    "exp",
    "log",
    "pow",
    "sin",
    "cos",
    "tan",
    "tanh",
    "sqrt",
    "floor",
    "ceil",
    "min",
    "max",
    "select",
    "round",
    "ldexp",
    "frexp",
    "fract",
    "sign",
    "uniform",
    "storage",
    "read",
    "read_write",
    "function",
    "private",
    "workgroup",
];

/// A valid WGSL identifier for a script name, distinct from every name in `taken`; added to it.
fn ident(name: &str, taken: &mut BTreeSet<String>) -> String {
    let mut s: String = name
        .chars()
        .map(|c| if c.is_ascii_alphanumeric() { c } else { '_' })
        .collect();
    if s.is_empty() || s.starts_with(|c: char| c.is_ascii_digit()) {
        s.insert(0, 'k');
    }
    if s.starts_with("__") {
        s.insert(0, 'k');
    }
    // Names the generated code uses for locals, helpers and the launch blocks stay free.
    let local = |s: &str| {
        s == "_"
            || s.starts_with("softc_")
            || s.starts_with("launch_")
            || [
                "v", "arg", "n", "g", "e", "i", "j", "gid", "nwg", "ent", "corner",
            ]
            .iter()
            .any(|p| {
                s.strip_prefix(p)
                    .is_some_and(|r| r.is_empty() || r.chars().all(|c| c.is_ascii_digit()))
            })
    };
    if RESERVED.contains(&s.as_str()) || local(&s) {
        s.push('_');
    }
    while taken.contains(&s) || RESERVED.contains(&s.as_str()) {
        s.push('_');
    }
    taken.insert(s.clone());
    s
}

/// A constant as a `real` literal (f32 constants are rounded to f32 first, so the literal is
/// exactly the value the f32 code computes with).
fn literal(c: f64, p: Precision) -> String {
    let (finite, text) = match p {
        Precision::F32 => {
            let c = c as f32;
            (c.is_finite(), format!("{c:?}f"))
        }
        Precision::F64 => (c.is_finite(), format!("{c:?}lf")),
    };
    if finite {
        return text;
    }
    // WGSL has no literal for infinities or NaN: computed at run time.
    if c.is_nan() {
        "softc_nan()".into()
    } else if c > 0.0 {
        "softc_inf()".into()
    } else {
        "(-softc_inf())".into()
    }
}

/// Emit the WGSL module of `module`. Errors describe a kernel that does not fit its module
/// (an access outside a buffer's declared layout), as the Cranelift backend checks them.
/// The module's kernels for one scene.
pub fn emit(module: &Module, precision: Precision) -> Result<WgslModule, String> {
    emit_with(module, precision, None, LaunchMode::Uniform)
}

/// The module's kernels for `batch` scenes (`None`: one, as [`emit`]; `Some(n)`: as
/// [`emit_batched`]) with their launch blocks where `launch` says.
pub fn emit_for(
    module: &Module,
    precision: Precision,
    batch: Option<u32>,
    launch: LaunchMode,
) -> Result<WgslModule, String> {
    if batch == Some(0) {
        return Err("a batch needs at least one scene".into());
    }
    emit_with(module, precision, batch, launch)
}

/// The module's kernels for a batch of up to `scenes` scenes that share a mesh and differ in
/// their uniforms (a controller's targets, a sweep's pressures): one dispatch runs a kernel for
/// every scene of the batch. Each buffer holds the scenes one after another (scene `s`'s entity
/// `e` is entity `s × count + e`); the launch binding is an array of `scenes` launch blocks,
/// one per workgroup row `z`, each naming its scene and the entity counts; connectivity is
/// shared.
pub fn emit_batched(
    module: &Module,
    precision: Precision,
    scenes: u32,
) -> Result<WgslModule, String> {
    if scenes == 0 {
        return Err("a batch needs at least one scene".into());
    }
    emit_with(module, precision, Some(scenes), LaunchMode::Uniform)
}

/// Whether kernels `a` and `b` may run in one dispatch in either order: neither stores to a
/// buffer the other reads or stores to.
pub fn independent(module: &Module, a: usize, b: usize) -> bool {
    let touches = |k: &Kernel| -> BTreeSet<u32> {
        let mut t: BTreeSet<u32> = k.stores.iter().map(|s| s.buffer.0).collect();
        for arg in &k.args {
            match arg {
                ArgSource::Own { buffer, .. }
                | ArgSource::Corner { buffer, .. }
                | ArgSource::Gather { buffer, .. } => {
                    t.insert(buffer.0);
                }
                ArgSource::Uniform(_) => {}
            }
        }
        t
    };
    let (ka, kb) = (&module.kernels[a], &module.kernels[b]);
    let stores = |k: &Kernel| {
        k.stores
            .iter()
            .map(|s| s.buffer.0)
            .collect::<BTreeSet<u32>>()
    };
    stores(ka).is_disjoint(&touches(kb)) && stores(kb).is_disjoint(&touches(ka))
}

/// The module's kernels for one scene ([`emit`]) and, after them, one fused entry point per
/// group of `groups`: the group's kernels (mutually [`independent`]) in one dispatch, the
/// invocations running the first kernel's entities, then the next's, each reading its own
/// launch block (bound at its own dynamic offset). The arithmetic of each entity is the
/// kernel's own, so results are the same bits as launching the kernels one by one; a step
/// saves a dispatch (~6 µs of GPU time on an H100) per kernel fused.
pub fn emit_fused(
    module: &Module,
    precision: Precision,
    groups: &[Vec<usize>],
) -> Result<WgslModule, String> {
    let mut m = emit_with(module, precision, None, LaunchMode::Uniform)?;
    let n = m.kernels.len();
    for g in groups {
        if g.len() < 2 || g.iter().any(|&k| k >= n) {
            return Err(format!("cannot fuse kernels {g:?} of {n}"));
        }
        for (i, &a) in g.iter().enumerate() {
            for &b in &g[i + 1..] {
                if a == b || !independent(module, a, b) {
                    return Err(format!(
                        "kernels `{}` and `{}` depend on each other: they cannot share a dispatch",
                        module.kernels[a].name, module.kernels[b].name
                    ));
                }
            }
        }
    }
    let nb = module.buffers.len() as u32;
    let launch_binding = |k: usize| nb + TopoArray::ALL.len() as u32 + k as u32;
    let mut parts: BTreeSet<usize> = BTreeSet::new();
    for g in groups {
        parts.extend(g.iter().copied());
    }
    // Each part's body as a function of its invocation index.
    let mut taken: BTreeSet<String> = BTreeSet::new();
    let buf_names: Vec<String> = module
        .buffers
        .iter()
        .map(|b| ident(&b.name, &mut taken))
        .collect();
    let mut helpers = math::Helpers::default();
    let mut out = String::new();
    let w = &mut out;
    let _ = writeln!(
        w,
        "\n// ======== fused dispatches: kernels with no data between them, one after another"
    );
    for &ki in &parts {
        let k = &module.kernels[ki];
        let entry = &m.kernels[ki].entry;
        let uniform_ids = k.uniforms();
        let mut fields = BTreeSet::new();
        let field_names: Vec<String> = uniform_ids
            .iter()
            .map(|&u| ident(module.uniform_name(u), &mut fields))
            .collect();
        let launch = format!("launch_{entry}");
        let _ = writeln!(w, "\nfn softc_part_{entry}(i: u32) {{");
        let _ = writeln!(w, "    let e = {launch}.begin + i;");
        emit_body(
            w,
            module,
            k,
            &buf_names,
            &launch,
            false,
            &uniform_ids,
            &field_names,
            precision,
            &mut helpers,
        );
        let _ = writeln!(w, "}}");
    }
    for g in groups {
        let mut g = g.clone();
        g.sort_unstable();
        let entry = format!(
            "softc_fused_{}",
            g.iter()
                .map(|&k| m.kernels[k].entry.as_str())
                .collect::<Vec<_>>()
                .join("_")
        );
        let _ = writeln!(w, "\n@compute @workgroup_size({WORKGROUP_OVERRIDE})");
        let _ = writeln!(
            w,
            "fn {entry}(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {{"
        );
        let _ = writeln!(
            w,
            "    var i = gid.x + gid.y * nwg.x * {WORKGROUP_OVERRIDE};"
        );
        for (j, &k) in g.iter().enumerate() {
            let part = &m.kernels[k].entry;
            let launch = format!("launch_{part}");
            let _ = writeln!(w, "    if (i < {launch}.count) {{");
            let _ = writeln!(w, "        softc_part_{part}(i);");
            let _ = writeln!(w, "        return;");
            let _ = writeln!(w, "    }}");
            if j + 1 < g.len() {
                let _ = writeln!(w, "    i -= {launch}.count;");
            }
        }
        let _ = writeln!(w, "}}");
        let mut bindings: Vec<(u32, Binding)> = Vec::new();
        for &k in &g {
            for b in &m.kernels[k].bindings {
                if !bindings.contains(b) {
                    bindings.push(*b);
                }
            }
        }
        bindings.sort_by_key(|b| b.0);
        debug_assert!(
            g.iter()
                .all(|&k| bindings.iter().any(|b| b.0 == launch_binding(k)))
        );
        let storage_buffers = bindings
            .iter()
            .filter(|b| !matches!(b.1, Binding::Launch))
            .count() as u32;
        let mut stores: Vec<BufferId> = g
            .iter()
            .flat_map(|&k| m.kernels[k].stores.iter().copied())
            .collect();
        stores.sort();
        stores.dedup();
        let first = &m.kernels[g[0]];
        m.kernels.push(WgslKernel {
            name: entry.clone(),
            entry,
            domain: first.domain,
            uniforms: Vec::new(),
            bindings,
            launch_size: 0,
            uniform_offset: 0,
            storage_buffers,
            stores,
            parts: g,
        });
    }
    let h = helpers.source(precision);
    // Helpers the parts use are in the module already (their kernels use them).
    let _ = h;
    m.source.push_str(&out);
    Ok(m)
}

fn emit_with(
    module: &Module,
    precision: Precision,
    batch: Option<u32>,
    launch_mode: LaunchMode,
) -> Result<WgslModule, String> {
    let table = launch_mode == LaunchMode::Table;
    crate::ir::valid::validate_module(module)?;
    let nb = module.buffers.len() as u32;
    let topo_binding = |t: TopoArray| nb + t.index();
    let launch_binding = |k: usize| nb + TopoArray::ALL.len() as u32 + k as u32;

    let mut taken = BTreeSet::new();
    let buf_names: Vec<String> = module
        .buffers
        .iter()
        .map(|b| ident(&b.name, &mut taken))
        .collect();
    for t in TopoArray::ALL {
        taken.insert(t.name().to_string());
    }
    taken.insert("SoftcRow".to_string());
    let entries: Vec<String> = module
        .kernels
        .iter()
        .map(|k| ident(&k.name, &mut taken))
        .collect();

    let written: BTreeSet<u32> = module
        .kernels
        .iter()
        .flat_map(|k| k.stores.iter().map(|s| s.buffer.0))
        .collect();

    let real = match precision {
        Precision::F32 => "f32",
        Precision::F64 => "f64",
    };
    let mut out = String::new();
    let w = &mut out;
    let _ = writeln!(w, "// Generated by softc from the kernel IR: do not edit.");
    let _ = writeln!(
        w,
        "// {} kernels, {} buffers; one entry point per kernel, workgroups of {WORKGROUP_OVERRIDE} invocations.",
        module.kernels.len(),
        module.buffers.len()
    );
    if let Some(n) = batch {
        let _ = writeln!(
            w,
            "// A batch of up to {n} scenes: buffers hold the scenes one after another, workgroup \
             row z runs the scene its launch block names."
        );
    }
    let _ = writeln!(w, "\nalias real = {real};\n");
    let _ = writeln!(
        w,
        "// Invocations per workgroup, set per pipeline by the runtime.\noverride {WORKGROUP_OVERRIDE}: u32 = {WORKGROUP_SIZE}u;\n"
    );
    if table {
        let _ = writeln!(
            w,
            "// The launch blocks are rows of each kernel's launch table; a dispatch's row comes as \
             an immediate."
        );
        let _ = writeln!(w, "struct SoftcRow {{\n    row: u32,\n}}");
        let _ = writeln!(w, "var<immediate> softc_row: SoftcRow;\n");
    }
    let _ = writeln!(
        w,
        "// ---- buffers: len(domain) x width values, entity-major"
    );
    for (i, b) in module.buffers.iter().enumerate() {
        let access = if written.contains(&(i as u32)) {
            "read_write"
        } else {
            "read"
        };
        let doc = if b.doc.is_empty() {
            String::new()
        } else {
            format!(": {}", b.doc)
        };
        let _ = writeln!(
            w,
            "// {} per {}, width {}{doc}",
            b.name,
            domain_word(b.domain),
            b.width
        );
        let ty = if RowLayout::of(b.width).is_vector() {
            "array<vec4<real>>"
        } else {
            "array<real>"
        };
        let _ = writeln!(
            w,
            "@group(0) @binding({i}) var<storage, {access}> {}: {ty};",
            buf_names[i]
        );
    }
    let _ = writeln!(w, "\n// ---- connectivity");
    let _ = writeln!(w, "// 4 nodes per element, 3 per chamber triangle");
    let _ = writeln!(
        w,
        "// node CSR lists: offsets (nodes + 1), slots: each incidence as entity * corners + corner"
    );
    for t in TopoArray::ALL {
        let _ = writeln!(
            w,
            "@group(0) @binding({}) var<storage, read> {}: array<u32>;",
            topo_binding(t),
            t.name()
        );
    }

    let mut helpers = math::Helpers::default();
    let mut kernels = Vec::new();
    let mut bodies = String::new();
    for (ki, k) in module.kernels.iter().enumerate() {
        let uniform_ids = k.uniforms();
        let uniforms: Vec<&str> = uniform_ids
            .iter()
            .map(|&u| module.uniform_name(u))
            .collect();
        let mut fields = BTreeSet::new();
        let field_names: Vec<String> = uniforms.iter().map(|u| ident(u, &mut fields)).collect();
        let launch = format!("launch_{}", entries[ki]);
        let struct_name = format!("Launch_{}", entries[ki]);
        let w = &mut bodies;
        let _ = writeln!(
            w,
            "\n// ======== kernel {} over {} (from {})",
            k.name,
            domain_word(k.domain),
            k.origin
        );
        let _ = writeln!(w, "struct {struct_name} {{");
        if batch.is_some() || table {
            // 16-byte alignment: uniform arrays need a stride that is a multiple of 16.
            let _ = writeln!(w, "    @align(16) begin: u32,");
            let _ = writeln!(w, "    count: u32,");
        }
        if batch.is_some() {
            let _ = writeln!(w, "    scene: u32,");
            let _ = writeln!(w, "    elements: u32,");
            let _ = writeln!(w, "    triangles: u32,");
            let _ = writeln!(w, "    nodes: u32,");
        } else if !table {
            let _ = writeln!(w, "    begin: u32,");
            let _ = writeln!(w, "    count: u32,");
        }
        for (f, u) in field_names.iter().zip(&uniforms) {
            if f == *u {
                let _ = writeln!(w, "    {f}: real,");
            } else {
                let _ = writeln!(w, "    {f}: real, // {u}");
            }
        }
        let _ = writeln!(w, "}}");
        let lb = launch_binding(ki);
        if table {
            let _ = writeln!(
                w,
                "@group(0) @binding({lb}) var<storage, read> {launch}: array<{struct_name}>;"
            );
        } else {
            let ty = match batch {
                Some(n) => format!("array<{struct_name}, {n}>"),
                None => struct_name.clone(),
            };
            let _ = writeln!(w, "@group(0) @binding({lb}) var<uniform> {launch}: {ty};");
        }

        // Bindings this entry uses.
        let mut used_bufs: BTreeSet<u32> = BTreeSet::new();
        let mut used_topo: BTreeSet<TopoArray> = BTreeSet::new();
        for a in &k.args {
            match a {
                ArgSource::Own { buffer, .. } => {
                    used_bufs.insert(buffer.0);
                }
                ArgSource::Corner { buffer, .. } => {
                    used_bufs.insert(buffer.0);
                    used_topo.insert(if k.domain == Domain::Element {
                        TopoArray::ElemConn
                    } else {
                        TopoArray::TriConn
                    });
                }
                ArgSource::Gather { buffer, over, .. } => {
                    used_bufs.insert(buffer.0);
                    if *over == Domain::Element {
                        used_topo.insert(TopoArray::NodeElemOffsets);
                        used_topo.insert(TopoArray::NodeElemSlots);
                    } else {
                        used_topo.insert(TopoArray::NodeTriOffsets);
                        used_topo.insert(TopoArray::NodeTriSlots);
                    }
                }
                ArgSource::Uniform(_) => {}
            }
        }
        used_bufs.extend(k.stores.iter().map(|s| s.buffer.0));
        let mut bindings: Vec<(u32, Binding)> = used_bufs
            .iter()
            .map(|&b| {
                (
                    b,
                    Binding::Buffer {
                        id: BufferId(b),
                        writable: written.contains(&b),
                    },
                )
            })
            .collect();
        bindings.extend(
            used_topo
                .iter()
                .map(|&t| (topo_binding(t), Binding::Topo(t))),
        );
        let storage_buffers = bindings.len() as u32 + u32::from(table);
        bindings.push((
            lb,
            if table {
                Binding::LaunchTable
            } else {
                Binding::Launch
            },
        ));

        let _ = writeln!(w, "\n@compute @workgroup_size({WORKGROUP_OVERRIDE})");
        let _ = writeln!(
            w,
            "fn {}(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {{",
            entries[ki]
        );
        let _ = writeln!(
            w,
            "    let i = gid.x + gid.y * nwg.x * {WORKGROUP_OVERRIDE};"
        );
        let block = match (batch.is_some(), table) {
            (true, true) => {
                let _ = writeln!(w, "    let l = &{launch}[softc_row.row + gid.z];");
                "(*l)".to_string()
            }
            (false, true) => {
                let _ = writeln!(w, "    let l = &{launch}[softc_row.row];");
                "(*l)".to_string()
            }
            (true, false) => {
                let _ = writeln!(w, "    let l = &{launch}[gid.z];");
                "(*l)".to_string()
            }
            (false, false) => launch.clone(),
        };
        let _ = writeln!(w, "    if (i >= {block}.count) {{");
        let _ = writeln!(w, "        return;");
        let _ = writeln!(w, "    }}");
        let _ = writeln!(w, "    let e = {block}.begin + i;");
        emit_body(
            w,
            module,
            k,
            &buf_names,
            &block,
            batch.is_some(),
            &uniform_ids,
            &field_names,
            precision,
            &mut helpers,
        );
        let _ = writeln!(w, "}}");

        let header: u64 = if batch.is_some() { 24 } else { 8 };
        let real = precision.size() as u64;
        let uniform_offset = header.div_ceil(real) * real;
        let size = uniform_offset + uniforms.len() as u64 * real;
        kernels.push(WgslKernel {
            name: k.name.clone(),
            entry: entries[ki].clone(),
            domain: k.domain,
            uniforms: uniform_ids,
            bindings,
            launch_size: size,
            uniform_offset,
            storage_buffers,
            stores: k
                .stores
                .iter()
                .map(|st| st.buffer)
                .collect::<BTreeSet<_>>()
                .into_iter()
                .collect(),
            parts: vec![ki],
        });
    }
    let h = helpers.source(precision);
    if !h.is_empty() {
        let _ = writeln!(out, "\n// ---- math helpers");
        out.push_str(&h);
    }
    out.push_str(&bodies);
    Ok(WgslModule {
        precision,
        batch,
        launch: launch_mode,
        source: out,
        kernels,
    })
}

fn domain_word(d: Domain) -> &'static str {
    match d {
        Domain::Element => "element",
        Domain::Triangle => "triangle",
        Domain::Node => "node",
        Domain::Single => "single",
    }
}

#[allow(clippy::too_many_arguments)]
fn emit_body(
    w: &mut String,
    module: &Module,
    k: &Kernel,
    buf_names: &[String],
    launch: &str,
    batched: bool,
    uniforms: &[UniformId],
    fields: &[String],
    p: Precision,
    helpers: &mut math::Helpers,
) {
    let width = |b: BufferId| module.buffers[b.0 as usize].width;
    let layout = |b: BufferId| RowLayout::of_buffer(module, b, batched);
    // The entities of each corner-major buffer the kernel touches (its rows' `vec4`s lie
    // `rows` apart).
    let mut touched: BTreeSet<u32> = k.stores.iter().map(|s| s.buffer.0).collect();
    for a in &k.args {
        if let ArgSource::Own { buffer, .. } | ArgSource::Gather { buffer, .. } = a {
            touched.insert(buffer.0);
        }
    }
    for &b in &touched {
        let l = layout(BufferId(b));
        if l.corner_major {
            let name = &buf_names[b as usize];
            let _ = writeln!(
                w,
                "    let rows_{name} = arrayLength(&{name}) / {}u;",
                l.groups()
            );
        }
    }
    // In a batch, a buffer's entity `e` of this launch's scene is entity `base + e`.
    let base_name = |d: Domain| match d {
        Domain::Element => "base_element",
        Domain::Triangle => "base_triangle",
        Domain::Node => "base_node",
        Domain::Single => "base_single",
    };
    if batched {
        let mut domains: BTreeSet<u8> = BTreeSet::new();
        let mut note = |b: &BufferId| {
            domains.insert(module.buffers[b.0 as usize].domain as u8);
        };
        for a in &k.args {
            match a {
                ArgSource::Own { buffer, .. }
                | ArgSource::Corner { buffer, .. }
                | ArgSource::Gather { buffer, .. } => note(buffer),
                ArgSource::Uniform(_) => {}
            }
        }
        for s in &k.stores {
            note(&s.buffer);
        }
        for d in [
            Domain::Element,
            Domain::Triangle,
            Domain::Node,
            Domain::Single,
        ] {
            if !domains.contains(&(d as u8)) {
                continue;
            }
            let count = match d {
                Domain::Element => format!("{launch}.elements"),
                Domain::Triangle => format!("{launch}.triangles"),
                Domain::Node => format!("{launch}.nodes"),
                Domain::Single => "1u".to_string(),
            };
            let _ = writeln!(w, "    let {} = {launch}.scene * {count};", base_name(d));
        }
    }
    // The entity index of a buffer's row: in a batch, past the earlier scenes' rows.
    let entity_of = |b: BufferId, entity: &str| {
        if batched {
            format!(
                "({} + {entity})",
                base_name(module.buffers[b.0 as usize].domain)
            )
        } else {
            entity.to_string()
        }
    };
    // Value `comp` (an expression) of a plain row.
    let row = |b: BufferId, entity: &str, comp: String| {
        let wd = width(b);
        let name = &buf_names[b.0 as usize];
        let entity = entity_of(b, entity);
        if wd == 1 {
            if comp == "0u" {
                format!("{name}[{entity}]")
            } else {
                format!("{name}[{entity} + {comp}]")
            }
        } else {
            format!("{name}[{wd}u * {entity} + {comp}]")
        }
    };
    // The `vec4` `g` of a vector row.
    let vec_at = |b: BufferId, entity: &str, g: u32| {
        let l = layout(b);
        let groups = l.groups();
        let name = &buf_names[b.0 as usize];
        let entity = entity_of(b, entity);
        if l.corner_major && g > 0 {
            let rows = format!("rows_{name}");
            return match g {
                1 => format!("{name}[{rows} + {entity}]"),
                g => format!("{name}[{g}u * {rows} + {entity}]"),
            };
        }
        match (groups, g) {
            (_, 0) if l.corner_major => format!("{name}[{entity}]"),
            (1, _) => format!("{name}[{entity}]"),
            (n, 0) => format!("{name}[{n}u * {entity}]"),
            (n, g) => format!("{name}[{n}u * {entity} + {g}u]"),
        }
    };
    // Node indices of the corners this kernel reads.
    let mut corners_used: BTreeSet<u32> = BTreeSet::new();
    for a in &k.args {
        if let ArgSource::Corner { corner, .. } = a {
            corners_used.insert(*corner);
        }
    }
    if let Some(nc) = module.corners(k.domain) {
        let conn = if k.domain == Domain::Element {
            "elem_conn"
        } else {
            "tri_conn"
        };
        for c in &corners_used {
            let _ = writeln!(w, "    let n{c} = {conn}[{nc}u * e + {c}u];");
        }
    }
    // Plain loads; a vector row's `vec4`s are loaded whole, once each, in order of first use.
    let mut vectors: Vec<(BufferId, String, u32)> = Vec::new();
    for (i, a) in k.args.iter().enumerate() {
        let (buffer, entity, component) = match a {
            ArgSource::Own { buffer, component } => (*buffer, "e".to_string(), *component),
            ArgSource::Corner {
                buffer,
                corner,
                component,
            } => (*buffer, format!("n{corner}"), *component),
            ArgSource::Uniform(id) => {
                let j = uniforms.iter().position(|u| u == id).unwrap_or(0);
                let _ = writeln!(w, "    let arg{i} = {launch}.{};", fields[j]);
                continue;
            }
            ArgSource::Gather { .. } => continue,
        };
        let layout = layout(buffer);
        if !layout.is_vector() {
            let _ = writeln!(
                w,
                "    let arg{i} = {};",
                row(buffer, &entity, format!("{component}u"))
            );
            continue;
        }
        let (g, lane) = layout.place(component);
        let key = (buffer, entity.clone(), g);
        let at = match vectors.iter().position(|v| *v == key) {
            Some(at) => at,
            None => {
                let _ = writeln!(
                    w,
                    "    let q{} = {};",
                    vectors.len(),
                    vec_at(buffer, &entity, g)
                );
                vectors.push(key);
                vectors.len() - 1
            }
        };
        let _ = writeln!(w, "    let arg{i} = q{at}.{};", lane_name(lane));
    }
    // Gathers: one loop per CSR list, one accumulator per gathered value, in list order.
    for over in [Domain::Element, Domain::Triangle] {
        let gathers: Vec<(usize, BufferId, u32, u32)> = k
            .args
            .iter()
            .enumerate()
            .filter_map(|(i, a)| match a {
                ArgSource::Gather {
                    buffer,
                    over: o,
                    stride,
                    component,
                } if *o == over => Some((i, *buffer, *stride, *component)),
                _ => None,
            })
            .collect();
        if gathers.is_empty() {
            continue;
        }
        let (offsets, slots) = if over == Domain::Element {
            ("node_elem_offsets", "node_elem_slots")
        } else {
            ("node_tri_offsets", "node_tri_slots")
        };
        let nc = module.corners(over).unwrap_or(1);
        // How a gather finds its value from the incidence's slot (entity · corners + corner).
        // A per-corner 3-vector in a row of the corners' vectors: `vec4` `slot` of the buffer
        // (one 16-byte load for the three). A per-corner value of a plain row of the corners'
        // values: value `stride · slot + component`. Anything else needs the entity and corner.
        let by_vec4 = |buffer: BufferId, stride: u32| {
            let l = layout(buffer);
            l.lanes == 3 && stride == 3 && width(buffer) == 3 * nc
        };
        let by_slot = |buffer: BufferId, stride: u32| {
            !RowLayout::of(width(buffer)).is_vector() && stride > 0 && width(buffer) == nc * stride
        };
        let _ = writeln!(
            w,
            "    // sum over the node's incident {}s, in CSR order",
            domain_word(over)
        );
        for (i, ..) in &gathers {
            let _ = writeln!(w, "    var arg{i}: real = {};", literal(0.0, p));
        }
        let _ = writeln!(
            w,
            "    for (var j = {offsets}[e]; j < {offsets}[e + 1u]; j += 1u) {{"
        );
        let _ = writeln!(w, "        let slot = {slots}[j];");
        if gathers
            .iter()
            .any(|&(_, b, s, _)| !by_vec4(b, s) && !by_slot(b, s))
        {
            let _ = writeln!(w, "        let ent = slot / {nc}u;");
            let _ = writeln!(w, "        let corner = slot - {nc}u * ent;");
        }
        let mut loaded: Vec<BufferId> = Vec::new();
        for &(i, buffer, stride, component) in &gathers {
            let name = &buf_names[buffer.0 as usize];
            let domain = module.buffers[buffer.0 as usize].domain;
            if by_vec4(buffer, stride) {
                let at = match loaded.iter().position(|&b| b == buffer) {
                    Some(at) => at,
                    None => {
                        let index = if layout(buffer).corner_major {
                            format!("(slot % {nc}u) * rows_{name} + slot / {nc}u")
                        } else if batched {
                            format!("{nc}u * {} + slot", base_name(domain))
                        } else {
                            "slot".to_string()
                        };
                        let _ = writeln!(w, "        let g{} = {name}[{index}];", loaded.len());
                        loaded.push(buffer);
                        loaded.len() - 1
                    }
                };
                let _ = writeln!(w, "        arg{i} += g{at}.{};", lane_name(component));
                continue;
            }
            if by_slot(buffer, stride) {
                let base = if batched {
                    format!("{}u * {} + ", width(buffer), base_name(domain))
                } else {
                    String::new()
                };
                let at = match (stride, component) {
                    (1, 0) => "slot".to_string(),
                    (1, c) => format!("slot + {c}u"),
                    (s, 0) => format!("{s}u * slot"),
                    (s, c) => format!("{s}u * slot + {c}u"),
                };
                let _ = writeln!(w, "        arg{i} += {name}[{base}{at}];");
                continue;
            }
            let layout = layout(buffer);
            if layout.is_vector() {
                // The value's place in the row depends on the corner: its `vec4` and lane at
                // run time.
                let (groups, lanes) = (layout.groups(), layout.lanes);
                let in_row = match stride {
                    0 => format!("{component}u"),
                    s => format!("({s}u * corner + {component}u)"),
                };
                let at = if layout.corner_major {
                    format!("{in_row} / {lanes}u * rows_{name} + ent")
                } else {
                    format!(
                        "{groups}u * {} + {in_row} / {lanes}u",
                        entity_of(buffer, "ent")
                    )
                };
                let _ = writeln!(w, "        arg{i} += {name}[{at}][{in_row} % {lanes}u];");
                continue;
            }
            let comp = match (stride, component) {
                (0, c) => format!("{c}u"),
                (1, 0) => "corner".to_string(),
                (1, c) => format!("corner + {c}u"),
                (s, 0) => format!("{s}u * corner"),
                (s, c) => format!("{s}u * corner + {c}u"),
            };
            let _ = writeln!(w, "        arg{i} += {};", row(buffer, "ent", comp));
        }
        let _ = writeln!(w, "    }}");
    }
    // The body.
    let name = |v: V, names: &[String]| names[v.0 as usize].clone();
    let mut names: Vec<String> = Vec::with_capacity(k.body.insts.len());
    for (n, inst) in k.body.insts.iter().enumerate() {
        let expr = match *inst {
            Inst::Arg(a) => {
                names.push(format!("arg{a}"));
                continue;
            }
            Inst::Const(c) => literal(c, p),
            Inst::Un(op, a) => {
                let a = name(a, &names);
                match op {
                    UnOp::Neg => format!("-{a}"),
                    UnOp::Abs => format!("abs({a})"),
                    UnOp::Sqrt => format!("sqrt({a})"),
                    UnOp::Cbrt => format!("{}({a})", helpers.use_fn(math::Fun::Cbrt, p)),
                    UnOp::Floor => format!("floor({a})"),
                    UnOp::Ceil => format!("ceil({a})"),
                    UnOp::Exp => format!("{}({a})", helpers.use_fn(math::Fun::Exp, p)),
                    UnOp::Ln => format!("{}({a})", helpers.use_fn(math::Fun::Ln, p)),
                    UnOp::Sin => format!("{}({a})", helpers.use_fn(math::Fun::Sin, p)),
                    UnOp::Cos => format!("{}({a})", helpers.use_fn(math::Fun::Cos, p)),
                    UnOp::Tan => format!("{}({a})", helpers.use_fn(math::Fun::Tan, p)),
                    UnOp::Tanh => format!("{}({a})", helpers.use_fn(math::Fun::Tanh, p)),
                }
            }
            Inst::Bin(op, a, b) => {
                let (a, b) = (name(a, &names), name(b, &names));
                match op {
                    BinOp::Add => format!("{a} + {b}"),
                    BinOp::Sub => format!("{a} - {b}"),
                    BinOp::Mul => format!("{a} * {b}"),
                    BinOp::Div => format!("{a} / {b}"),
                    BinOp::Min => format!("min({a}, {b})"),
                    BinOp::Max => format!("max({a}, {b})"),
                    BinOp::Pow => format!("{}({a}, {b})", helpers.use_fn(math::Fun::Pow, p)),
                }
            }
            Inst::Cmp(op, a, b) => {
                let (a, b) = (name(a, &names), name(b, &names));
                let o = match op {
                    CmpOp::Lt => "<",
                    CmpOp::Le => "<=",
                    CmpOp::Gt => ">",
                    CmpOp::Ge => ">=",
                    CmpOp::Eq => "==",
                    CmpOp::Ne => "!=",
                };
                format!(
                    "select({}, {}, {a} {o} {b})",
                    literal(0.0, p),
                    literal(1.0, p)
                )
            }
            Inst::Select(c, a, b) => {
                let (c, a, b) = (name(c, &names), name(a, &names), name(b, &names));
                format!("select({b}, {a}, {c} != {})", literal(0.0, p))
            }
        };
        let _ = writeln!(w, "    let v{n}: real = {expr};");
        names.push(format!("v{n}"));
    }
    // Stores: a vector row's `vec4` in one store when the kernel writes all its used lanes
    // (the unused lane 0), lane by lane otherwise.
    let mut done = vec![false; k.stores.len()];
    for (j, s) in k.stores.iter().enumerate() {
        if done[j] {
            continue;
        }
        let layout = layout(s.buffer);
        let value = |st: &crate::ir::Store| name(k.body.outputs[st.output], &names);
        if !layout.is_vector() {
            let target = row(s.buffer, "e", format!("{}u", s.component));
            let _ = writeln!(w, "    {target} = {};", value(s));
            continue;
        }
        let (g, _) = layout.place(s.component);
        let used = layout.lanes.min(layout.width - g * layout.lanes);
        let lanes: Vec<Option<usize>> = (0..used)
            .map(|l| {
                k.stores.iter().enumerate().position(|(m, t)| {
                    !done[m] && t.buffer == s.buffer && t.component == g * layout.lanes + l
                })
            })
            .collect();
        let target = vec_at(s.buffer, "e", g);
        if lanes.iter().all(Option::is_some) {
            let parts: Vec<String> = (0..4)
                .map(|l| match lanes.get(l).copied().flatten() {
                    Some(m) => value(&k.stores[m]),
                    None => literal(0.0, p),
                })
                .collect();
            let _ = writeln!(w, "    {target} = vec4<real>({});", parts.join(", "));
            for m in lanes.into_iter().flatten() {
                done[m] = true;
            }
        } else {
            let (_, lane) = layout.place(s.component);
            let _ = writeln!(w, "    {target}.{} = {};", lane_name(lane), value(s));
            done[j] = true;
        }
    }
}

/// Validate a WGSL module with naga (`FLOAT64` allowed in f64). The error shows the offending
/// source lines.
pub fn validate(source: &str, precision: Precision) -> Result<(), String> {
    let module = naga::front::wgsl::parse_str(source).map_err(|e| e.emit_to_string(source))?;
    // Immediates: the row of a `LaunchMode::Table` module.
    let caps = naga::valid::Capabilities::default() | naga::valid::Capabilities::IMMEDIATES;
    let caps = match precision {
        Precision::F32 => caps,
        Precision::F64 => caps | naga::valid::Capabilities::FLOAT64,
    };
    naga::valid::Validator::new(naga::valid::ValidationFlags::all(), caps)
        .validate(&module)
        .map_err(|e| e.emit_to_string(source))?;
    Ok(())
}
