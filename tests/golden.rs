//! Generated kernels are golden files: `tests/golden/ir/NAME.ir` holds the kernel IR of every
//! example, so a change to generated code shows in review. Update after an intended change:
//!     SOFTC_BLESS=1 cargo test -p softc-tests --test golden
//! and read the diff.

use softc_tests::{bless, files_with_ext, root, softc};

#[test]
fn example_kernels_match_their_golden_ir() {
    let dir = root().join("tests/golden/ir");
    let mut failures = Vec::new();
    for script in files_with_ext(&root().join("examples"), "soft") {
        let (code, out, err) = softc(&["compile", "--emit", "ir", script.to_str().unwrap()]);
        assert_eq!(code, 0, "{}: {err}", script.display());
        let golden = dir.join(script.file_stem().unwrap()).with_extension("ir");
        if bless() {
            std::fs::write(&golden, &out).unwrap();
            continue;
        }
        let expected = std::fs::read_to_string(&golden).unwrap_or_default();
        if expected != out {
            failures.push(format!(
                "{} differs from {} (run with SOFTC_BLESS=1 and review the diff)",
                script.display(),
                golden.display()
            ));
        }
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
    let controller = ir("controller_synthesis.soft");
    // Constant damping is a literal; windowed damping selects among params.
    assert!(bench.contains("const 2e1"), "constant damping folded");
    assert!(!bench.contains("uniform param.beta"));
    assert!(meta.contains("uniform param.beta.29") && meta.contains("select"));
    // One pressure kernel per chamber, and one adjoint of each.
    assert_eq!(bench.matches("kernel pressure_").count(), 1);
    assert_eq!(controller.matches("kernel pressure_").count(), 3);
    assert_eq!(controller.matches("kernel adj_pressure_").count(), 3);
    // The adjoint accumulates derivatives only for the params each kernel reads: the
    // benchmark's pressure kernel for p_peak, the meta study's integrator for its 30 windows.
    assert!(bench.contains("buffer grad@tri_force: triangle × 1"));
    assert!(!bench.contains("grad@elem_force") && !bench.contains("grad@x_next"));
    assert!(meta.contains("buffer grad@x_next: node × 30"));
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
    let (code, _, err) = softc(&["compile", "--emit", "wgsl", good.to_str().unwrap()]);
    assert_eq!(code, 2);
    assert!(err.contains("not implemented yet"), "{err}");
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
        "--examples",
        examples.to_str().unwrap(),
        "--json",
        json.to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{err}");
    assert!(out.starts_with("size"), "{out}");
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    let rows = v["rows"].as_array().unwrap();
    let backends: Vec<&str> = rows
        .iter()
        .map(|r| r["backend"].as_str().unwrap())
        .collect();
    assert_eq!(backends, ["cpu-f64", "cpu-f32", "interp", "reference"]);
    for r in rows {
        assert!(r["forward_steps_per_second"].as_f64().unwrap() > 0.0, "{r}");
        assert!(r["tip_mean_z"].as_f64().unwrap().is_finite(), "{r}");
        assert!(out.contains(r["backend"].as_str().unwrap()));
    }
    // cpu f64 and the reference simulate the same physics: the same tip after 20 steps.
    let z = |i: usize| rows[i]["tip_mean_z"].as_f64().unwrap();
    assert!(
        (z(0) - z(3)).abs() <= 1e-6 * z(3).abs(),
        "{} vs {}",
        z(0),
        z(3)
    );
    std::fs::remove_file(&json).ok();
    // An unknown size is a usage error naming the valid ones.
    let (code, _, err) = softc(&["bench", "--sizes", "2k"]);
    assert_eq!(code, 2);
    assert!(err.contains("1k, 10k or 50k"), "{err}");
}
