//! `softc._softc`: the native half of the Python package. It exposes the runtime's embedding API
//! ([`softc::embed`]) — a script compiled once through the compiler driver, then run with param
//! values — and leaves the Pythonic surface (NumPy arrays, dicts, torch, ray) to `softc/*.py`.
//! Nothing here panics into Python: every failure is a `CompileError` or a `SimulationError`
//! (a `ValueError` for a malformed argument), and simulations run with the GIL released.

use pyo3::create_exception;
use pyo3::exceptions::{PyException, PyValueError};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};
use softc::devices::{BackendChoice, PrecisionChoice};
use softc::embed::{LoadError, Model, Request, Settings};
use softc::engine::statics::LinearSolver;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

create_exception!(
    softc,
    CompileError,
    PyException,
    "A script that does not compile; `.diagnostics` lists its errors and warnings."
);
create_exception!(
    softc,
    SimulationError,
    PyException,
    "A run that failed (instability, no equilibrium, a device error), with the CLI's message."
);

/// A Python object from JSON text (numbers round-trip exactly through `json.loads`).
fn from_json<'py>(py: Python<'py>, text: &str) -> PyResult<Bound<'py, PyAny>> {
    py.import("json")?.call_method1("loads", (text,))
}

fn compile_error(py: Python<'_>, e: LoadError) -> PyErr {
    let (message, diagnostics) = match &e {
        LoadError::Compile(f) => {
            let file = softc_compiler::diag::SourceFile::new(&f.name, &f.text);
            let mut list = Vec::new();
            for d in &f.diagnostics {
                list.push(file.render_json(d));
            }
            if let Some(l) = &f.lowering {
                list.push(
                    serde_json::json!({
                        "file": f.name, "severity": "error", "code": null, "message": l,
                        "start": null, "end": null, "hint": null, "notes": [],
                    })
                    .to_string(),
                );
            }
            (e.to_string(), list)
        }
        LoadError::Other(m) => (m.clone(), Vec::new()),
    };
    let err = CompileError::new_err(message);
    let value = err.value(py);
    let diags = PyList::empty(py);
    for text in diagnostics {
        let d = match from_json(py, &text) {
            Ok(d) => d,
            Err(e) => return e,
        };
        // `line` and `column` of the start, as a caller reads them first.
        if let Ok(dict) = d.cast::<PyDict>() {
            let start = dict.get_item("start").ok().flatten();
            let pos = |key: &str| {
                start
                    .as_ref()
                    .and_then(|s| s.get_item(key).ok())
                    .unwrap_or_else(|| py.None().into_bound(py))
            };
            let _ = dict.set_item("line", pos("line"));
            let _ = dict.set_item("column", pos("column"));
        }
        let _ = diags.append(d);
    }
    let _ = value.setattr("diagnostics", diags);
    err
}

fn parse_choice<T: clap::ValueEnum>(what: &str, text: &str) -> PyResult<T> {
    T::from_str(text, true).map_err(|_| {
        let names: Vec<String> = T::value_variants()
            .iter()
            .filter_map(|v| v.to_possible_value().map(|p| p.get_name().to_string()))
            .collect();
        PyValueError::new_err(format!(
            "{what} = {text:?}: expected one of {}",
            names.join(", ")
        ))
    })
}

/// How a run failed: a malformed argument, or the simulation itself.
enum Failure {
    Value(String),
    Simulation(String),
}

/// A compiled scene (the Python `softc.Scene` wraps it).
#[pyclass(module = "softc._softc", name = "NativeScene")]
struct NativeScene {
    model: Mutex<Model>,
    path: PathBuf,
}

#[pymethods]
impl NativeScene {
    /// The params (source order), then the inputs: dicts of name, kind, shape, unit, bounds,
    /// initial values (SI, row-major) and a field's element set.
    fn slots<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyList>> {
        let model = self.lock()?;
        let out = PyList::empty(py);
        for s in model.slots() {
            let d = PyDict::new(py);
            d.set_item("name", &s.name)?;
            d.set_item("kind", s.kind)?;
            d.set_item("shape", s.shape.clone())?;
            d.set_item("unit", &s.unit)?;
            d.set_item("lower", s.lower)?;
            d.set_item("upper", s.upper)?;
            d.set_item("initial", s.initial.clone())?;
            d.set_item("set", s.set.clone())?;
            out.append(d)?;
        }
        Ok(out)
    }

    /// The mesh in metres, tets in the kernels' order (grouped by material), node and element
    /// sets: flat lists the Python side reshapes.
    fn mesh<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let model = self.lock()?;
        let scene = model.scene();
        let d = PyDict::new(py);
        let nodes: Vec<f64> = scene.mesh.nodes.iter().flatten().copied().collect();
        let tets: Vec<u32> = scene.mesh.tets.iter().flatten().copied().collect();
        d.set_item("nodes", nodes)?;
        d.set_item("tets", tets)?;
        // Quadratic scenes: the 10 nodes per element (corners, then the mid-edge nodes in VTK
        // order); linear ones: the corners again.
        let order = match scene.order() {
            softc_compiler::ir::ElementOrder::Linear => 1,
            softc_compiler::ir::ElementOrder::Quadratic => 2,
        };
        d.set_item("order", order)?;
        d.set_item("elements", scene.elem_conn())?;
        let sets = PyDict::new(py);
        for (name, nodes) in &scene.node_sets {
            sets.set_item(name, nodes.clone())?;
        }
        d.set_item("node_sets", sets)?;
        let elem_sets = PyDict::new(py);
        for (name, elems) in &scene.element_sets {
            elem_sets.set_item(name, elems.clone())?;
        }
        d.set_item("element_sets", elem_sets)?;
        let fixed: Vec<u32> = (0..scene.fixed.len() as u32)
            .filter(|&n| scene.fixed[n as usize])
            .collect();
        d.set_item("fixed_nodes", fixed)?;
        Ok(d)
    }

    /// The script's path and the device settings.
    fn describe<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let model = self.lock()?;
        let s = model.settings();
        let d = PyDict::new(py);
        d.set_item("path", self.path.display().to_string())?;
        d.set_item("backend", format!("{:?}", s.backend).to_lowercase())?;
        d.set_item("precision", s.precision.map(|p| p.to_string()))?;
        d.set_item("threads", s.threads)?;
        d.set_item("adapter", s.adapter.clone())?;
        let has_loss = model.scene().loss.is_some();
        d.set_item("has_loss", has_loss)?;
        d.set_item(
            "integrator",
            match &model.scene().lowered.statics {
                None => "explicit",
                Some(s) if s.implicit.is_some() => "implicit_euler",
                Some(_) => "quasi_static",
            },
        )?;
        Ok(d)
    }

    /// One run: `values` are (name, SI values row-major) pairs. Returns the summary's JSON text,
    /// the loss, the gradients as (name, shape, values) and the final (x, v) when `keep_state`.
    #[pyo3(signature = (values, steps=None, dt=None, grad=false, checkpoint=None, memory_budget=None, keep_state=false))]
    #[allow(clippy::too_many_arguments, clippy::type_complexity)]
    fn run(
        &self,
        py: Python<'_>,
        values: Vec<(String, Vec<f64>)>,
        steps: Option<u64>,
        dt: Option<f64>,
        grad: bool,
        checkpoint: Option<String>,
        memory_budget: Option<String>,
        keep_state: bool,
    ) -> PyResult<(
        String,
        Option<f64>,
        Vec<(String, Vec<usize>, Vec<f64>)>,
        Option<(Vec<f64>, Vec<f64>)>,
    )> {
        let path = self.path.display().to_string();
        let interrupt = Arc::new(AtomicBool::new(false));
        let stop = interrupt.clone();
        // Everything that touches the model runs on a thread of its own, without the GIL (the
        // lock is taken there: a guard cannot cross threads), while this one answers Ctrl-C.
        let outcome = run_interruptibly(py, &interrupt, move || {
            let mut model = self.model.lock().unwrap_or_else(|p| p.into_inner());
            let grad = if grad {
                if model.scene().loss.is_none() {
                    return Err(Failure::Simulation(format!(
                        "{path}: the script has no `loss`, so there is nothing to \
                         differentiate; add one (e.g. `loss = sum(n in tip) (x[n].z - x0[n].z)^2 \
                         at end`)"
                    )));
                }
                Some(
                    softc::session::grad_options(
                        model.scene(),
                        checkpoint.as_deref(),
                        memory_budget.as_deref(),
                    )
                    .map_err(Failure::Value)?,
                )
            } else {
                None
            };
            let request = Request {
                steps,
                dt,
                grad,
                keep_state,
                interrupt: Some(stop),
            };
            let run = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
                model.run(&values, &request)
            }));
            match run {
                Ok(Ok(outcome)) => Ok(outcome),
                Ok(Err(e)) => Err(Failure::Simulation(format!("{path}: {e}"))),
                Err(p) => {
                    let why = p
                        .downcast_ref::<String>()
                        .cloned()
                        .or_else(|| p.downcast_ref::<&str>().map(|s| s.to_string()))
                        .unwrap_or_default();
                    Err(Failure::Simulation(format!(
                        "{path}: internal error (a bug in softc, please report it): {why}"
                    )))
                }
            }
        })?;
        let outcome = match outcome {
            Ok(o) => o,
            Err(Failure::Value(m)) => return Err(PyValueError::new_err(m)),
            Err(Failure::Simulation(m)) => return Err(SimulationError::new_err(m)),
        };
        let text = serde_json::to_string(&outcome.json)
            .map_err(|e| SimulationError::new_err(e.to_string()))?;
        Ok((text, outcome.loss, outcome.gradients, outcome.state))
    }
}

/// Run `work` on a thread of its own without the GIL; this thread waits for it and checks
/// for signals every 50 ms. On Ctrl-C (KeyboardInterrupt, or whatever the signal handler
/// raises) it sets `interrupt`, which the engine polls at its checks, waits for the run to
/// stop, and returns that exception: a long run stops within a fraction of a second instead
/// of ignoring Ctrl-C until it ends, and the scene stays usable.
fn run_interruptibly<T: Send>(
    py: Python<'_>,
    interrupt: &AtomicBool,
    work: impl FnOnce() -> T + Send,
) -> PyResult<T> {
    let done = (std::sync::Mutex::new(false), std::sync::Condvar::new());
    std::thread::scope(|s| {
        let worker = s.spawn(|| {
            let r = work();
            *done.0.lock().unwrap_or_else(|e| e.into_inner()) = true;
            done.1.notify_all();
            r
        });
        let mut raised = None;
        loop {
            let finished = py.detach(|| {
                let guard = done.0.lock().unwrap_or_else(|e| e.into_inner());
                let (guard, _) = done
                    .1
                    .wait_timeout_while(guard, Duration::from_millis(50), |d| !*d)
                    .unwrap_or_else(|e| e.into_inner());
                *guard
            });
            if finished || worker.is_finished() {
                break;
            }
            if raised.is_none()
                && let Err(e) = py.check_signals()
            {
                interrupt.store(true, Ordering::Relaxed);
                raised = Some(e);
            }
        }
        let result = worker
            .join()
            .unwrap_or_else(|p| std::panic::resume_unwind(p));
        match raised {
            Some(e) => Err(e),
            None => Ok(result),
        }
    })
}

impl NativeScene {
    fn lock(&self) -> PyResult<std::sync::MutexGuard<'_, Model>> {
        // A panic inside a run is caught and reported; the model stays usable.
        Ok(self.model.lock().unwrap_or_else(|p| p.into_inner()))
    }
}

/// Compile a script: `backend` cpu, interp or gpu; `precision` f32/f64 (None: the script's,
/// else the backend's default); `linear_solver` auto, direct, amg or krylov; `warm_start`:
/// static solves start from the previous run's equilibrium.
#[pyfunction]
#[pyo3(signature = (path, backend="cpu", precision=None, threads=None, adapter=None, linear_solver="auto", warm_start=false))]
#[allow(clippy::too_many_arguments)]
fn compile(
    py: Python<'_>,
    path: PathBuf,
    backend: &str,
    precision: Option<&str>,
    threads: Option<usize>,
    adapter: Option<String>,
    linear_solver: &str,
    warm_start: bool,
) -> PyResult<NativeScene> {
    let backend: BackendChoice = parse_choice("backend", backend)?;
    let precision = precision
        .map(|p| parse_choice::<PrecisionChoice>("precision", p))
        .transpose()?
        .map(Into::into);
    let linear_solver: LinearSolver = parse_choice("linear_solver", linear_solver)?;
    let settings = Settings {
        backend,
        precision,
        adapter,
        threads,
        linear_solver,
        warm_start,
    };
    let model = py
        .detach(|| Model::compile(&path, settings))
        .map_err(|e| compile_error(py, e))?;
    Ok(NativeScene {
        model: Mutex::new(model),
        path,
    })
}

/// A value with its unit (`"12 kPa"`, `"20 us"`), read by the language's own front end: the
/// value in SI units and the SI unit of its dimension (`"Pa"`, `"s"`, `"1"` for none).
#[pyfunction]
fn quantity(text: &str) -> PyResult<(f64, String)> {
    let (value, dim) = softc::session::parse_quantity(text)
        .map_err(|e| PyValueError::new_err(format!("{text:?}: {e}")))?;
    Ok((value, dim.si_unit()))
}

#[pymodule]
fn _softc(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(compile, m)?)?;
    m.add_function(wrap_pyfunction!(quantity, m)?)?;
    m.add_class::<NativeScene>()?;
    m.add("CompileError", m.py().get_type::<CompileError>())?;
    m.add("SimulationError", m.py().get_type::<SimulationError>())?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    Ok(())
}
