//! Generated kernels are golden files: `tests/golden/ir/NAME.ir` holds the kernel IR of every
//! example and `tests/golden/wgsl/NAME.wgsl` its WGSL (f32), with specialization cases
//! (f64, a trainable material constant, …) in `tests/golden/wgsl/cases/`, so a change to
//! generated code shows in review. Update after an intended change:
//!     SOFTC_BLESS=1 cargo test -p softc-tests --test golden
//! and read the diff.
//!
//! Not insta snapshots (as tests/diagnostics.rs uses): insta stores text as `NAME.snap` with a
//! YAML header and compares it with trailing whitespace trimmed and CRLF folded, and its binary
//! snapshots split each golden into `NAME.snap` + `NAME.snap.wgsl`. These goldens stay plain
//! `.wgsl`/`.ir` files (an editor highlights them) compared byte for byte.

use softc_tests::{bless, files_with_ext, root, softc};
use std::path::{Path, PathBuf};

/// Compare `out` with a golden file (or write it when blessing); a mismatch is pushed.
fn check_golden(golden: &Path, out: &str, what: &str, failures: &mut Vec<String>) {
    if bless() {
        std::fs::create_dir_all(golden.parent().unwrap()).unwrap();
        std::fs::write(golden, out).unwrap();
        return;
    }
    let expected = std::fs::read_to_string(golden).unwrap_or_default();
    if expected != out {
        failures.push(format!(
            "{what} differs from {} (run with SOFTC_BLESS=1 and review the diff)",
            golden.display()
        ));
    }
}

/// A copy of an example with some text replaced, written next to the example (so its mesh
/// paths still resolve) under a name that cannot clash with a real example.
fn variant(example: &str, name: &str, edits: &[(&str, &str)]) -> PathBuf {
    let mut text = std::fs::read_to_string(root().join("examples").join(example)).unwrap();
    for (from, to) in edits {
        assert!(text.contains(from), "{example}: `{from}` not found");
        text = text.replace(from, to);
    }
    let dir = std::env::temp_dir().join(format!("softc-golden-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let text = text.replace("\"../meshes/", &format!("\"{}/meshes/", root().display()));
    let path = dir.join(format!("{name}.soft"));
    std::fs::write(&path, text).unwrap();
    path
}

fn wgsl_of(script: &Path, precision: &str) -> String {
    let (code, out, err) = softc(&[
        "compile",
        "--emit",
        "wgsl",
        "--precision",
        precision,
        script.to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{}: {err}", script.display());
    out
}

/// `softc compile --emit wgsl` validates every module with naga before printing it, so a
/// zero exit status here also means naga accepted the module.
#[test]
fn example_kernels_match_their_golden_wgsl() {
    let dir = root().join("tests/golden/wgsl");
    let mut failures = Vec::new();
    for script in files_with_ext(&root().join("examples"), "soft") {
        let out = wgsl_of(&script, "f32");
        let golden = dir.join(script.file_stem().unwrap()).with_extension("wgsl");
        check_golden(&golden, &out, &script.display().to_string(), &mut failures);
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

/// Specialization cases: the same scene in f64 (software transcendental functions), and with
/// a trainable instead of a constant material modulus (a uniform instead of a folded literal).
#[test]
fn specialization_cases_match_their_golden_wgsl() {
    let dir = root().join("tests/golden/wgsl/cases");
    let mut failures = Vec::new();
    let ex = |n: &str| root().join("examples").join(n);
    let trainable = variant(
        "benchmark-1k.soft",
        "benchmark-1k-trainable-E",
        &[(
            "let E = 0.3 MPa",
            "param E: pressure = 0.3 MPa in [0.1 MPa, 1 MPa]",
        )],
    );
    // Explicit contact with Coulomb friction: the projection's friction impulse in the node
    // kernel.
    let friction = variant(
        "finger_on_table.soft",
        "finger_on_table-explicit-friction",
        &[
            (
                "integrator = quasi_static",
                "integrator = semi_implicit_euler\n  dt = 20 us",
            ),
            ("(gap: 0.2 mm)", "(gap: 0.2 mm, friction: 0.5)"),
        ],
    );
    // Backward Euler with friction: the smoothed Coulomb force in the implicit residual.
    let implicit_friction = variant(
        "finger_on_table.soft",
        "finger_on_table-implicit-friction",
        &[
            (
                "integrator = quasi_static",
                "integrator = implicit_euler\n  dt = 5 ms",
            ),
            ("(gap: 0.2 mm)", "(gap: 0.2 mm, friction: 0.5)"),
        ],
    );
    // Explicit contact with a bounded obstacle: each step's path tested for an entry
    // (collision detection, closed-form per node) before the projection.
    let bounded = variant(
        "finger_on_table.soft",
        "finger_on_table-explicit-box",
        &[
            (
                "integrator = quasi_static",
                "integrator = semi_implicit_euler\n  dt = 20 us",
            ),
            (
                "plane(point: [0, 0, -7] mm, normal: [0, 0, 1])",
                "box(min: [-10, -10, -9] mm, max: [80, 20, -7] mm)",
            ),
        ],
    );
    let cases: Vec<(&str, PathBuf, &str)> = vec![
        ("benchmark-1k-f64", ex("benchmark-1k.soft"), "f64"),
        ("finger_on_table-explicit-box", bounded, "f32"),
        ("finger_on_table-explicit-friction", friction, "f32"),
        (
            "finger_on_table-implicit-friction",
            implicit_friction,
            "f32",
        ),
        ("meta_optimization-f64", ex("meta_optimization.soft"), "f64"),
        (
            "controller_synthesis-f64",
            ex("controller_synthesis_explicit.soft"),
            "f64",
        ),
        ("benchmark-1k-trainable-E", trainable.clone(), "f32"),
        ("field-mu", field_fixture(), "f32"),
    ];
    let mut texts = std::collections::HashMap::new();
    for (name, script, precision) in &cases {
        let out = wgsl_of(script, precision);
        let golden = dir.join(name).with_extension("wgsl");
        check_golden(&golden, &out, name, &mut failures);
        texts.insert(*name, out);
    }
    // The controller study's four targets per iteration, as the GPU runs them: one batch.
    let script = ex("controller_synthesis_explicit.soft");
    let (code, batched, err) = softc(&[
        "compile",
        "--emit",
        "wgsl",
        "--batch",
        "4",
        script.to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{err}");
    check_golden(
        &dir.join("controller_synthesis-batch4.wgsl"),
        &batched,
        "controller_synthesis --batch 4",
        &mut failures,
    );
    assert!(failures.is_empty(), "{}", failures.join("\n"));
    // A batch reads each scene's launch block by workgroup row and offsets the scene's data.
    assert!(batched.contains("var<uniform> launch_fem_silicone: array<Launch_fem_silicone, 4>;"));
    assert!(batched.contains("let base_node = (*l).scene * (*l).nodes;"));
    // What the specializations must show.
    let bench = wgsl_of(&ex("benchmark-1k.soft"), "f32");
    let meta = wgsl_of(&ex("meta_optimization.soft"), "f32");
    let controller = wgsl_of(&ex("controller_synthesis_explicit.soft"), "f32");
    // One pressure entry point per chamber: 1 in the benchmark, 3 in the controller study,
    // and the adjoint of each.
    assert_eq!(bench.matches("kernel pressure_").count(), 1);
    assert_eq!(controller.matches("kernel pressure_").count(), 3);
    assert_eq!(controller.matches("kernel adj_pressure_").count(), 3);
    // Constant damping is a literal; windowed damping selects among the window's params.
    assert!(!bench.contains("param_beta"));
    assert!(meta.contains("param_beta_11: real, // param.beta.11"));
    assert!(meta.contains("select("));
    // f32 uses the built-in exp but a software ln (Vulkan's log may be 2^-21 off absolutely
    // near 1, where the neo-Hookean ln J lives); f64 has software functions only (SPIR-V has
    // no f64 exp/log).
    assert!(bench.contains("alias real = f32;"));
    assert!(bench.contains("fn softc_ln(") && bench.contains("= softc_ln(v"));
    assert!(!bench.contains("log(") && !bench.contains("log2("));
    let f64_bench = &texts["benchmark-1k-f64"];
    assert!(f64_bench.contains("alias real = f64;"));
    assert!(f64_bench.contains("fn softc_ln("));
    assert!(!f64_bench.contains(" exp(") && !f64_bench.contains(" log("));
    // f64's ln takes only an estimate of the exponent from the f32 log2 (then corrected).
    assert_eq!(f64_bench.matches("log2(").count(), 1);
    // The simplification pass leaves the benchmark's powers of J no `pow` and no cube root:
    // it cancels J^(2/3)·Ī1 to I1 before the adjoint differentiates the element kernel, so
    // neither kernel takes a root (the f64 module then carries no software cube root either).
    assert!(!f64_bench.contains("softc_pow(") && !bench.contains("softc_pow("));
    assert!(!f64_bench.contains("softc_cbrt(") && !bench.contains("cbrt"));
    // A trainable modulus is read from the launch block instead of folded.
    let tr = &texts["benchmark-1k-trainable-E"];
    assert!(tr.contains("param_E: real, // param.E"), "{tr}");
    assert!(!bench.contains("param_E"));
    // A per-element param is a storage buffer read at the element, not a launch uniform, and
    // its adjoint accumulates into a per-element buffer.
    let field = &texts["field-mu"];
    assert!(
        field.contains("var<storage, read> param_mu: array<real>;"),
        "{field}"
    );
    assert!(field.contains("param_mu[e]"), "{field}");
    assert!(field.contains("var<storage, read_write> grad_param_mu: array<real>;"));
    assert!(!field.contains("param_mu_0"));
}

/// The gradient tests' scene with a per-element shear modulus.
fn field_fixture() -> PathBuf {
    root().join("runtime/tests/fixtures/grad/field.soft")
}

/// A per-element param in the kernel IR: the element kernel of the material that reads it
/// loads `param.mu[self]`, the other material's kernel does not, and the adjoint of the
/// former adds its derivative into `grad_param.mu[self]`.
#[test]
fn per_element_params_are_element_buffers_in_the_ir() {
    let (code, out, err) = softc(&["compile", "--emit", "ir", field_fixture().to_str().unwrap()]);
    assert_eq!(code, 0, "{err}");
    let mut failures = Vec::new();
    check_golden(
        &root().join("tests/golden/ir/cases/field-mu.ir"),
        &out,
        "field.soft",
        &mut failures,
    );
    assert!(failures.is_empty(), "{}", failures.join("\n"));
    assert!(out.contains("buffer param.mu: element × 1"), "{out}");
    assert!(out.contains("buffer grad_param.mu: element × 1"), "{out}");
    let kernel = |name: &str| {
        let start = out.find(&format!("kernel {name} over")).unwrap();
        let rest = &out[start..];
        rest[..rest[1..].find("\nkernel ").map_or(rest.len(), |e| e + 1)].to_string()
    };
    assert!(kernel("fem_graded").contains("= param.mu[self].0"));
    assert!(!kernel("fem_gel").contains("param.mu"));
    let adj = kernel("adj_fem_graded");
    assert!(adj.contains("= param.mu[self].0") && adj.contains("= grad_param.mu[self].0"));
    assert!(adj.contains("store grad_param.mu[self].0"));
    assert!(!kernel("adj_fem_gel").contains("grad_param.mu"));
}

#[test]
fn example_kernels_match_their_golden_ir() {
    let dir = root().join("tests/golden/ir");
    let mut failures = Vec::new();
    for script in files_with_ext(&root().join("examples"), "soft") {
        let (code, out, err) = softc(&["compile", "--emit", "ir", script.to_str().unwrap()]);
        assert_eq!(code, 0, "{}: {err}", script.display());
        let golden = dir.join(script.file_stem().unwrap()).with_extension("ir");
        check_golden(&golden, &out, &script.display().to_string(), &mut failures);
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

#[test]
fn specialization_is_visible_in_the_kernels() {
    let ir = |name: &str| {
        let path = root().join("examples").join(name);
        softc(&["compile", path.to_str().unwrap()]).1
    };
    let bench = ir("benchmark-1k.soft");
    let meta = ir("meta_optimization.soft");
    let controller = ir("controller_synthesis_explicit.soft");
    // Constant damping is a literal; windowed damping selects among params.
    assert!(bench.contains("const 2e1"), "constant damping folded");
    assert!(!bench.contains("uniform param.beta"));
    assert!(meta.contains("uniform param.beta.11") && meta.contains("select"));
    // One pressure kernel per chamber, and one adjoint of each.
    assert_eq!(bench.matches("kernel pressure_").count(), 1);
    assert_eq!(controller.matches("kernel pressure_").count(), 3);
    assert_eq!(controller.matches("kernel adj_pressure_").count(), 3);
    // The adjoint accumulates derivatives only for the params each kernel reads: the
    // benchmark's pressure kernel for p_peak, the meta study's integrator for its 12 windows.
    assert!(bench.contains("buffer grad@tri_force: triangle × 1"));
    assert!(!bench.contains("grad@elem_force") && !bench.contains("grad@x_next"));
    assert!(meta.contains("buffer grad@x_next: node × 12"));
    // A user-defined W and the prelude's Yeoh generate different element code.
    assert!(bench.contains("kernel fem_rubber") && meta.contains("kernel fem_silicone"));
}

#[test]
fn compile_reports_script_errors_and_unsupported_emits() {
    let bad = root().join("tests/diagnostics/add_pressure_and_length.soft");
    let (code, _, err) = softc(&["compile", bad.to_str().unwrap()]);
    assert_eq!(code, 1);
    assert!(err.contains("E0201"), "{err}");
    let good = root().join("examples/benchmark-1k.soft");
    let (code, _, err) = softc(&[
        "compile",
        "--emit",
        "ir",
        "--precision",
        "f64",
        good.to_str().unwrap(),
    ]);
    assert_eq!(code, 2);
    assert!(
        err.contains("--precision and --batch apply to --emit wgsl"),
        "{err}"
    );
}

/// `--emit clif` prints every kernel's Cranelift IR and the time loop that calls them, by
/// name (no addresses: the same text every run).
#[test]
fn compile_emits_the_cranelift_ir_of_the_kernels_and_the_time_loop() {
    let script = root().join("examples/benchmark-1k.soft");
    let (code, out, err) = softc(&["compile", "--emit", "clif", script.to_str().unwrap()]);
    assert_eq!(code, 0, "{err}");
    let (kernels, time_loop) = out.split_once("; time loop").expect("the time loop");
    assert!(kernels.matches("function u0:").count() >= 3, "{kernels}");
    // One call per launch of a step: the element, pressure and node kernels.
    assert!(
        time_loop.contains("n steps of kernels [0, 1, 2]"),
        "{time_loop}"
    );
    for k in 0..3 {
        assert!(
            time_loop.contains(&format!("fn{k} = u0:{k}")),
            "{time_loop}"
        );
        assert!(time_loop.contains(&format!("call fn{k}(")), "{time_loop}");
    }
    assert!(!time_loop.contains("0x7f"), "addresses in the printed loop");
    let (_, again, _) = softc(&["compile", "--emit", "clif", script.to_str().unwrap()]);
    assert_eq!(out, again);
}

#[test]
fn bench_prints_a_table_and_well_formed_json() {
    let json = std::env::temp_dir().join(format!("softc-bench-{}.json", std::process::id()));
    let examples = root().join("examples");
    let (code, out, err) = softc(&[
        "bench",
        "--sizes",
        "1k",
        "--repeats",
        "1",
        "--steps",
        "20",
        "--grad-steps",
        "20",
        "--examples",
        examples.to_str().unwrap(),
        "--baseline",
        root()
            .join("runtime/benches/baseline.json")
            .to_str()
            .unwrap(),
        "--json",
        json.to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{err}");
    assert!(out.starts_with("size"), "{out}");
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    let rows = v["rows"].as_array().unwrap();
    // Every row names the element kernel's size and its adjoint's; the cpu rows compare
    // with the committed baseline's rows of the same size and backend.
    for r in rows {
        let (fwd, adj) = (
            r["element_ops"].as_u64().unwrap(),
            r["adjoint_element_ops"].as_u64().unwrap(),
        );
        assert!(fwd > 50 && adj > fwd, "{r}");
    }
    let cpu64 = rows.iter().find(|r| r["backend"] == "cpu-f64").unwrap();
    assert!(cpu64["vs_baseline"][0].as_f64().unwrap() > 0.0, "{cpu64}");
    // The cpu rows (run on the backend's own choice of threads) also time one thread where
    // there is more than one core; the other rows do not.
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    for r in rows {
        let one = &r["forward_steps_per_second_one_thread"];
        if cores > 1 && r["backend"].as_str().unwrap().starts_with("cpu") {
            assert!(one.as_f64().unwrap() > 0.0, "{r}");
        } else {
            assert!(one.is_null(), "{r}");
        }
    }
    let backends: Vec<&str> = rows
        .iter()
        .map(|r| r["backend"].as_str().unwrap())
        .collect();
    // GPU rows where an adapter exists (lavapipe in CI, where one must exist).
    let gpu: Vec<&str> = backends
        .iter()
        .copied()
        .filter(|b| b.starts_with("gpu"))
        .collect();
    let cpu: Vec<&str> = backends
        .iter()
        .copied()
        .filter(|b| !b.starts_with("gpu"))
        .collect();
    assert_eq!(cpu, ["cpu-f64", "cpu-f32", "interp", "reference"]);
    if std::env::var("CI").is_ok_and(|v| v == "true") {
        assert!(gpu.contains(&"gpu-f32"), "{backends:?}");
    }
    if gpu.contains(&"gpu-f32") {
        // The batch row (4 copies in one batch, the default) follows the single-scene row and
        // simulates the same first scene.
        let at = backends.iter().position(|b| *b == "gpu-f32").unwrap();
        assert_eq!(backends[at + 1], "gpu-f32 x4");
        assert_eq!(rows[at]["tip_mean_z"], rows[at + 1]["tip_mean_z"]);
    }
    for r in rows.iter().filter(|r| {
        let b = r["backend"].as_str().unwrap();
        b.starts_with("gpu") && !b.contains(" x")
    }) {
        assert!(
            r["forward_backward_steps_per_second"].as_f64().unwrap() > 0.0,
            "{r}"
        );
    }
    for r in rows {
        assert!(r["forward_steps_per_second"].as_f64().unwrap() > 0.0, "{r}");
        assert!(r["tip_mean_z"].as_f64().unwrap().is_finite(), "{r}");
        assert!(out.contains(r["backend"].as_str().unwrap()));
    }
    // cpu f64 and the reference simulate the same physics: the same tip after 20 steps.
    let z = |name: &str| {
        rows.iter().find(|r| r["backend"] == name).unwrap()["tip_mean_z"]
            .as_f64()
            .unwrap()
    };
    let (cpu, reference) = (z("cpu-f64"), z("reference"));
    assert!(
        (cpu - reference).abs() <= 1e-6 * reference.abs(),
        "{cpu} vs {reference}"
    );
    // The forward+backward pass reports its peak memory on Linux.
    if cfg!(target_os = "linux") {
        assert!(
            rows[0]["forward_backward_peak_rss_bytes"]
                .as_u64()
                .is_some(),
            "{}",
            rows[0]
        );
    }
    std::fs::remove_file(&json).ok();
    // An unknown size is a usage error naming the valid ones.
    let (code, _, err) = softc(&["bench", "--sizes", "2k"]);
    assert_eq!(code, 2);
    assert!(err.contains("1k, 10k or 50k"), "{err}");
}

/// `softc bench --solvers`: a row per solver with the solve's figures, and the static and
/// implicit tips agree with each other to the dynamics' lag (the scene still moves at 0.16 s).
#[test]
fn bench_solvers_prints_a_row_per_solver_and_well_formed_json() {
    let json =
        std::env::temp_dir().join(format!("softc-bench-solvers-{}.json", std::process::id()));
    let examples = root().join("examples");
    let (code, out, err) = softc(&[
        "bench",
        "--solvers",
        "--krylov",
        "--sizes",
        "1k",
        "--repeats",
        "1",
        "--examples",
        examples.to_str().unwrap(),
        "--json",
        json.to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{err}");
    assert!(out.starts_with("size"), "{out}");
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    let rows = v.as_array().unwrap();
    let solvers: Vec<&str> = rows.iter().map(|r| r["solver"].as_str().unwrap()).collect();
    assert_eq!(
        solvers,
        [
            "quasi_static",
            "quasi_static+grad",
            "implicit_euler x40",
            "quasi_static krylov",
            "implicit x40 krylov"
        ]
    );
    for r in rows {
        assert!(r["newton_iterations"].as_u64().unwrap() >= 1, "{r}");
        assert!(r["dofs"].as_u64().unwrap() > 0, "{r}");
    }
    assert!(rows[1]["gradient_p_peak"].as_f64().unwrap() < 0.0);
    let (s, i) = (
        rows[0]["tip_mean_z"].as_f64().unwrap(),
        rows[2]["tip_mean_z"].as_f64().unwrap(),
    );
    assert!(
        s < 0.0 && ((s - i) / s).abs() < 0.1,
        "static {s}, implicit {i}"
    );
    // The matrix-free rows solve the same equations: the same tips, by GMRES, nothing factored.
    for (direct, krylov) in [(0, 3), (2, 4)] {
        let (d, k) = (
            rows[direct]["tip_mean_z"].as_f64().unwrap(),
            rows[krylov]["tip_mean_z"].as_f64().unwrap(),
        );
        assert!(((d - k) / d).abs() < 1e-6, "direct {d}, krylov {k}");
        assert!(rows[krylov]["krylov_iterations"].as_u64().unwrap() > 0);
        assert_eq!(rows[krylov]["factorizations"].as_u64().unwrap(), 0);
    }
    std::fs::remove_file(&json).ok();
}

/// The benchmark's kernels with their launch blocks in a storage table whose row comes as an
/// immediate (`SOFTC_GPU_LAUNCH=table` on the GPU): the same bodies as the uniform blocks'
/// golden, only where `begin`, `count` and the uniforms are read from differs.
#[test]
fn the_launch_table_variant_matches_its_golden_wgsl() {
    use softc_compiler::back::Precision;
    use softc_compiler::back::wgsl::{self, LaunchMode};
    let scene =
        softc::engine::scene::Scene::load(&root().join("examples/benchmark-1k.soft"), &[]).unwrap();
    let module = &scene.lowered.adjoint.module;
    let table = wgsl::emit_for(module, Precision::F32, None, LaunchMode::Table).unwrap();
    wgsl::validate(&table.source, Precision::F32).unwrap();
    let mut failures = Vec::new();
    check_golden(
        &root().join("tests/golden/wgsl/cases/benchmark-1k-table.wgsl"),
        &table.source,
        "benchmark-1k, launch table",
        &mut failures,
    );
    assert!(failures.is_empty(), "{}", failures.join("\n"));
    assert!(table.source.contains("var<immediate> softc_row: SoftcRow;"));
    assert!(table.source.contains(
        "@group(0) @binding(30) var<storage, read> launch_pressure_cavity: array<Launch_pressure_cavity>;"
    ));
    assert!(
        table
            .source
            .contains("    let l = &launch_pressure_cavity[softc_row.row];")
    );
    // Every kernel reads its block from the table and nothing else changed: the uniform
    // variant's entry points, bindings and bodies are the same apart from the block.
    let uniform = wgsl::emit(module, Precision::F32).unwrap();
    assert_eq!(table.kernels.len(), uniform.kernels.len());
    for (t, u) in table.kernels.iter().zip(&uniform.kernels) {
        assert_eq!((&t.entry, &t.uniforms), (&u.entry, &u.uniforms));
        assert_eq!(t.storage_buffers, u.storage_buffers + 1, "{}", t.name);
        assert_eq!(t.launch_stride(), u.launch_stride());
    }
}

/// Kernels with no data between them share a dispatch on the GPU: the benchmark's element and
/// pressure kernels fuse (each part reading its own launch block), the node kernel that
/// gathers their forces does not.
#[test]
fn independent_kernels_fuse_into_one_entry_point() {
    use softc_compiler::back::Precision;
    use softc_compiler::back::wgsl;
    let scene =
        softc::engine::scene::Scene::load(&root().join("examples/benchmark-1k.soft"), &[]).unwrap();
    let module = &scene.lowered.module;
    let names: Vec<&str> = module.kernels.iter().map(|k| k.name.as_str()).collect();
    let (fem, pressure, integrate) = (
        names.iter().position(|n| *n == "fem_rubber").unwrap(),
        names.iter().position(|n| *n == "pressure_cavity").unwrap(),
        names.iter().position(|n| *n == "integrate").unwrap(),
    );
    assert!(wgsl::independent(module, fem, pressure));
    assert!(!wgsl::independent(module, pressure, integrate));
    let fused = wgsl::emit_fused(module, Precision::F32, &[vec![fem, pressure]]).unwrap();
    wgsl::validate(&fused.source, Precision::F32).unwrap();
    let entry = fused.kernels.last().unwrap();
    assert_eq!(entry.parts, vec![fem, pressure]);
    assert_eq!(entry.entry, "softc_fused_fem_rubber_pressure_cavity");
    assert!(
        fused
            .source
            .contains("        softc_part_pressure_cavity(i);")
    );
    assert!(fused.source.contains("    i -= launch_fem_rubber.count;"));
    // Both launch blocks are bound (two dynamic offsets).
    let launches = entry
        .bindings
        .iter()
        .filter(|b| matches!(b.1, wgsl::Binding::Launch))
        .count();
    assert_eq!(launches, 2);
    let err = wgsl::emit_fused(module, Precision::F32, &[vec![pressure, integrate]]).unwrap_err();
    assert!(err.contains("depend on each other"), "{err}");
}
