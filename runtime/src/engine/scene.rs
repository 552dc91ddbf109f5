//! A scene ready to simulate: the compiled script ([`softc_compiler::driver`]), its mesh with
//! elements in kernel order (grouped by material), chamber triangles, fixed nodes, node sets,
//! masses, the time step and the values of params and inputs. Everything here is data the
//! compiler resolved, bound to the mesh; the physics lives in the kernels (and, for testing,
//! in the reference simulator).

use crate::mesh::{Mesh, Precomputed};
use softc_compiler::driver::SceneModule;
use softc_compiler::driver::{Bound, CompileOptions, LossKernels, ParamSlots, Resolved};
use std::collections::BTreeMap;
use std::ops::Range;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use softc_compiler::ir::ElementOrder;

pub use softc_compiler::driver::{DtChoice, FieldSlots as FieldParam};

/// Why a scene could not be built; the message is ready to print.
#[derive(Debug)]
pub struct SceneError(pub String);

impl std::fmt::Display for SceneError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

/// Why a scene could not be built: the script's errors as diagnostics, or anything else.
#[derive(Debug)]
pub enum LoadFailure {
    Compile(softc_compiler::CompileFailure),
    Other(SceneError),
}

impl From<SceneError> for LoadFailure {
    fn from(e: SceneError) -> Self {
        LoadFailure::Other(e)
    }
}

/// Node → incident entity adjacency in CSR form (the compiler's one connectivity type).
pub use softc_compiler::back::NodeCsr as Csr;

#[derive(Debug)]
pub struct Scene {
    pub script: PathBuf,
    pub source: String,
    /// What the script means: settings, params, inputs, the optimize block.
    pub resolved: Resolved,
    pub lowered: SceneModule,
    /// Nodes in metres, tets grouped by material (kernel order).
    pub mesh: Mesh,
    pub pre: Precomputed,
    /// The `rest_shape` buffer (FEM): per element, or per quadrature point of a quadratic one.
    pub rest_shape: Vec<f64>,
    /// Element range of each material, in `lowered.materials` order.
    pub material_ranges: Vec<Range<usize>>,
    /// Chamber triangles, concatenated in `lowered.chambers` order.
    pub tris: Vec<[u32; 3]>,
    /// Quadratic scenes: the mid-edge nodes of `tris` (edges 0-1, 1-2, 2-0); empty otherwise.
    pub tri_mids: Vec<[u32; 3]>,
    pub chamber_ranges: Vec<Range<usize>>,
    pub node_elements: Csr,
    pub node_tris: Csr,
    pub fixed: Vec<bool>,
    /// Every declared node set with its nodes (for outputs).
    pub node_sets: Vec<(String, Vec<u32>)>,
    /// Per `contact` statement: its nodes and their lumped boundary areas.
    pub contact_nodes: Vec<softc_compiler::driver::ContactNodes>,
    /// The contact stiffness where a statement gives none: 3 × the largest shear modulus at
    /// the script's params (a constant of the scene), probed at the first solve that needs it.
    pub default_contact_stiffness: std::sync::OnceLock<f64>,
    /// Every declared element set with its elements, as indices of the mesh file's element
    /// order (before the grouping by material), in the set's order.
    pub element_sets: Vec<(String, Vec<u32>)>,
    /// The per-element params: where each entry's element is in the kernels' element order.
    pub fields: Vec<FieldParam>,
    /// The params (source order), then the inputs, with their entries' uniforms.
    pub slots: Vec<ParamSlots>,
    /// The compiled loss, `None` without one.
    pub loss: Option<LossKernels>,
    /// Closed-loop control's sensors ([`super::sensors`]), one per scalar.
    pub sensors: Vec<softc_compiler::driver::SensorKernels>,
    pub dt: DtChoice,
    pub steps: Option<u64>,
    pub duration: Option<f64>,
    /// Values of the uniforms `param.*` and `input.*` (first scene of a batch).
    pub uniforms: BTreeMap<String, f64>,
    /// The declared params with their bounds, in source order.
    pub params: Vec<softc_compiler::driver::ParamInfo>,
}

impl Scene {
    /// Compile and set up the scene of a script. `overrides` are `--set NAME=VALUE` param
    /// values in SI units.
    pub fn load(path: &Path, overrides: &[(String, f64)]) -> Result<Scene, SceneError> {
        Scene::load_with(path, overrides, None)
    }

    /// As [`Scene::load`], for a variant of the script (another mesh, other sim settings).
    pub fn load_with(
        path: &Path,
        overrides: &[(String, f64)],
        variant: Option<&softc_compiler::Variant>,
    ) -> Result<Scene, SceneError> {
        Scene::load_inner(path, overrides, variant).map_err(|e| match e {
            LoadFailure::Compile(f) => SceneError(f.render()),
            LoadFailure::Other(e) => e,
        })
    }

    /// As [`Scene::load`], keeping a compile failure's diagnostics (for callers that report
    /// them as data, such as the Python package).
    pub fn load_checked(path: &Path, overrides: &[(String, f64)]) -> Result<Scene, LoadFailure> {
        Scene::load_inner(path, overrides, None)
    }

    fn load_inner(
        path: &Path,
        overrides: &[(String, f64)],
        variant: Option<&softc_compiler::Variant>,
    ) -> Result<Scene, LoadFailure> {
        let bytes = crate::files::read_regular(path).map_err(|e| {
            LoadFailure::Other(SceneError(format!("cannot read `{}`: {e}", path.display())))
        })?;
        let probe = Arc::new(crate::mesh::probe::CachingProbe::default());
        let mut options = CompileOptions::for_file(path, Some(probe.clone()));
        if let Some(v) = variant {
            options.variant = v.clone();
        }
        let name = path.display().to_string();
        let compiled =
            softc_compiler::compile(&name, &bytes, &options).map_err(LoadFailure::Compile)?;
        let resolved = compiled.program;
        let lowered = compiled.kernels;
        // The mesh the checks read (one read and validation per run).
        let mut mesh = (*probe
            .mesh(&resolved.mesh.path, resolved.mesh.unit)
            .map_err(|e| SceneError(e.to_string()))?)
        .clone();
        let quadratic = lowered.module.order == ElementOrder::Quadratic;
        if quadratic {
            // Straight-sided mid-edge nodes where the file has none.
            mesh = mesh.with_mid_edges();
        } else if mesh.is_quadratic() {
            return Err(LoadFailure::Other(SceneError(format!(
                "`{}` has quadratic (10-node) tetrahedra; load it with `order: 2`, or convert \
                 it to linear ones with `softc mesh convert --order 1`",
                resolved.mesh.written.display()
            ))));
        }
        let bound: Bound = resolved.bind(&lowered, &mesh).map_err(SceneError)?;
        let uniforms = resolved.initial_uniforms(&bound, overrides);
        // The kernels' element order (the file's element numbers follow, for messages).
        mesh.ids.tets = bound.order.iter().map(|&e| mesh.tet_id(e)).collect();
        mesh.tets = bound.order.iter().map(|&e| mesh.tets[e]).collect();
        mesh.tet_tags = bound.order.iter().map(|&e| mesh.tet_tags[e]).collect();
        if let Some(q) = &mut mesh.mid_edges {
            q.tets = bound.order.iter().map(|&e| q.tets[e]).collect();
        }
        let rho: Vec<f64> = bound
            .material_of
            .iter()
            .map(|&m| resolved.densities[m])
            .collect();
        let mut pre = Precomputed::new(&mesh, &rho).map_err(|e| SceneError(e.to_string()))?;
        for m in &mut pre.mass {
            *m *= resolved.sim.mass_scaling;
        }
        let mut tris = Vec::new();
        let mut chamber_ranges = Vec::new();
        for t in bound.chamber_tris {
            let start = tris.len();
            tris.extend(t);
            chamber_ranges.push(start..tris.len());
        }
        let rest_shape = rest_shape_rows(&mesh, &pre)?;
        let tri_mids: Vec<[u32; 3]> = bound.chamber_mids.into_iter().flatten().collect();
        let (node_elements, node_tris) = if quadratic {
            let conn = element_nodes(&mesh);
            let tri_conn = triangle_nodes(&tris, &tri_mids);
            (
                Csr::build(mesh.nodes.len(), conn.chunks(10)),
                Csr::build(mesh.nodes.len(), tri_conn.chunks(6)),
            )
        } else {
            (
                pre.node_elements.clone(),
                Csr::build(mesh.nodes.len(), tris.iter()),
            )
        };
        Ok(Scene {
            script: path.to_path_buf(),
            source: resolved.source.clone(),
            lowered,
            mesh,
            pre,
            rest_shape,
            material_ranges: bound.material_ranges,
            tris,
            tri_mids,
            chamber_ranges,
            node_elements,
            node_tris,
            fixed: bound.fixed,
            node_sets: bound.node_sets,
            element_sets: bound.element_sets,
            fields: bound.fields,
            slots: bound.slots,
            loss: bound.loss,
            sensors: bound.sensors,
            contact_nodes: bound.contacts,
            default_contact_stiffness: std::sync::OnceLock::new(),
            dt: resolved.sim.dt,
            steps: resolved.sim.steps,
            duration: resolved.sim.duration,
            uniforms,
            params: resolved.params.clone(),
            resolved,
        })
    }

    /// The order of the scene's elements.
    pub fn order(&self) -> ElementOrder {
        self.lowered.module.order
    }

    /// The elements' nodes as the kernels read them: 4 corners per element, or 10 nodes (the
    /// corners, then the mid-edge nodes) for quadratic ones.
    pub fn elem_conn(&self) -> Vec<u32> {
        element_nodes(&self.mesh)
    }

    /// The chamber triangles' nodes as the kernels read them: 3 per triangle, or 6.
    pub fn tri_conn(&self) -> Vec<u32> {
        triangle_nodes(&self.tris, &self.tri_mids)
    }

    /// The number of steps for a time step `dt`.
    pub fn steps_for(&self, dt: f64) -> u64 {
        self.resolved.sim.steps_for(dt)
    }

    /// The slots of a param or input by name.
    pub fn slots_of(&self, name: &str) -> Option<&ParamSlots> {
        self.slots.iter().find(|s| s.name == name)
    }
}

/// A mesh's elements as the kernels read them: the corners, then (quadratic) the mid-edge nodes.
fn element_nodes(mesh: &Mesh) -> Vec<u32> {
    match &mesh.mid_edges {
        None => mesh.tets.iter().flatten().copied().collect(),
        Some(q) => mesh
            .tets
            .iter()
            .zip(&q.tets)
            .flat_map(|(c, m)| c.iter().chain(m).copied())
            .collect(),
    }
}

/// Chamber triangles as the kernels read them: the corners, then any mid-edge nodes.
fn triangle_nodes(tris: &[[u32; 3]], mids: &[[u32; 3]]) -> Vec<u32> {
    if mids.is_empty() {
        return tris.iter().flatten().copied().collect();
    }
    tris.iter()
        .zip(mids)
        .flat_map(|(c, m)| c.iter().chain(m).copied())
        .collect()
}

/// The `rest_shape` buffer's rows: per linear element G = Dm⁻¹·Dm⁻ᵀ and det Dm⁻¹; per
/// quadratic one the same at each quadrature point and the point's volume. An error names a
/// curved element whose Jacobian is not positive at a quadrature point.
fn rest_shape_rows(mesh: &Mesh, pre: &Precomputed) -> Result<Vec<f64>, SceneError> {
    let Some(q) = &mesh.mid_edges else {
        return Ok(pre
            .dm_inv
            .iter()
            .flat_map(softc_compiler::driver::rest_shape)
            .collect());
    };
    let mut rows = Vec::new();
    for (e, (c, m)) in mesh.tets.iter().zip(&q.tets).enumerate() {
        let x: [[f64; 3]; 10] =
            std::array::from_fn(|a| mesh.nodes[if a < 4 { c[a] } else { m[a - 4] } as usize]);
        let row = softc_compiler::driver::quadratic_rest_shape(&x).ok_or_else(|| {
            SceneError(format!(
                "element {} is inverted or degenerate at a quadrature point (its mid-edge nodes \
                 are too far from its edges' midpoints); fix the mesh or load it with `order: 1`",
                mesh.tet_id(e)
            ))
        })?;
        rows.extend(row);
    }
    Ok(rows)
}
