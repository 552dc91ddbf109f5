//! The Cranelift backend against the IR interpreter: every instruction kind bit for bit in f64
//! (and against an f32 evaluation in f32) on awkward values; the generated FEM element kernels
//! over a perturbed Kuhn-split box mesh; CSR gathers against a plain Rust loop; uniforms,
//! comparisons and selects; thread-count independence; and errors instead of panics.

use softc_compiler::back::Precision;
use softc_compiler::back::cranelift::{Buffers, CpuModule, Options, Topology};
use softc_compiler::front::parse;
use softc_compiler::ir::{
    ArgSource, BinOp, Buffer, BufferId, BuiltKernel, CmpOp, Domain, ElementOrder, Func, Inst,
    Kernel, KernelBuilder, Module, Store, UnOp, V, interp,
};
use softc_compiler::lower::fem::element_force_kernel;
use softc_compiler::sema;

// ------------------------------------------------------------------ helpers

/// A small deterministic generator (xorshift64*), so the test needs no dependency.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_F491_4F6C_DD1D)
    }
    /// Uniform in [-1, 1).
    fn sym(&mut self) -> f64 {
        (self.next() >> 11) as f64 / (1u64 << 52) as f64 - 1.0
    }
}

fn same_bits(a: f64, b: f64) -> bool {
    a.to_bits() == b.to_bits()
}

fn buffer(name: &str, domain: Domain, width: u32) -> Buffer {
    Buffer {
        name: name.into(),
        domain,
        width,
        doc: String::new(),
    }
}

const UN: [UnOp; 12] = [
    UnOp::Neg,
    UnOp::Abs,
    UnOp::Sqrt,
    UnOp::Cbrt,
    UnOp::Exp,
    UnOp::Ln,
    UnOp::Sin,
    UnOp::Cos,
    UnOp::Tan,
    UnOp::Tanh,
    UnOp::Floor,
    UnOp::Ceil,
];
const BIN: [BinOp; 7] = [
    BinOp::Add,
    BinOp::Sub,
    BinOp::Mul,
    BinOp::Div,
    BinOp::Pow,
    BinOp::Min,
    BinOp::Max,
];
const CMP: [CmpOp; 6] = [
    CmpOp::Lt,
    CmpOp::Le,
    CmpOp::Gt,
    CmpOp::Ge,
    CmpOp::Eq,
    CmpOp::Ne,
];

/// Values that exercise signs, zeros, infinities, NaNs (with payloads and signs), subnormals,
/// integers and large arguments.
fn special_values() -> Vec<f64> {
    vec![
        0.0,
        -0.0,
        1.0,
        -1.0,
        0.5,
        -2.5,
        2.0,
        3.0,
        0.1,
        std::f64::consts::PI,
        1e300,
        -1e-300,
        700.0,
        -745.5,
        5e-324,
        -2.225e-309,
        f64::MIN_POSITIVE,
        f64::MAX,
        f64::INFINITY,
        f64::NEG_INFINITY,
        f64::NAN,
        f64::from_bits(0xfff8_0000_0000_0000),
        f64::from_bits(0x7ff8_0000_0000_0123),
    ]
}

/// A node kernel `x, y → every instruction kind`, built by hand (no folding, no canonical
/// operand order), so `min(y, x)` is tested as well as `min(x, y)`.
fn all_ops_module() -> (Module, BufferId, BufferId) {
    let mut insts = vec![Inst::Arg(0), Inst::Arg(1)];
    let (x, y) = (V(0), V(1));
    let mut outputs = Vec::new();
    let mut push = |insts: &mut Vec<Inst>, i: Inst| {
        insts.push(i);
        let v = V(insts.len() as u32 - 1);
        outputs.push(v);
        v
    };
    for op in UN {
        push(&mut insts, Inst::Un(op, x));
    }
    for op in BIN {
        push(&mut insts, Inst::Bin(op, x, y));
        push(&mut insts, Inst::Bin(op, y, x));
    }
    for op in CMP {
        push(&mut insts, Inst::Cmp(op, x, y));
    }
    push(&mut insts, Inst::Select(x, x, y));
    push(&mut insts, Inst::Select(y, y, x));
    // Constants inline: x + (-0.0), x * 3, 2.5 ^ y, and a compare-select chain.
    let mz = push(&mut insts, Inst::Const(-0.0));
    push(&mut insts, Inst::Bin(BinOp::Add, x, mz));
    let three = push(&mut insts, Inst::Const(3.0));
    push(&mut insts, Inst::Bin(BinOp::Mul, x, three));
    let c25 = push(&mut insts, Inst::Const(2.5));
    push(&mut insts, Inst::Bin(BinOp::Pow, c25, y));
    let lt = push(&mut insts, Inst::Cmp(CmpOp::Lt, x, y));
    let sq = push(&mut insts, Inst::Un(UnOp::Sqrt, y));
    push(&mut insts, Inst::Select(lt, sq, three));
    let n = outputs.len() as u32;
    let body = Func {
        insts,
        n_args: 2,
        outputs,
    };
    let input = BufferId(0);
    let out = BufferId(1);
    let kernel = Kernel {
        name: "all_ops".into(),
        domain: Domain::Node,
        origin: "test".into(),
        args: vec![
            ArgSource::Own {
                buffer: input,
                component: 0,
            },
            ArgSource::Own {
                buffer: input,
                component: 1,
            },
        ],
        stores: (0..n)
            .map(|i| Store {
                buffer: out,
                component: i,
                output: i as usize,
            })
            .collect(),
        body,
    };
    let module = Module {
        buffers: vec![
            buffer("xy", Domain::Node, 2),
            buffer("out", Domain::Node, n),
        ],
        kernels: vec![kernel],
        uniforms: vec![],
        ..Module::default()
    };
    (module, input, out)
}

/// The interpreter's semantics in f32, with the same std functions (and the IR's own `ln`).
fn eval_f32(func: &Func, args: &[f32]) -> Vec<f32> {
    let mut vals: Vec<f32> = Vec::new();
    for inst in &func.insts {
        let v = |x: V| vals[x.0 as usize];
        let r = match *inst {
            Inst::Const(c) => c as f32,
            Inst::Arg(i) => args[i as usize],
            Inst::Un(op, a) => {
                let x = v(a);
                match op {
                    UnOp::Neg => -x,
                    UnOp::Abs => x.abs(),
                    UnOp::Sqrt => x.sqrt(),
                    UnOp::Cbrt => x.cbrt(),
                    UnOp::Exp => x.exp(),
                    UnOp::Ln => softc_compiler::ir::math::ln_f32(x),
                    UnOp::Sin => x.sin(),
                    UnOp::Cos => x.cos(),
                    UnOp::Tan => x.tan(),
                    UnOp::Tanh => x.tanh(),
                    UnOp::Floor => x.floor(),
                    UnOp::Ceil => x.ceil(),
                }
            }
            Inst::Bin(op, a, b) => {
                let (x, y) = (v(a), v(b));
                match op {
                    BinOp::Add => x + y,
                    BinOp::Sub => x - y,
                    BinOp::Mul => x * y,
                    BinOp::Div => x / y,
                    BinOp::Pow => x.powf(y),
                    BinOp::Min => x.min(y),
                    BinOp::Max => x.max(y),
                }
            }
            Inst::Cmp(op, a, b) => {
                let (x, y) = (v(a), v(b));
                let c = match op {
                    CmpOp::Lt => x < y,
                    CmpOp::Le => x <= y,
                    CmpOp::Gt => x > y,
                    CmpOp::Ge => x >= y,
                    CmpOp::Eq => x == y,
                    CmpOp::Ne => x != y,
                };
                if c { 1.0 } else { 0.0 }
            }
            Inst::Select(c, a, b) => {
                if v(c) != 0.0 {
                    v(a)
                } else {
                    v(b)
                }
            }
        };
        vals.push(r);
    }
    func.outputs.iter().map(|o| vals[o.0 as usize]).collect()
}

/// The module compiled both ways: vector code (checked to be in use) and scalar code.
fn both_ways(m: &Module, p: Precision) -> [CpuModule; 2] {
    let simd = CpuModule::compile(m, p).unwrap();
    let lanes = match p {
        Precision::F64 => 2,
        Precision::F32 => 4,
    };
    for k in simd.kernels() {
        let want = if k.domain != Domain::Single { lanes } else { 1 };
        assert_eq!(k.lanes, want, "kernel {} lanes", k.name);
    }
    let scalar = CpuModule::compile_with(m, p, &Options { simd: false }).unwrap();
    assert!(scalar.kernels().iter().all(|k| k.lanes == 1));
    [simd, scalar]
}

// ------------------------------------------------------------------ every instruction

#[test]
fn every_instruction_is_bit_identical_to_the_interpreter_in_f64() {
    let (module, input, out) = all_ops_module();
    let vals = special_values();
    let pairs: Vec<(f64, f64)> = vals
        .iter()
        .flat_map(|&x| vals.iter().map(move |&y| (x, y)))
        .collect();
    let topo = Topology::new(pairs.len(), vec![], vec![]).unwrap();
    let width = module.buffers[1].width as usize;
    let mut reference = None;
    for (cpu, threads) in both_ways(&module, Precision::F64)
        .iter()
        .flat_map(|c| [(c, 1), (c, 3)])
    {
        let mut bufs = Buffers::new(&module, &topo, Precision::F64);
        let flat: Vec<f64> = pairs.iter().flat_map(|&(x, y)| [x, y]).collect();
        bufs.set(input, &flat).unwrap();
        cpu.run_parallel(0, &mut bufs, &topo, &[], 0..pairs.len(), threads)
            .unwrap();
        let got = bufs.f64(out).unwrap().to_vec();
        let mut bad = Vec::new();
        for (n, &(x, y)) in pairs.iter().enumerate() {
            let want = interp::eval(&module.kernels[0].body, &[x, y]);
            for (o, &w) in want.iter().enumerate() {
                let g = got[n * width + o];
                if !same_bits(g, w) {
                    bad.push(format!(
                        "output {o} ({:?}) at x={x:e} y={y:e}: jit {g:e} ({:#x}), interp {w:e} ({:#x})",
                        module.kernels[0].body.insts[module.kernels[0].body.outputs[o].0 as usize],
                        g.to_bits(),
                        w.to_bits()
                    ));
                }
            }
        }
        assert!(
            bad.is_empty(),
            "{} mismatches, first: {:#?}",
            bad.len(),
            &bad[..bad.len().min(10)]
        );
        match &reference {
            None => reference = Some(got),
            Some(r) => assert!(r.iter().zip(&got).all(|(a, b)| same_bits(*a, *b))),
        }
    }
}

#[test]
fn every_instruction_matches_an_f32_evaluation_in_f32() {
    let (module, input, out) = all_ops_module();
    let vals: Vec<f32> = special_values()
        .into_iter()
        .map(|v| v as f32)
        .chain([1e-45f32, -1.1754942e-38, 88.0, -103.5, 3.4e38])
        .collect();
    let pairs: Vec<(f32, f32)> = vals
        .iter()
        .flat_map(|&x| vals.iter().map(move |&y| (x, y)))
        .collect();
    let topo = Topology::new(pairs.len(), vec![], vec![]).unwrap();
    let width = module.buffers[1].width as usize;
    let mut bad = 0;
    for cpu in both_ways(&module, Precision::F32) {
        let mut bufs = Buffers::new(&module, &topo, Precision::F32);
        let data = bufs.f32_mut(input).unwrap();
        for (n, &(x, y)) in pairs.iter().enumerate() {
            data[2 * n] = x;
            data[2 * n + 1] = y;
        }
        // An odd start and a length that is no multiple of 4: vector and scalar loops both run.
        cpu.run(0, &mut bufs, &topo, &[], 1..pairs.len()).unwrap();
        let got = bufs.f32(out).unwrap();
        for (o, g) in got[..width].iter().enumerate() {
            assert_eq!(*g, 0.0, "entity 0 is outside the range (output {o})");
        }
        for (n, &(x, y)) in pairs.iter().enumerate().skip(1) {
            let want = eval_f32(&module.kernels[0].body, &[x, y]);
            for (o, &w) in want.iter().enumerate() {
                let g = got[n * width + o];
                if g.to_bits() != w.to_bits() {
                    bad += 1;
                    eprintln!("output {o} at x={x:e} y={y:e}: jit {g:e}, f32 eval {w:e}");
                }
            }
        }
    }
    assert_eq!(bad, 0);
}

#[test]
fn the_clif_text_shows_calls_for_transcendentals_and_no_fused_ops() {
    let (module, _, _) = all_ops_module();
    let cpu = CpuModule::compile(&module, Precision::F64).unwrap();
    let clif = cpu.clif(0);
    assert!(clif.contains("function"), "{clif}");
    assert!(clif.contains("call fn"), "{clif}");
    assert!(clif.contains("sqrt") && clif.contains("fcmp"), "{clif}");
    assert!(!clif.contains("fma"), "{clif}");
    assert_eq!(cpu.kernel(0).name, "all_ops");
    assert!(cpu.clif_all().contains("; kernel all_ops over Node"));
}

/// A node kernel `out = ln(x)`.
fn ln_module() -> (Module, BufferId, BufferId) {
    let (input, out) = (BufferId(0), BufferId(1));
    let kernel = Kernel {
        name: "ln".into(),
        domain: Domain::Node,
        origin: "test".into(),
        args: vec![ArgSource::Own {
            buffer: input,
            component: 0,
        }],
        stores: vec![Store {
            buffer: out,
            component: 0,
            output: 0,
        }],
        body: Func {
            insts: vec![Inst::Arg(0), Inst::Un(UnOp::Ln, V(0))],
            n_args: 1,
            outputs: vec![V(1)],
        },
    };
    let module = Module {
        buffers: vec![buffer("x", Domain::Node, 1), buffer("out", Domain::Node, 1)],
        kernels: vec![kernel],
        uniforms: vec![],
        ..Module::default()
    };
    (module, input, out)
}

/// Arguments for `ln`: every binade (subnormals too), arguments within a few ulps of 1 and
/// within 1e-3 of it (small strains: J = 1 + d), and the special values.
fn ln_arguments(rng: &mut Rng, tiny: f64, huge: f64, eps: f64) -> Vec<f64> {
    let mut xs = special_values();
    let mut x = tiny;
    while x < huge {
        for _ in 0..8 {
            xs.push(x * (1.5 + 0.5 * rng.sym()));
        }
        x *= 2.0;
    }
    for k in 1..400 {
        xs.push(1.0 + f64::from(k) * eps);
        xs.push(1.0 - f64::from(k) * eps / 2.0);
        xs.push(1.0 + 1e-3 * rng.sym());
    }
    xs
}

#[test]
fn inline_ln_is_the_irs_ln_bit_for_bit_in_vector_and_scalar_code() {
    // The backend compiles `ln` inline (no library call); its vector lanes and its scalar
    // code must give exactly `ir::math`'s values, the interpreter's, at every argument.
    use softc_compiler::ir::math::{ln_f32, ln_f64};
    let (module, input, out) = ln_module();
    let mut rng = Rng(0x5eed_1234_abcd_0001);
    let xs = ln_arguments(&mut rng, 5e-324, f64::MAX / 2.0, f64::EPSILON);
    let topo = Topology::new(xs.len(), vec![], vec![]).unwrap();
    for cpu in both_ways(&module, Precision::F64) {
        assert!(
            !cpu.clif(0).contains("call fn"),
            "ln is inline: {}",
            cpu.clif(0)
        );
        let mut bufs = Buffers::new(&module, &topo, Precision::F64);
        bufs.set(input, &xs).unwrap();
        cpu.run(0, &mut bufs, &topo, &[], 0..xs.len()).unwrap();
        let got = bufs.f64(out).unwrap();
        for (&x, &g) in xs.iter().zip(got) {
            let want = ln_f64(x);
            assert!(
                same_bits(g, want) || (g.is_nan() && want.is_nan()),
                "ln({x:e}): jit {g:e}, ir::math {want:e}"
            );
        }
    }
    let xs32: Vec<f32> = ln_arguments(&mut rng, 1e-45, 1.7e38, f64::from(f32::EPSILON))
        .into_iter()
        .map(|x| x as f32)
        .collect();
    let topo = Topology::new(xs32.len(), vec![], vec![]).unwrap();
    for cpu in both_ways(&module, Precision::F32) {
        let mut bufs = Buffers::new(&module, &topo, Precision::F32);
        bufs.f32_mut(input).unwrap().copy_from_slice(&xs32);
        cpu.run(0, &mut bufs, &topo, &[], 0..xs32.len()).unwrap();
        let got = bufs.f32(out).unwrap();
        for (&x, &g) in xs32.iter().zip(got) {
            let want = ln_f32(x);
            assert!(
                g.to_bits() == want.to_bits() || (g.is_nan() && want.is_nan()),
                "ln({x:e}): jit {g:e}, ir::math {want:e}"
            );
        }
    }
}

// ------------------------------------------------------------------ FEM over a mesh

mod common;
use common::{MATERIALS, NAMES};

/// One module per material, holding the element force kernel.
fn fem_modules() -> Vec<(String, Module)> {
    let ast = parse(MATERIALS).unwrap();
    let (checked, diags) = sema::check(&ast, &Default::default());
    assert!(diags.iter().all(|d| !d.is_error()), "{diags:?}");
    let program = checked.program;
    NAMES
        .iter()
        .map(|n| {
            let mut m = Module::default();
            let k = element_force_kernel(&program, &mut m, n).unwrap();
            m.push_kernel(k);
            (n.to_string(), m)
        })
        .collect()
}

/// A Kuhn-split box of `n.0 × n.1 × n.2` cells (6 tets per cell) in millimetres with
/// perturbed rest positions, deformed by a smooth finite strain plus noise.
struct Mesh {
    rest: Vec<[f64; 3]>,
    x: Vec<[f64; 3]>,
    tets: Vec<[u32; 4]>,
    tris: Vec<[u32; 3]>,
}

fn box_mesh(n: (usize, usize, usize), seed: u64) -> Mesh {
    let mm = 1e-3;
    let mut rng = Rng(seed);
    let id = |i: usize, j: usize, k: usize| (i + (n.0 + 1) * (j + (n.1 + 1) * k)) as u32;
    let mut rest = Vec::new();
    for k in 0..=n.2 {
        for j in 0..=n.1 {
            for i in 0..=n.0 {
                rest.push([
                    (i as f64 + 0.15 * rng.sym()) * mm,
                    (j as f64 + 0.15 * rng.sym()) * mm,
                    (k as f64 + 0.15 * rng.sym()) * mm,
                ]);
            }
        }
    }
    // Kuhn split: the 6 paths from corner 000 to 111 through the cube.
    let perms = [
        [0, 1, 2],
        [0, 2, 1],
        [1, 0, 2],
        [1, 2, 0],
        [2, 0, 1],
        [2, 1, 0],
    ];
    let mut tets = Vec::new();
    for k in 0..n.2 {
        for j in 0..n.1 {
            for i in 0..n.0 {
                for p in perms {
                    let mut c = [i, j, k];
                    let mut t = [id(c[0], c[1], c[2]); 4];
                    for (s, &axis) in p.iter().enumerate() {
                        c[axis] += 1;
                        t[s + 1] = id(c[0], c[1], c[2]);
                    }
                    if signed_volume(&rest, &t) < 0.0 {
                        t.swap(2, 3);
                    }
                    tets.push(t);
                }
            }
        }
    }
    let x = rest
        .iter()
        .map(|p| {
            let f = [[1.12, 0.07, -0.04], [0.02, 0.93, 0.09], [-0.05, 0.04, 1.04]];
            let mut q = [0, 1, 2].map(|r| f[r][0] * p[0] + f[r][1] * p[1] + f[r][2] * p[2]);
            for c in &mut q {
                *c += 0.04 * mm * rng.sym() + 0.2 * mm;
            }
            q
        })
        .collect();
    // Some triangles: one face of every third tet.
    let tris = tets
        .iter()
        .step_by(3)
        .map(|t: &[u32; 4]| [t[0], t[1], t[2]])
        .collect();
    Mesh {
        rest,
        x,
        tets,
        tris,
    }
}

fn signed_volume(p: &[[f64; 3]], t: &[u32; 4]) -> f64 {
    common::signed_volume(t.map(|n| p[n as usize]))
}

fn rest_shape(p: &[[f64; 3]], t: &[u32; 4]) -> [f64; 7] {
    common::rest_shape(t.map(|n| p[n as usize]))
}

impl Mesh {
    fn topology(&self) -> Topology {
        Topology::new(
            self.x.len(),
            self.tets.iter().flatten().copied().collect(),
            self.tris.iter().flatten().copied().collect(),
        )
        .unwrap()
    }

    /// Fill the FEM input buffers.
    fn fill(&self, m: &Module, bufs: &mut Buffers) {
        let id = |n: &str| m.buffer_named(n).unwrap();
        bufs.set(id("x"), &self.x.concat()).unwrap();
        let rest: Vec<f64> = self
            .tets
            .iter()
            .flat_map(|t| rest_shape(&self.rest, t))
            .collect();
        bufs.set(id("rest_shape"), &rest).unwrap();
        let vol: Vec<f64> = self
            .tets
            .iter()
            .map(|t| signed_volume(&self.rest, t))
            .collect();
        bufs.set(id("vol0"), &vol).unwrap();
    }

    /// The interpreter's outputs of an element kernel at element `e`, by store.
    fn interp_element(&self, m: &Module, k: &Kernel, e: usize) -> Vec<f64> {
        let t = &self.tets[e];
        let rest = rest_shape(&self.rest, t);
        let args: Vec<f64> = k
            .args
            .iter()
            .map(|a| match a {
                ArgSource::Corner {
                    corner, component, ..
                } => self.x[t[*corner as usize] as usize][*component as usize],
                ArgSource::Own { buffer, component } => {
                    match m.buffers[buffer.0 as usize].name.as_str() {
                        "rest_shape" => rest[*component as usize],
                        "vol0" => signed_volume(&self.rest, t),
                        other => panic!("unexpected buffer {other}"),
                    }
                }
                other => panic!("unexpected argument {other:?}"),
            })
            .collect();
        interp::eval(&k.body, &args)
    }
}

#[test]
fn fem_element_kernels_are_bit_identical_to_the_interpreter_in_f64_for_any_thread_count() {
    let mesh = box_mesh((5, 4, 5), 0x5eed_f00d);
    let topo = mesh.topology();
    let n_el = mesh.tets.len();
    assert_eq!(n_el, 600);
    for (name, m) in fem_modules() {
        let k = &m.kernels[0];
        let mut first: Option<Vec<Vec<f64>>> = None;
        let ways = both_ways(&m, Precision::F64);
        for (cpu, threads) in ways.iter().flat_map(|c| [1, 2, 3, 8].map(|t| (c, t))) {
            let mut bufs = Buffers::new(&m, &topo, Precision::F64);
            mesh.fill(&m, &mut bufs);
            cpu.run_parallel(0, &mut bufs, &topo, &[], 0..n_el, threads)
                .unwrap();
            let outs: Vec<Vec<f64>> = m
                .buffers
                .iter()
                .enumerate()
                .map(|(i, _)| bufs.get(BufferId(i as u32)))
                .collect();
            match &first {
                None => {
                    for e in 0..n_el {
                        let want = mesh.interp_element(&m, k, e);
                        for s in &k.stores {
                            let w = m.buffers[s.buffer.0 as usize].width as usize;
                            let got = outs[s.buffer.0 as usize][e * w + s.component as usize];
                            assert!(
                                same_bits(got, want[s.output]),
                                "{name}: element {e} store {s:?}: jit {got:e}, interp {:e}",
                                want[s.output]
                            );
                            assert!(got.is_finite());
                        }
                    }
                    first = Some(outs);
                }
                Some(f) => {
                    let same = f
                        .iter()
                        .flatten()
                        .zip(outs.iter().flatten())
                        .all(|(a, b)| same_bits(*a, *b));
                    assert!(same, "{name}: {threads} threads differ from 1 thread");
                }
            }
        }
    }
}

/// f32 against the f64 interpreter. Every input is rounded to f32 (relative 6e-8 of the
/// coordinate, up to ~6 mm, while edges are ~1 mm: Ds = x_i − x_0 carries ~4e-7 relative
/// error), the invariants Ī1 − 3 and J − 1 of a ~10 % strain amplify relative errors by 10–30,
/// and a few hundred f32 operations each add half an ulp. Observed worst over 600 elements and
/// six materials: 6e-5 of the element's largest force component, 2.5e-5 relative on the
/// energy. We allow 2.5e-4 and 1e-4 (4× headroom): a wrong operation or a precision mix-up
/// shows as errors of order 1, or of 1e-3 for an f64 constant rounded the wrong way.
#[test]
fn fem_element_kernels_in_f32_are_close_to_f64() {
    let mesh = box_mesh((5, 4, 5), 0xabcdef);
    let topo = mesh.topology();
    let n_el = mesh.tets.len();
    for (name, m) in fem_modules() {
        let [cpu, scalar] = both_ways(&m, Precision::F32);
        let k = &m.kernels[0];
        let mut bufs = Buffers::new(&m, &topo, Precision::F32);
        mesh.fill(&m, &mut bufs);
        let mut b1 = bufs.clone();
        cpu.run_parallel(0, &mut bufs, &topo, &[], 0..n_el, 2)
            .unwrap();
        scalar
            .run_parallel(0, &mut b1, &topo, &[], 0..n_el, 3)
            .unwrap();
        for i in 0..m.buffers.len() {
            let id = BufferId(i as u32);
            let same = bufs
                .f32(id)
                .unwrap()
                .iter()
                .zip(b1.f32(id).unwrap())
                .all(|(a, b)| a.to_bits() == b.to_bits());
            assert!(same, "{name}: f32 vector and scalar code differ");
        }
        let force = m.buffer_named("elem_force").unwrap();
        let energy = m.buffer_named("elem_energy").unwrap();
        let (fs, es) = (bufs.get(force), bufs.get(energy));
        let (mut worst_f, mut worst_e) = (0.0f64, 0.0f64);
        for e in 0..n_el {
            let want = mesh.interp_element(&m, k, e);
            let mut wf = [0.0; 12];
            let mut we = 0.0;
            for s in &k.stores {
                if s.buffer == force {
                    wf[s.component as usize] = want[s.output];
                } else if s.buffer == energy {
                    we = want[s.output];
                }
            }
            let scale = wf.iter().fold(0.0f64, |a, b| a.max(b.abs()));
            for c in 0..12 {
                worst_f = worst_f.max((fs[e * 12 + c] - wf[c]).abs() / scale);
            }
            worst_e = worst_e.max((es[e] - we).abs() / we.abs());
        }
        eprintln!("{name}: f32 worst force error {worst_f:e} (of element max), energy {worst_e:e}");
        assert!(worst_f < 2.5e-4, "{name}: f32 force error {worst_f:e}");
        assert!(worst_e < 1e-4, "{name}: f32 energy error {worst_e:e}");
    }
}

// ------------------------------------------------------------------ gathers

/// A node kernel: the sum of incident element forces (over the node→element CSR) plus an
/// external load, and the sum of incident triangle loads (node→triangle CSR) scaled by a
/// uniform.
fn gather_kernel(m: &mut Module) -> BuiltKernel {
    let force = m.buffer_named("elem_force").unwrap();
    let tri_load = m.buffer("tri_load", Domain::Triangle, 9, "load per triangle corner");
    let ext = m.buffer("ext", Domain::Node, 3, "external load");
    let out = m.buffer("node_force", Domain::Node, 3, "total force");
    let mut k = KernelBuilder::new("assemble", Domain::Node, "test");
    let scale = k.uniform("pressure_scale");
    for d in 0..3 {
        let fe = k.load(ArgSource::Gather {
            buffer: force,
            over: Domain::Element,
            stride: 3,
            component: d,
        });
        let ft = k.load(ArgSource::Gather {
            buffer: tri_load,
            over: Domain::Triangle,
            stride: 3,
            component: d,
        });
        let fx = k.load(ArgSource::Own {
            buffer: ext,
            component: d,
        });
        let a = k.b.add(fe, fx);
        let p = k.b.mul(scale, ft);
        let s = k.b.add(a, p);
        k.store(out, d, s);
    }
    k.finish()
}

#[test]
fn gathers_equal_a_plain_loop_over_the_csr_bit_for_bit() {
    let mesh = box_mesh((6, 5, 5), 77);
    let topo = mesh.topology();
    let (_, mut m) = fem_modules().swap_remove(0);
    let k = gather_kernel(&mut m);
    m.push_kernel(k);
    let [cpu, _] = both_ways(&m, Precision::F64);
    assert_eq!(
        cpu.kernel(1).uniforms,
        [m.uniform_named("pressure_scale").unwrap()]
    );
    let n_el = mesh.tets.len();
    let n_nodes = mesh.x.len();
    let n_tri = mesh.tris.len();
    let mut rng = Rng(99);
    let ext: Vec<f64> = (0..3 * n_nodes).map(|_| rng.sym()).collect();
    let tri_load: Vec<f64> = (0..9 * n_tri).map(|_| rng.sym() * 1e-3).collect();
    let id = |n: &str| m.buffer_named(n).unwrap();
    let scale = 1.7;
    let mut first: Option<Vec<f64>> = None;
    for threads in [1, 2, 3, 8] {
        let mut bufs = Buffers::new(&m, &topo, Precision::F64);
        mesh.fill(&m, &mut bufs);
        bufs.set(id("ext"), &ext).unwrap();
        bufs.set(id("tri_load"), &tri_load).unwrap();
        cpu.run_parallel(0, &mut bufs, &topo, &[], 0..n_el, threads)
            .unwrap();
        cpu.run_parallel(1, &mut bufs, &topo, &[scale], 0..n_nodes, threads)
            .unwrap();
        let got = bufs.get(id("node_force"));
        match &first {
            None => {
                let force = bufs.f64(id("elem_force")).unwrap();
                let (eo, ee) = topo.node_elem();
                let (to, te) = topo.node_tri();
                for n in 0..n_nodes {
                    for d in 0..3 {
                        let mut se = 0.0;
                        for j in eo[n] as usize..eo[n + 1] as usize {
                            let (e, c) = (ee[2 * j] as usize, te_pair(ee, j).1);
                            se += force[e * 12 + c * 3 + d];
                        }
                        let mut st = 0.0;
                        for j in to[n] as usize..to[n + 1] as usize {
                            let (t, c) = te_pair(te, j);
                            st += tri_load[t * 9 + c * 3 + d];
                        }
                        let want = (se + ext[3 * n + d]) + scale * st;
                        let g = got[3 * n + d];
                        assert!(
                            same_bits(g, want),
                            "node {n} dim {d}: jit {g:e}, loop {want:e}"
                        );
                    }
                }
                // Interior forces cancel: the sum over all nodes of the element part is ~0.
                first = Some(got);
            }
            Some(f) => assert!(
                f.iter().zip(&got).all(|(a, b)| same_bits(*a, *b)),
                "{threads} threads differ"
            ),
        }
    }
}

fn te_pair(entries: &[u32], j: usize) -> (usize, usize) {
    (entries[2 * j] as usize, entries[2 * j + 1] as usize)
}

#[test]
fn a_caller_given_csr_order_is_the_summation_order() {
    // Reverse each node's incidence list: the gather must follow it.
    let mesh = box_mesh((3, 3, 3), 5);
    let base = mesh.topology();
    let rev = |(o, e): (&[u32], &[u32])| {
        let mut out = Vec::with_capacity(e.len());
        for n in 0..o.len() - 1 {
            for j in (o[n] as usize..o[n + 1] as usize).rev() {
                out.extend_from_slice(&e[2 * j..2 * j + 2]);
            }
        }
        (o.to_vec(), out)
    };
    let topo = Topology::with_csr(
        ElementOrder::Linear,
        mesh.x.len(),
        base.elem_conn().to_vec(),
        base.tri_conn().to_vec(),
        rev(base.node_elem()),
        rev(base.node_tri()),
    )
    .unwrap();
    let mut m = Module::default();
    let f = m.buffer("f", Domain::Element, 12, "");
    let out = m.buffer("sum", Domain::Node, 1, "");
    let mut k = KernelBuilder::new("g", Domain::Node, "test");
    let g = k.load(ArgSource::Gather {
        buffer: f,
        over: Domain::Element,
        stride: 3,
        component: 1,
    });
    k.store(out, 0, g);
    m.push_kernel(k.finish());
    let cpu = CpuModule::compile(&m, Precision::F64).unwrap();
    let mut rng = Rng(3);
    // Values of very different magnitudes, so the summation order shows in the bits.
    let vals: Vec<f64> = (0..12 * mesh.tets.len())
        .map(|i| rng.sym() * 10f64.powi((i % 17) as i32 - 8))
        .collect();
    let mut bufs = Buffers::new(&m, &topo, Precision::F64);
    bufs.set(f, &vals).unwrap();
    cpu.run(0, &mut bufs, &topo, &[], 0..mesh.x.len()).unwrap();
    let got = bufs.get(out);
    let (o, e) = topo.node_elem();
    let mut differs = 0;
    for n in 0..mesh.x.len() {
        let mut s = 0.0;
        for j in o[n] as usize..o[n + 1] as usize {
            let (el, c) = te_pair(e, j);
            s += vals[el * 12 + c * 3 + 1];
        }
        assert!(same_bits(got[n], s), "node {n}");
        let (bo, be) = base.node_elem();
        let mut fwd = 0.0;
        for j in bo[n] as usize..bo[n + 1] as usize {
            let (el, c) = te_pair(be, j);
            fwd += vals[el * 12 + c * 3 + 1];
        }
        differs += usize::from(!same_bits(fwd, s));
    }
    assert!(differs > 0, "the test data should make the order visible");
}

/// Node kernels with gathers run 2 (f64) / 4 (f32) nodes per iteration, walking the lanes'
/// CSR lists side by side: every node must still get the scalar code's sum, in its list's
/// order, bit for bit, whatever its neighbours' incidence counts (0 included), where the range
/// starts (which nodes share a vector) and how many threads run it; a scalar tail included.
#[test]
fn vector_gathers_equal_scalar_gathers_and_a_plain_loop_bit_for_bit() {
    // 23 nodes; elements and triangles drawn so that incidence counts vary from 0 to many
    // (node 7 and node 22 are in no entity, nodes 0..4 are in many).
    let n_nodes = 23;
    let mut rng = Rng(2026);
    let mut pick = |k: usize| -> Vec<u32> {
        let mut v: Vec<u32> = Vec::new();
        while v.len() < k {
            let r = rng.next();
            // Skewed towards low node numbers.
            let n = if r.is_multiple_of(3) {
                r % 5
            } else {
                (r >> 8) % 22
            } as u32;
            if n != 7 && !v.contains(&n) {
                v.push(n);
            }
        }
        v
    };
    let elem_conn: Vec<u32> = (0..37).flat_map(|_| pick(4)).collect();
    let tri_conn: Vec<u32> = (0..11).flat_map(|_| pick(3)).collect();
    let topo = Topology::new(n_nodes, elem_conn, tri_conn).unwrap();
    let (o, _) = topo.node_elem();
    let counts: Vec<u32> = o.windows(2).map(|w| w[1] - w[0]).collect();
    let (least, most) = (counts.iter().min().unwrap(), counts.iter().max().unwrap());
    assert!(*least == 0 && *most >= 8, "incidence counts {counts:?}");

    let mut m = Module::default();
    let fe = m.buffer("fe", Domain::Element, 12, "");
    let ft = m.buffer("ft", Domain::Triangle, 9, "");
    let own = m.buffer("own", Domain::Node, 3, "");
    let out = m.buffer("out", Domain::Node, 3, "");
    let mut k = KernelBuilder::new("gsum", Domain::Node, "test");
    let u = k.uniform("u");
    for d in 0..3 {
        let a = k.load(ArgSource::Gather {
            buffer: fe,
            over: Domain::Element,
            stride: 3,
            component: d,
        });
        let t = k.load(ArgSource::Gather {
            buffer: ft,
            over: Domain::Triangle,
            stride: 3,
            component: d,
        });
        let x = k.load(ArgSource::Own {
            buffer: own,
            component: d,
        });
        let p = k.b.mul(u, t);
        let s = k.b.add(a, p);
        let s = k.b.sub(s, x);
        k.store(out, d, s);
    }
    m.push_kernel(k.finish());

    // Values of very different magnitudes and signs (and signed zeros), so any change of
    // summation order or an added zero shows in the bits.
    let vals = |n: usize| -> Vec<f64> {
        (0..n)
            .map(|i| match i % 11 {
                0 => -0.0,
                1 => 0.0,
                _ => rng_sym(i) * 10f64.powi((i % 13) as i32 - 6),
            })
            .collect()
    };
    let fe_v = vals(12 * 37);
    let ft_v = vals(9 * 11);
    let own_v = vals(3 * n_nodes);
    let uniform = 0.37;
    // The plain loop in f64.
    let sum = |buf: &[f64], width: usize, (o, e): (&[u32], &[u32]), n: usize, d: usize| {
        let mut s = 0.0;
        for j in o[n] as usize..o[n + 1] as usize {
            let (ent, c) = te_pair(e, j);
            s += buf[ent * width + c * 3 + d];
        }
        s
    };
    let mut want = vec![0.0; 3 * n_nodes];
    for n in 0..n_nodes {
        for d in 0..3 {
            let a = sum(&fe_v, 12, topo.node_elem(), n, d);
            let t = sum(&ft_v, 9, topo.node_tri(), n, d);
            want[3 * n + d] = (a + uniform * t) - own_v[3 * n + d];
        }
    }
    for p in [Precision::F64, Precision::F32] {
        let [simd, scalar] = both_ways(&m, p);
        let mut reference: Option<Vec<f64>> = None;
        for (cpu, threads, start) in [
            (&scalar, 1, 0),
            (&simd, 1, 0),
            (&simd, 1, 1),
            (&simd, 1, 3),
            (&simd, 2, 0),
            (&simd, 3, 2),
            (&simd, 8, 0),
        ] {
            let mut bufs = Buffers::new(&m, &topo, p);
            bufs.set(fe, &fe_v).unwrap();
            bufs.set(ft, &ft_v).unwrap();
            bufs.set(own, &own_v).unwrap();
            // Nodes before `start` in a separate launch: lanes group other nodes together.
            if start > 0 {
                cpu.run(0, &mut bufs, &topo, &[uniform], 0..start).unwrap();
            }
            cpu.run_parallel(0, &mut bufs, &topo, &[uniform], start..n_nodes, threads)
                .unwrap();
            let got = bufs.get(out);
            if p == Precision::F64 {
                for (i, (&g, &w)) in got.iter().zip(&want).enumerate() {
                    assert!(
                        same_bits(g, w),
                        "node {} component {}: {g:e} against {w:e} ({threads} threads, from {start})",
                        i / 3,
                        i % 3
                    );
                }
            }
            match &reference {
                None => reference = Some(got),
                Some(r) => assert!(
                    r.iter().zip(&got).all(|(a, b)| same_bits(*a, *b)),
                    "{p}: vector code ({threads} threads, from {start}) differs from scalar code"
                ),
            }
        }
    }
}

/// A deterministic value in [-1, 1) for index `i`.
fn rng_sym(i: usize) -> f64 {
    Rng(i as u64 * 0x9E37_79B9 + 1).sym()
}

// ------------------------------------------------------------------ uniforms, selects

#[test]
fn uniforms_compares_and_selects_on_triangles() {
    // A triangle kernel with corner loads, uniforms and a compare/select path:
    //   area vector a = (x1 − x0) × (x2 − x0) / 2,
    //   load = p · a / 3 where a·n̂ > threshold, else −p · a / 3 (clamped by min/max).
    let mesh = box_mesh((4, 3, 3), 11);
    let topo = mesh.topology();
    let mut m = Module::default();
    let x = m.buffer("x", Domain::Node, 3, "");
    let out = m.buffer("load", Domain::Triangle, 4, "");
    let mut k = KernelBuilder::new("pressure", Domain::Triangle, "test");
    let p = k.uniform("p");
    let thr = k.uniform("threshold");
    let cap = k.uniform("cap");
    let xs: Vec<[V; 3]> = (0..3)
        .map(|c| {
            [0, 1, 2].map(|d| {
                k.load(ArgSource::Corner {
                    buffer: x,
                    corner: c,
                    component: d,
                })
            })
        })
        .collect();
    let e1 = [0, 1, 2].map(|d| k.b.sub(xs[1][d], xs[0][d]));
    let e2 = [0, 1, 2].map(|d| k.b.sub(xs[2][d], xs[0][d]));
    let cross = [0, 1, 2].map(|d| {
        let (i, j) = ((d + 1) % 3, (d + 2) % 3);
        let a = k.b.mul(e1[i], e2[j]);
        let b = k.b.mul(e1[j], e2[i]);
        k.b.sub(a, b)
    });
    let sixth = k.b.constant(1.0 / 6.0);
    let ps = k.b.mul(p, sixth);
    let up = k.b.cmp(CmpOp::Gt, cross[2], thr);
    for (d, &c) in cross.iter().enumerate() {
        let f = k.b.mul(ps, c);
        let nf = k.b.neg(f);
        let s = k.b.select(up, f, nf);
        let lo = k.b.neg(cap);
        let s = k.b.bin(BinOp::Min, s, cap);
        let s = k.b.bin(BinOp::Max, s, lo);
        k.store(out, d as u32, s);
    }
    let ne = k.b.cmp(CmpOp::Ne, cross[0], cross[1]);
    let le = k.b.cmp(CmpOp::Le, cross[0], thr);
    let both = k.b.mul(ne, le);
    k.store(out, 3, both);
    m.push_kernel(k.finish());
    let kernel = &m.kernels[0];
    let cpu = CpuModule::compile(&m, Precision::F64).unwrap();
    let names: Vec<&str> = cpu
        .kernel(0)
        .uniforms
        .iter()
        .map(|&u| m.uniform_name(u))
        .collect();
    assert_eq!(names, ["p", "threshold", "cap"]);
    let n_tri = mesh.tris.len();
    for uniforms in [
        [3e3, 0.0, 1e-3],
        [-2e3, 1e-8, 5e-4],
        [1e4, f64::NAN, f64::INFINITY],
    ] {
        let mut bufs = Buffers::new(&m, &topo, Precision::F64);
        bufs.set(x, &mesh.x.concat()).unwrap();
        cpu.run_parallel(0, &mut bufs, &topo, &uniforms, 0..n_tri, 3)
            .unwrap();
        let got = bufs.get(out);
        let mut ups = 0;
        for (t, tri) in mesh.tris.iter().enumerate() {
            let args: Vec<f64> = kernel
                .args
                .iter()
                .map(|a| match a {
                    ArgSource::Uniform(n) => match m.uniform_name(*n) {
                        "p" => uniforms[0],
                        "threshold" => uniforms[1],
                        _ => uniforms[2],
                    },
                    ArgSource::Corner {
                        corner, component, ..
                    } => mesh.x[tri[*corner as usize] as usize][*component as usize],
                    other => panic!("{other:?}"),
                })
                .collect();
            let want = interp::eval(&kernel.body, &args);
            for s in &kernel.stores {
                let g = got[t * 4 + s.component as usize];
                assert!(same_bits(g, want[s.output]), "triangle {t} {s:?}");
            }
            ups += usize::from(got[t * 4] != 0.0 && want[0] == want[0]);
        }
        assert!(ups > 0);
    }
}

// ------------------------------------------------------------------ errors, not panics

#[test]
fn misuse_is_an_error() {
    let mesh = box_mesh((2, 2, 2), 1);
    let topo = mesh.topology();
    let (_, mut m) = fem_modules().swap_remove(2);
    let k = gather_kernel(&mut m);
    m.push_kernel(k);
    let cpu = CpuModule::compile(&m, Precision::F64).unwrap();
    let n_el = mesh.tets.len();
    let mut bufs = Buffers::new(&m, &topo, Precision::F64);
    // Wrong number of uniforms, range past the end, wrong precision, wrong sizes.
    assert!(cpu.run(1, &mut bufs, &topo, &[], 0..1).is_err());
    assert!(cpu.run(0, &mut bufs, &topo, &[], 0..n_el + 1).is_err());
    assert!(cpu.run(9, &mut bufs, &topo, &[], 0..1).is_err());
    let mut b32 = Buffers::new(&m, &topo, Precision::F32);
    assert!(cpu.run(0, &mut b32, &topo, &[], 0..1).is_err());
    let small = box_mesh((1, 1, 1), 1).topology();
    let err = cpu.run(0, &mut bufs, &small, &[], 0..1).unwrap_err();
    assert!(err.contains("values"), "{err}");
    assert!(bufs.set(BufferId(0), &[1.0]).is_err());
    // Bad connectivity.
    assert!(Topology::new(3, vec![0, 1, 2, 3], vec![]).is_err());
    assert!(Topology::new(4, vec![0, 1, 2], vec![]).is_err());
    let t = mesh.topology();
    let (o, e) = t.node_elem();
    let mut bad = e.to_vec();
    bad[1] = (bad[1] + 1) % 4;
    let r = Topology::with_csr(
        ElementOrder::Linear,
        mesh.x.len(),
        t.elem_conn().to_vec(),
        t.tri_conn().to_vec(),
        (o.to_vec(), bad),
        (t.node_tri().0.to_vec(), t.node_tri().1.to_vec()),
    );
    assert!(r.unwrap_err().contains("not an incidence"));

    // Kernels that do not fit their module fail to compile.
    let mut m2 = Module::default();
    let nodebuf = m2.buffer("n", Domain::Node, 3, "");
    let el = m2.buffer("e", Domain::Element, 1, "");
    let mut k = KernelBuilder::new("bad_own", Domain::Element, "test");
    let v = k.load(ArgSource::Own {
        buffer: nodebuf,
        component: 0,
    });
    k.store(el, 0, v);
    m2.push_kernel(k.finish());
    let err = CpuModule::compile(&m2, Precision::F64).unwrap_err();
    assert!(err.contains("bad_own"), "{err}");
    m2.kernels.clear();
    let mut k = KernelBuilder::new("bad_component", Domain::Element, "test");
    let v = k.load(ArgSource::Corner {
        buffer: nodebuf,
        corner: 4,
        component: 0,
    });
    k.store(el, 0, v);
    m2.push_kernel(k.finish());
    assert!(CpuModule::compile(&m2, Precision::F64).is_err());
    m2.kernels.clear();
    let mut k = KernelBuilder::new("bad_gather", Domain::Node, "test");
    let v = k.load(ArgSource::Gather {
        buffer: el,
        over: Domain::Element,
        stride: 1,
        component: 0,
    });
    k.store(nodebuf, 0, v);
    m2.push_kernel(k.finish());
    assert!(CpuModule::compile(&m2, Precision::F64).is_err());

    // Stores go to the kernel's own entity of its own domain, corners read node buffers
    // and gathers element or triangle buffers: no kernel can write what it reads at another
    // entity, so every valid kernel may run on threads, reading and writing in place too.
    let mut k = KernelBuilder::new("in_place", Domain::Element, "test");
    let a = k.load(ArgSource::Own {
        buffer: el,
        component: 0,
    });
    let s = k.b.scale(2.0, a);
    k.store(el, 0, s);
    m2.kernels.clear();
    m2.push_kernel(k.finish());
    let cpu2 = CpuModule::compile(&m2, Precision::F64).unwrap();
    let mut b2 = Buffers::new(&m2, &topo, Precision::F64);
    b2.set(el, &vec![1.5; n_el]).unwrap();
    cpu2.run_parallel(0, &mut b2, &topo, &[], 0..n_el, 4)
        .unwrap();
    assert!(b2.get(el).iter().all(|&v| v == 3.0));
}

// ------------------------------------------------------------------ measurements

/// Compile time per kernel and run time per element of the FEM kernels, f64 and f32, on 1
/// and 2 threads, against the interpreter. `cargo test --release --test cranelift -- --ignored
/// --nocapture measure`.
#[test]
#[ignore]
fn measure() {
    use std::time::Instant;
    let cells: usize = std::env::var("SOFTC_CELLS").map_or(30, |v| v.parse().unwrap());
    let mesh = box_mesh((cells, cells, cells), 42);
    let topo = mesh.topology();
    let n_el = mesh.tets.len();
    let reps = 9;
    for (name, m) in fem_modules() {
        let k = &m.kernels[0];
        let n_interp = n_el.min(10_000);
        let mut sink = 0.0;
        let mut best = f64::INFINITY;
        for _ in 0..3 {
            let t0 = Instant::now();
            for e in 0..n_interp {
                sink += mesh.interp_element(&m, k, e)[0];
            }
            best = best.min(t0.elapsed().as_secs_f64());
        }
        let interp_ns = best * 1e9 / n_interp as f64;
        let mut line = format!(
            "{name:7} {:4} insts  interp {interp_ns:7.1} ns/el",
            k.body.insts.len()
        );
        for p in [Precision::F64, Precision::F32] {
            let t0 = Instant::now();
            let cpu = CpuModule::compile(&m, p).unwrap();
            let compile_ms = t0.elapsed().as_secs_f64() * 1e3;
            let mut bufs = Buffers::new(&m, &topo, p);
            mesh.fill(&m, &mut bufs);
            line += &format!(
                "  {p}: compile {compile_ms:5.1} ms (kernel {:4.1})",
                cpu.kernel(0).compile_time.as_secs_f64() * 1e3
            );
            let threads_list: Vec<usize> = std::env::var("SOFTC_THREADS")
                .map(|v| v.split(',').map(|t| t.parse().unwrap()).collect())
                .unwrap_or(vec![1, 2]);
            for threads in threads_list {
                cpu.run_parallel(0, &mut bufs, &topo, &[], 0..n_el, threads)
                    .unwrap();
                // Best of `reps`: the machine may be shared.
                let mut best = f64::INFINITY;
                for _ in 0..reps {
                    let t0 = Instant::now();
                    cpu.run_parallel(0, &mut bufs, &topo, &[], 0..n_el, threads)
                        .unwrap();
                    best = best.min(t0.elapsed().as_secs_f64());
                }
                let ns = best * 1e9 / n_el as f64;
                line += &format!(" {threads}t {ns:5.1} ns/el");
            }
        }
        println!("{line} ({sink:e})");
    }
    // The node kernel with gathers (scalar code), after the yeoh element kernel.
    let (_, mut m) = fem_modules().swap_remove(0);
    let k = gather_kernel(&mut m);
    m.push_kernel(k);
    let n_nodes = mesh.x.len();
    for p in [Precision::F64, Precision::F32] {
        let cpu = CpuModule::compile(&m, p).unwrap();
        let mut bufs = Buffers::new(&m, &topo, p);
        mesh.fill(&m, &mut bufs);
        cpu.run(0, &mut bufs, &topo, &[], 0..n_el).unwrap();
        let mut line = format!(
            "assemble (gather, {p}): compile {:.1} ms",
            cpu.kernel(1).compile_time.as_secs_f64() * 1e3
        );
        for threads in [1, 2] {
            let mut best = f64::INFINITY;
            for _ in 0..reps {
                let t0 = Instant::now();
                cpu.run_parallel(1, &mut bufs, &topo, &[1.0], 0..n_nodes, threads)
                    .unwrap();
                best = best.min(t0.elapsed().as_secs_f64());
            }
            let ns = best * 1e9 / n_nodes as f64;
            line += &format!(" {threads}t {ns:5.1} ns/node");
        }
        println!("{line}");
    }
    println!("{n_el} elements, {n_nodes} nodes");

    // Per-call cost of a small launch (~1k tets): thread start-up shows here.
    let small = box_mesh((6, 6, 5), 3);
    let st = small.topology();
    let (_, m) = fem_modules().swap_remove(2);
    let cpu = CpuModule::compile(&m, Precision::F64).unwrap();
    let mut bufs = Buffers::new(&m, &st, Precision::F64);
    small.fill(&m, &mut bufs);
    let n = small.tets.len();
    let mut line = format!("nh f64, {n} elements per call:");
    for threads in [1, 2] {
        let mut best = f64::INFINITY;
        for _ in 0..2000 {
            let t0 = Instant::now();
            cpu.run_parallel(0, &mut bufs, &st, &[], 0..n, threads)
                .unwrap();
            best = best.min(t0.elapsed().as_secs_f64());
        }
        let us = best * 1e6;
        line += &format!(" {threads}t {us:6.1} µs/call");
    }
    println!("{line}");
}

#[test]
fn compiled_modules_can_be_shared_between_threads() {
    fn send_sync<T: Send + Sync>() {}
    send_sync::<CpuModule>();
}

#[test]
fn single_kernels_run_once() {
    // A parameter transform: p = lo + (hi − lo) · sigmoid(raw), raw read from a single buffer,
    // bounds as uniforms; also the raw value doubled in place.
    let mut m = Module::default();
    let raw = m.buffer("raw", Domain::Single, 2, "");
    let out = m.buffer("p", Domain::Single, 1, "");
    let mut k = KernelBuilder::new("transform", Domain::Single, "test");
    let lo = k.uniform("lo");
    let hi = k.uniform("hi");
    let r = k.load(ArgSource::Own {
        buffer: raw,
        component: 1,
    });
    let nr = k.b.neg(r);
    let e = k.b.un(UnOp::Exp, nr);
    let one = k.b.constant(1.0);
    let den = k.b.add(one, e);
    let s = k.b.div(one, den);
    let span = k.b.sub(hi, lo);
    let t = k.b.mul(span, s);
    let p = k.b.add(lo, t);
    k.store(out, 0, p);
    let r2 = k.b.scale(2.0, r);
    k.store(raw, 1, r2);
    m.push_kernel(k.finish());
    let topo = Topology::new(0, vec![], vec![]).unwrap();
    for cpu in both_ways(&m, Precision::F64) {
        assert_eq!(cpu.kernel(0).lanes, 1);
        let mut bufs = Buffers::new(&m, &topo, Precision::F64);
        bufs.set(raw, &[9.0, 0.3]).unwrap();
        cpu.run_parallel(0, &mut bufs, &topo, &[1e3, 5e4], 0..1, 4)
            .unwrap();
        let want = interp::eval(&m.kernels[0].body, &[1e3, 5e4, 0.3]);
        assert!(same_bits(bufs.get(out)[0], want[0]));
        assert_eq!(bufs.get(raw), [9.0, 0.6]);
        assert!(cpu.run(0, &mut bufs, &topo, &[1e3, 5e4], 0..2).is_err());
    }
}

#[test]
fn caller_owned_storage_and_double_buffering() {
    use softc_compiler::back::cranelift::Storage;
    // x_new = x_old + 1 per node; swap, run again: x = 2.
    let mut m = Module::default();
    let old = m.buffer("x_old", Domain::Node, 1, "");
    let new = m.buffer("x_new", Domain::Node, 1, "");
    let mut k = KernelBuilder::new("step", Domain::Node, "test");
    let x = k.load(ArgSource::Own {
        buffer: old,
        component: 0,
    });
    let one = k.b.constant(1.0);
    let y = k.b.add(x, one);
    k.store(new, 0, y);
    m.push_kernel(k.finish());
    let topo = Topology::new(5, vec![], vec![]).unwrap();
    let cpu = CpuModule::compile(&m, Precision::F64).unwrap();
    let mut bufs = Buffers::from_storage(
        Precision::F64,
        vec![Storage::F64(vec![0.0; 5]), Storage::F64(vec![0.0; 5])],
    )
    .unwrap();
    for _ in 0..2 {
        cpu.run(0, &mut bufs, &topo, &[], 0..5).unwrap();
        bufs.swap(old, new);
    }
    assert_eq!(bufs.get(old), [2.0; 5]);
    // A wrong precision or length slipped in through `storage_mut` is caught at run time.
    bufs.storage_mut()[1] = Storage::F32(vec![0.0; 5]);
    assert!(cpu.run(0, &mut bufs, &topo, &[], 0..5).is_err());
    bufs.storage_mut()[1] = Storage::F64(vec![0.0; 4]);
    assert!(cpu.run(0, &mut bufs, &topo, &[], 0..5).is_err());
    assert!(Buffers::from_storage(Precision::F32, bufs.into_storage()).is_err());
}
