//! The one driver: source text → checked script → resolved program → scene kernels and their
//! adjoint, in one call ([`compile`]). Everything after it (the runtime's scene set-up, the time
//! loop, the optimizer, `bench`, `--tradeoff`, the CLI's `compile`) consumes the [`Compiled`]
//! result: the kernels, and a [`Resolved`] program whose settings are SI numbers, whose params
//! and inputs are a typed table, and whose selections are evaluated against a mesh by
//! [`Resolved::bind`]. Nothing outside the compiler walks the syntax tree to learn what a
//! script means (the independent reference oracle parses the script itself, on purpose).

mod area;
pub mod bind;
pub mod loss;
pub mod plan;
pub mod settings;

use crate::Variant;
pub use crate::sema::units::parse_quantity;
pub use bind::{Bound, FieldSlots, MeshView, ParamSlots, SlotKind};
pub use loss::{LossArg, LossKernels, LossWindow, SensorKernels};
pub use plan::{
    InputDecl, InputSource, LrScheduleSpec, NormalizeSpec, OptimizeSpec, OptimizerSpec,
    StopCondition,
};
pub use settings::{
    CheckpointSpec, CsvLog, DtChoice, ForceModelKind, GradSettings, Integrator, SimSettings,
};

// What the runtime needs of the compiler's other layers, in one place.
pub use crate::lower::contact::{Contact, ContactNodes, Contacts, NO_LIMIT};
pub use crate::lower::fem::{REST_SHAPE_WIDTH, rest_shape};
pub use crate::lower::quadratic::quadratic_rest_shape;
pub use crate::lower::scene::{ImplicitStep, MatrixFree, NodeJacobian, SceneModule, StaticKernels};
pub use crate::lower::springs::TET_EDGES;
pub use crate::sema::ParamInfo;
pub use crate::sema::mesh_probe::{MeshProbe, MeshSummary};
pub use crate::sema::units::Dim;

use crate::diag::{Diagnostic, SourceFile};
use crate::ir::{Domain, KernelBuilder};
use crate::lower::expr::{Env, ExprLowerer, Program, flatten};
use crate::lower::scene::lower_scene;
use crate::sema::CheckOptions;
use crate::sema::hir::Expr;
use crate::sema::mesh_probe::MeshRefs;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// How to compile: where the script's relative paths resolve, how its mesh is read for the
/// checks, and which mesh to use.
#[derive(Clone, Default)]
pub struct CompileOptions {
    /// Directory of the script; `None` skips file-existence checks (editors, fuzzing).
    pub base_dir: Option<PathBuf>,
    /// Reads the mesh so surfaces, tags and selections can be checked against it.
    pub mesh_probe: Option<Arc<dyn MeshProbe>>,
    /// Compile a variant of the script (another mesh, other sim settings): `bench
    /// --tradeoff`'s configurations. A choice of the call; the caller edits no text.
    pub variant: Variant,
}

impl CompileOptions {
    /// Options for a script file: paths relative to its folder, the mesh read by `probe`.
    pub fn for_file(path: &Path, probe: Option<Arc<dyn MeshProbe>>) -> Self {
        CompileOptions {
            base_dir: Some(script_dir(path)),
            mesh_probe: probe,
            variant: Variant::default(),
        }
    }

    fn check_options(&self) -> CheckOptions {
        CheckOptions {
            base_dir: self.base_dir.clone(),
            mesh_probe: self.mesh_probe.clone(),
        }
    }
}

/// The folder a script's relative paths resolve against.
pub fn script_dir(path: &Path) -> PathBuf {
    path.parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."))
        .to_path_buf()
}

/// Why a script did not compile: its errors (with the text they point into), or a construct
/// the checker accepts but no kernel implements yet.
#[derive(Debug)]
pub struct CompileFailure {
    /// The display name of the script (`examples/x.soft`).
    pub name: String,
    /// The text the diagnostics point into (invalid UTF-8 replaced).
    pub text: String,
    /// Every diagnostic, errors and warnings, sorted by position (empty for a lowering error).
    pub diagnostics: Vec<Diagnostic>,
    /// The message of a lowering error, when checking passed.
    pub lowering: Option<String>,
    /// Whether the lowering error came from generating the kernels (its rendering names the
    /// script) rather than from resolving a setting.
    pub in_kernels: bool,
}

impl CompileFailure {
    /// The errors rendered for a terminal, one after another.
    pub fn render(&self) -> String {
        if let Some(l) = &self.lowering {
            return if self.in_kernels {
                format!("{}: {l}", self.name)
            } else {
                l.clone()
            };
        }
        let file = SourceFile::new(&self.name, &self.text);
        self.diagnostics
            .iter()
            .filter(|d| d.is_error())
            .map(|d| file.render(d))
            .collect::<Vec<_>>()
            .join("\n")
    }
}

impl std::fmt::Display for CompileFailure {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.render())
    }
}

/// A compiled script: the scene's kernels (forward step and adjoint) and the resolved program.
#[derive(Debug)]
pub struct Compiled {
    pub kernels: SceneModule,
    pub program: Resolved,
}

/// What a script means, resolved: settings as SI numbers, the params and inputs, the optimize
/// block, the mesh it loads. Selections, the loss and the param slots need the mesh:
/// [`Resolved::bind`].
#[derive(Debug)]
pub struct Resolved {
    /// The display name of the script.
    pub name: String,
    /// The script's text.
    pub source: String,
    /// Warnings of the check (errors stop the compile).
    pub warnings: Vec<Diagnostic>,
    /// The mesh file (resolved against the script's folder) and the length of one of its
    /// units in metres.
    pub mesh: MeshDecl,
    pub sim: SimSettings,
    pub grad: GradSettings,
    /// The declared params with their bounds, in source order.
    pub params: Vec<ParamInfo>,
    /// The declared inputs, in source order.
    pub inputs: Vec<InputDecl>,
    pub optimize: Option<OptimizeSpec>,
    /// The materials in kernel order (element kernel `i` runs over material `i`'s elements).
    pub materials: Vec<String>,
    /// The chambers with a pressure, in kernel order.
    pub chambers: Vec<String>,
    /// Per material (kernel order): its density, kg/m³.
    pub densities: Vec<f64>,
    /// What the script refers to in its mesh, as the checker evaluated it.
    mesh_refs: MeshRefs,
    /// The checked program (selections and the loss are lowered from it once a mesh is bound).
    program: crate::sema::hir::Program,
}

/// The mesh a script loads.
#[derive(Debug, Clone)]
pub struct MeshDecl {
    /// As written in the script (`"../meshes/cuboid.msh"`).
    pub written: PathBuf,
    /// Resolved against the script's folder.
    pub path: PathBuf,
    /// Metres per file unit.
    pub unit: f64,
    /// The element order the script asks for (`load(…, order: 2)`): a linear mesh gets
    /// straight-sided mid-edge nodes when it is 2.
    pub order: crate::ir::ElementOrder,
    /// The byte span of the path's string literal in the script, when it is one.
    pub span: Option<(usize, usize)>,
}

/// Compile a script given as raw bytes: check it (every diagnostic a user can get), resolve it,
/// and lower its scene to kernels with their adjoint.
pub fn compile(
    name: &str,
    bytes: &[u8],
    options: &CompileOptions,
) -> Result<Compiled, CompileFailure> {
    let edited;
    let bytes = if options.variant.is_empty() {
        bytes
    } else {
        let original = String::from_utf8_lossy(bytes);
        edited = options
            .variant
            .apply(&original)
            .map_err(|e| CompileFailure {
                name: name.to_string(),
                text: original.to_string(),
                diagnostics: Vec::new(),
                lowering: Some(format!("the variant cannot be applied: {e}")),
                in_kernels: false,
            })?;
        edited.as_bytes()
    };
    let (text, checked) = crate::check_bytes(bytes, &options.check_options());
    let fail = |diagnostics: Vec<Diagnostic>, lowering: Option<String>| CompileFailure {
        name: name.to_string(),
        text: text.to_string(),
        diagnostics,
        lowering,
        in_kernels: false,
    };
    if checked.has_errors() {
        return Err(fail(checked.diagnostics, None));
    }
    let checked_script = checked.script.unwrap_or_default();
    let source = text.to_string();
    let lower_err = |e: String| fail(Vec::new(), Some(e));
    let program = &checked_script.program;
    let kernels = lower_scene(program).map_err(|e| CompileFailure {
        in_kernels: true,
        ..lower_err(e.to_string())
    })?;
    let base = options
        .base_dir
        .clone()
        .unwrap_or_else(|| PathBuf::from("."));
    let mesh = settings::mesh_decl(program, &base).map_err(&lower_err)?;
    let sim = SimSettings::resolve(program, checked_script.duration).map_err(&lower_err)?;
    let grad = GradSettings::resolve(program).map_err(&lower_err)?;
    let inputs = plan::inputs(program).map_err(&lower_err)?;
    let optimize =
        OptimizeSpec::resolve(program, &checked_script.params, &inputs).map_err(&lower_err)?;
    let densities = kernels
        .materials
        .iter()
        .map(|m| crate::lower::fem::material_density(program, m).map_err(|e| e.to_string()))
        .collect::<Result<_, _>>()
        .map_err(&lower_err)?;
    let warnings = checked.diagnostics;
    // The resolved scene's materials and chambers, read from the script (the reference oracle
    // takes them from here, not from the kernels it checks).
    let materials =
        crate::lower::scene::scene_materials(program).map_err(|e| lower_err(e.to_string()))?;
    let chambers = crate::lower::scene::scene_chambers(program);
    Ok(Compiled {
        kernels,
        program: Resolved {
            name: name.to_string(),
            source,
            warnings,
            mesh,
            sim,
            grad,
            params: checked_script.params,
            inputs,
            optimize,
            materials,
            chambers,
            densities,
            mesh_refs: checked_script.mesh_refs,
            program: checked_script.program,
        },
    })
}

impl Resolved {
    /// The physical dimension of a param or input given by name (`p_max`, or an entry
    /// `beta.3`): what a value set from outside the script (`softc run --set`) must have.
    pub fn value_dim(&self, name: &str) -> Option<Dim> {
        let base = name.split('.').next().unwrap_or(name);
        if let Some(p) = self.params.iter().find(|p| p.name == base) {
            return match &p.ty {
                crate::sema::types::Ty::Num { dim, .. } => Some(*dim),
                _ => None,
            };
        }
        self.inputs.iter().find(|i| i.name == base).map(|i| i.dim)
    }
}

/// Evaluate a constant expression (SI values, flattened).
pub(crate) fn const_values(program: &Program, e: &Expr) -> Result<Vec<f64>, String> {
    let mut k = KernelBuilder::new("const", Domain::Single, "constant");
    let mut lw = ExprLowerer::new(program);
    let v = lw
        .lower(&mut k, &Env::new(), e)
        .map_err(|e| e.to_string())?;
    flatten(&v)
        .into_iter()
        .map(|x| {
            k.b.func
                .constant(x)
                .ok_or_else(|| "expected a constant".to_string())
        })
        .collect()
}

/// Evaluate a constant scalar expression (SI units).
pub(crate) fn const_scalar(program: &Program, e: &Expr) -> Result<f64, String> {
    const_values(program, e)?
        .first()
        .copied()
        .ok_or_else(|| "expected a number".to_string())
}
