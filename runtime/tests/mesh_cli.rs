//! The work behind `softc mesh generate|info|convert|kuhn` (exit codes, messages, JSON).

use std::path::{Path, PathBuf};

use softc::mesh::LengthUnit;
use softc::mesh::commands::{convert, generate, info, kuhn};

fn tmp(tag: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("softc-mesh-cli-{tag}-{}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn run(f: impl FnOnce(&mut Vec<u8>, &mut Vec<u8>) -> i32) -> (i32, String, String) {
    let (mut o, mut e) = (Vec::new(), Vec::new());
    let c = f(&mut o, &mut e);
    (
        c,
        String::from_utf8(o).unwrap(),
        String::from_utf8(e).unwrap(),
    )
}

fn meshes() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../meshes")
}

#[test]
fn generate_then_info_json_reports_si_quantities() {
    let d = tmp("gen");
    let out = d.join("endo.msh");
    let (c, o, e) = run(|o, e| generate(&meshes().join("endoscope.toml"), &out, None, o, e));
    assert_eq!(c, 0, "{e}");
    assert!(o.contains("tets/s") && o.contains("dihedral"), "{o}");
    let (c, o, e) = run(|o, e| info(&out, LengthUnit::Millimetre, true, o, e));
    assert_eq!(c, 0, "{e}");
    let j: serde_json::Value = serde_json::from_str(&o).unwrap();
    assert!(j["nodes"].as_u64().unwrap() > 1000);
    assert!(j["tets"].as_u64().unwrap() > 1000);
    assert!(j["min_dihedral_deg"].as_f64().unwrap() > 10.0);
    assert_eq!(j["valid"], true);
    let ch = j["chambers"].as_array().unwrap();
    assert_eq!(ch.len(), 3);
    let names: Vec<&str> = ch.iter().map(|c| c["name"].as_str().unwrap()).collect();
    assert_eq!(names, ["c1", "c2", "c3"]);
    let vols: Vec<f64> = ch.iter().map(|c| c["volume"].as_f64().unwrap()).collect();
    // m³: chambers of radius 2.5 mm and length 32 mm are ≈ 6.3e-7 m³.
    for v in &vols {
        assert!((*v - 6.28e-7).abs() < 0.05 * 6.28e-7, "{vols:?}");
        assert!((*v - vols[0]).abs() < 0.01 * vols[0], "{vols:?}");
    }
    // The generated file equals the shipped one (the regeneration command is reproducible).
    assert_eq!(
        std::fs::read(&out).unwrap(),
        std::fs::read(meshes().join("endoscope.msh")).unwrap()
    );
    std::fs::remove_dir_all(&d).unwrap();
}

#[test]
fn shipped_meshes_are_reproducible_and_valid() {
    let d = tmp("repro");
    for name in [
        "cuboid",
        "endoscope_coarse",
        // The soft endoscope at both lattices: generating the 93k-tet one takes ~0.5 s.
        "endoscope_soft",
        "endoscope_soft_coarse",
        // The boundary-conforming quadratic one (issue 30).
        "endoscope_soft_quadratic",
        // The guide's first actuator (docs/src/tutorials/first-actuator.md).
        "finger",
        "bench_1k",
        "bench_10k",
        "bench_50k",
    ] {
        let out = d.join(format!("{name}.msh"));
        let (c, _, e) =
            run(|o, e| generate(&meshes().join(format!("{name}.toml")), &out, None, o, e));
        assert_eq!(c, 0, "{name}: {e}");
        assert_eq!(
            std::fs::read(&out).unwrap(),
            std::fs::read(meshes().join(format!("{name}.msh"))).unwrap(),
            "{name}.msh differs from its spec's output: regenerate it (meshes/README.md)"
        );
        let (c, o, e) = run(|o, e| {
            info(
                &meshes().join(format!("{name}.msh")),
                LengthUnit::Millimetre,
                false,
                o,
                e,
            )
        });
        assert_eq!(c, 0, "{name}: {e}");
        assert!(o.contains("valid: no issues"), "{name}: {o}");
    }
    // `softc mesh kuhn 12 4 4` makes the same file as bench_1k.toml.
    let out = d.join("k.msh");
    let (c, _, e) = run(|o, e| kuhn([12, 4, 4], 1, &out, o, e));
    assert_eq!(c, 0, "{e}");
    assert_eq!(
        std::fs::read(&out).unwrap(),
        std::fs::read(meshes().join("bench_1k.msh")).unwrap()
    );
    // `--order 2`: the same grid as 10-node tets, the same file as converting it.
    let (quadratic, converted) = (d.join("k2.msh"), d.join("k2c.msh"));
    let (c, o, e) = run(|o, e| kuhn([12, 4, 4], 2, &quadratic, o, e));
    assert_eq!(c, 0, "{e}");
    assert!(o.contains("wrote"), "{o}");
    let (c, _, e) = run(|o, e| {
        convert(
            &out,
            &converted,
            LengthUnit::Millimetre,
            false,
            Some(2),
            o,
            e,
        )
    });
    assert_eq!(c, 0, "{e}");
    assert_eq!(
        std::fs::read(&quadratic).unwrap(),
        std::fs::read(&converted).unwrap()
    );
    let (c, o, _) = run(|o, e| info(&quadratic, LengthUnit::Millimetre, false, o, e));
    assert_eq!(c, 0);
    assert!(
        o.contains("quadratic") && o.contains("valid: no issues"),
        "{o}"
    );
    std::fs::remove_dir_all(&d).unwrap();
}

#[test]
fn convert_between_formats() {
    let d = tmp("conv");
    let fx = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/mesh");
    let vtu = d.join("cube.vtu");
    let (c, _, e) = run(|o, e| {
        convert(
            &fx.join("gmsh_cube_v22_bin.msh"),
            &vtu,
            LengthUnit::Millimetre,
            false,
            None,
            o,
            e,
        )
    });
    assert_eq!(c, 0, "{e}");
    let msh = d.join("cube.msh");
    let (c, _, e) = run(|o, e| convert(&vtu, &msh, LengthUnit::Millimetre, false, None, o, e));
    assert_eq!(c, 0, "{e}");
    let a = softc::mesh::load(&fx.join("gmsh_cube_v22_bin.msh"), LengthUnit::Millimetre).unwrap();
    let b = softc::mesh::load(&msh, LengthUnit::Millimetre).unwrap();
    assert_eq!(a.tets, b.tets);
    assert_eq!(a.tri_tags, b.tri_tags);
    // Unsupported output format: exit 1, message names the file.
    let (c, _, e) = run(|o, e| {
        convert(
            &msh,
            &d.join("x.inp"),
            LengthUnit::Millimetre,
            false,
            None,
            o,
            e,
        )
    });
    assert_eq!(c, 1);
    assert!(e.contains("x.inp"), "{e}");
    std::fs::remove_dir_all(&d).unwrap();
}

#[test]
fn bad_inputs_exit_1_with_file_and_problem() {
    let d = tmp("bad");
    // Missing spec: an unreadable file is a usage error (2, issue 31 item 13).
    let (c, _, e) = run(|o, e| generate(&d.join("nope.toml"), &d.join("o.msh"), None, o, e));
    assert_eq!(c, 2);
    assert!(e.contains("nope.toml"), "{e}");
    // Spec with an error.
    std::fs::write(
        d.join("bad.toml"),
        "resolution = 1\n[body]\nshape = \"cone\"\n",
    )
    .unwrap();
    let (c, _, e) = run(|o, e| generate(&d.join("bad.toml"), &d.join("o.msh"), None, o, e));
    assert_eq!(c, 1);
    assert!(e.contains("bad.toml") && e.contains("cone"), "{e}");
    assert!(!d.join("o.msh").exists());
    // Invalid mesh: info exits 1 and lists the issue.
    let m = softc::mesh::kuhn::kuhn_grid(
        &softc::mesh::kuhn::KuhnSpec::benchmark(12, 4, 4),
        LengthUnit::Millimetre,
    )
    .unwrap();
    let mut broken = m.clone();
    let k = broken.tri_tags.iter().position(|t| *t == 2).unwrap();
    broken.tris.remove(k);
    broken.tri_tags.remove(k);
    let p = d.join("open.msh");
    softc::mesh::save(&broken, &p, LengthUnit::Millimetre).unwrap();
    let (c, o, e) = run(|o, e| info(&p, LengthUnit::Millimetre, false, o, e));
    assert_eq!(c, 1);
    assert!(o.contains("is open") && e.contains("open.msh"), "{o}\n{e}");
    let (c, o, _) = run(|o, e| info(&p, LengthUnit::Millimetre, true, o, e));
    assert_eq!(c, 1);
    let j: serde_json::Value = serde_json::from_str(&o).unwrap();
    assert_eq!(j["valid"], false);
    // Unreadable file: a usage error (issue 31 item 13).
    let (c, _, e) = run(|o, e| info(&d.join("missing.vtu"), LengthUnit::Millimetre, false, o, e));
    assert_eq!(c, 2);
    assert!(e.contains("missing.vtu"));
    std::fs::remove_dir_all(&d).unwrap();
}

/// Issue 20 item 12: an argument that is not UTF-8 panicked the binary (`std::env::args`). A
/// file name may be any bytes; a flag value that must be text is refused with a message.
#[test]
fn the_binary_takes_arguments_that_are_not_utf8() {
    use std::ffi::OsString;
    use std::os::unix::ffi::OsStringExt;
    let d = tmp("nonutf8");
    let mut name = b"beam-\xff\xfe".to_vec();
    name.extend_from_slice(b".msh");
    let mesh = d.join(OsString::from_vec(name));
    std::fs::copy(meshes().join("bench_1k.msh"), &mesh).unwrap();
    let softc = || std::process::Command::new(env!("CARGO_BIN_EXE_softc"));
    let out = softc().args(["mesh", "info"]).arg(&mesh).output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(0), "{err}");
    assert!(String::from_utf8_lossy(&out.stdout).contains("valid"));
    let out = softc()
        .args(["mesh", "info", "--unit"])
        .arg(OsString::from_vec(b"m\xff".to_vec()))
        .arg(&mesh)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(
        err.contains("not valid UTF-8") && err.contains("argument 4"),
        "{err}"
    );
    assert!(!err.contains("panicked"), "{err}");
    std::fs::remove_dir_all(&d).ok();
}

/// `mesh` with its nodes renumbered by a permutation from a linear congruential sequence
/// seeded with `seed`: deterministic, far from local.
fn scattered(mesh: &softc::mesh::model::Mesh, seed: u64) -> softc::mesh::model::Mesh {
    let n = mesh.nodes.len();
    let mut scatter: Vec<u32> = (0..n as u32).collect();
    let mut state = seed;
    for i in (1..n).rev() {
        state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        scatter.swap(i, (state >> 33) as usize % (i + 1));
    }
    let mut scattered = mesh.clone();
    scattered.renumber_nodes(&scatter);
    scattered
}

/// A mesh whose nodes are scattered (a fixed pseudo-random renumbering of the 10k benchmark
/// mesh) is flagged by `info` and renumbered by `convert --renumber` into one with the same
/// elements, sets and surfaces, its nodes numbered close together.
#[test]
fn scattered_node_numbering_is_reported_and_renumbered() {
    use softc::mesh::renumber::{locality_order, span};
    let d = tmp("renumber");
    let original =
        softc::mesh::load(&meshes().join("bench_10k.msh"), LengthUnit::Millimetre).unwrap();
    let scattered = scattered(&original, 12345);
    assert!(span(&original) < 0.15, "{}", span(&original));
    assert!(span(&scattered) > 0.5, "{}", span(&scattered));
    let file = d.join("scattered.msh");
    softc::mesh::save(&scattered, &file, LengthUnit::Millimetre).unwrap();
    let (c, o, e) = run(|o, e| info(&file, LengthUnit::Millimetre, false, o, e));
    assert_eq!(c, 0, "{e}");
    assert!(o.contains("convert --renumber"), "{o}");

    let out = d.join("renumbered.msh");
    let (c, o, e) = run(|o, e| convert(&file, &out, LengthUnit::Millimetre, true, None, o, e));
    assert_eq!(c, 0, "{e}");
    assert!(o.contains("renumbered the nodes"), "{o}");
    let renumbered = softc::mesh::load(&out, LengthUnit::Millimetre).unwrap();
    assert!(span(&renumbered) < span(&original), "{}", span(&renumbered));
    let (c, o, _) = run(|o, e| info(&out, LengthUnit::Millimetre, false, o, e));
    assert_eq!(c, 0);
    assert!(!o.contains("convert --renumber"), "{o}");
    // The same elements in the same order (their corners at the same points), the same sets
    // and surfaces, each node once.
    let at = |m: &softc::mesh::model::Mesh, v: u32| m.nodes[v as usize];
    assert_eq!(renumbered.tets.len(), original.tets.len());
    for (a, b) in original.tets.iter().zip(&renumbered.tets) {
        assert_eq!(a.map(|v| at(&original, v)), b.map(|v| at(&renumbered, v)));
    }
    for (a, b) in original.tris.iter().zip(&renumbered.tris) {
        assert_eq!(a.map(|v| at(&original, v)), b.map(|v| at(&renumbered, v)));
    }
    assert_eq!(original.tri_tags, renumbered.tri_tags);
    for (name, set) in &original.node_sets {
        let mut a: Vec<[u64; 3]> = set
            .iter()
            .map(|&v| at(&original, v).map(f64::to_bits))
            .collect();
        let mut b: Vec<[u64; 3]> = renumbered.node_sets[name]
            .iter()
            .map(|&v| at(&renumbered, v).map(f64::to_bits))
            .collect();
        a.sort_unstable();
        b.sort_unstable();
        assert_eq!(a, b, "node set {name}");
    }
    let mut order = locality_order(&scattered);
    order.sort_unstable();
    assert_eq!(
        order,
        (0..original.nodes.len() as u32).collect::<Vec<_>>(),
        "a permutation"
    );
    assert!(
        renumbered.validate().is_empty(),
        "{:?}",
        renumbered.validate()
    );
    std::fs::remove_dir_all(&d).unwrap();
}

/// Issue 31 item 15: `mesh info` named its worst tets by softc's 0-based index where every
/// other message uses the file's numbers, and a small mesh with a 60 % node span got no
/// renumbering hint although the README promises one above 25 %.
#[test]
fn mesh_info_names_tets_by_the_files_numbers_and_hints_at_renumbering_any_scattered_mesh() {
    use softc::mesh::renumber::span;
    let d = tmp("info-ids");
    let original =
        softc::mesh::load(&meshes().join("bench_1k.msh"), LengthUnit::Millimetre).unwrap();
    let scattered = scattered(&original, 777);
    let file = d.join("small-scattered.msh");
    softc::mesh::save(&scattered, &file, LengthUnit::Millimetre).unwrap();
    let loaded = softc::mesh::load(&file, LengthUnit::Millimetre).unwrap();
    assert!(
        loaded.nodes.len() < 1000 && span(&loaded) > 0.25,
        "{}",
        span(&loaded)
    );
    let (c, o, e) = run(|o, e| info(&file, LengthUnit::Millimetre, false, o, e));
    assert_eq!(c, 0, "{e}");
    assert!(o.contains("convert --renumber"), "{o}");
    let q = loaded.quality(None);
    let (worst, id) = (
        q.worst_dihedral_element,
        loaded.tet_id(q.worst_dihedral_element),
    );
    assert_ne!(
        id, worst as i64,
        "the file numbers its tets differently from softc"
    );
    assert!(o.contains(&format!("(worst tet {id})")), "{o}");
    let (_, o, _) = run(|o, e| info(&file, LengthUnit::Millimetre, true, o, e));
    let j: serde_json::Value = serde_json::from_str(&o).unwrap();
    assert_eq!(j["worst_dihedral_tet"], id);
    std::fs::remove_dir_all(&d).unwrap();
}

/// `softc mesh convert --order 2` inserts straight-sided mid-edge nodes (one per edge, node
/// sets and tagged surfaces carried over), `mesh info` reports the order, and `--order 1` gives
/// the linear mesh back.
#[test]
fn convert_order_2_then_info_then_order_1_round_trips() {
    let d = tmp("order");
    let fx = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/mesh");
    let input = fx.join("gmsh_cube_v41.msh");
    let lin = softc::mesh::load(&input, LengthUnit::Millimetre).unwrap();
    let quad = d.join("quad.msh");
    let (c, o, e) =
        run(|o, e| convert(&input, &quad, LengthUnit::Millimetre, false, Some(2), o, e));
    assert_eq!(c, 0, "{e}");
    let mids = lin.with_mid_edges().nodes.len() - lin.nodes.len();
    assert!(
        o.contains(&format!("quadratic (10-node tets, {mids} mid-edge nodes)")),
        "{o}"
    );
    let q = softc::mesh::load(&quad, LengthUnit::Millimetre).unwrap();
    assert!(q.is_quadratic());
    assert_eq!(q.tets, lin.tets);
    assert_eq!(q.tris, lin.tris);
    assert_eq!(q.nodes.len(), lin.nodes.len() + mids);
    assert_eq!(q.mid_edges, lin.with_mid_edges().mid_edges);
    // info: text and JSON name the order; the quadratic mesh is valid.
    let (c, o, e) = run(|o, e| info(&quad, LengthUnit::Millimetre, false, o, e));
    assert_eq!(c, 0, "{e}");
    assert!(
        o.contains(&format!(
            "elements: quadratic (10-node tets, {mids} mid-edge nodes)"
        )),
        "{o}"
    );
    let (c, o, _) = run(|o, e| info(&quad, LengthUnit::Millimetre, true, o, e));
    assert_eq!(c, 0);
    let j: serde_json::Value = serde_json::from_str(&o).unwrap();
    assert_eq!(j["order"], 2);
    assert_eq!(j["mid_edge_nodes"], mids);
    assert_eq!(j["valid"], true);
    let (_, o, _) = run(|o, e| info(&input, LengthUnit::Millimetre, false, o, e));
    assert!(o.contains("elements: linear (4-node tets)"), "{o}");
    // Through .vtu (VTK type 24) and renumbered, still the same elements.
    let vtu = d.join("quad.vtu");
    let (c, _, e) = run(|o, e| convert(&quad, &vtu, LengthUnit::Millimetre, true, None, o, e));
    assert_eq!(c, 0, "{e}");
    let v = softc::mesh::load(&vtu, LengthUnit::Millimetre).unwrap();
    assert!(v.is_quadratic());
    assert_eq!(v.nodes.len(), q.nodes.len());
    assert!((v.total_volume() - q.total_volume()).abs() < 1e-12 * q.total_volume());
    // --order 1: the corners only, as the input.
    let back = d.join("back.msh");
    let (c, o, e) = run(|o, e| convert(&quad, &back, LengthUnit::Millimetre, false, Some(1), o, e));
    assert_eq!(c, 0, "{e}");
    assert!(o.contains("linear (4-node tets)"), "{o}");
    let b = softc::mesh::load(&back, LengthUnit::Millimetre).unwrap();
    assert!(!b.is_quadratic());
    assert_eq!(b.tets, lin.tets);
    assert_eq!(b.tris, lin.tris);
    assert_eq!(b.names, lin.names);
    for (p, r) in b.nodes.iter().zip(&lin.nodes) {
        for k in 0..3 {
            assert!((p[k] - r[k]).abs() < 1e-15);
        }
    }
    // The binary: --order takes 1 or 2 only (usage error 2).
    let softc = || std::process::Command::new(env!("CARGO_BIN_EXE_softc"));
    let out = softc()
        .args(["mesh", "convert", "--order", "2"])
        .arg(&input)
        .arg(d.join("bin.msh"))
        .output()
        .unwrap();
    assert_eq!(
        out.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(String::from_utf8_lossy(&out.stdout).contains("quadratic"));
    let out = softc()
        .args(["mesh", "convert", "--order", "3"])
        .arg(&input)
        .arg(d.join("bad.msh"))
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    assert!(!d.join("bad.msh").exists());
    std::fs::remove_dir_all(&d).unwrap();
}
