//! Readers and writers: every format on hand-written fixtures and on meshes written by the
//! real gmsh, round trips, and malformed input that must be refused with a message (no
//! panic).

#![allow(clippy::sliced_string_as_bytes)]

use std::path::{Path, PathBuf};

use softc::mesh::{LengthUnit, Mesh, MeshErrorKind, load, read, save};

fn fx(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures/mesh")
        .join(name)
}

fn tmpdir(tag: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("softc-mesh-io-{tag}-{}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// The Kuhn unit cube fixtures: 8 nodes, 6 tets (all given with negative orientation),
/// region 1 "solid", two "base" triangles tagged 10 on x = 0.
fn check_cube(m: &Mesh, names: bool) {
    assert_eq!(m.nodes.len(), 8);
    assert_eq!(m.tets.len(), 6);
    assert_eq!(
        m.report.reoriented_tets, 6,
        "the whole mesh, written with the other orientation, is reordered"
    );
    for e in 0..6 {
        assert!(m.tet_volume(e) > 0.0, "tet {e} positive after load");
    }
    assert!((m.total_volume() - 1e-9).abs() < 1e-21, "1 mm³ in m³");
    assert_eq!(m.tet_tags, vec![1; 6]);
    assert_eq!(m.tri_tags, vec![10, 10]);
    // Base triangles point into the solid (+x).
    for f in &m.tris {
        let n = softc::mesh::model::area_vector(
            m.nodes[f[0] as usize],
            m.nodes[f[1] as usize],
            m.nodes[f[2] as usize],
        );
        assert!(
            n[0] > 0.0 && n[1].abs() < 1e-15 && n[2].abs() < 1e-15,
            "{n:?}"
        );
        for &v in f {
            assert_eq!(m.nodes[v as usize][0], 0.0);
        }
    }
    if names {
        assert_eq!(m.tag_name(3, 1), Some("solid"));
        assert_eq!(m.tag_name(2, 10), Some("base"));
        assert_eq!(m.resolve_surface("base"), Ok(10));
    }
    let issues = m.validate();
    assert!(issues.is_empty(), "{issues:?}");
}

#[test]
fn gmsh_v22_ascii_fixture() {
    let m = load(&fx("cube_v22.msh"), LengthUnit::Millimetre).unwrap();
    check_cube(&m, true);
    assert_eq!(m.report.ignored_elements.get("point"), Some(&1));
}

#[test]
fn gmsh_v41_ascii_fixture() {
    check_cube(
        &load(&fx("cube_v41.msh"), LengthUnit::Millimetre).unwrap(),
        true,
    );
}

#[test]
fn vtk_legacy_fixture() {
    check_cube(
        &load(&fx("cube.vtk"), LengthUnit::Millimetre).unwrap(),
        false,
    );
}

#[test]
fn vtu_ascii_and_binary_fixtures() {
    let a = load(&fx("cube_ascii.vtu"), LengthUnit::Millimetre).unwrap();
    let b = load(&fx("cube_binary.vtu"), LengthUnit::Millimetre).unwrap();
    check_cube(&a, false);
    check_cube(&b, false);
    assert_eq!(a, b);
}

#[test]
fn tetgen_fixture_from_any_of_its_files() {
    let a = load(&fx("cube.ele"), LengthUnit::Millimetre).unwrap();
    let b = load(&fx("cube.node"), LengthUnit::Millimetre).unwrap();
    let c = load(&fx("cube.face"), LengthUnit::Millimetre).unwrap();
    check_cube(&a, false);
    assert_eq!(a, b);
    assert_eq!(a, c);
}

#[test]
fn abaqus_fixture_with_sets_and_surface() {
    let m = load(&fx("cube.inp"), LengthUnit::Millimetre).unwrap();
    // Abaqus surfaces are numbered in order: "base" is surface tag 1.
    let m2 = {
        let mut m2 = m.clone();
        for t in &mut m2.tri_tags {
            *t = 10;
        }
        m2.names.clear();
        m2.set_name(3, 1, "solid");
        m2.set_name(2, 10, "base");
        m2
    };
    check_cube(&m2, true);
    assert_eq!(m.tag_name(2, 1), Some("base"));
    assert_eq!(m.tag_name(3, 1), Some("solid"));
    assert_eq!(
        m.node_sets["base"],
        vec![0, 2, 4, 6],
        "GENERATE 1..7 step 2"
    );
    assert_eq!(m.element_sets["base_elems"], vec![3, 5]);
    assert_eq!(m.element_sets["solid"].len(), 6);
}

#[test]
fn unit_parameter_scales_coordinates() {
    let m = load(&fx("cube_v22.msh"), LengthUnit::Metre).unwrap();
    assert!((m.total_volume() - 1.0).abs() < 1e-12);
    let m = load(&fx("cube_v22.msh"), LengthUnit::Centimetre).unwrap();
    assert!((m.total_volume() - 1e-6).abs() < 1e-18);
}

/// Meshes written by gmsh 4.8.4 from gmsh_cube.geo (command in that file): a 10 mm cube
/// with a 4 mm cubic cavity tagged "cavity" (2) and the x = 0 face tagged "base" (10).
#[test]
fn real_gmsh_files_in_all_four_encodings() {
    let files = [
        "gmsh_cube_v22.msh",
        "gmsh_cube_v22_bin.msh",
        "gmsh_cube_v41.msh",
        "gmsh_cube_v41_bin.msh",
    ];
    let meshes: Vec<Mesh> = files
        .iter()
        .map(|f| load(&fx(f), LengthUnit::Millimetre).unwrap_or_else(|e| panic!("{e}")))
        .collect();
    let m = &meshes[0];
    assert_eq!(m.nodes.len(), 251);
    assert!(m.tets.len() > 500, "{}", m.tets.len());
    assert!((m.total_volume() - (1000.0 - 64.0) * 1e-9).abs() < 1e-18);
    assert_eq!(m.tag_name(2, 2), Some("cavity"));
    assert_eq!(m.tag_name(2, 10), Some("base"));
    assert_eq!(m.tag_name(3, 1), Some("solid"));
    assert_eq!(m.chamber_tags(), vec![2]);
    assert!(
        (m.enclosed_volume(2) - 64e-9).abs() < 1e-20,
        "{}",
        m.enclosed_volume(2)
    );
    assert!((m.surface_area(10) - 100e-6).abs() < 1e-16);
    assert!(m.validate().is_empty(), "{:?}", m.validate());
    for (f, other) in files.iter().zip(&meshes).skip(1) {
        assert_eq!(other.tets.len(), m.tets.len(), "{f}");
        assert_eq!(other.tets, m.tets, "{f}");
        assert_eq!(other.tri_tags, m.tri_tags, "{f}");
        for (p, q) in other.nodes.iter().zip(&m.nodes) {
            for k in 0..3 {
                assert!((p[k] - q[k]).abs() < 1e-17, "{f}: {p:?} vs {q:?}");
            }
        }
    }
    // gmsh's legacy VTK export: same topology, tags are elementary entities.
    let v = load(&fx("gmsh_cube.vtk"), LengthUnit::Millimetre).unwrap();
    assert_eq!(v.tets.len(), m.tets.len());
    assert_eq!(v.nodes.len(), 251);
}

fn round_trip(m: &Mesh, ext: &str) -> Mesh {
    let d = tmpdir(ext);
    let p = d.join(format!("rt.{ext}"));
    save(m, &p, LengthUnit::Millimetre).unwrap();
    let back = load(&p, LengthUnit::Millimetre).unwrap();
    // No temp file left behind by the atomic write.
    let left: Vec<_> = std::fs::read_dir(&d)
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    assert_eq!(left.len(), 1, "{left:?}");
    std::fs::remove_dir_all(&d).unwrap();
    back
}

#[test]
fn msh_and_vtu_round_trips_keep_topology_and_tags() {
    let m = load(&fx("gmsh_cube_v41.msh"), LengthUnit::Millimetre).unwrap();
    for ext in ["msh", "vtu"] {
        let b = round_trip(&m, ext);
        assert_eq!(b.tets, m.tets, "{ext}");
        assert_eq!(b.tet_tags, m.tet_tags, "{ext}");
        assert_eq!(b.tris, m.tris, "{ext}");
        assert_eq!(b.tri_tags, m.tri_tags, "{ext}");
        assert_eq!(b.report.reoriented_tets, 0);
        assert_eq!(b.report.reoriented_faces, 0);
        for (p, q) in b.nodes.iter().zip(&m.nodes) {
            for k in 0..3 {
                assert!((p[k] - q[k]).abs() < 1e-15, "{ext}: {p:?} vs {q:?}");
            }
        }
        if ext == "msh" {
            assert_eq!(b.names, m.names);
        }
    }
    // Kuhn benchmark grid through msh: names and tags survive.
    let k = softc::mesh::kuhn::kuhn_grid(
        &softc::mesh::kuhn::KuhnSpec::benchmark(12, 4, 4),
        LengthUnit::Millimetre,
    )
    .unwrap();
    let b = round_trip(&k, "msh");
    assert_eq!(b.tets, k.tets);
    assert_eq!(b.tris, k.tris);
    assert_eq!(b.names, k.names);
}

#[test]
fn pvd_series_writes_steps_and_collection() {
    use softc::mesh::writers::{Field, PvdSeries};
    let m = load(&fx("cube_v22.msh"), LengthUnit::Millimetre).unwrap();
    let d = tmpdir("pvd");
    let mut s = PvdSeries::new(&d, "run", LengthUnit::Millimetre);
    for step in 0..3 {
        let pos: Vec<[f64; 3]> = m
            .nodes
            .iter()
            .map(|p| [p[0], p[1], p[2] + 1e-4 * step as f64])
            .collect();
        let disp: Vec<[f64; 3]> = m
            .nodes
            .iter()
            .map(|_| [0.0, 0.0, 1e-4 * step as f64])
            .collect();
        let energy = vec![step as f64; m.tets.len()];
        s.write_step(
            &m,
            0.1 * step as f64,
            &pos,
            &[("displacement", Field::Vector(&disp))],
            &[("strain_energy", Field::Scalar(&energy))],
        )
        .unwrap();
    }
    let pvd = std::fs::read_to_string(s.pvd_path()).unwrap();
    assert_eq!(pvd.matches("<DataSet").count(), 3);
    assert!(pvd.contains("run_000002.vtu"));
    // The deformed step reads back as a mesh with the same topology.
    let b = load(&d.join("run_000002.vtu"), LengthUnit::Millimetre).unwrap();
    assert_eq!(b.tets, m.tets);
    assert!((b.nodes[0][2] - 2e-4).abs() < 1e-15);
    std::fs::remove_dir_all(&d).unwrap();
}

/// Write `content` to a temp file with `name` and read it; it must fail (never panic) with
/// a message naming the file and containing each of `needles`.
fn refuse(name: &str, content: &[u8], needles: &[&str]) {
    let d = tmpdir(&name.replace('.', "_"));
    let p = d.join(name);
    std::fs::write(&p, content).unwrap();
    let r = load(&p, LengthUnit::Millimetre);
    std::fs::remove_dir_all(&d).unwrap();
    let e = match r {
        Ok(m) => panic!("{name}: malformed input accepted ({} tets)", m.tets.len()),
        Err(e) => e,
    };
    let msg = e.to_string();
    assert!(
        msg.contains(name),
        "{name}: message does not name the file: {msg}"
    );
    for n in needles {
        assert!(msg.contains(n), "{name}: `{n}` missing from: {msg}");
    }
}

fn fixture_text(name: &str) -> String {
    std::fs::read_to_string(fx(name)).unwrap()
}

#[test]
fn malformed_gmsh_is_refused_with_line_and_reason() {
    let good = fixture_text("cube_v22.msh");
    // Truncated in the middle of the element list.
    let cut = &good[..good.find("7 4 2 1 1").unwrap()];
    refuse("trunc.msh", cut.as_bytes(), &["truncated"]);
    // Wrong node count.
    refuse(
        "count.msh",
        good.replace("$Nodes\n8", "$Nodes\n9").as_bytes(),
        &["expected"],
    );
    // NaN coordinate: names the node and line.
    refuse(
        "nan.msh",
        good.replace("\n3 0 1 0\n", "\n3 nan 1 0\n").as_bytes(),
        &["node 3", ":13", "non-finite"],
    );
    // Out-of-range node id in an element: names element and node.
    refuse(
        "range.msh",
        good.replace("4 4 2 1 1 2 1 4 8", "4 4 2 1 1 2 1 4 80")
            .as_bytes(),
        &["element 4", "node 80", ":25"],
    );
    // Not a number.
    refuse(
        "word.msh",
        good.replace("1 0 0 0\n", "1 zero 0 0\n").as_bytes(),
        &["zero", ":11"],
    );
    // One 10-node tet among 4-node ones: refused by its neighbour's line, with a fix.
    refuse(
        "quad.msh",
        good.replace("4 4 2 1 1 2 1 4 8", "4 11 2 1 1 2 1 4 8 1 2 3 4 5 6")
            .as_bytes(),
        &[
            "element 5 is a 4-node tetrahedron",
            "element 4 has 10 nodes",
            "fix:",
        ],
    );
    // Binary garbage.
    let mut garbage = b"$MeshFormat\n2.2 1 8\n".to_vec();
    garbage.extend((0..200u32).map(|i| (i * 7919 % 251) as u8));
    refuse("garbage.msh", &garbage, &[]);
    refuse("empty.msh", b"", &["$MeshFormat"]);
    // Truncated binary file.
    let bin = std::fs::read(fx("gmsh_cube_v41_bin.msh")).unwrap();
    refuse("trunc_bin.msh", &bin[..bin.len() / 2], &["truncated"]);
    let bin = std::fs::read(fx("gmsh_cube_v22_bin.msh")).unwrap();
    refuse("trunc_bin2.msh", &bin[..bin.len() * 2 / 3], &[]);
}

#[test]
fn malformed_other_formats_are_refused() {
    let vtk = fixture_text("cube.vtk");
    refuse(
        "trunc.vtk",
        vtk[..vtk.len() / 2].as_bytes(),
        &["end of file"],
    );
    refuse(
        "range.vtk",
        vtk.replace("4 1 0 3 7", "4 1 0 3 70").as_bytes(),
        &["node 70"],
    );
    refuse(
        "nan.vtk",
        vtk.replace("\n1 1 1\n", "\n1 NaN 1\n").as_bytes(),
        &["non-finite"],
    );
    let bin = std::fs::read(fx("cube_binary.vtk")).unwrap();
    refuse("trunc_bin.vtk", &bin[..bin.len() - 40], &["truncated"]);
    refuse("kind.vtk", vtk.replace("ASCII", "HEX").as_bytes(), &["HEX"]);
    let vtu = fixture_text("cube_ascii.vtu");
    // A cut XML file is called truncated, at its last line (it was "no <Piece> element").
    refuse(
        "trunc.vtu",
        vtu[..vtu.len() * 2 / 3].as_bytes(),
        &["truncated", "without `</VTKFile>`"],
    );
    refuse(
        "offs.vtu",
        vtu.replace("4 8 12 16 20 24 27 30", "4 8 12 16 20 24 27 99")
            .as_bytes(),
        &["offset"],
    );
    let b = fixture_text("cube_binary.vtu");
    refuse(
        "b64.vtu",
        b.replacen("format=\"binary\">", "format=\"binary\">!!", 1)
            .as_bytes(),
        &["base64"],
    );
    let inp = fixture_text("cube.inp");
    refuse(
        "range.inp",
        inp.replace("6, 1, 5, 7, 8", "6, 1, 5, 7, 99").as_bytes(),
        &["element 6", "node 99"],
    );
    refuse(
        "c3d10.inp",
        inp.replace("C3D4", "C3D10").as_bytes(),
        &["C3D10", ":13"],
    );
    refuse(
        "nonum.inp",
        inp.replace("3, 0., 1., 0.", "3, 0., x, 0.").as_bytes(),
        &["`x`"],
    );
    // tetgen: .ele count larger than its lines.
    let d = tmpdir("tetgen-bad");
    for f in ["cube.node", "cube.face"] {
        std::fs::copy(fx(f), d.join(f)).unwrap();
    }
    std::fs::write(
        d.join("cube.ele"),
        fixture_text("cube.ele").replace("6 4 1", "60 4 1"),
    )
    .unwrap();
    let e = load(&d.join("cube.ele"), LengthUnit::Millimetre).unwrap_err();
    assert!(
        e.to_string().contains("cube.ele") && e.to_string().contains("60"),
        "{e}"
    );
    // Cut short by one line: refused as truncated at its last line (it was read as a mesh
    // with one tet fewer), and by half.
    let ele = fixture_text("cube.ele");
    let lines: Vec<&str> = ele.lines().collect();
    for keep in [lines.len() - 1, lines.len() / 2] {
        std::fs::write(d.join("cube.ele"), lines[..keep].join("\n")).unwrap();
        let e = load(&d.join("cube.ele"), LengthUnit::Millimetre).unwrap_err();
        let data = keep - 1; // the header, then one tet per line
        assert!(
            e.to_string()
                .contains(&format!("cube.ele:{keep}: the file is truncated"))
                && e.to_string()
                    .contains(&format!("after {data} of the 6 tetrahedra")),
            "{e}"
        );
    }
    std::fs::write(d.join("cube.ele"), fixture_text("cube.ele")).unwrap();
    std::fs::write(
        d.join("cube.node"),
        fixture_text("cube.node").replace("3 0 1 0", "3 0 nan 0"),
    )
    .unwrap();
    let e = load(&d.join("cube.face"), LengthUnit::Millimetre).unwrap_err();
    assert!(
        e.to_string().contains("cube.node:5") && e.to_string().contains("node 3"),
        "{e}"
    );
    std::fs::remove_dir_all(&d).unwrap();
    // STL is a surface: told to mesh it.
    let e = read(Path::new("body.stl"), LengthUnit::Millimetre).unwrap_err();
    assert_eq!(e.kind, MeshErrorKind::Unsupported);
    assert!(e.to_string().contains("softc mesh generate"), "{e}");
    // Unknown extension.
    let e = read(Path::new("body.obj"), LengthUnit::Millimetre).unwrap_err();
    assert!(e.to_string().contains("body.obj"));
    // Missing file.
    let e = read(Path::new("/nonexistent/x.msh"), LengthUnit::Millimetre).unwrap_err();
    assert_eq!(e.kind, MeshErrorKind::Io);
}

#[test]
fn random_byte_flips_never_panic() {
    // Deterministic pseudo-random corruption of every fixture: readers may accept or refuse,
    // but must not panic.
    let names = [
        "cube_v22.msh",
        "cube_v41.msh",
        "cube.vtk",
        "cube_ascii.vtu",
        "cube_binary.vtu",
        "cube.inp",
        "gmsh_cube_v41_bin.msh",
        "gmsh_cube_v22_bin.msh",
    ];
    let d = tmpdir("flips");
    let mut seed = 12345u64;
    for n in names {
        let orig = std::fs::read(fx(n)).unwrap();
        for k in 0..25 {
            let mut b = orig.clone();
            for _ in 0..3 {
                seed = seed
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                let i = (seed >> 33) as usize % b.len();
                b[i] = (seed >> 17) as u8;
            }
            if k % 5 == 0 {
                b.truncate(b.len() * (k + 1) / 26);
            }
            let p = d.join(format!("f{k}_{n}"));
            std::fs::write(&p, &b).unwrap();
            let _ = read(&p, LengthUnit::Millimetre);
        }
    }
    std::fs::remove_dir_all(&d).unwrap();
}

#[test]
fn every_truncation_of_the_small_fixtures_is_handled() {
    // Truncating a file at any byte must give an error or (for a cut inside trailing data)
    // a mesh — never a panic.
    let d = tmpdir("truncate");
    for n in [
        "cube_v22.msh",
        "cube_v41.msh",
        "cube.vtk",
        "cube_binary.vtk",
        "cube_ascii.vtu",
        "cube_binary.vtu",
        "cube.inp",
    ] {
        let orig = std::fs::read(fx(n)).unwrap();
        let p = d.join(n);
        let mut accepted = 0;
        // Every third byte, and every byte of the last 64 (closing sections).
        let cuts = (0..orig.len())
            .step_by(3)
            .chain(orig.len().saturating_sub(64)..orig.len());
        for cut in cuts {
            std::fs::write(&p, &orig[..cut]).unwrap();
            // The closing tags of XML / trailing newlines may be missing without loss.
            if read(&p, LengthUnit::Millimetre).is_ok() && cut + 64 < orig.len() {
                accepted += 1;
            }
        }
        // Earlier cuts must be refused, except a cut exactly before an optional trailing
        // section (legacy VTK without its CELL_DATA is a valid file) — and Abaqus, whose
        // format has no counts: a file cut after its elements is a valid smaller model.
        if !n.ends_with(".inp") {
            assert!(accepted <= 2, "{n}: {accepted} truncated versions accepted");
        }
    }
    std::fs::remove_dir_all(&d).unwrap();
}

#[test]
fn vtu_binary_and_ascii_encodings_read_back_identically() {
    use softc::mesh::writers::{Field, VtuEncoding, vtu_document};
    let m = load(&fx("gmsh_cube_v41.msh"), LengthUnit::Millimetre).unwrap();
    let d = tmpdir("vtuenc");
    let e: Vec<f64> = (0..m.tets.len()).map(|i| i as f64 * 0.5).collect();
    let stress: Vec<[f64; 9]> = (0..m.tets.len()).map(|i| [i as f64; 9]).collect();
    let mut back = Vec::new();
    for (enc, name) in [
        (VtuEncoding::Ascii, "a.vtu"),
        (VtuEncoding::Binary, "b.vtu"),
    ] {
        let doc = vtu_document(
            &m,
            LengthUnit::Millimetre,
            None,
            &[],
            &[
                ("energy", Field::Scalar(&e)),
                ("stress", Field::Tensor(&stress)),
            ],
            enc,
        );
        assert!(doc.contains("Name=\"stress\" NumberOfComponents=\"9\""));
        if enc == VtuEncoding::Ascii {
            assert!(doc.contains("\n2e0 2e0 2e0 2e0 2e0 2e0 2e0 2e0 2e0\n"));
        }
        if enc == VtuEncoding::Binary {
            assert!(doc.contains("format=\"binary\"") && !doc.contains("format=\"ascii\""));
        }
        std::fs::write(d.join(name), doc).unwrap();
        back.push(load(&d.join(name), LengthUnit::Millimetre).unwrap());
    }
    std::fs::remove_dir_all(&d).unwrap();
    assert_eq!(back[0].tets, m.tets);
    assert_eq!(back[1].tets, m.tets);
    assert_eq!(back[1].tri_tags, m.tri_tags);
    assert_eq!(back[1].tet_tags, m.tet_tags);
    // Binary keeps coordinates to the rounding of the mm→m conversion.
    for (p, q) in back[1].nodes.iter().zip(&m.nodes) {
        for k in 0..3 {
            assert!((p[k] - q[k]).abs() <= 1e-17, "{p:?} {q:?}");
        }
    }
}

#[test]
fn gmsh_named_point_groups_become_node_sets() {
    // Hand-written: point elements on nodes 1 and 3 in physical group 7 "anchor"; a point
    // element in no named group is ignored. (Five of the six Kuhn tets: it loads, with a
    // warning for the base triangle whose tet is missing.)
    let m = load(&fx("cube_points_v22.msh"), LengthUnit::Millimetre).unwrap();
    assert_eq!(m.node_sets.len(), 1);
    assert_eq!(m.node_sets["anchor"], vec![0, 2]);
    assert_eq!(m.report.ignored_elements.get("point"), Some(&3));
}
