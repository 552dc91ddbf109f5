//! The kernel IR: the single source of truth for the physics.
//!
//! A kernel runs once per entity of its domain (element, chamber triangle, node, or once). Its
//! body is a straight-line SSA function over real scalars ([`Func`]): no loops, no branches
//! (`select` instead), no memory access. What a body reads comes in as arguments whose sources
//! the kernel lists ([`ArgSource`]: a component of a buffer at this entity or at a node of this
//! element, a uniform such as `t` or a param, or a deterministic CSR gather-sum); what it
//! writes leaves through [`Store`]s to buffers indexed by the entity itself. There is no
//! scatter, so every backend can run entities in parallel with bit-identical results.
//!
//! Bodies are built through [`Builder`], which folds constants, simplifies algebraic identities
//! and shares common subexpressions as it goes; [`Func::prune`] removes dead code, and
//! [`ad`] appends reverse-mode derivatives of a body (used for stresses from a strain energy
//! now, and for adjoint kernels later).
//!
//! [`valid`] checks that a kernel's accesses fit its module's buffers; every backend runs it
//! before generating code.

pub mod ad;
pub mod interp;
pub mod math;
mod print;
pub mod valid;

use std::collections::HashMap;

/// A value of a function body: the index of the instruction that computes it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct V(pub u32);

#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum UnOp {
    Neg,
    Abs,
    Sqrt,
    /// The real cube root (defined for negative arguments: `cbrt(-8) = -2`), as C's `cbrt`.
    Cbrt,
    Exp,
    Ln,
    Sin,
    Cos,
    Tan,
    Tanh,
    Floor,
    Ceil,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum BinOp {
    Add,
    Sub,
    Mul,
    Div,
    /// `a^b` for real `b` (`a > 0`, or any `a` with an integral `b`).
    Pow,
    Min,
    Max,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum CmpOp {
    Lt,
    Le,
    Gt,
    Ge,
    Eq,
    Ne,
}

/// One instruction. Comparisons give 1.0 or 0.0; `Select(c, a, b)` is `a` where `c != 0`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Inst {
    Const(f64),
    Arg(u32),
    Un(UnOp, V),
    Bin(BinOp, V, V),
    Cmp(CmpOp, V, V),
    Select(V, V, V),
}

/// Hashable form of an instruction (constants by their bits) for common-subexpression sharing.
#[derive(Clone, Copy, PartialEq, Eq, Hash)]
enum Key {
    Const(u64),
    Arg(u32),
    Un(UnOp, V),
    Bin(BinOp, V, V),
    Cmp(CmpOp, V, V),
    Select(V, V, V),
}

impl Key {
    fn of(i: &Inst) -> Key {
        match *i {
            // -0.0 and 0.0 differ in bits and stay distinct, as they must (1/-0 = -inf).
            Inst::Const(c) => Key::Const(c.to_bits()),
            Inst::Arg(a) => Key::Arg(a),
            Inst::Un(o, a) => Key::Un(o, a),
            Inst::Bin(o, a, b) => Key::Bin(o, a, b),
            Inst::Cmp(o, a, b) => Key::Cmp(o, a, b),
            Inst::Select(c, a, b) => Key::Select(c, a, b),
        }
    }
}

/// A straight-line function body with named outputs.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Func {
    pub insts: Vec<Inst>,
    /// Number of arguments (`Arg(0..n_args)`).
    pub n_args: u32,
    /// Values the body produces, in order (a kernel stores them; a caller uses them).
    pub outputs: Vec<V>,
}

impl Func {
    pub fn inst(&self, v: V) -> Inst {
        self.insts[v.0 as usize]
    }

    pub fn constant(&self, v: V) -> Option<f64> {
        match self.inst(v) {
            Inst::Const(c) => Some(c),
            _ => None,
        }
    }

    /// Remove instructions no output depends on, renumbering values (dead-code elimination).
    /// Returns the map from old to new values for the kept ones.
    pub fn prune(&mut self) -> Vec<Option<V>> {
        let n = self.insts.len();
        let mut live = vec![false; n];
        for o in &self.outputs {
            live[o.0 as usize] = true;
        }
        for i in (0..n).rev() {
            if !live[i] {
                continue;
            }
            for u in operands(&self.insts[i]) {
                live[u.0 as usize] = true;
            }
        }
        let mut map = vec![None; n];
        let mut kept = Vec::new();
        for (i, inst) in self.insts.iter().enumerate() {
            if live[i] {
                map[i] = Some(V(kept.len() as u32));
                kept.push(rename(inst, &map));
            }
        }
        self.insts = kept;
        for o in &mut self.outputs {
            *o = map[o.0 as usize].expect("outputs are live");
        }
        map
    }
}

/// The operands of an instruction.
pub fn operands(i: &Inst) -> Vec<V> {
    match *i {
        Inst::Const(_) | Inst::Arg(_) => vec![],
        Inst::Un(_, a) => vec![a],
        Inst::Bin(_, a, b) | Inst::Cmp(_, a, b) => vec![a, b],
        Inst::Select(c, a, b) => vec![c, a, b],
    }
}

fn rename(i: &Inst, map: &[Option<V>]) -> Inst {
    let m = |v: V| map[v.0 as usize].expect("operands precede their uses");
    match *i {
        Inst::Const(_) | Inst::Arg(_) => *i,
        Inst::Un(o, a) => Inst::Un(o, m(a)),
        Inst::Bin(o, a, b) => Inst::Bin(o, m(a), m(b)),
        Inst::Cmp(o, a, b) => Inst::Cmp(o, m(a), m(b)),
        Inst::Select(c, a, b) => Inst::Select(m(c), m(a), m(b)),
    }
}

/// Builds a [`Func`], folding constants, simplifying identities and sharing equal
/// subexpressions. Simplifications never change a result: `x * 0` is not folded (it is NaN for
/// an infinite `x`), `x + 0` and `x * 1` are.
#[derive(Default)]
pub struct Builder {
    pub func: Func,
    memo: HashMap<Key, V>,
}

impl Builder {
    pub fn new(n_args: u32) -> Self {
        let mut b = Builder::default();
        b.func.n_args = n_args;
        b
    }

    /// Continue building on an existing function (e.g. appending derivatives).
    pub fn extend(func: Func) -> Self {
        let mut memo = HashMap::new();
        for (i, inst) in func.insts.iter().enumerate() {
            memo.entry(Key::of(inst)).or_insert(V(i as u32));
        }
        Builder { func, memo }
    }

    pub fn finish(self) -> Func {
        self.func
    }

    fn push(&mut self, inst: Inst) -> V {
        let key = Key::of(&inst);
        if let Some(&v) = self.memo.get(&key) {
            return v;
        }
        let v = V(self.func.insts.len() as u32);
        self.func.insts.push(inst);
        self.memo.insert(key, v);
        v
    }

    fn c(&self, v: V) -> Option<f64> {
        self.func.constant(v)
    }

    pub fn constant(&mut self, x: f64) -> V {
        self.push(Inst::Const(x))
    }

    pub fn arg(&mut self, i: u32) -> V {
        assert!(i < self.func.n_args, "argument {i} out of range");
        self.push(Inst::Arg(i))
    }

    pub fn un(&mut self, op: UnOp, a: V) -> V {
        if let Some(x) = self.c(a) {
            return self.constant(eval_un(op, x));
        }
        if op == UnOp::Neg
            && let Inst::Un(UnOp::Neg, inner) = self.func.inst(a)
        {
            return inner;
        }
        self.push(Inst::Un(op, a))
    }

    pub fn bin(&mut self, op: BinOp, a: V, b: V) -> V {
        let (ca, cb) = (self.c(a), self.c(b));
        if let (Some(x), Some(y)) = (ca, cb) {
            return self.constant(eval_bin(op, x, y));
        }
        match op {
            BinOp::Add if cb == Some(0.0) => return a,
            BinOp::Add if ca == Some(0.0) => return b,
            BinOp::Sub if cb == Some(0.0) => return a,
            BinOp::Sub if ca == Some(0.0) => return self.un(UnOp::Neg, b),
            BinOp::Mul if cb == Some(1.0) => return a,
            BinOp::Mul if ca == Some(1.0) => return b,
            BinOp::Mul if cb == Some(-1.0) => return self.un(UnOp::Neg, a),
            BinOp::Mul if ca == Some(-1.0) => return self.un(UnOp::Neg, b),
            BinOp::Div if cb == Some(1.0) => return a,
            BinOp::Pow if cb == Some(1.0) => return a,
            // Small integer powers as products: exact for squares, within an ulp or two of
            // `powf` otherwise, and several times cheaper than a `pow` call in every backend.
            BinOp::Pow if cb == Some(2.0) => return self.bin(BinOp::Mul, a, a),
            BinOp::Pow if cb == Some(3.0) => {
                let sq = self.bin(BinOp::Mul, a, a);
                return self.bin(BinOp::Mul, sq, a);
            }
            BinOp::Pow if cb == Some(4.0) => {
                let sq = self.bin(BinOp::Mul, a, a);
                return self.bin(BinOp::Mul, sq, sq);
            }
            _ => {}
        }
        // Commutative operations in a canonical order, so `a*b` and `b*a` are shared.
        let (a, b) = match op {
            BinOp::Add | BinOp::Mul | BinOp::Min | BinOp::Max if b < a => (b, a),
            _ => (a, b),
        };
        self.push(Inst::Bin(op, a, b))
    }

    pub fn cmp(&mut self, op: CmpOp, a: V, b: V) -> V {
        if let (Some(x), Some(y)) = (self.c(a), self.c(b)) {
            return self.constant(f64::from(u8::from(eval_cmp(op, x, y))));
        }
        self.push(Inst::Cmp(op, a, b))
    }

    pub fn select(&mut self, c: V, a: V, b: V) -> V {
        if let Some(x) = self.c(c) {
            return if x != 0.0 { a } else { b };
        }
        if a == b {
            return a;
        }
        self.push(Inst::Select(c, a, b))
    }

    // Shorthands.
    pub fn add(&mut self, a: V, b: V) -> V {
        self.bin(BinOp::Add, a, b)
    }
    pub fn sub(&mut self, a: V, b: V) -> V {
        self.bin(BinOp::Sub, a, b)
    }
    pub fn mul(&mut self, a: V, b: V) -> V {
        self.bin(BinOp::Mul, a, b)
    }
    pub fn div(&mut self, a: V, b: V) -> V {
        self.bin(BinOp::Div, a, b)
    }
    pub fn neg(&mut self, a: V) -> V {
        self.un(UnOp::Neg, a)
    }
    pub fn powf(&mut self, a: V, p: f64) -> V {
        let e = self.constant(p);
        self.bin(BinOp::Pow, a, e)
    }
    pub fn scale(&mut self, k: f64, a: V) -> V {
        let c = self.constant(k);
        self.mul(c, a)
    }
    /// Sum of several values, left to right (a fixed order: results are reproducible).
    pub fn sum(&mut self, vs: &[V]) -> V {
        let mut it = vs.iter();
        let Some(&first) = it.next() else {
            return self.constant(0.0);
        };
        it.fold(first, |acc, &v| self.add(acc, v))
    }
}

pub fn eval_un(op: UnOp, x: f64) -> f64 {
    match op {
        UnOp::Neg => -x,
        UnOp::Abs => x.abs(),
        UnOp::Sqrt => x.sqrt(),
        UnOp::Cbrt => x.cbrt(),
        UnOp::Exp => x.exp(),
        UnOp::Ln => math::ln_f64(x),
        UnOp::Sin => x.sin(),
        UnOp::Cos => x.cos(),
        UnOp::Tan => x.tan(),
        UnOp::Tanh => x.tanh(),
        UnOp::Floor => x.floor(),
        UnOp::Ceil => x.ceil(),
    }
}

pub fn eval_bin(op: BinOp, x: f64, y: f64) -> f64 {
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

pub fn eval_cmp(op: CmpOp, x: f64, y: f64) -> bool {
    match op {
        CmpOp::Lt => x < y,
        CmpOp::Le => x <= y,
        CmpOp::Gt => x > y,
        CmpOp::Ge => x >= y,
        CmpOp::Eq => x == y,
        CmpOp::Ne => x != y,
    }
}

// ---------------------------------------------------------------- kernels

/// What a kernel runs over.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Domain {
    /// Each tetrahedron.
    Element,
    /// Each chamber triangle.
    Triangle,
    /// Each node.
    Node,
    /// Once (reductions, parameter transforms).
    Single,
}

/// A buffer the kernels read or write: `len(domain) × width` reals.
#[derive(Clone, Debug, PartialEq)]
pub struct Buffer {
    pub name: String,
    pub domain: Domain,
    pub width: u32,
    pub doc: String,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct BufferId(pub u32);

/// A scalar known for a whole launch (`t`, `dt`, `param.w.1`, …): an index in
/// [`Module::uniforms`], or, in a kernel still being built, in its builder's own table.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct UniformId(pub u32);

/// Where a kernel argument comes from.
#[derive(Clone, Debug, PartialEq)]
pub enum ArgSource {
    /// `buffer[entity][component]`.
    Own { buffer: BufferId, component: u32 },
    /// `buffer[node k of this element (or triangle)][component]`.
    Corner {
        buffer: BufferId,
        corner: u32,
        component: u32,
    },
    /// A scalar known for the whole launch: `t`, `dt`, a param, a constant of the scene.
    Uniform(UniformId),
    /// Node kernels: the sum over the node's incident entities (CSR order) of
    /// `buffer[entity][corner * stride + component]`, where `corner` is the node's position in
    /// the entity. Deterministic: the order is fixed by the CSR list.
    Gather {
        buffer: BufferId,
        /// The incident domain: `Element` or `Triangle`.
        over: Domain,
        stride: u32,
        component: u32,
    },
}

/// `buffer[entity][component] = body.outputs[output]`.
#[derive(Clone, Debug, PartialEq)]
pub struct Store {
    pub buffer: BufferId,
    pub component: u32,
    pub output: usize,
}

#[derive(Clone, Debug, PartialEq)]
pub struct Kernel {
    pub name: String,
    pub domain: Domain,
    /// Which declaration produced it (shown in printed IR and generated code).
    pub origin: String,
    pub args: Vec<ArgSource>,
    pub body: Func,
    pub stores: Vec<Store>,
}

impl Kernel {
    /// The uniforms the kernel reads, in order of first appearance among its arguments (the
    /// order of a launch's uniform values in every backend).
    pub fn uniforms(&self) -> Vec<UniformId> {
        let mut ids = Vec::new();
        for a in &self.args {
            if let ArgSource::Uniform(u) = a
                && !ids.contains(u)
            {
                ids.push(*u);
            }
        }
        ids
    }

    /// Remove the arguments the body does not read, renumbering the others.
    pub fn drop_unused_args(&mut self) {
        let mut used = vec![false; self.args.len()];
        for i in &self.body.insts {
            if let Inst::Arg(a) = i {
                used[*a as usize] = true;
            }
        }
        let mut new_index = vec![0u32; self.args.len()];
        let mut kept = Vec::new();
        for (i, a) in self.args.drain(..).enumerate() {
            if used[i] {
                new_index[i] = kept.len() as u32;
                kept.push(a);
            }
        }
        self.args = kept;
        for i in &mut self.body.insts {
            if let Inst::Arg(a) = i {
                *a = new_index[*a as usize];
            }
        }
        self.body.n_args = self.args.len() as u32;
    }
}

/// The elements of a scene: linear (4-node tets, 3-node chamber triangles) or quadratic
/// (10-node tets, 6-node triangles; corners first, then the mid-edge nodes in VTK's order).
/// A module is generated for one order; [`Domain::Element`] and [`Domain::Triangle`] entities
/// have that order's corners.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum ElementOrder {
    #[default]
    Linear,
    Quadratic,
}

impl ElementOrder {
    /// Nodes per element.
    pub fn element_nodes(self) -> u32 {
        match self {
            ElementOrder::Linear => 4,
            ElementOrder::Quadratic => 10,
        }
    }
    /// Nodes per chamber triangle.
    pub fn triangle_nodes(self) -> u32 {
        match self {
            ElementOrder::Linear => 3,
            ElementOrder::Quadratic => 6,
        }
    }
    /// 1 or 2.
    pub fn degree(self) -> u32 {
        match self {
            ElementOrder::Linear => 1,
            ElementOrder::Quadratic => 2,
        }
    }
}

/// A scene's kernels and the buffers they share.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Module {
    pub buffers: Vec<Buffer>,
    pub kernels: Vec<Kernel>,
    /// The name of each uniform the kernels read, indexed by [`UniformId`] (for printing,
    /// generated code and the edges that take values by name).
    pub uniforms: Vec<String>,
    /// The order of the elements and chamber triangles the kernels run over.
    pub order: ElementOrder,
}

impl Module {
    /// Nodes per entity of a domain with connectivity (elements and chamber triangles).
    pub fn corners(&self, d: Domain) -> Option<u32> {
        match d {
            Domain::Element => Some(self.order.element_nodes()),
            Domain::Triangle => Some(self.order.triangle_nodes()),
            Domain::Node | Domain::Single => None,
        }
    }

    /// The id of the uniform `name`, added to the table if new.
    pub fn uniform(&mut self, name: &str) -> UniformId {
        if let Some(id) = self.uniform_named(name) {
            return id;
        }
        self.uniforms.push(name.into());
        UniformId(self.uniforms.len() as u32 - 1)
    }

    pub fn uniform_named(&self, name: &str) -> Option<UniformId> {
        self.uniforms
            .iter()
            .position(|u| u == name)
            .map(|i| UniformId(i as u32))
    }

    pub fn uniform_name(&self, id: UniformId) -> &str {
        &self.uniforms[id.0 as usize]
    }

    /// Add a kernel built by a [`KernelBuilder`], its uniforms renumbered into this module's
    /// table. Returns its index.
    pub fn push_kernel(&mut self, built: BuiltKernel) -> usize {
        let BuiltKernel {
            mut kernel,
            uniforms,
        } = built;
        for a in &mut kernel.args {
            if let ArgSource::Uniform(u) = a {
                *u = self.uniform(&uniforms[u.0 as usize]);
            }
        }
        self.kernels.push(kernel);
        self.kernels.len() - 1
    }

    pub fn buffer(&mut self, name: &str, domain: Domain, width: u32, doc: &str) -> BufferId {
        if let Some(i) = self.buffers.iter().position(|b| b.name == name) {
            return BufferId(i as u32);
        }
        self.buffers.push(Buffer {
            name: name.into(),
            domain,
            width,
            doc: doc.into(),
        });
        BufferId(self.buffers.len() as u32 - 1)
    }

    pub fn buffer_named(&self, name: &str) -> Option<BufferId> {
        self.buffers
            .iter()
            .position(|b| b.name == name)
            .map(|i| BufferId(i as u32))
    }
}

/// A kernel as a [`KernelBuilder`] finished it: its [`ArgSource::Uniform`] ids index
/// `uniforms` until [`Module::push_kernel`] renumbers them into the module's table.
#[derive(Clone, Debug, PartialEq)]
pub struct BuiltKernel {
    pub kernel: Kernel,
    pub uniforms: Vec<String>,
}

/// The arguments of a function built standalone ([`KernelBuilder::into_parts`]): its sources,
/// and the names of the uniforms their ids index.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Args {
    pub sources: Vec<ArgSource>,
    pub uniforms: Vec<String>,
}

impl Args {
    /// The name of a uniform source (`None` for a buffer read).
    pub fn uniform_name(&self, a: &ArgSource) -> Option<&str> {
        match a {
            ArgSource::Uniform(u) => Some(&self.uniforms[u.0 as usize]),
            _ => None,
        }
    }
}

/// Helps write a kernel: arguments are allocated as they are requested, so the body reads
/// like the physics and the argument list is exactly what it uses. Uniforms are numbered in
/// the builder's own table (see [`BuiltKernel`]).
pub struct KernelBuilder {
    pub b: Builder,
    /// Unique in the process: what a memo of lowered values is keyed by.
    id: u64,
    args: Vec<ArgSource>,
    uniforms: Vec<String>,
    stores: Vec<Store>,
    name: String,
    domain: Domain,
    origin: String,
}

impl KernelBuilder {
    /// Unique among the builders of the process.
    pub fn id(&self) -> u64 {
        self.id
    }

    pub fn new(name: &str, domain: Domain, origin: &str) -> Self {
        static NEXT_ID: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
        KernelBuilder {
            b: Builder::new(u32::MAX),
            id: NEXT_ID.fetch_add(1, std::sync::atomic::Ordering::Relaxed),
            args: Vec::new(),
            uniforms: Vec::new(),
            stores: Vec::new(),
            name: name.into(),
            domain,
            origin: origin.into(),
        }
    }

    /// A builder whose uniform ids are `module`'s (to load arguments of its kernels as they
    /// are).
    pub fn in_module(module: &Module, name: &str, domain: Domain, origin: &str) -> Self {
        let mut k = KernelBuilder::new(name, domain, origin);
        k.uniforms = module.uniforms.clone();
        k
    }

    /// The value of an argument source (the same source twice gives the same value).
    pub fn load(&mut self, src: ArgSource) -> V {
        let i = match self.args.iter().position(|a| *a == src) {
            Some(i) => i,
            None => {
                self.args.push(src);
                self.args.len() - 1
            }
        };
        self.b.arg(i as u32)
    }

    /// The 3-vectors of `buffer` (node × 3) at an entity's first `corners` corners.
    pub fn corner_vectors(&mut self, buffer: BufferId, corners: u32) -> Vec<[V; 3]> {
        (0..corners)
            .map(|corner| {
                [0, 1, 2].map(|component| {
                    self.load(ArgSource::Corner {
                        buffer,
                        corner,
                        component,
                    })
                })
            })
            .collect()
    }

    pub fn uniform(&mut self, name: &str) -> V {
        let id = match self.uniforms.iter().position(|u| u == name) {
            Some(i) => i,
            None => {
                self.uniforms.push(name.into());
                self.uniforms.len() - 1
            }
        };
        self.load(ArgSource::Uniform(UniformId(id as u32)))
    }

    pub fn store(&mut self, buffer: BufferId, component: u32, value: V) {
        self.b.func.outputs.push(value);
        let output = self.b.func.outputs.len() - 1;
        self.stores.push(Store {
            buffer,
            component,
            output,
        });
    }

    /// The arguments and the body built so far (for a sub-function to be inlined, or a
    /// function evaluated on its own).
    pub fn into_parts(self) -> (Args, Func) {
        let args = Args {
            sources: self.args,
            uniforms: self.uniforms,
        };
        (args, self.b.finish())
    }

    /// Inline `func` (built by another `KernelBuilder` whose arguments were `sub`): its first
    /// `bound.len()` arguments take the given values, the others are loaded here. Returns the
    /// values of its outputs.
    pub fn inline(&mut self, sub: &Args, func: &Func, bound: &[V]) -> Vec<V> {
        self.inline_sources(&sub.sources, &sub.uniforms, func, bound)
    }

    /// [`KernelBuilder::inline`] with the sub-function's sources and uniform names apart (a
    /// module's kernel: its sources and the module's table).
    pub fn inline_sources(
        &mut self,
        sub_args: &[ArgSource],
        sub_uniforms: &[String],
        func: &Func,
        bound: &[V],
    ) -> Vec<V> {
        let mut map: Vec<V> = Vec::with_capacity(func.insts.len());
        for inst in &func.insts {
            let m = |v: V| map[v.0 as usize];
            let v = match *inst {
                Inst::Const(c) => self.b.constant(c),
                Inst::Arg(i) => match bound.get(i as usize) {
                    Some(&v) => v,
                    None => match &sub_args[i as usize] {
                        ArgSource::Uniform(u) => self.uniform(&sub_uniforms[u.0 as usize]),
                        a => self.load(a.clone()),
                    },
                },
                Inst::Un(op, a) => self.b.un(op, m(a)),
                Inst::Bin(op, a, b) => self.b.bin(op, m(a), m(b)),
                Inst::Cmp(op, a, b) => self.b.cmp(op, m(a), m(b)),
                Inst::Select(c, a, b) => self.b.select(m(c), m(a), m(b)),
            };
            map.push(v);
        }
        func.outputs.iter().map(|o| map[o.0 as usize]).collect()
    }

    /// The kernel, to be added to a module with [`Module::push_kernel`].
    pub fn finish(self) -> BuiltKernel {
        let mut body = self.b.finish();
        body.n_args = self.args.len() as u32;
        body.prune();
        BuiltKernel {
            kernel: Kernel {
                name: self.name,
                domain: self.domain,
                origin: self.origin,
                args: self.args,
                body,
                stores: self.stores,
            },
            uniforms: self.uniforms,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn kernels_built_apart_share_the_module_uniform_table() {
        let mut m = Module::default();
        let y = m.buffer("y", Domain::Single, 2, "");
        let mut a = KernelBuilder::new("a", Domain::Single, "test");
        let (t, p) = (a.uniform("t"), a.uniform("param.p"));
        let s = a.b.add(t, p);
        a.store(y, 0, s);
        let mut b = KernelBuilder::new("b", Domain::Single, "test");
        // A sub-function with its own table, inlined: its unbound uniform is renamed.
        let mut sub = KernelBuilder::new("sub", Domain::Single, "test");
        let (x, q) = (sub.uniform("x"), sub.uniform("param.q"));
        let r = sub.b.mul(x, q);
        sub.b.func.outputs.push(r);
        let (sub_args, func) = sub.into_parts();
        assert_eq!(sub_args.uniform_name(&sub_args.sources[1]), Some("param.q"));
        let p2 = b.uniform("param.p");
        let out = b.inline(&sub_args, &func, &[p2])[0];
        b.store(y, 1, out);
        m.push_kernel(a.finish());
        m.push_kernel(b.finish());
        assert_eq!(m.uniforms, ["t", "param.p", "param.q"]);
        let id = |n: &str| m.uniform_named(n).unwrap();
        assert_eq!(m.kernels[0].uniforms(), [id("t"), id("param.p")]);
        assert_eq!(m.kernels[1].uniforms(), [id("param.p"), id("param.q")]);
        for k in &m.kernels {
            valid::validate_kernel(&m, k).unwrap();
        }
        let text = m.to_string();
        assert!(text.contains("uniform param.q"), "{text}");
    }
}
