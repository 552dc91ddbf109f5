//! How nearly incompressible the scene's materials are: the small-strain bulk-to-shear modulus
//! ratio K/μ of each, measured with the scene's own energy kernels (any strain energy, built-in
//! or written in the script, per-element fields included) on two homogeneous deformations of the
//! mesh. Linear tetrahedra lock volumetrically as K/μ grows, and a locked answer is a silent
//! wrong answer: measured on the verification cuboid (9,600 linear tets, neo-Hookean from
//! E = 1 MPa, 3 kPa, static), the tip moves −16.5, −8.0, −3.9, −0.5 and +0.7 µm at K/μ = 100,
//! 500, 1,000, 2,500 and 5,000 (ν = 0.495 … 0.4999), while 10-node tets on the same mesh give
//! −9.6 and −8.5 µm at 100 and 500: from K/μ ≈ 500 the linear answer collapses towards zero
//! and then changes sign.

use super::Simulation;
use super::scene::Scene;
use crate::devices::interp::Interpreter;
use crate::devices::{Backend, Uniforms};
use softc_compiler::ir::ElementOrder;

/// K/μ above which linear tetrahedra are warned about (ν ≈ 0.498).
pub const LOCKING_RATIO: f64 = 250.0;
/// Strain of the two probe deformations (evaluated in f64): the nonlinear terms are ~1e-4 of
/// the small-strain moduli, the round-off of the energies ~1e-8.
const PROBE_STRAIN: f64 = 1e-4;
/// Elements probed per material (the first of its range; per-element fields may differ).
const PROBED: usize = 256;

/// One material's ratio.
#[derive(Clone, Debug, PartialEq)]
pub struct BulkToShear {
    pub material: String,
    /// The largest K/μ over the probed elements.
    pub ratio: f64,
}

impl BulkToShear {
    /// Poisson's ratio of an isotropic material with this K/μ.
    pub fn poisson(&self) -> f64 {
        let r = self.ratio;
        (3.0 * r - 2.0) / (2.0 * (3.0 * r + 1.0))
    }
}

/// Each material's K/μ, from the energy W of a uniform dilation F = (1 + ε)·I (W = 9/2·K·ε²)
/// and of a pure shear F = diag(1 + ε, 1/(1 + ε), 1) (J = 1, W = 2·μ·ε²), evaluated by the
/// scene's diagnostics kernels in the interpreter (f64) on the first [`PROBED`] elements of the
/// material. Materials without an energy kernel (springs) or without shear stiffness are left
/// out.
pub fn bulk_to_shear(scene: &Scene) -> Vec<BulkToShear> {
    bulk_to_shear_at(scene, None)
}

/// [`bulk_to_shear`] at the param values of `uniforms` (a run's, an optimization's current
/// ones), else at the script's.
pub fn bulk_to_shear_at(scene: &Scene, uniforms: Option<&Uniforms>) -> Vec<BulkToShear> {
    let e = PROBE_STRAIN;
    let [dilation, shear] = probe_energies(scene, uniforms, [[1.0 + e; 3], pure_shear()]);
    let mut out = Vec::new();
    for (k, (dilated, sheared)) in dilation.iter().zip(&shear).enumerate() {
        let ratio = dilated
            .iter()
            .zip(sheared)
            .filter(|(_, s)| **s > 0.0)
            .map(|(d, s)| 4.0 / 9.0 * d / s)
            .filter(|r| r.is_finite())
            .fold(f64::NAN, f64::max);
        if ratio.is_finite() {
            out.push(BulkToShear {
                material: scene.lowered.materials[k].clone(),
                ratio,
            });
        }
    }
    out
}

/// The pure shear F = diag(1 + ε, 1/(1 + ε), 1) of the probes.
fn pure_shear() -> [f64; 3] {
    let e = PROBE_STRAIN;
    [1.0 + e, 1.0 / (1.0 + e), 1.0]
}

/// The largest small-strain shear modulus μ (Pa) over the probed elements of every material,
/// from the pure shear's energy V·W = 2·μ·ε²·V (at the param values of `uniforms`, else at
/// the script's); `None` without energy kernels (springs). Linear tetrahedra.
pub fn shear_modulus_at(scene: &Scene, uniforms: Option<&Uniforms>) -> Option<f64> {
    let [shear] = probe_energies(scene, uniforms, [pure_shear()]);
    // Rest volumes in kernel element order, as the material ranges count them.
    let volume = |e: usize| scene.pre.rest_volume[e];
    let e2 = PROBE_STRAIN * PROBE_STRAIN;
    let mu = (scene.material_ranges.iter().zip(&shear))
        .flat_map(|(range, energies)| {
            energies
                .iter()
                .enumerate()
                .map(move |(i, w)| w / (2.0 * e2 * volume(range.start + i)))
        })
        .filter(|m| m.is_finite())
        .fold(f64::NAN, f64::max);
    mu.is_finite().then_some(mu)
}

/// The energies (`elem_energy`, V·W) of the first [`PROBED`] elements of each material under
/// each homogeneous stretch of the mesh about its centre, evaluated in the interpreter (f64);
/// empty for a material without an energy kernel.
fn probe_energies<const N: usize>(
    scene: &Scene,
    uniforms: Option<&Uniforms>,
    stretches: [[f64; 3]; N],
) -> [Vec<Vec<f64>>; N] {
    let Some(energy) = scene.lowered.buffers.elem_energy else {
        return std::array::from_fn(|_| Vec::new());
    };
    let mut sim = Simulation::new(scene, Interpreter::new(&scene.lowered.module));
    if let Some(u) = uniforms {
        sim.uniforms = u.clone();
        sim.upload_fields();
    }
    let nodes = &scene.mesh.nodes;
    let n = nodes.len().max(1) as f64;
    let centre = [0, 1, 2].map(|d| nodes.iter().map(|p| p[d]).sum::<f64>() / n);
    stretches.map(|stretch| {
        let x: Vec<f64> = nodes
            .iter()
            .flat_map(|p| [0, 1, 2].map(|d| centre[d] + stretch[d] * (p[d] - centre[d])))
            .collect();
        sim.backend.set(scene.lowered.buffers.x, &x);
        let mut out = Vec::new();
        for (k, range) in scene.material_ranges.iter().enumerate() {
            let probed = range.start..range.end.min(range.start + PROBED);
            let ran = scene.lowered.diagnostics.get(k).map(|&kernel| {
                sim.backend
                    .run(kernel, probed.clone(), &sim.uniforms)
                    .is_ok()
            });
            out.push(match ran {
                Some(true) => sim.backend.get(energy)[probed].to_vec(),
                _ => Vec::new(),
            });
        }
        out
    })
}

/// The warning for linear tetrahedra of a material whose K/μ exceeds [`LOCKING_RATIO`].
pub fn locking_warning(scene: &Scene) -> Option<String> {
    if scene.lowered.module.order != ElementOrder::Linear {
        return None;
    }
    let worst = bulk_to_shear(scene)
        .into_iter()
        .filter(|m| m.ratio > LOCKING_RATIO)
        .max_by(|a, b| a.ratio.total_cmp(&b.ratio))?;
    Some(format!(
        "warning: material `{}` is nearly incompressible (bulk/shear modulus ratio K/μ = {:.0}, \
         ν = {:.5}): linear tetrahedra lock volumetrically at this ratio, and the \
         displacements come out too small, beyond K/μ ≈ 2,500 even with the wrong sign (the \
         verification cuboid's tip: −8.0 µm at K/μ = 500, −3.9 at 1,000, +0.7 at 5,000, \
         against −8.5 µm with quadratic elements). Use quadratic elements (`softc mesh \
         convert --order 2`, then `load(…, order: 2)`) or K/μ ≤ {LOCKING_RATIO:.0} \
         (ν ≤ 0.498)",
        worst.material,
        worst.ratio,
        worst.poisson()
    ))
}
