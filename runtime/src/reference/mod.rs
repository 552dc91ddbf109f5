//! The reference simulator: a plain-Rust f64 implementation of softc's physics, written
//! independently of the kernel IR so that it can serve as the test oracle of every backend.
//!
//! From the [`Scene`] it takes only data: the mesh (nodes in metres, tets grouped by material),
//! the material of each element range, the chamber triangles, the fixed nodes, the values of
//! params and inputs, the time-step choice and the parsed script. Everything else it computes
//! itself: rest shapes Dm⁻¹ and volumes (nalgebra), densities and lumped masses (with
//! `mass_scaling`), and every expression of the script (material constants, W, pressures,
//! damping, gravity) with its own tree-walking evaluator over the AST ([`eval`]). It
//! differentiates W(Ī1, Ī2, J) in forward mode with dual numbers ([`dual`]), where the kernels
//! use reverse-mode AD on the IR. Per step, with t = step·dt at the start of the step:
//!
//! - element forces: F = Ds·Dm⁻¹, P = ∂W/∂F by the chain rule through Ī1 = J^(−2/3)·I1,
//!   Ī2 = J^(−4/3)·I2 and J (F⁻ᵀ from `try_inverse`), the columns of −V0·P·Dm⁻ᵀ on corners
//!   1–3, minus their sum on corner 0;
//! - follower pressure: p(t)/6 · (x1 − x0) × (x2 − x0) on each corner of each chamber triangle;
//! - quadratic (10-node) elements ([`quadratic`]): F, P and the forces −V_q·P_q·∇_X Nₐ at each
//!   point of the 4-point rule from the element's own isoparametric rest Jacobians, follower
//!   pressure p ∫ Nₐ (x,ξ × x,η) on 6-node triangles by a 7-point rule (exact), HRZ masses;
//! - semi-implicit Euler: v' = (v + dt·(F/m − β·v + g))·(1 − fixed), x' = x + dt·v'.
//!
//! Closed-loop control: pressures and damping that read reductions over node sets evaluate
//! them here too, by the same tree walk over the state each step starts from.
//!
//! Every step is checked: an inverted element (J ≤ 0) or a non-finite position stops the run
//! with the step, the time and the element or node. `dt = auto` is resolved by its own power
//! iteration on M⁻¹K (K·u from central differences of its own forces, M its own lumped
//! masses, so it holds for 10-node elements as well).
//!
//! Entry points: [`run`] (what `softc run --backend reference` calls), [`Reference::step`] for
//! per-step comparisons, [`Reference::element`] and [`Reference::element_quadratic`] for
//! element-level checks.

pub mod dual;
pub mod eval;
pub mod quadratic;

use crate::engine::RunSummary;
use crate::engine::scene::{DtChoice, Scene};
use dual::Dual;
use eval::{Evaluator, Scope};
use nalgebra::{Matrix3, Vector3};
use softc_compiler::front::ast::*;
use softc_compiler::ir::ElementOrder;

type Vec3 = Vector3<f64>;

/// A material ready to evaluate: its template arguments and `let`s, and its W. A material
/// whose constants read a per-element param has one of these per element.
struct Material<'a> {
    name: String,
    density: f64,
    scope: Scope<'a>,
    /// Derivative slot (0 = Ī1, or I1 for a non-isochoric W; 1 = Ī2; 2 = J) of each argument
    /// of W, with its name.
    args: Vec<(&'a str, usize)>,
    body: &'a Expr,
    /// W is written in Ī1, Ī2 (else in I1 = tr C and J: no isochoric factors, finite and
    /// evaluated for J ≤ 0, i.e. inversion-safe).
    isochoric: bool,
}

/// What one element contributes at a deformed configuration.
#[derive(Clone, Debug)]
pub struct ElementResult {
    /// Forces on the four corners, N.
    pub forces: [[f64; 3]; 4],
    /// Strain energy V0·W, J.
    pub energy: f64,
    /// Volume ratio det F.
    pub j: f64,
    /// First Piola–Kirchhoff stress, row-major, Pa.
    pub piola: [[f64; 3]; 3],
}

/// What a quadratic element contributes at a deformed configuration.
#[derive(Clone, Debug)]
pub struct QuadraticElementResult {
    /// Forces on the 10 nodes (corners, then mid-edge nodes), N.
    pub forces: [[f64; 3]; 10],
    /// Strain energy Σ_q V_q·W(F_q), J.
    pub energy: f64,
    /// det F at each quadrature point.
    pub j: [f64; 4],
}

/// A quadratic scene's elements and chamber triangles with all their nodes, and each
/// element's rest data per quadrature point.
struct Quadratic {
    conn: Vec<[u32; 10]>,
    rest: Vec<[quadratic::RestPoint; 4]>,
    tris: Vec<[u32; 6]>,
}

/// The reference simulator bound to a scene.
pub struct Reference<'a> {
    scene: &'a Scene,
    ev: Evaluator<'a>,
    /// Materials as evaluated: one per material, or one per element for a material whose
    /// constants vary per element.
    materials: Vec<Material<'a>>,
    /// The entry of `materials` of each element.
    elem_material: Vec<usize>,
    /// Dm⁻¹ per element (linear scenes only).
    dm_inv: Vec<Matrix3<f64>>,
    /// Rest volume per element (a quadratic one's ∫ det J).
    rest_volume: Vec<f64>,
    /// Lumped node masses ρ·V0/4 from each adjacent tet (quadratic: HRZ), times
    /// `mass_scaling`.
    mass: Vec<f64>,
    /// Quadratic scenes: 10-node elements and 6-node triangles.
    quad: Option<Quadratic>,
    /// Pressure expression per chamber, in `scene.lowered.chambers` order.
    pressures: Vec<&'a Expr>,
    damping: Option<&'a Expr>,
    gravity: Option<Vec3>,
    /// `model = springs(…)`: the spring mesh instead of FEM.
    springs: Option<SpringMesh>,
}

/// The spring mesh (thesis eq. 2.3–2.7, 2.16), built per unique edge here (the kernels add
/// each tet's share instead).
struct SpringMesh {
    /// The volume-conservation scale α, N/m³.
    alpha: f64,
    edges: Vec<SpringEdge>,
}

struct SpringEdge {
    nodes: [usize; 2],
    l0: f64,
    /// Rest volume of the edge's tets per material: (material, V0).
    volumes: Vec<(usize, f64)>,
}

/// The oracle's own parse of a script's text: it reads the script itself, not the compiler's
/// checked program whose lowering it checks. Kept for the process's life, one per distinct
/// text (the oracle runs in tests and in `softc bench`'s check, on a handful of scripts).
fn parsed(source: &str) -> Result<&'static softc_compiler::front::ast::Script, String> {
    use std::collections::HashMap;
    use std::sync::{Mutex, OnceLock};
    type Cache = Mutex<HashMap<String, &'static softc_compiler::front::ast::Script>>;
    static CACHE: OnceLock<Cache> = OnceLock::new();
    let mut cache = (CACHE.get_or_init(Default::default).lock())
        .unwrap_or_else(|poisoned| poisoned.into_inner());
    if let Some(s) = cache.get(source) {
        return Ok(s);
    }
    let script = softc_compiler::front::parse(source).map_err(|d| d.message)?;
    let script: &'static _ = Box::leak(Box::new(script));
    cache.insert(source.to_string(), script);
    Ok(script)
}

impl<'a> Reference<'a> {
    pub fn new(scene: &'a Scene) -> Result<Self, String> {
        let syntax = parsed(&scene.source)?;
        let prelude = softc_compiler::sema::prelude_ast();
        let mut ev = Evaluator::new(syntax, prelude, &scene.uniforms);
        // Closed-loop control: the sim block's lets and the node sets its reductions read.
        for s in syntax.sim_block() {
            if let StmtKind::Let(l) = &s.kind {
                ev.sim_lets.insert(l.name.name.as_str(), &l.value);
            }
        }
        ev.node_sets = scene.node_sets.iter().cloned().collect();
        let n_tets = scene.mesh.tets.len();
        for f in &scene.fields {
            let mut entries = vec![None; n_tets];
            for (i, &e) in f.elements.iter().enumerate() {
                entries[e as usize] = Some(i);
            }
            ev.add_field(&f.name, entries);
        }
        // Each material once, evaluated at its first element; again at every element if its
        // constants read a per-element param.
        let mut materials = Vec::new();
        let mut elem_material = vec![usize::MAX; n_tets];
        for (name, range) in scene.resolved.materials.iter().zip(&scene.material_ranges) {
            ev.element = Some(range.start);
            ev.field_reads = 0;
            if range.is_empty() {
                continue;
            }
            let first = material(&mut ev, name)?;
            if ev.field_reads == 0 {
                elem_material[range.clone()].fill(materials.len());
                materials.push(first);
                continue;
            }
            for e in range.clone() {
                ev.element = Some(e);
                elem_material[e] = materials.len();
                materials.push(material(&mut ev, name)?);
            }
        }
        ev.element = None;
        if let Some(e) = elem_material.iter().position(|&m| m == usize::MAX) {
            return Err(format!("element {} has no material", scene.mesh.tet_id(e)));
        }
        let sim = syntax.sim_block();
        // The oracle has no contact: it would silently let the body pass through.
        if sim
            .iter()
            .any(|s| matches!(s.kind, StmtKind::Contact { .. }))
        {
            return Err("the reference simulator has no contact with obstacles".into());
        }
        let pressure_stmts: Vec<(&str, &Expr)> = sim
            .iter()
            .filter_map(|s| match &s.kind {
                StmtKind::Pressure { chamber, value } => Some((chamber.name.as_str(), value)),
                _ => None,
            })
            .collect();
        if pressure_stmts.len() != scene.resolved.chambers.len()
            || pressure_stmts
                .iter()
                .zip(&scene.resolved.chambers)
                .any(|((a, _), b)| a != b)
        {
            return Err("the scene's chambers do not match the sim block's pressures".into());
        }
        let gravity = match &syntax.sim_setting("gravity") {
            Some(e) => {
                let g = ev.eval(&Scope::root(), e)?.flat();
                if g.len() != 3 {
                    return Err("`gravity` is not a 3-vector".into());
                }
                Some(Vec3::new(g[0].v, g[1].v, g[2].v))
            }
            None => None,
        };
        // Rest shapes and masses from the mesh, independently of the scene's precomputation.
        let n_nodes = scene.mesh.nodes.len();
        let mut dm_inv = Vec::with_capacity(scene.mesh.tets.len());
        let mut rest_volume = Vec::with_capacity(scene.mesh.tets.len());
        let mut mass = vec![0.0; n_nodes];
        let scaling = match &syntax.sim_setting("mass_scaling") {
            Some(e) => ev.eval(&Scope::root(), e)?.scalar()?.v,
            None => 1.0,
        };
        let mids = match (scene.order(), &scene.mesh.mid_edges) {
            (ElementOrder::Linear, _) => None,
            (ElementOrder::Quadratic, Some(q)) if q.tets.len() == n_tets => Some(q),
            (ElementOrder::Quadratic, _) => {
                return Err("a quadratic scene without the mid-edge nodes of its elements".into());
            }
        };
        let mut quad = match mids {
            None => None,
            Some(_) if scene.tri_mids.len() != scene.tris.len() => {
                return Err(
                    "a quadratic scene without its chamber triangles' mid-edge nodes".into(),
                );
            }
            Some(_) => Some(Quadratic {
                conn: Vec::with_capacity(n_tets),
                rest: Vec::with_capacity(n_tets),
                tris: scene
                    .tris
                    .iter()
                    .zip(&scene.tri_mids)
                    .map(|(c, m)| [c[0], c[1], c[2], m[0], m[1], m[2]])
                    .collect(),
            }),
        };
        for (e, tet) in scene.mesh.tets.iter().enumerate() {
            if let (Some(q), Some(mids)) = (&mut quad, mids) {
                let m = mids.tets[e];
                let conn: [u32; 10] =
                    std::array::from_fn(|a| if a < 4 { tet[a] } else { m[a - 4] });
                let x = conn.map(|n| Vec3::from(scene.mesh.nodes[n as usize]));
                let rest = quadratic::rest_points(&x).map_err(|det| {
                    format!(
                        "element {} has det J = {det:e} ≤ 0 at a quadrature point",
                        scene.mesh.tet_id(e)
                    )
                })?;
                let (v0, lumped) = quadratic::hrz_masses(&x);
                if !(v0 > 0.0 && v0.is_finite()) {
                    return Err(format!(
                        "element {} has rest volume {v0:e} m³ ≤ 0",
                        scene.mesh.tet_id(e)
                    ));
                }
                let rho = materials[elem_material[e]].density * scaling;
                for (&n, l) in conn.iter().zip(lumped) {
                    mass[n as usize] += rho * l;
                }
                q.conn.push(conn);
                q.rest.push(rest);
                rest_volume.push(v0);
                continue;
            }
            let p = tet.map(|n| Vec3::from(scene.mesh.nodes[n as usize]));
            let dm = Matrix3::from_columns(&[p[1] - p[0], p[2] - p[0], p[3] - p[0]]);
            let v0 = dm.determinant() / 6.0;
            if !(v0 > 0.0 && v0.is_finite()) {
                return Err(format!(
                    "element {} has rest volume {v0:e} m³ ≤ 0",
                    scene.mesh.tet_id(e)
                ));
            }
            let inv = dm.try_inverse().ok_or_else(|| {
                format!("element {} has a singular rest shape", scene.mesh.tet_id(e))
            })?;
            let m = materials[elem_material[e]].density * v0 / 4.0 * scaling;
            for &n in tet {
                mass[n as usize] += m;
            }
            dm_inv.push(inv);
            rest_volume.push(v0);
        }
        let springs = match syntax.sim_setting("model").map(|e| &e.kind) {
            Some(ExprKind::Call { args, .. }) => {
                let a = args
                    .iter()
                    .find(|a| {
                        a.name
                            .as_ref()
                            .is_some_and(|n| n.name == "volume_stiffness")
                    })
                    .or_else(|| args.first())
                    .ok_or("`springs(…)` without a volume stiffness")?;
                let alpha = ev.eval(&Scope::root(), &a.value)?.scalar()?.v;
                if quad.is_some() {
                    return Err("the spring mesh is defined on linear (4-node) tets only".into());
                }
                Some(spring_mesh(scene, &elem_material, &rest_volume, alpha))
            }
            _ => None,
        };
        Ok(Reference {
            scene,
            materials,
            elem_material,
            dm_inv,
            rest_volume,
            mass,
            quad,
            springs,
            pressures: pressure_stmts.into_iter().map(|(_, e)| e).collect(),
            damping: syntax.sim_setting("damping"),
            // Gravity acts on the physical mass: an acceleration g / mass_scaling.
            gravity: gravity.map(|g| g / scaling),
            ev,
        })
    }

    /// Lumped node masses (kg, with `mass_scaling`), computed by the reference itself.
    pub fn masses(&self) -> &[f64] {
        &self.mass
    }

    /// Rest volume per element (m³), computed by the reference itself.
    pub fn rest_volumes(&self) -> &[f64] {
        &self.rest_volume
    }

    /// W's value and partial derivatives (Ī1, Ī2, J) for material `m`.
    fn energy(&mut self, m: usize, inv: [f64; 3]) -> Result<Dual, String> {
        let mat = &self.materials[m];
        let scope = Scope {
            vars: mat
                .args
                .iter()
                .map(|&(n, slot)| (n, eval::Val::S(Dual::var(inv[slot], slot))))
                .collect(),
            parent: Some(&mat.scope),
        };
        self.ev
            .eval(&scope, mat.body)
            .and_then(|v| v.scalar())
            .map_err(|e| format!("material `{}`: {e}", mat.name))
    }

    /// P(F), W(F) and J = det F of element `e`'s material. J ≤ 0 (or not finite) is returned
    /// with zero stress and W = NaN for the caller to judge, unless W is inversion-safe; a
    /// singular F with J > 0 is an error.
    fn stress(&mut self, e: usize, f: &Matrix3<f64>) -> Result<(Matrix3<f64>, f64, f64), String> {
        let f = *f;
        let j = f.determinant();
        let m = self.elem_material[e];
        if !self.materials[m].isochoric {
            // W(I1, J): P = W_I1·2F + W_J·cof(F), defined for any F (inversion-safe).
            let i1 = (f.transpose() * f).trace();
            let w = self.energy(m, [i1, 0.0, j])?;
            let [w1, _, wj] = w.d;
            let p = f * (2.0 * w1) + cofactor(&f) * wj;
            return Ok((p, w.v, j));
        }
        if !(j > 0.0 && j.is_finite()) {
            return Ok((Matrix3::zeros(), f64::NAN, j));
        }
        let finv_t = f
            .try_inverse()
            .ok_or_else(|| {
                format!(
                    "element {}: singular deformation gradient (J = {j:e})",
                    self.scene.mesh.tet_id(e)
                )
            })?
            .transpose();
        let c = f.transpose() * f;
        let i1 = c.trace();
        let i2 = 0.5 * (i1 * i1 - (c * c).trace());
        let j23 = j.powf(-2.0 / 3.0);
        let j43 = j.powf(-4.0 / 3.0);
        let w = self.energy(m, [j23 * i1, j43 * i2, j])?;
        let [w1, w2, wj] = w.d;
        // ∂Ī1/∂F = J^(−2/3)(2F − ⅔ I1 F⁻ᵀ), ∂Ī2/∂F = J^(−4/3)(2(I1 F − F C) − ⁴⁄₃ I2 F⁻ᵀ),
        // ∂J/∂F = J F⁻ᵀ.
        let mut p = (f * 2.0 - finv_t * (2.0 / 3.0 * i1)) * (w1 * j23);
        p += ((f * i1 - f * c) * 2.0 - finv_t * (4.0 / 3.0 * i2)) * (w2 * j43);
        p += finv_t * (wj * j);
        Ok((p, w.v, j))
    }

    /// Energy, stress and H = −V0·P·Dm⁻ᵀ of linear element `e` (its material, Dm⁻¹ and V0)
    /// with its corners at `x`, as [`Reference::stress`] judges J.
    fn element_at(&mut self, e: usize, x: &[Vec3; 4]) -> Result<Local, String> {
        let dm_inv = self.dm_inv[e];
        let ds = Matrix3::from_columns(&[x[1] - x[0], x[2] - x[0], x[3] - x[0]]);
        let (p, w, j) = self.stress(e, &(ds * dm_inv))?;
        let vol0 = self.rest_volume[e];
        Ok(Local {
            h: p * dm_inv.transpose() * (-vol0),
            p,
            energy: vol0 * w,
            j,
        })
    }

    /// Node forces, energy and det F per point of quadratic element `e` (rest data `rest`) with
    /// its 10 nodes at `x`.
    fn quadratic_at(
        &mut self,
        e: usize,
        rest: &[quadratic::RestPoint; 4],
        x: &[Vec3; 10],
    ) -> Result<([Vec3; 10], f64, [f64; 4]), String> {
        let mut forces = [Vec3::zeros(); 10];
        let mut energy = 0.0;
        let mut js = [0.0; 4];
        for (q, point) in rest.iter().enumerate() {
            let f = quadratic::deformation_gradient(point, x);
            let (p, w, j) = self.stress(e, &f)?;
            quadratic::forces(point, &p, &mut forces);
            energy += point.volume * w;
            js[q] = j;
        }
        Ok((forces, energy, js))
    }

    /// Energy, det F per quadrature point and node forces of quadratic element `e` with its
    /// 10 nodes (corners, then mid-edge nodes in VTK's order) at `x` (metres).
    pub fn element_quadratic(
        &mut self,
        e: usize,
        x: &[[f64; 3]; 10],
    ) -> Result<QuadraticElementResult, String> {
        let q = self.quad.take().ok_or("the scene's elements are linear")?;
        let result = self.quadratic_at(e, &q.rest[e], &x.map(Vec3::from));
        self.quad = Some(q);
        let (forces, energy, j) = result?;
        Ok(QuadraticElementResult {
            forces: forces.map(|f| [f[0], f[1], f[2]]),
            energy,
            j,
        })
    }

    /// The nodes of each element: 4 corners, or the 10 nodes of a quadratic one.
    pub fn element_nodes(&self, e: usize) -> Vec<u32> {
        match &self.quad {
            Some(q) => q.conn[e].to_vec(),
            None => self.scene.mesh.tets[e].to_vec(),
        }
    }

    /// Energy, stress and corner forces of element `e` with its corners at `x` (metres).
    pub fn element(&mut self, e: usize, x: &[[f64; 3]; 4]) -> Result<ElementResult, String> {
        if self.quad.is_some() {
            return Err("the scene's elements are quadratic (see `element_quadratic`)".into());
        }
        let xs = x.map(Vec3::from);
        let l = self.element_at(e, &xs)?;
        let mut forces = [[0.0; 3]; 4];
        for k in 0..3 {
            let col = l.h.column(k);
            forces[k + 1] = [col[0], col[1], col[2]];
        }
        let s = l.h.column(0) + l.h.column(1) + l.h.column(2);
        forces[0] = [-s[0], -s[1], -s[2]];
        Ok(ElementResult {
            forces,
            energy: l.energy,
            j: l.j,
            piola: std::array::from_fn(|r| std::array::from_fn(|c| l.p[(r, c)])),
        })
    }

    /// Internal (element) forces per node at positions `x`; the first element with J ≤ 0 is
    /// an error `(element, J)`.
    fn internal_forces(&mut self, x: &[Vec3], out: &mut [Vec3]) -> Result<(), InvertedOr> {
        out.iter_mut().for_each(|f| *f = Vec3::zeros());
        if self.springs.is_some() {
            return self.spring_forces(x, out);
        }
        if let Some(q) = self.quad.take() {
            let result = self.quadratic_forces(&q, x, out);
            self.quad = Some(q);
            return result;
        }
        for (e, tet) in self.scene.mesh.tets.iter().enumerate() {
            let xs = tet.map(|n| x[n as usize]);
            let l = self.element_at(e, &xs).map_err(InvertedOr::Other)?;
            let inverted = !(l.j > 0.0 && l.j.is_finite());
            let safe = !self.materials[self.elem_material[e]].isochoric;
            if inverted && !safe {
                return Err(InvertedOr::Inverted(e, l.j));
            }
            let (c0, c1, c2) = (l.h.column(0), l.h.column(1), l.h.column(2));
            out[tet[1] as usize] += c0;
            out[tet[2] as usize] += c1;
            out[tet[3] as usize] += c2;
            out[tet[0] as usize] -= c0 + c1 + c2;
        }
        Ok(())
    }

    /// [`Reference::internal_forces`] of a quadratic scene.
    fn quadratic_forces(
        &mut self,
        q: &Quadratic,
        x: &[Vec3],
        out: &mut [Vec3],
    ) -> Result<(), InvertedOr> {
        for (e, (conn, rest)) in q.conn.iter().zip(&q.rest).enumerate() {
            let xs = conn.map(|n| x[n as usize]);
            let (f, _, js) = self.quadratic_at(e, rest, &xs).map_err(InvertedOr::Other)?;
            let safe = !self.materials[self.elem_material[e]].isochoric;
            if let Some(&j) = js.iter().find(|j| !(**j > 0.0 && j.is_finite()))
                && !safe
            {
                return Err(InvertedOr::Inverted(e, j));
            }
            for (&n, f) in conn.iter().zip(f) {
                out[n as usize] += f;
            }
        }
        Ok(())
    }

    /// Nominal uniaxial stress P(λ) = dW/dλ of material `m` along incompressible uniaxial
    /// tension (Ī1 = λ² + 2/λ, Ī2 = 2λ + 1/λ², J = 1; I1 = Ī1 there).
    fn uniaxial_stress(&mut self, m: usize, lam: f64) -> Result<f64, String> {
        let w = self.energy(
            m,
            [lam * lam + 2.0 / lam, 2.0 * lam + 1.0 / (lam * lam), 1.0],
        )?;
        let [w1, w2, _] = w.d;
        Ok(w1 * (2.0 * lam - 2.0 / (lam * lam)) + w2 * (2.0 - 2.0 / (lam * lam * lam)))
    }

    /// E(λ) = dP/dλ, the slope of the stress–strain curve (eq. 2.3): a central difference of
    /// the exact P (error ~1e-8 relative), a different method from the kernels' second AD.
    fn tangent_modulus(&mut self, m: usize, lam: f64) -> Result<f64, String> {
        let h = 1e-4 * lam;
        Ok((self.uniaxial_stress(m, lam + h)? - self.uniaxial_stress(m, lam - h)?) / (2.0 * h))
    }

    /// Spring-mesh forces: every unique edge (eq. 2.3–2.5), then the volume-conservation
    /// force of every tet (eq. 2.16).
    fn spring_forces(&mut self, x: &[Vec3], out: &mut [Vec3]) -> Result<(), InvertedOr> {
        let sm = self.springs.take().expect("spring mesh");
        let result = (|| {
            for edge in &sm.edges {
                let [a, b] = edge.nodes;
                let d = x[b] - x[a];
                let l = d.norm();
                let lam = l / edge.l0;
                let mut k = 0.0;
                for &(m, v0) in &edge.volumes {
                    k += self.tangent_modulus(m, lam).map_err(InvertedOr::Other)? * v0;
                }
                let f = d * (k / (edge.l0 * edge.l0) * (l - edge.l0) / l);
                out[a] += f;
                out[b] -= f;
            }
            for (e, tet) in self.scene.mesh.tets.iter().enumerate() {
                let p = tet.map(|n| x[n as usize]);
                let vol = Matrix3::from_columns(&[p[1] - p[0], p[2] - p[0], p[3] - p[0]])
                    .determinant()
                    / 6.0;
                let v0 = self.rest_volume[e];
                if !(vol > 0.0 && vol.is_finite()) {
                    return Err(InvertedOr::Inverted(e, vol / v0));
                }
                let bc = (p[0] + p[1] + p[2] + p[3]) / 4.0;
                for (c, &n) in tet.iter().enumerate() {
                    let r = bc - p[c];
                    out[n as usize] += r * (sm.alpha * (vol - v0) / r.norm());
                }
            }
            Ok(())
        })();
        self.springs = Some(sm);
        result
    }

    fn scalar_at(&mut self, e: &'a Expr, what: &str) -> Result<f64, String> {
        let v = self
            .ev
            .eval(&Scope::root(), e)
            .and_then(|v| v.scalar())
            .map_err(|err| format!("{what}: {err}"))?;
        Ok(v.v)
    }

    /// The largest stable step of semi-implicit Euler at rest, 2/ω_max with ω_max² the largest
    /// eigenvalue of M⁻¹K over the free nodes: power iteration, K·u by central differences of
    /// this simulator's own internal forces.
    pub fn stable_dt_estimate(&mut self) -> Result<f64, String> {
        let scene = self.scene;
        let n = scene.mesh.nodes.len();
        let x0: Vec<Vec3> = scene.mesh.nodes.iter().map(|p| Vec3::from(*p)).collect();
        let mass = self.mass.clone();
        let free: Vec<bool> = scene.fixed.iter().map(|f| !f).collect();
        // A length of the smallest element: the cube root of its volume.
        let h_min = self
            .rest_volume
            .iter()
            .copied()
            .fold(f64::INFINITY, f64::min)
            .cbrt();
        let eps = h_min.max(1e-12) * 1e-6;
        // A deterministic pseudo-random start (xorshift).
        let mut seed: u64 = 0x9E37_79B9_7F4A_7C15;
        let mut rnd = || {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            (seed >> 11) as f64 / (1u64 << 53) as f64 - 0.5
        };
        let mut u: Vec<Vec3> = (0..n)
            .map(|i| {
                let r = Vec3::new(rnd(), rnd(), rnd());
                if free[i] { r } else { Vec3::zeros() }
            })
            .collect();
        let (mut fp, mut fm) = (vec![Vec3::zeros(); n], vec![Vec3::zeros(); n]);
        let mut xs = x0.clone();
        let mut lambda = 0.0_f64;
        let mut history: Vec<f64> = Vec::new();
        for it in 0..400 {
            let norm = u.iter().map(|v| v.norm_squared()).sum::<f64>().sqrt();
            if norm == 0.0 {
                break;
            }
            u.iter_mut().for_each(|v| *v /= norm);
            for i in 0..n {
                xs[i] = x0[i] + u[i] * eps;
            }
            self.internal_forces(&xs, &mut fp)
                .map_err(|e| e.message(&self.scene.mesh))?;
            for i in 0..n {
                xs[i] = x0[i] - u[i] * eps;
            }
            self.internal_forces(&xs, &mut fm)
                .map_err(|e| e.message(&self.scene.mesh))?;
            let (mut num, mut den) = (0.0, 0.0);
            for i in 0..n {
                if !free[i] {
                    u[i] = Vec3::zeros();
                    continue;
                }
                let ku = -(fp[i] - fm[i]) / (2.0 * eps);
                num += u[i].dot(&ku);
                den += mass[i] * u[i].norm_squared();
                u[i] = ku / mass[i];
            }
            if den > 0.0 {
                lambda = lambda.max(num / den);
            }
            history.push(lambda);
            if it >= 40 {
                let old = history[it - 20];
                if (lambda - old).abs() <= 1e-6 * lambda {
                    break;
                }
            }
        }
        Ok(if lambda <= 0.0 {
            f64::INFINITY
        } else {
            2.0 / lambda.sqrt()
        })
    }

    /// The state at rest: positions from the mesh, zero velocities.
    pub fn initial_state(&self) -> RefState {
        let n = self.scene.mesh.nodes.len();
        RefState {
            x: self
                .scene
                .mesh
                .nodes
                .iter()
                .map(|p| Vec3::from(*p))
                .collect(),
            v: vec![Vec3::zeros(); n],
            f_el: vec![Vec3::zeros(); n],
            f_pr: vec![Vec3::zeros(); n],
        }
    }

    /// Advance `st` by one step of `dt`, the step with index `step` (t = step·dt at its start).
    pub fn step(&mut self, st: &mut RefState, step: u64, dt: f64) -> Result<(), String> {
        let scene = self.scene;
        let t = step as f64 * dt;
        self.ev.t = t;
        self.ev.dt = dt;
        if !scene.sensors.is_empty() {
            // Closed loop: pressures and damping read the state this step starts from.
            let rows = |p: &[Vec3]| p.iter().map(|p| [p[0], p[1], p[2]]).collect();
            self.ev.state = Some(eval::NodeState {
                x: rows(&st.x),
                v: rows(&st.v),
                x0: scene.mesh.nodes.clone(),
            });
        }
        match self.internal_forces(&st.x, &mut st.f_el) {
            Ok(()) => {}
            Err(InvertedOr::Inverted(e, j)) => {
                return Err(format!(
                    "element {} inverted at step {step} (t = {t:.6} s): J = {j:e}. \
                     Reduce dt (now {dt:e} s) or the load rate, or refine the mesh near that element",
                    scene.mesh.tet_id(e)
                ));
            }
            Err(InvertedOr::Other(m)) => return Err(m),
        }
        st.f_pr.iter_mut().for_each(|f| *f = Vec3::zeros());
        for c in 0..self.pressures.len() {
            let p = self.scalar_at(self.pressures[c], "pressure")?;
            if let Some(q) = &self.quad {
                for tri in &q.tris[scene.chamber_ranges[c].clone()] {
                    let xs = tri.map(|i| st.x[i as usize]);
                    for (&i, f) in tri.iter().zip(quadratic::pressure_forces(&xs, p)) {
                        st.f_pr[i as usize] += f;
                    }
                }
                continue;
            }
            let p6 = p / 6.0;
            for tri in &scene.tris[scene.chamber_ranges[c].clone()] {
                let [a, b, cc] = tri.map(|i| st.x[i as usize]);
                let fc = (b - a).cross(&(cc - a)) * p6;
                for &i in tri {
                    st.f_pr[i as usize] += fc;
                }
            }
        }
        let beta = match self.damping {
            Some(e) => self.scalar_at(e, "damping")?,
            None => 0.0,
        };
        let g = self.gravity.unwrap_or_else(Vec3::zeros);
        for i in 0..st.x.len() {
            if scene.fixed[i] {
                st.v[i] = Vec3::zeros();
                continue;
            }
            let f = st.f_el[i] + st.f_pr[i];
            let a = f / self.mass[i] - st.v[i] * beta + g;
            st.v[i] += a * dt;
            st.x[i] += st.v[i] * dt;
        }
        if let Some(i) = st.x.iter().position(|p| !p.iter().all(|c| c.is_finite())) {
            return Err(format!(
                "the simulation became unstable at step {} (t = {:.6} s): node {} has a non-finite position. \
                 The time step dt = {dt:e} s is too large for this mesh and material; try a smaller dt, e.g. {:e} s",
                step + 1,
                (step + 1) as f64 * dt,
                scene.mesh.node_id(i),
                dt / 4.0
            ));
        }
        Ok(())
    }

    /// Simulate: `dt` and `steps` override the script's.
    pub fn run(&mut self, dt: Option<f64>, steps: Option<u64>) -> Result<RunSummary, String> {
        let start = std::time::Instant::now();
        let scene = self.scene;
        let estimate = match (scene.dt, dt) {
            (DtChoice::Auto { .. }, None) => Some(self.stable_dt_estimate()?),
            _ => None,
        };
        let dt = match (dt, scene.dt, estimate) {
            (Some(dt), _, _) | (None, DtChoice::Given(dt), _) => dt,
            (None, DtChoice::Auto { safety }, Some(est)) => safety * est,
            (None, DtChoice::Auto { .. }, None) => unreachable!("estimated above"),
        };
        if !dt.is_finite() || dt <= 0.0 {
            return Err(format!("no usable time step (dt = {dt} s)"));
        }
        let steps = steps.unwrap_or_else(|| scene.steps_for(dt));
        let mut st = self.initial_state();
        for step in 0..steps {
            self.step(&mut st, step, dt)?;
        }
        let (x, v) = (&st.x, &st.v);
        Ok(RunSummary {
            // The reference reports the loss through `loss::Loss` at the end state (cli).
            loss: None,
            steps,
            dt,
            dt_stable_estimate: estimate,
            wall_seconds: start.elapsed().as_secs_f64(),
            x: x.iter().map(|p| [p[0], p[1], p[2]]).collect(),
            v: v.iter().map(|p| [p[0], p[1], p[2]]).collect(),
            solver: None,
            contact: Vec::new(),
        })
    }
}

/// The state of a reference run: positions and velocities per node (plus scratch buffers).
pub struct RefState {
    pub x: Vec<Vector3<f64>>,
    pub v: Vec<Vector3<f64>>,
    f_el: Vec<Vector3<f64>>,
    f_pr: Vec<Vector3<f64>>,
}

/// Per-element intermediate results.
struct Local {
    h: Matrix3<f64>,
    p: Matrix3<f64>,
    energy: f64,
    j: f64,
}

enum InvertedOr {
    Inverted(usize, f64),
    Other(String),
}

impl InvertedOr {
    fn message(self, mesh: &crate::mesh::Mesh) -> String {
        match self {
            InvertedOr::Inverted(e, j) => {
                format!("element {} is inverted (J = {j:e})", mesh.tet_id(e))
            }
            InvertedOr::Other(m) => m,
        }
    }
}

/// Resolve a material (a block, or an instance of a prelude or user template).
fn material<'a>(ev: &mut Evaluator<'a>, name: &str) -> Result<Material<'a>, String> {
    let mut item = ev
        .find(name)
        .ok_or_else(|| format!("unknown material `{name}`"))?;
    // A `let` may alias a material.
    for _ in 0..8 {
        match &item.kind {
            ItemKind::Let(LetDecl {
                value:
                    Expr {
                        kind: ExprKind::Name(id),
                        ..
                    },
                ..
            }) => {
                item = ev
                    .find(&id.name)
                    .ok_or_else(|| format!("unknown material `{}`", id.name))?;
            }
            _ => break,
        }
    }
    let ItemKind::Material(m) = &item.kind else {
        return Err(format!("`{name}` is not a material"));
    };
    let (stmts, scope): (&'a [Stmt], Scope<'a>) = match &m.body {
        MaterialBody::Block(stmts) => (stmts, Scope::root()),
        MaterialBody::Expr(e) => {
            let ExprKind::Call { callee, args } = &e.kind else {
                return Err(format!("material `{name}` is not a call to a template"));
            };
            let ExprKind::Name(t) = &callee.kind else {
                return Err(format!("material `{name}` is not a call to a template"));
            };
            let template = ev
                .find(&t.name)
                .ok_or_else(|| format!("unknown material template `{}`", t.name))?;
            let ItemKind::Material(MaterialDecl {
                params: Some(params),
                body: MaterialBody::Block(stmts),
                ..
            }) = &template.kind
            else {
                return Err(format!("`{}` is not a material template", t.name));
            };
            let scope = ev
                .bind(&Scope::root(), params, args)
                .map_err(|e| format!("material `{name}`: {e}"))?;
            (stmts, scope)
        }
    };
    let mut scope = scope;
    let mut density = None;
    let mut energy = None;
    for s in stmts {
        match &s.kind {
            StmtKind::Let(l) => {
                let v = ev
                    .eval(&scope, &l.value)
                    .map_err(|e| format!("material `{name}`: {e}"))?;
                scope.vars.push((l.name.name.as_str(), v));
            }
            StmtKind::Assign { name: n, value } if n.name == "density" => {
                let v = ev
                    .eval(&scope, value)
                    .and_then(|v| v.scalar())
                    .map_err(|e| format!("material `{name}`: density: {e}"))?;
                density = Some(v.v);
            }
            StmtKind::Energy { args, body, .. } if energy.is_none() => {
                let args = args
                    .iter()
                    .map(|a| match a.name.as_str() {
                        "I1bar" | "I1" => Ok((a.name.as_str(), 0)),
                        "I2bar" => Ok((a.name.as_str(), 1)),
                        "J" => Ok((a.name.as_str(), 2)),
                        other => Err(format!(
                            "material `{name}`: W has an unknown argument `{other}`"
                        )),
                    })
                    .collect::<Result<Vec<_>, _>>()?;
                energy = Some((args, body));
            }
            _ => {}
        }
    }
    let (args, body) = energy.ok_or_else(|| format!("material `{name}` has no strain energy"))?;
    let density = density.ok_or_else(|| format!("material `{name}` has no density"))?;
    let isochoric = !args.iter().any(|(n, _)| *n == "I1");
    if !isochoric && args.iter().any(|(n, _)| *n == "I1bar" || *n == "I2bar") {
        return Err(format!(
            "material `{name}`: W mixes I1 with the isochoric invariants"
        ));
    }
    Ok(Material {
        name: name.to_string(),
        density,
        scope,
        args,
        body,
        isochoric,
    })
}

/// The unique edges of the mesh with their rest lengths and the rest volume of their tets
/// per material.
fn spring_mesh(
    scene: &Scene,
    elem_material: &[usize],
    rest_volume: &[f64],
    alpha: f64,
) -> SpringMesh {
    let mut map: std::collections::BTreeMap<(usize, usize), Vec<(usize, f64)>> = Default::default();
    for (e, tet) in scene.mesh.tets.iter().enumerate() {
        for (i, j) in [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)] {
            let (a, b) = (tet[i] as usize, tet[j] as usize);
            let key = (a.min(b), a.max(b));
            let vols = map.entry(key).or_default();
            let m = elem_material[e];
            match vols.iter_mut().find(|(mm, _)| *mm == m) {
                Some((_, v)) => *v += rest_volume[e],
                None => vols.push((m, rest_volume[e])),
            }
        }
    }
    let edges = map
        .into_iter()
        .map(|((a, b), volumes)| SpringEdge {
            nodes: [a, b],
            l0: (Vec3::from(scene.mesh.nodes[b]) - Vec3::from(scene.mesh.nodes[a])).norm(),
            volumes,
        })
        .collect();
    SpringMesh { alpha, edges }
}

/// The cofactor matrix of F (J·F⁻ᵀ for an invertible F, defined for any F).
fn cofactor(f: &Matrix3<f64>) -> Matrix3<f64> {
    Matrix3::from_fn(|r, c| {
        let (r1, r2) = ((r + 1) % 3, (r + 2) % 3);
        let (c1, c2) = ((c + 1) % 3, (c + 2) % 3);
        f[(r1, c1)] * f[(r2, c2)] - f[(r1, c2)] * f[(r2, c1)]
    })
}

/// Run a scene with the reference simulator (`dt`, `steps` override the script's).
pub fn run(scene: &Scene, dt: Option<f64>, steps: Option<u64>) -> Result<RunSummary, String> {
    Reference::new(scene)?.run(dt, steps)
}
