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
    /// Element range of each material, in `lowered.materials` order.
    pub material_ranges: Vec<Range<usize>>,
    /// Chamber triangles, concatenated in `lowered.chambers` order.
    pub tris: Vec<[u32; 3]>,
    pub chamber_ranges: Vec<Range<usize>>,
    pub node_elements: Csr,
    pub node_tris: Csr,
    pub fixed: Vec<bool>,
    /// Every declared node set with its nodes (for outputs).
    pub node_sets: Vec<(String, Vec<u32>)>,
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
        variant: Option<&softc_compiler::driver::Variant>,
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
        variant: Option<&softc_compiler::driver::Variant>,
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
        let bound: Bound = resolved.bind(&lowered, &mesh).map_err(SceneError)?;
        let uniforms = resolved.initial_uniforms(&bound, overrides);
        // The kernels' element order (the file's element numbers follow, for messages).
        mesh.ids.tets = bound.order.iter().map(|&e| mesh.tet_id(e)).collect();
        mesh.tets = bound.order.iter().map(|&e| mesh.tets[e]).collect();
        mesh.tet_tags = bound.order.iter().map(|&e| mesh.tet_tags[e]).collect();
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
        let node_elements = pre.node_elements.clone();
        let node_tris = Csr::build(mesh.nodes.len(), tris.iter());
        Ok(Scene {
            script: path.to_path_buf(),
            source: resolved.source.clone(),
            lowered,
            mesh,
            pre,
            material_ranges: bound.material_ranges,
            tris,
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
            dt: resolved.sim.dt,
            steps: resolved.sim.steps,
            duration: resolved.sim.duration,
            uniforms,
            params: resolved.params.clone(),
            resolved,
        })
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
