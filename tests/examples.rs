//! The examples are the user's first contact: each must check clean (no errors, no warnings),
//! be a fixed point of `softc fmt`, and formatting must never change what a script means.

use softc_compiler::front::parse;
use softc_compiler::sema::CheckOptions;
use softc_tests::{files_with_ext, root, softc};

/// The examples and the valid-feature scripts in tests/valid.
fn examples() -> Vec<std::path::PathBuf> {
    let mut v = files_with_ext(&root().join("examples"), "soft");
    assert!(v.len() >= 4, "the four studies are missing from examples/");
    v.extend(files_with_ext(&root().join("tests/valid"), "soft"));
    v
}

#[test]
fn every_example_checks_clean() {
    for path in examples() {
        let (code, _, err) = softc(&["check", "--deny-warnings", path.to_str().unwrap()]);
        assert_eq!(code, 0, "{}:\n{err}", path.display());
    }
}

#[test]
fn every_example_is_a_fixed_point_of_fmt() {
    for path in examples() {
        let (code, _, err) = softc(&["fmt", "--check", path.to_str().unwrap()]);
        assert_eq!(code, 0, "{} is not formatted:\n{err}", path.display());
    }
}

/// The AST without source positions, for comparing a script with its formatted self.
fn shape(text: &str) -> String {
    let ast = parse(text).expect("parses");
    let dbg = format!("{ast:?}");
    let mut out = String::with_capacity(dbg.len());
    let mut rest = dbg.as_str();
    while let Some(i) = rest.find("Span {") {
        out.push_str(&rest[..i]);
        let j = rest[i..].find('}').unwrap();
        rest = &rest[i + j + 1..];
    }
    out.push_str(rest);
    out
}

fn corpus() -> Vec<(String, String)> {
    let mut v: Vec<(String, String)> = examples()
        .into_iter()
        .map(|p| {
            (
                p.display().to_string(),
                std::fs::read_to_string(&p).unwrap(),
            )
        })
        .collect();
    v.push(("prelude".into(), softc_compiler::sema::PRELUDE.to_string()));
    for p in files_with_ext(&root().join("tests/diagnostics"), "soft") {
        let bytes = std::fs::read(&p).unwrap();
        if let Ok(t) = String::from_utf8(bytes)
            && parse(&t).is_ok()
        {
            v.push((p.display().to_string(), t));
        }
    }
    v
}

#[test]
fn fmt_preserves_meaning_and_comments_and_is_idempotent() {
    for (name, text) in corpus() {
        let once = softc_compiler::fmt::format_source(&text).unwrap();
        let twice = softc_compiler::fmt::format_source(&once).unwrap();
        assert_eq!(once, twice, "{name}: fmt is not idempotent");
        assert_eq!(
            shape(&text),
            shape(&once),
            "{name}: fmt changed the meaning"
        );
        let comments = |s: &str| {
            s.lines()
                .filter_map(|l| l.find('#').map(|i| l[i..].trim_end().to_string()))
                .collect::<Vec<_>>()
        };
        let mut a = comments(&text);
        let mut b = comments(&once);
        a.sort();
        b.sort();
        assert_eq!(a, b, "{name}: fmt lost or changed a comment");
    }
}

#[test]
fn fmt_canonicalizes_layout() {
    let messy = "# head\nmesh   body=load( \"tet.msh\" )  # the body\n\n\n\nsim{dt=20 us;duration=1 s\n# fixes\nfix  clamp}\nregion clamp=box(min:[0,0,0]mm,max:[1,1,1] mm)\nlet a=-(1+2)^2*3 kPa/2\n";
    let want = "# head\nmesh body = load(\"tet.msh\")  # the body\n\nsim {\n  dt = 20 us\n  duration = 1 s\n  # fixes\n  fix clamp\n}\nregion clamp = box(min: [0, 0, 0] mm, max: [1, 1, 1] mm)\nlet a = -(1 + 2)^2 * 3 kPa / 2\n";
    assert_eq!(softc_compiler::fmt::format_source(messy).unwrap(), want);
}

#[test]
fn fmt_canonicalizes_obstacles_and_contact() {
    let messy = "obstacle   floor=plane(point:[0,0,-1]mm,normal:[0,0,1])\n\
                 sim{contact  body  with floor(gap:0.1 mm,stiffness:1 MPa);contact tip with floor\n\
                 contact tip with ball ( 0.2 mm )}\n";
    let want = "obstacle floor = plane(point: [0, 0, -1] mm, normal: [0, 0, 1])\n\
                sim {\n  contact body with floor (gap: 0.1 mm, stiffness: 1 MPa)\n  \
                contact tip with floor\n  contact tip with ball (0.2 mm)\n}\n";
    let once = softc_compiler::fmt::format_source(messy).unwrap();
    assert_eq!(once, want);
    assert_eq!(shape(messy), shape(&once));
    // `obstacle` and `contact` stay usable as names.
    let names = "let contact = 2 mm\nlet obstacle = contact * 2\n";
    assert_eq!(softc_compiler::fmt::format_source(names).unwrap(), names);
}

#[test]
fn fmt_rewrites_files_in_place_and_refuses_broken_ones() {
    let dir = std::env::temp_dir().join(format!("softc-fmt-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let good = dir.join("good.soft");
    std::fs::write(&good, "let   a = 1 mm").unwrap();
    let (code, _, err) = softc(&["fmt", "--check", good.to_str().unwrap()]);
    assert_eq!(code, 1, "{err}");
    assert!(err.contains("not formatted"), "{err}");
    let (code, _, err) = softc(&["fmt", good.to_str().unwrap()]);
    assert_eq!(code, 0, "{err}");
    assert_eq!(std::fs::read_to_string(&good).unwrap(), "let a = 1 mm\n");
    let broken = dir.join("broken.soft");
    std::fs::write(&broken, "let a = (1 mm").unwrap();
    let (code, _, err) = softc(&["fmt", broken.to_str().unwrap()]);
    assert_eq!(code, 1, "{err}");
    assert!(err.contains("error[E0003]"), "{err}");
    assert_eq!(std::fs::read_to_string(&broken).unwrap(), "let a = (1 mm");
    // No temporary files are left behind.
    let leftovers: Vec<_> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    assert_eq!(leftovers.len(), 2, "{leftovers:?}");
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn usage_errors_exit_with_status_2() {
    let (code, _, _) = softc(&["check"]);
    assert_eq!(code, 2);
    let (code, _, _) = softc(&["frobnicate"]);
    assert_eq!(code, 2);
    let (code, _, err) = softc(&["check", "/nonexistent/x.soft"]);
    assert_eq!(code, 2);
    assert!(err.contains("cannot read"), "{err}");
    let (code, _, err) = softc(&["run", "/nonexistent/x.soft"]);
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("cannot read"), "{err}");
    let bench = root().join("examples/benchmark-1k.soft");
    // An adapter that does not exist (or no adapter at all) is an error with a message.
    let (code, _, err) = softc(&[
        "run",
        "--backend",
        "gpu",
        "--adapter",
        "no-such-adapter-xyz",
        bench.to_str().unwrap(),
    ]);
    assert_eq!(code, 1, "{err}");
    assert!(
        err.contains("no GPU adapter matches") || err.contains("mesa-vulkan-drivers"),
        "{err}"
    );
    let (code, _, err) = softc(&["run", "--set", "nope=3kPa", bench.to_str().unwrap()]);
    assert_eq!(code, 2);
    assert!(err.contains("no param or input `nope`"), "{err}");
    let (code, _, _) = softc(&["mesh", "generate"]);
    assert_eq!(code, 2, "a missing spec is a usage error");
    let (code, out, _) = softc(&["--help"]);
    assert_eq!(code, 0);
    assert!(out.contains("check") && out.contains("fmt"));
}

#[test]
fn check_uses_the_script_folder_for_relative_paths() {
    // A script that checks clean apart from the mesh path, run from another working directory.
    let script = root().join("tests/diagnostics/mesh_file_not_found.soft");
    let (code, _, err) = softc(&["check", script.to_str().unwrap()]);
    assert_eq!(code, 1);
    assert!(err.contains("missing.msh"), "{err}");
    let _ = CheckOptions::default();
}

#[test]
fn mesh_info_accepts_the_shipped_meshes_and_refuses_a_missing_one() {
    let cuboid = root().join("meshes/cuboid.msh");
    let (code, _, _) = softc(&["mesh", "info", cuboid.to_str().unwrap()]);
    assert_eq!(code, 0);
    // An unreadable file is a usage error (README's exit-status table; issue 31 item 13).
    let (code, _, _) = softc(&["mesh", "info", "/nonexistent/x.msh"]);
    assert_eq!(code, 2);
}

#[test]
fn run_writes_a_json_summary_in_si_units() {
    let dir = std::env::temp_dir().join(format!("softc-run-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let json = dir.join("out.json");
    let bench = root().join("examples/benchmark-1k.soft");
    let (code, _, err) = softc(&[
        "run",
        bench.to_str().unwrap(),
        "--steps",
        "20",
        "--set",
        "p_peak=5kPa",
        "--json",
        json.to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{err}");
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    assert_eq!(v["steps"], 20);
    assert!((v["dt"].as_f64().unwrap() - 40e-6).abs() < 1e-12);
    // The benchmark's loss: sum over the tip of (uz + 10 mm)^2, in m^2.
    assert!(v["loss"].as_f64().unwrap() > 0.0);
    for key in ["wall_seconds", "steps_per_second"] {
        assert!(v[key].as_f64().unwrap() > 0.0, "{key}");
    }
    let tip = &v["sets"]["tip"];
    for key in ["mean_displacement", "min_displacement", "max_displacement"] {
        assert_eq!(tip[key].as_array().unwrap().len(), 3, "{key}");
    }
    // The base is clamped: no displacement at all.
    assert_eq!(v["sets"]["base"]["max_displacement"][2], 0.0);
    // A ParaView series: the first state, every 100 steps, and the last.
    let vtk = dir.join("vtk");
    let (code, _, err) = softc(&[
        "run",
        bench.to_str().unwrap(),
        "--steps",
        "250",
        "--vtk",
        vtk.to_str().unwrap(),
        "--json",
        json.to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{err}");
    let pvd = std::fs::read_to_string(vtk.join("benchmark-1k.pvd")).unwrap();
    assert_eq!(pvd.matches("<DataSet").count(), 4, "{pvd}");
    let last = softc::mesh::read(
        &vtk.join("benchmark-1k_000003.vtu"),
        softc::mesh::LengthUnit::Millimetre,
    )
    .unwrap();
    assert_eq!(last.tets.len(), 1032);
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn run_warns_before_an_unstable_step_and_stops_with_a_suggestion() {
    let bench = root().join("examples/benchmark-1k.soft");
    let (code, _, err) = softc(&[
        "run",
        bench.to_str().unwrap(),
        "--dt",
        "60us",
        "--steps",
        "300",
    ]);
    assert_eq!(code, 1, "{err}");
    assert!(err.contains("stable step estimate"), "{err}");
    assert!(err.contains("warning: dt = "), "{err}");
    // The step where it went wrong, an inversion or a non-finite node (issue 20 item 15).
    assert!(
        err.contains("unstable") && err.contains(" at step "),
        "{err}"
    );
    assert!(err.contains("dt = auto"), "{err}");
}

#[test]
fn run_grad_reports_every_param_gradient_and_the_adjoint() {
    let dir = std::env::temp_dir().join(format!("softc-grad-cli-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let json = dir.join("grad.json");
    let script = root().join("runtime/tests/fixtures/grad/all_kinds.soft");
    let (code, _, err) = softc(&[
        "run",
        script.to_str().unwrap(),
        "--steps",
        "40",
        "--grad",
        "--checkpoint",
        "revolve:3",
        "--json",
        json.to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{err}");
    assert!(err.contains("backward pass over 40 steps"), "{err}");
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    let g = &v["gradients"];
    // Scalars are numbers, arrays keep their shape.
    for scalar in ["p0", "c10"] {
        assert!(g[scalar].as_f64().unwrap() != 0.0, "{scalar}: {g}");
    }
    assert_eq!(g["beta"].as_array().unwrap().len(), 4);
    assert_eq!(g["w"].as_array().unwrap().len(), 2);
    let a = &v["adjoint"];
    assert_eq!(a["schedule"], "revolve(snapshots: 3)");
    assert!(a["recompute_ratio"].as_f64().unwrap() > 1.0);
    assert!(!a["health"].as_array().unwrap().is_empty());
    // Bad schedules and scenes without a loss are clear errors.
    let (code, _, err) = softc(&[
        "run",
        script.to_str().unwrap(),
        "--grad",
        "--checkpoint",
        "revolve:0",
    ]);
    // A bad flag value is a usage error, found before any work (issue 20 item 18).
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("--checkpoint revolve:0"), "{err}");
    let verification = root().join("examples/verification.soft");
    let (code, _, err) = softc(&[
        "run",
        verification.to_str().unwrap(),
        "--steps",
        "2",
        "--grad",
    ]);
    assert_eq!(code, 1, "{err}");
    assert!(err.contains("no `loss`"), "{err}");
    let (code, _, err) = softc(&[
        "run",
        script.to_str().unwrap(),
        "--grad",
        "--backend",
        "reference",
    ]);
    assert_eq!(code, 2, "{err}");
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn run_grad_reports_a_per_element_param_as_one_entry_per_element() {
    let dir = std::env::temp_dir().join(format!("softc-field-cli-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let json = dir.join("grad.json");
    let script = root().join("runtime/tests/fixtures/grad/field.soft");
    let run = |extra: &[&str]| {
        let mut args = vec!["run", script.to_str().unwrap(), "--steps", "20", "--json"];
        args.push(json.to_str().unwrap());
        args.extend_from_slice(extra);
        let (code, _, err) = softc(&args);
        assert_eq!(code, 0, "{err}");
        serde_json::from_str::<serde_json::Value>(&std::fs::read_to_string(&json).unwrap()).unwrap()
    };
    let v = run(&["--grad"]);
    let mu = v["gradients"]["mu"].as_array().unwrap();
    // `near` (x < 30 mm) holds 516 of the beam's elements.
    assert_eq!(mu.len(), 516, "{}", v["gradients"]);
    assert!(mu.iter().all(|d| d.as_f64().unwrap().is_finite()));
    assert!(mu.iter().any(|d| d.as_f64().unwrap() != 0.0));
    assert!(v["gradients"]["p0"].as_f64().unwrap() != 0.0);
    // `--set` sets every entry: a stiffer half moves less, on every backend.
    let tip = |v: &serde_json::Value| v["loss"].as_f64().unwrap();
    let base = tip(&run(&[]));
    for backend in ["cpu", "interp", "reference"] {
        let stiff = run(&["--set", "mu=40kPa", "--backend", backend]);
        assert!(tip(&stiff) < base, "{backend}: {} vs {base}", tip(&stiff));
    }
    std::fs::remove_dir_all(&dir).ok();
}

/// A copy of the 1k benchmark scene in a temp folder, with its mesh spec beside its mesh (so
/// `bench --tradeoff` can refine it), and the given lines replaced.
fn bench_variant(dir: &std::path::Path, name: &str, edits: &[(&str, &str)]) -> std::path::PathBuf {
    std::fs::create_dir_all(dir).unwrap();
    let mesh = dir.join("beam.msh");
    if !mesh.exists() {
        std::fs::copy(root().join("meshes/bench_1k.msh"), &mesh).unwrap();
        std::fs::copy(root().join("meshes/bench_1k.toml"), dir.join("beam.toml")).unwrap();
    }
    let mut text = std::fs::read_to_string(root().join("examples/benchmark-1k.soft")).unwrap();
    text = text.replace("../meshes/bench_1k.msh", "beam.msh");
    for (from, to) in edits {
        assert!(text.contains(from), "{from}");
        text = text.replace(from, to);
    }
    let path = dir.join(name);
    std::fs::write(&path, text).unwrap();
    path
}

#[test]
fn run_simulates_every_scene_of_a_listed_input_and_writes_csv_logs() {
    let dir = std::env::temp_dir().join(format!("softc-scenes-{}", std::process::id()));
    let script = bench_variant(
        &dir,
        "scenes.soft",
        &[
            (
                "param p_peak: pressure = 3 kPa in [0 kPa, 50 kPa]",
                "input p_peak: pressure from [2 kPa, 4 kPa]",
            ),
            ("  fix base\n", "  fix base\n  output csv(tip) every 2 ms\n"),
        ],
    );
    let (json, csv) = (dir.join("out.json"), dir.join("csv"));
    let run = |extra: &[&str]| {
        let mut args = vec!["run", script.to_str().unwrap(), "--steps", "200", "--json"];
        args.push(json.to_str().unwrap());
        args.extend_from_slice(extra);
        let (code, _, err) = softc(&args);
        assert_eq!(code, 0, "{err}");
        let v: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
        (v, err)
    };
    let (v, err) = run(&["--csv", csv.to_str().unwrap()]);
    let scenes = v["scenes"].as_array().unwrap();
    assert_eq!(scenes.len(), 2, "{err}");
    let uz = |s: &serde_json::Value| s["sets"]["tip"]["mean_displacement"][2].as_f64().unwrap();
    assert_eq!(scenes[0]["inputs"]["p_peak"].as_f64(), Some(2000.0));
    assert_eq!(scenes[1]["inputs"]["p_peak"].as_f64(), Some(4000.0));
    // Small strains: twice the pressure, about twice the (downward) deflection.
    let ratio = uz(&scenes[1]) / uz(&scenes[0]);
    assert!(
        uz(&scenes[0]) < 0.0 && (1.9..2.1).contains(&ratio),
        "{ratio}"
    );
    let mean = (scenes[0]["loss"].as_f64().unwrap() + scenes[1]["loss"].as_f64().unwrap()) / 2.0;
    assert_eq!(v["loss"].as_f64(), Some(mean));
    // `--set` on an input runs that one scene, bit for bit the same as in the list.
    let (single, _) = run(&["--set", "p_peak=4kPa"]);
    assert!(single.get("scenes").is_none());
    assert_eq!(uz(&single), uz(&scenes[1]));
    // The logs: every 2 ms = 50 steps of 40 µs, from step 0 to the last, in SI units; the last
    // row is the JSON's final state.
    for (k, scene) in scenes.iter().enumerate() {
        let text = std::fs::read_to_string(csv.join(format!("scene{k}/tip.csv"))).unwrap();
        let rows: Vec<Vec<&str>> = text.lines().map(|l| l.split(',').collect()).collect();
        assert_eq!(rows[0][..3], ["step", "t_s", "mean_ux_m"]);
        let steps: Vec<&str> = rows[1..].iter().map(|r| r[0]).collect();
        assert_eq!(steps, ["0", "50", "100", "150", "200"]);
        assert_eq!(rows[1][4].parse::<f64>().unwrap(), 0.0);
        let last: f64 = rows[5][4].parse().unwrap();
        assert_eq!(last, uz(scene));
        assert!((rows[5][1].parse::<f64>().unwrap() - 8e-3).abs() < 1e-12);
    }
    // Without --csv the log is not written, and a note says how to get it.
    let (_, err) = run(&[]);
    assert!(err.contains("add --csv DIR"), "{err}");
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn bench_tradeoff_measures_error_against_wall_time_and_marks_the_pareto_front() {
    let dir = std::env::temp_dir().join(format!("softc-tradeoff-{}", std::process::id()));
    // A quasi-static version of the beam: heavy nodes for a large stable step.
    let script = bench_variant(
        &dir,
        "quasi.soft",
        &[(
            "  dt = 40 us\n  steps = 4000\n",
            "  dt = auto\n  duration = 2 s\n  mass_scaling = 100\n",
        )],
    );
    // A small beam whose cavity lies on the grid planes at both resolutions (cells of 4 × 2 × 2
    // and 2 × 1 × 1 mm), so refining changes the discretization, not the geometry.
    let spec = std::fs::read_to_string(dir.join("beam.toml"))
        .unwrap()
        .replace("n = [12, 4, 4]", "n = [10, 4, 4]")
        .replace("max = [60, 10, 10]", "max = [40, 8, 8]")
        .replace("min = [5, 2.5, 4]", "min = [4, 2, 4]")
        .replace("max = [55, 7.5, 8]", "max = [36, 6, 6]");
    std::fs::write(dir.join("beam.toml"), spec).unwrap();
    let out = dir.join("trade");
    let (code, table, err) = softc(&[
        "bench",
        "--tradeoff",
        script.to_str().unwrap(),
        "--resolutions",
        "1,2",
        "--safeties",
        "0.9,0.45",
        "--settle",
        "1e-2,1e-3",
        "--springs",
        "1 kPa/mm",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{err}");
    println!("{table}");
    assert!(
        table.contains("pareto") && table.contains("reference"),
        "{table}"
    );
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("tradeoff.json")).unwrap()).unwrap();
    // Two resolutions cannot be extrapolated: the finest f64 FEM run is the reference.
    let method = v["reference"]["method"].as_str().unwrap();
    assert!(
        method.contains("finest explicit f64 FEM solution (resolution 2"),
        "{method}"
    );
    let points = v["points"].as_array().unwrap();
    // Explicit: 2 resolutions × 2 precisions, 1 more dt, 1 more tolerance, 2 spring meshes;
    // then a static solve per resolution and precision, and one implicit Euler run.
    assert_eq!(points.len(), 13, "{table}");
    let get = |p: &serde_json::Value, k: &str| p[k].as_f64().unwrap();
    assert!(points.iter().all(|p| p["settled"] == true), "{table}");
    assert!(
        points
            .iter()
            .all(|p| get(p, "value") < 0.0 && get(p, "error").is_finite())
    );
    assert!(points.iter().any(|p| p["pareto"] == true));
    let find = |res: f64, prec: &str, model: &str, safety: f64, settle: f64| {
        points
            .iter()
            .find(|p| {
                p["solver"] == "explicit"
                    && get(p, "resolution") == res
                    && p["precision"] == prec
                    && p["model"] == model
                    && get(p, "safety") == safety
                    && get(p, "settle") == settle
            })
            .unwrap_or_else(|| panic!("{res} {prec} {model} {safety} {settle}\n{table}"))
    };
    let base = find(1.0, "f64", "fem", 0.9, 1e-3);
    // The static solve finds the steady state the settled explicit run approaches, on either
    // mesh; the implicit run gets there by numerical damping.
    let solved = |solver: &str, res: f64| {
        points
            .iter()
            .find(|p| {
                p["solver"] == solver && get(p, "resolution") == res && p["precision"] == "f64"
            })
            .unwrap_or_else(|| panic!("{solver} {res}\n{table}"))
    };
    for res in [1.0, 2.0] {
        let explicit = find(res, "f64", "fem", 0.9, 1e-3);
        let statics = solved("quasi_static", res);
        let rel =
            (get(statics, "value") - get(explicit, "value")).abs() / get(explicit, "value").abs();
        assert!(
            rel < 1e-2,
            "resolution {res}: static vs settled explicit {rel:e}\n{table}"
        );
    }
    let implicit = solved("implicit_euler", 1.0);
    let rel = (get(implicit, "value") - get(solved("quasi_static", 1.0), "value")).abs()
        / get(implicit, "value").abs();
    assert!(rel < 5e-2, "implicit Euler vs static {rel:e}\n{table}");
    let fine = find(2.0, "f64", "fem", 0.9, 1e-3);
    assert_eq!(get(fine, "error"), 0.0);
    assert!(get(base, "error") > 0.0 && get(fine, "tets") > 7.0 * get(base, "tets"));
    // f32 at the same resolution reaches the same steady state to f32 round-off; a smaller dt
    // the same one as well (a steady state does not depend on the step).
    for other in [
        find(1.0, "f32", "fem", 0.9, 1e-3),
        find(1.0, "f64", "fem", 0.45, 1e-3),
    ] {
        let (a, b) = (get(base, "value"), get(other, "value"));
        assert!(((a - b) / a).abs() < 1e-3, "{a} {b}\n{table}");
    }
    // A loose tolerance stops earlier.
    let loose = find(1.0, "f64", "fem", 0.9, 1e-2);
    assert!(get(loose, "steps") < get(base, "steps"), "{table}");
    for f in ["tradeoff.png", "tradeoff.svg"] {
        assert!(std::fs::metadata(out.join(f)).unwrap().len() > 1000, "{f}");
    }
    // Every point is a script `softc run` reruns.
    let variant = points[0]["script"].as_str().unwrap();
    let (code, _, err) = softc(&["run", variant, "--steps", "10"]);
    assert_eq!(code, 0, "{err}");
    std::fs::remove_dir_all(&dir).ok();
}

/// Issue 31 item 5: a study of static solves only called its first listed resolution the
/// finest (with `--resolutions 1,2` the coarse mesh was the reference, error 0), and a
/// one-point study printed its table, then failed on the plot (exit 1). The static variant
/// solves one state at the script's end time (it solved all 4,000 of the script's `steps`).
#[test]
fn a_static_only_tradeoff_study_has_a_reference_and_a_plot() {
    let dir = std::env::temp_dir().join(format!("softc-tradeoff-static-{}", std::process::id()));
    let script = bench_variant(&dir, "static.soft", &[]);
    for (resolutions, finest) in [("1,2", "resolution 2,"), ("1", "resolution 1,")] {
        let out = dir.join(format!("study-{resolutions}"));
        let (code, table, err) = softc(&[
            "bench",
            "--tradeoff",
            script.to_str().unwrap(),
            "--integrators",
            "quasi_static",
            "--precisions",
            "f64",
            "--resolutions",
            resolutions,
            "--out",
            out.to_str().unwrap(),
        ]);
        assert_eq!(code, 0, "{err}\n{table}");
        let v: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(out.join("tradeoff.json")).unwrap())
                .unwrap();
        let method = v["reference"]["method"].as_str().unwrap();
        assert!(
            method.contains("finest quasi_static f64 FEM solution") && method.contains(finest),
            "{method}"
        );
        for p in v["points"].as_array().unwrap() {
            assert_eq!(p["steps"], 1, "one equilibrium state: {p}");
            // The finest is the reference, exactly; the coarser one is not.
            let exact =
                p["resolution"].as_f64() == Some(if finest.contains('2') { 2.0 } else { 1.0 });
            assert_eq!(p["error"].as_f64() == Some(0.0), exact, "{p}");
        }
        for f in ["tradeoff.png", "tradeoff.svg"] {
            assert!(std::fs::metadata(out.join(f)).unwrap().len() > 1000, "{f}");
        }
    }
    std::fs::remove_dir_all(&dir).ok();
}

/// Issue 4: the verification cuboid's steady state at the thesis' two pressures (2 and 3
/// deka-kPa) converges under refinement — f64 FEM on the exact cuboid geometry at 1,200, 9,600
/// and 32,400 tets (Kuhn grids whose planes hold the cavity), extrapolated by Richardson.
#[test]
fn the_verification_cuboid_converges_under_refinement_at_both_pressures() {
    let dir = std::env::temp_dir().join(format!("softc-refine-{}", std::process::id()));
    let script = root().join("examples/verification.soft");
    let mut tips = Vec::new();
    for p in ["20kPa", "30kPa"] {
        let out = dir.join(p);
        let set = format!("p_peak={p}");
        let (code, table, err) = softc(&[
            "bench",
            "--tradeoff",
            script.to_str().unwrap(),
            "--set",
            &set,
            "--resolutions",
            "0.5,1,1.5",
            "--precisions",
            "f64",
            "--safeties",
            "0.9",
            "--settle",
            "1e-3",
            // The explicit runs' convergence under refinement (the static solves' is the
            // same discretization; `bench_tradeoff_…` compares the integrators).
            "--integrators",
            "explicit",
            "--out",
            out.to_str().unwrap(),
        ]);
        assert_eq!(code, 0, "{err}");
        println!("{p}:\n{table}");
        let v: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(out.join("tradeoff.json")).unwrap())
                .unwrap();
        let order = v["reference"]["order"].as_f64().unwrap_or(f64::NAN);
        // Linear tets converge at second order in displacement.
        assert!((1.5..3.0).contains(&order), "order {order}\n{table}");
        let mut points = v["points"].as_array().unwrap().clone();
        points.sort_by(|a, b| a["tets"].as_u64().cmp(&b["tets"].as_u64()));
        let errors: Vec<f64> = points
            .iter()
            .map(|p| p["error"].as_f64().unwrap())
            .collect();
        assert!(errors[0] > errors[1] && errors[1] > errors[2], "{errors:?}");
        // The finest mesh is within 1 % (20 kPa) and 2.3 % (30 kPa) of the extrapolated value.
        assert!(errors[2] < 0.03, "{errors:?}");
        assert!(points.iter().all(|p| p["settled"] == true));
        tips.push(v["reference"]["value"].as_f64().unwrap());
    }
    // The free end bends down, more than proportionally at the higher pressure (the walls
    // over the cavity balloon): 1.64 times as far for 1.5 times the pressure.
    let ratio = tips[1] / tips[0];
    assert!(tips[0] < 0.0 && (1.5..1.8).contains(&ratio), "{tips:?}");
    std::fs::remove_dir_all(&dir).ok();
}

/// `dt = auto` estimates the stable step at rest; a Yeoh material stiffens as the beam bends, so
/// under a large load that step blows up. The message re-estimates the step at the last finite
/// state and suggests a safety factor, and the suggestion runs.
#[test]
fn a_blow_up_under_stiffening_suggests_a_step_that_runs() {
    let dir = std::env::temp_dir().join(format!("softc-stiffen-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let script = |dt: &str| {
        format!(
            r#"mesh body = load("{}")
material silicone = yeoh(c10: 0.24162 MPa, c20: 0.19977 MPa, c30: -0.00541 MPa, d1: 1.0 /MPa, density: 1070 kg/m^3)
chamber cavity = surface(body, "cavity")
nodes base = named(body, "base")
sim {{
  dt = {dt}
  duration = 0.6 s
  damping = 20 /s
  mass_scaling = 100
  fix base
  pressure cavity = 400 kPa * ramp(t, 0.5 s)
}}
"#,
            root().join("meshes/bench_1k.msh").display()
        )
    };
    let path = dir.join("stiffen.soft");
    std::fs::write(&path, script("auto")).unwrap();
    let (code, _, err) = softc(&["run", path.to_str().unwrap()]);
    assert_eq!(code, 1, "{err}");
    // The step where it went wrong, an inversion or a non-finite node (issue 20 item 15).
    assert!(
        err.contains("unstable") && err.contains(" at step "),
        "{err}"
    );
    assert!(
        err.contains("stiffens as it deforms") && err.contains("at rest"),
        "{err}"
    );
    let safety = err
        .split("auto(safety: ")
        .nth(1)
        .and_then(|s| s.split(')').next())
        .unwrap_or_else(|| panic!("no suggested safety in: {err}"));
    let s: f64 = safety.parse().unwrap();
    assert!(s > 0.3 && s < 0.9, "{s}");
    std::fs::write(&path, script(&format!("auto(safety: {safety})"))).unwrap();
    let (code, _, err) = softc(&["run", path.to_str().unwrap()]);
    assert_eq!(code, 0, "{err}");
    std::fs::remove_dir_all(&dir).ok();
}

/// A static optimization warm-starts each iteration's solve from the last equilibrium, and
/// saves it with its state: stopped after 3 iterations and resumed, it ends bit for bit where
/// an uninterrupted run ends.
#[test]
fn a_static_optimization_resumes_bit_for_bit_with_its_warm_starts() {
    let dir = std::env::temp_dir().join(format!("softc-static-resume-{}", std::process::id()));
    let script = bench_variant(
        &dir,
        "static_opt.soft",
        &[
            (
                "  dt = 40 us\n  steps = 4000\n  damping = 20 /s\n",
                "  integrator = quasi_static\n  duration = 0.5 s\n",
            ),
            (
                "+ 10 mm)^2 at end",
                "+ 0.1 mm)^2 at end\n\noptimize p_peak with nadam(lr: 0.2) for 6 iterations {}",
            ),
        ],
    );
    let run = |out: &std::path::Path, extra: &[&str]| {
        let json = out.join("summary.json");
        let mut args = vec!["run", script.to_str().unwrap()];
        args.extend_from_slice(extra);
        args.extend_from_slice(&["--json", json.to_str().unwrap()]);
        let (code, _, err) = softc(&args);
        assert_eq!(code, 0, "{err}");
    };
    let (whole, split) = (dir.join("whole"), dir.join("split"));
    std::fs::create_dir_all(&whole).unwrap();
    std::fs::create_dir_all(&split).unwrap();
    run(&whole, &["--out", whole.to_str().unwrap()]);
    run(
        &split,
        &["--out", split.to_str().unwrap(), "--iterations", "3"],
    );
    let state: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(split.join("state.json")).unwrap()).unwrap();
    assert!(
        !state["warm_starts"].as_array().unwrap()[0]
            .as_array()
            .unwrap()
            .is_empty(),
        "the state keeps the warm start"
    );
    run(
        &split,
        &["--resume", split.to_str().unwrap(), "--iterations", "6"],
    );
    let read = |d: &std::path::Path| -> serde_json::Value {
        serde_json::from_str(&std::fs::read_to_string(d.join("result.json")).unwrap()).unwrap()
    };
    let (a, b) = (read(&whole), read(&split));
    let bits = |v: &serde_json::Value| v.as_f64().unwrap().to_bits();
    assert_eq!(bits(&a["params"]["p_peak"]), bits(&b["params"]["p_peak"]));
    assert_eq!(bits(&a["loss"]), bits(&b["loss"]));
    let losses = |v: &serde_json::Value| -> Vec<u64> {
        v["history"]
            .as_array()
            .unwrap()
            .iter()
            .map(|h| bits(&h["loss"]))
            .collect()
    };
    assert_eq!(losses(&a), losses(&b));
    assert_eq!(a["solver"]["kind"], "quasi_static");
    std::fs::remove_dir_all(&dir).ok();
}

/// `--linear-solver krylov` solves a static path of states and its gradient matrix-free, and
/// `amg` by multigrid-preconditioned CG, to what the direct solver finds; the JSON names the
/// solver and its iterations. The default (`auto`) factors a tangent this small.
#[test]
fn the_linear_solver_flag_selects_the_iterative_solves() {
    let dir = std::env::temp_dir().join(format!("softc-linear-solver-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let script = root().join("runtime/tests/fixtures/grad/static.soft");
    let solve = |linear: &str| -> serde_json::Value {
        let json = dir.join(format!("{linear}.json"));
        let (code, _, err) = softc(&[
            "run",
            script.to_str().unwrap(),
            "--grad",
            "--linear-solver",
            linear,
            "--json",
            json.to_str().unwrap(),
        ]);
        assert_eq!(code, 0, "{err}");
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap()
    };
    let direct = solve("direct");
    assert_eq!(direct["solver"]["linear_solver"], "direct");
    assert_eq!(solve("auto")["solver"]["linear_solver"], "direct");
    for name in ["krylov", "amg"] {
        let other = solve(name);
        assert_eq!(other["solver"]["linear_solver"], name);
        assert!(other["solver"]["krylov_iterations"].as_u64().unwrap() > 0);
        assert_eq!(other["solver"]["factorizations"].as_u64().unwrap(), 0);
        let (a, b) = (
            direct["loss"].as_f64().unwrap(),
            other["loss"].as_f64().unwrap(),
        );
        assert!(((a - b) / a).abs() < 1e-8, "direct {a}, {name} {b}");
        let (ga, gb) = (
            direct["gradients"]["p0"].as_f64().unwrap(),
            other["gradients"]["p0"].as_f64().unwrap(),
        );
        assert!(((ga - gb) / ga).abs() < 1e-6, "direct {ga}, {name} {gb}");
    }
    let amg = &solve("amg")["solver"];
    assert!(amg["multigrid_setups"].as_u64().unwrap() >= 1, "{amg}");
    let (code, _, err) = softc(&["run", script.to_str().unwrap(), "--linear-solver", "lu"]);
    assert_eq!(code, 2, "{err}");
    std::fs::remove_dir_all(&dir).ok();
}

/// `softc mesh converge`: the static answer at two orders on the script's own mesh (no spec
/// needed), and a quadratic resolution series extrapolated to an error estimate. The scene: a
/// cantilever 40 × 8 × 8 mm under its weight, a Kuhn grid of 10 × 2 × 2 cells (one cell through
/// half the depth, where linear tets lock).
#[test]
fn mesh_converge_reports_how_far_a_static_answer_is_from_convergence() {
    let dir = std::env::temp_dir().join(format!("softc-converge-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let spec = dir.join("beam.toml");
    std::fs::write(
        &spec,
        "unit = \"mm\"\n[body]\nshape = \"box\"\nmin = [0, 0, 0]\nmax = [40, 8, 8]\n\
         [base]\ntag = 10\nname = \"base\"\n[tip]\ntag = 11\nname = \"tip\"\n[kuhn]\nn = [10, 2, 2]\n",
    )
    .unwrap();
    let mesh = dir.join("beam.msh");
    let (code, _, err) = softc(&[
        "mesh",
        "generate",
        spec.to_str().unwrap(),
        "-o",
        mesh.to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{err}");
    let script = dir.join("beam.soft");
    std::fs::write(
        &script,
        "mesh body = load(\"beam.msh\")\n\
         material gel = neo_hookean(mu: 100 kPa, kappa: 300 kPa, density: 1000 kg/m^3)\n\
         nodes base = named(body, \"base\")\nnodes tip = named(body, \"tip\")\n\
         sim {\n  integrator = quasi_static\n  duration = 1 s\n  \
         gravity = [0, 0, -9.81] m/s^2\n  use gel\n  fix base\n}\n\
         loss = area_mean(n in tip) (x[n].z - x0[n].z) at end\n",
    )
    .unwrap();
    // Two orders, resolution 1 only: the spec is not needed (moved away here).
    std::fs::rename(&spec, dir.join("aside.toml")).unwrap();
    let (code, table, err) = softc(&[
        "mesh",
        "converge",
        script.to_str().unwrap(),
        "--out",
        dir.join("orders").to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{err}");
    println!("{table}");
    let apart = table
        .lines()
        .find(|l| l.contains("resolution 1: linear"))
        .unwrap_or_else(|| panic!("{table}"));
    // Linear tets lock: the quadratic answer bends about twice as far.
    let percent: f64 = apart
        .split(": ")
        .last()
        .and_then(|s| s.trim_end_matches(" % apart").parse().ok())
        .unwrap();
    assert!(percent > 30.0 && percent < 70.0, "{apart}");
    assert!(table.contains("the script's own answer (linear, resolution 1)"));
    assert!(table.contains("verdict: at least"), "{table}");
    assert!(dir.join("orders/tradeoff.json").exists());
    // Listed linear first, the linear answer is its own series' finest: it is judged by the
    // quadratic answer on the same mesh, not called unestimated.
    let (code, table, err) = softc(&[
        "mesh",
        "converge",
        script.to_str().unwrap(),
        "--orders",
        "1,2",
        "--out",
        dir.join("orders_linear_first").to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{err}");
    assert!(
        table.contains("verdict: the quadratic answer on the same mesh is")
            && table.contains("away: not converged"),
        "{table}"
    );
    // A quadratic resolution series from the spec: an extrapolated reference (order about 2
    // in the cell size) and an estimated error.
    std::fs::rename(dir.join("aside.toml"), &spec).unwrap();
    let (code, table, err) = softc(&[
        "mesh",
        "converge",
        script.to_str().unwrap(),
        "--orders",
        "2",
        "--resolutions",
        "0.5,1,2",
        "--out",
        dir.join("series").to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{err}");
    println!("{table}");
    let order: f64 = table
        .split("(observed order ")
        .nth(1)
        .and_then(|s| s.split(' ').next())
        .and_then(|s| s.parse().ok())
        .unwrap_or_else(|| panic!("{table}"));
    assert!((1.5..3.0).contains(&order), "observed order {order}");
    assert!(table.contains("quadratic: "), "{table}");
    let estimate: f64 = table
        .split("verdict: estimated error ")
        .nth(1)
        .and_then(|s| s.split(' ').next())
        .and_then(|s| s.parse().ok())
        .unwrap_or_else(|| panic!("{table}"));
    assert!(estimate > 0.5 && estimate < 5.0, "{table}");
    // An unknown node set is refused with the reason.
    let (code, _, err) = softc(&[
        "mesh",
        "converge",
        script.to_str().unwrap(),
        "--output",
        "nowhere.z",
        "--out",
        dir.join("bad").to_str().unwrap(),
    ]);
    assert_eq!(code, 1);
    assert!(err.contains("no node set `nowhere`"), "{err}");
    std::fs::remove_dir_all(&dir).ok();
}
