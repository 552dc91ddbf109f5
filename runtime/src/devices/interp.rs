//! The interpreter device: kernels evaluated by the IR interpreter (`ir::interp`), one entity
//! at a time. Slow, but the reference semantics every compiled device must reproduce.

use super::{Backend, Uniforms, domain_len};
use crate::engine::scene::{Csr, Scene};
use softc_compiler::ir::{ArgSource, BufferId, Domain, Kernel, Module, interp};
use std::ops::Range;

/// Buffers and connectivity as the interpreter reads them.
#[derive(Default)]
struct HostState {
    buffers: Vec<Vec<f64>>,
    widths: Vec<usize>,
    /// Element and triangle nodes as the kernels read them, and how many each has.
    elems: (Vec<u32>, usize),
    tris: (Vec<u32>, usize),
    node_elements: Csr,
    node_tris: Csr,
}

impl HostState {
    fn get(&self, b: BufferId, entity: usize, component: u32) -> f64 {
        self.buffers[b.0 as usize][entity * self.widths[b.0 as usize] + component as usize]
    }
}

/// Runs kernels with the IR interpreter (`ir::interp`), one entity at a time.
pub struct Interpreter {
    module: Module,
    state: HostState,
    args: Vec<f64>,
    vals: Vec<f64>,
}

impl Interpreter {
    pub fn new(module: &Module) -> Self {
        Interpreter {
            module: module.clone(),
            state: HostState::default(),
            args: Vec::new(),
            vals: Vec::new(),
        }
    }
}

/// The value of one kernel argument at one entity.
fn arg_value(k: &Kernel, a: &ArgSource, e: usize, st: &HostState, u: &Uniforms) -> f64 {
    match a {
        ArgSource::Own { buffer, component } => st.get(*buffer, e, *component),
        ArgSource::Corner {
            buffer,
            corner,
            component,
        } => {
            let node = match k.domain {
                Domain::Element => st.elems.0[e * st.elems.1 + *corner as usize],
                _ => st.tris.0[e * st.tris.1 + *corner as usize],
            };
            st.get(*buffer, node as usize, *component)
        }
        ArgSource::Uniform(id) => u.get(*id),
        ArgSource::Gather {
            buffer,
            over,
            stride,
            component,
        } => {
            let csr = if *over == Domain::Element {
                &st.node_elements
            } else {
                &st.node_tris
            };
            let mut sum = 0.0;
            for &(ent, corner) in csr.of(e) {
                sum += st.get(
                    *buffer,
                    ent as usize,
                    u32::from(corner) * stride + component,
                );
            }
            sum
        }
    }
}

impl Backend for Interpreter {
    fn name(&self) -> &'static str {
        "interp"
    }

    fn prepare(&mut self, scene: &Scene) -> Result<(), String> {
        self.state = HostState {
            buffers: self
                .module
                .buffers
                .iter()
                .map(|b| vec![0.0; domain_len(scene, b.domain) * b.width as usize])
                .collect(),
            widths: self
                .module
                .buffers
                .iter()
                .map(|b| b.width as usize)
                .collect(),
            elems: (scene.elem_conn(), scene.order().element_nodes() as usize),
            tris: (scene.tri_conn(), scene.order().triangle_nodes() as usize),
            node_elements: scene.node_elements.clone(),
            node_tris: scene.node_tris.clone(),
        };
        Ok(())
    }

    fn set(&mut self, b: BufferId, data: &[f64]) {
        let buf = &mut self.state.buffers[b.0 as usize];
        buf.clear();
        buf.extend_from_slice(data);
    }

    fn get(&self, b: BufferId) -> Vec<f64> {
        self.state.buffers[b.0 as usize].clone()
    }

    fn swap(&mut self, a: BufferId, b: BufferId) {
        self.state.buffers.swap(a.0 as usize, b.0 as usize);
    }

    fn run(&mut self, k: usize, range: Range<usize>, u: &Uniforms) -> Result<(), String> {
        let kernel = &self.module.kernels[k];
        for e in range {
            self.args.clear();
            for a in &kernel.args {
                self.args.push(arg_value(kernel, a, e, &self.state, u));
            }
            interp::eval_into(&kernel.body, &self.args, &mut self.vals);
            for s in &kernel.stores {
                let w = self.state.widths[s.buffer.0 as usize];
                let v = self.vals[kernel.body.outputs[s.output].0 as usize];
                self.state.buffers[s.buffer.0 as usize][e * w + s.component as usize] = v;
            }
        }
        Ok(())
    }
}
