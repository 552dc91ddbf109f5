//! Devices that run a scene's kernels, each behind the [`Backend`] trait the time loop
//! ([`crate::engine`]) drives: [`interp`], the kernel-IR interpreter (the reference semantics);
//! [`cpu`], native code through Cranelift; [`gpu`], wgpu on any GPU (or Mesa's lavapipe).
//! [`open`] is the one place that maps `--backend` and `--precision` to a device.

pub mod choice;
pub mod cpu;
pub mod gpu;
pub mod interp;

pub use choice::{BackendChoice, Device, DeviceChoice, Devices, PrecisionChoice, open, precision};

use crate::engine::scene::Scene;
use softc_compiler::back::Precision;
use softc_compiler::ir::{BufferId, Domain, UniformId};
use std::collections::BTreeMap;
use std::ops::Range;

/// Executes kernels and owns the buffers they read and write. The IR interpreter is the
/// reference semantics; compiled backends must reproduce it.
pub trait Backend {
    fn name(&self) -> &'static str;
    /// Allocate zeroed buffers for the scene's entity counts and take its connectivity.
    fn prepare(&mut self, scene: &Scene) -> Result<(), String>;
    fn set(&mut self, b: BufferId, data: &[f64]);
    fn get(&self, b: BufferId) -> Vec<f64>;
    /// Copy buffer `b` into `out` (a checkpoint slot, in the store's precision): exact when
    /// that is the device's. Backends that hold the buffer on the host copy it directly.
    fn get_into(&self, b: BufferId, out: HostSliceMut<'_>) {
        let v = self.get(b);
        match out {
            HostSliceMut::F64(o) => o.copy_from_slice(&v),
            HostSliceMut::F32(o) => {
                for (o, &x) in o.iter_mut().zip(&v) {
                    *o = x as f32;
                }
            }
        }
    }
    /// Set buffer `b` from `src` (a checkpoint slot).
    fn set_from(&mut self, b: BufferId, src: HostSlice<'_>) {
        match src {
            HostSlice::F64(s) => self.set(b, s),
            HostSlice::F32(s) => {
                let v: Vec<f64> = s.iter().map(|&x| f64::from(x)).collect();
                self.set(b, &v);
            }
        }
    }
    fn swap(&mut self, a: BufferId, b: BufferId);
    /// Run kernel `k` of the module over the entities in `range`.
    fn run(&mut self, k: usize, range: Range<usize>, uniforms: &Uniforms) -> Result<(), String>;
    /// The kernels' floating-point precision (the stable-step estimate sizes its probe by it).
    fn precision(&self) -> Precision {
        Precision::F64
    }
    /// A failure of the device that `get` or `set` could not return (a lost GPU, a failed
    /// readback): the time loop reports it at its next state check instead of reading garbage.
    fn device_error(&self) -> Option<String> {
        None
    }
    /// Join the lockstep group of a batch backend whose scenes run on threads of their own
    /// ([`crate::devices::gpu::GpuScene`]): until the token is dropped, the scene's readbacks
    /// wait for the group's, so the batch shares submissions and readbacks. Enter every
    /// scene's group before any of them runs, and drop each token when its scene's work ends
    /// (a scene that never asks again would hold the others). Other backends: no effect.
    fn lockstep(&self) -> Lockstep {
        Lockstep::default()
    }
    /// Whether the backend's steps run ahead of the host (a GPU: launches are recorded and
    /// the device works through them while the host goes on). The time loop then checks
    /// the state less often ([`crate::engine::CHECK_EVERY_RUNNING_AHEAD`] steps): a check
    /// reads the whole state back and scans it on the host, which must stay shorter than
    /// the device's steps between two checks or the device waits for it.
    fn runs_ahead(&self) -> bool {
        false
    }
    /// Start reading buffers back without waiting for them: a GPU copies them at this point
    /// of its recorded work and goes on; [`Backend::collect`] waits for the copy (and only
    /// for it). Backends that hold buffers on the host read them at once.
    fn read_later(&mut self, bufs: &[BufferId]) -> PendingRead {
        PendingRead::Done(bufs.iter().map(|&b| self.get(b)).collect())
    }
    /// The values of a [`Backend::read_later`], in its buffers' order.
    fn collect(&mut self, read: PendingRead) -> Vec<Vec<f64>> {
        match read {
            PendingRead::Done(v) => v,
            PendingRead::Ticket(..) => panic!("a read of another backend"),
        }
    }
    /// Keep up to `slots` states of `len` values each (a state's x and v) in the device's
    /// memory for [`Backend::store_state`] and [`Backend::restore_state`]: `Ok(Some(bytes))`
    /// when it does (the bytes reserved), `Ok(None)` when states stay on the host (the
    /// default; also a device without room). Replaces earlier slots.
    fn device_states(&mut self, slots: usize, len: usize) -> Result<Option<u64>, String> {
        let _ = (slots, len);
        Ok(None)
    }
    /// Copy `x` and `v` into device slot `slot` (after [`Backend::device_states`]).
    fn store_state(&mut self, slot: usize, x: BufferId, v: BufferId) -> Result<(), String> {
        let _ = (slot, x, v);
        Err("this backend keeps no states on the device".into())
    }
    /// Copy device slot `slot` into `x` and `v`.
    fn restore_state(&mut self, slot: usize, x: BufferId, v: BufferId) -> Result<(), String> {
        let _ = (slot, x, v);
        Err("this backend keeps no states on the device".into())
    }
    /// Run a [`Stepped`] stretch (steps up or down, with device state copies) at once, if
    /// the backend can; `Ok(false)`, having done nothing, if not. Bit-identical to the same
    /// copies and launches made one by one.
    fn run_stepped(&mut self, stepped: &Stepped<'_>) -> Result<bool, String> {
        let _ = stepped;
        Ok(false)
    }
    /// Run `n` whole steps at once, the first being step `first`, if the backend can: each
    /// step sets `t = step · dt`, runs `launches` (kernel, entity range) in order, then swaps
    /// the buffer pairs `swaps`. Returns `false`, having done nothing, when it cannot; the
    /// engine then steps one launch at a time. The result must be bit-identical either way.
    fn run_steps(
        &mut self,
        launches: &[Launch],
        swaps: &[(BufferId, BufferId)],
        first: u64,
        n: u64,
        dt: f64,
        uniforms: &Uniforms,
    ) -> Result<bool, String> {
        let _ = (launches, swaps, first, n, dt, uniforms);
        Ok(false)
    }
}

/// A stretch of steps a backend may run at once ([`Backend::run_stepped`]): step `j` of
/// the `n` is step `first + j` (`first - j` when `reverse`, the adjoint's order), runs at
/// `t = step · dt` (in every launch that reads `t`), first copying the state into or out of
/// device slot `step` when `states` says so, then `launches` in order, then swapping the
/// buffer pairs `swaps`.
pub struct Stepped<'a> {
    pub launches: &'a [Launch],
    pub swaps: &'a [(BufferId, BufferId)],
    pub first: u64,
    pub n: u64,
    pub dt: f64,
    pub uniforms: &'a Uniforms,
    pub reverse: bool,
    pub states: Option<StateCopy>,
}

/// The state copy before each step of a [`Stepped`] stretch: positions and velocities into
/// device slot `step` ([`Backend::store_state`]) or out of it ([`Backend::restore_state`]).
#[derive(Clone, Copy, Debug)]
pub enum StateCopy {
    Store { x: BufferId, v: BufferId },
    Restore { x: BufferId, v: BufferId },
}

/// A readback under way ([`Backend::read_later`]).
pub enum PendingRead {
    /// Read already.
    Done(Vec<Vec<f64>>),
    /// A GPU's copy in flight: its ticket and the values' counts.
    Ticket(u64, Vec<usize>),
}

/// Values kept on the host (a checkpoint slot), in their stored precision.
#[derive(Clone, Copy)]
pub enum HostSlice<'a> {
    F32(&'a [f32]),
    F64(&'a [f64]),
}

/// Room for values on the host (a checkpoint slot), in its precision.
pub enum HostSliceMut<'a> {
    F32(&'a mut [f32]),
    F64(&'a mut [f64]),
}

/// A kernel over a range of its entities.
pub(crate) type Launch = (usize, Range<usize>);

/// Membership of a lockstep group ([`Backend::lockstep`]); dropping it leaves the group.
#[derive(Default)]
pub struct Lockstep(Option<Box<dyn FnOnce() + Send>>);

impl Lockstep {
    pub fn new(leave: impl FnOnce() + Send + 'static) -> Self {
        Lockstep(Some(Box::new(leave)))
    }
}

impl Drop for Lockstep {
    fn drop(&mut self) {
        if let Some(leave) = self.0.take() {
            leave();
        }
    }
}

/// Values of the uniforms (`t`, `dt`, `param.*`, `input.*`), indexed by [`UniformId`]: the
/// first ids are those of the module the kernels come from (a scene's adjoint module extends
/// its forward module with the same table), then come the other named values a run may need
/// (params and inputs that only the loss reads). Kernel launches read values by id; names are
/// for the edges (the optimizer, `--set`, the loss).
#[derive(Clone, Debug, Default)]
pub struct Uniforms {
    names: Vec<String>,
    values: Vec<Option<f64>>,
}

impl Uniforms {
    /// A table that starts with `table` (a module's [`softc_compiler::ir::Module::uniforms`]), with the values of
    /// `named` (names outside `table` are added after it).
    pub fn new(table: &[String], named: &BTreeMap<String, f64>) -> Self {
        let mut u = Uniforms {
            names: table.to_vec(),
            values: vec![None; table.len()],
        };
        for (name, &v) in named {
            u.set_named(name, v);
        }
        u
    }

    /// The value of a uniform.
    #[inline]
    pub fn get(&self, id: UniformId) -> f64 {
        match self.values.get(id.0 as usize) {
            Some(Some(v)) => *v,
            _ => panic!("uniform `{}` has no value", self.name(id)),
        }
    }

    /// The value of a uniform, if it has one.
    pub fn value(&self, id: UniformId) -> Option<f64> {
        self.values.get(id.0 as usize).copied().flatten()
    }

    pub fn set(&mut self, id: UniformId, value: f64) {
        self.values[id.0 as usize] = Some(value);
    }

    /// The id of a uniform by name (resolve once, then use [`Uniforms::get`]).
    pub fn id(&self, name: &str) -> Option<UniformId> {
        self.names
            .iter()
            .position(|n| n == name)
            .map(|i| UniformId(i as u32))
    }

    /// The id of `name`, added to the table (without a value) if new.
    pub fn intern(&mut self, name: &str) -> UniformId {
        match self.id(name) {
            Some(id) => id,
            None => {
                self.names.push(name.into());
                self.values.push(None);
                UniformId(self.names.len() as u32 - 1)
            }
        }
    }

    pub fn name(&self, id: UniformId) -> &str {
        self.names.get(id.0 as usize).map_or("?", String::as_str)
    }

    /// The value of a uniform by name, if it has one.
    pub fn named(&self, name: &str) -> Option<f64> {
        self.id(name).and_then(|id| self.value(id))
    }

    /// Set a uniform by name (added to the table if new).
    pub fn set_named(&mut self, name: &str, value: f64) {
        let id = self.intern(name);
        self.set(id, value);
    }
}

/// Entity count of a domain in a scene.
pub fn domain_len(scene: &Scene, d: Domain) -> usize {
    match d {
        Domain::Node => scene.mesh.nodes.len(),
        Domain::Element => scene.mesh.tets.len(),
        Domain::Triangle => scene.tris.len(),
        Domain::Single => 1,
    }
}
