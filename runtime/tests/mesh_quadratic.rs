//! Quadratic (10-node) meshes through the readers and writers (issue 30): gmsh type 11 / 9 in
//! all four encodings, VTK type 24 / 22, round trips, files that mix orders, `.vtu` output.

use std::path::{Path, PathBuf};

use softc::mesh::kuhn::{KuhnSpec, kuhn_grid};
use softc::mesh::model::{QUAD_TET_EDGES, QUAD_TRI_EDGES};
use softc::mesh::quadratic::{element_points, hrz_lumped, jacobian_check_points, jacobian_det};
use softc::mesh::writers::{VtuEncoding, vtu_document};
use softc::mesh::{LengthUnit, Mesh, Precomputed, Severity, load, read, save};

fn fx(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures/mesh")
        .join(name)
}

fn tmpdir(tag: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("softc-mesh-quad-{tag}-{}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    d
}

const CENTRE: [f64; 3] = [5e-3, 5e-3, 5e-3];
const RADIUS: f64 = 3e-3;

fn dist(p: [f64; 3], q: [f64; 3]) -> f64 {
    ((p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) + (p[2] - q[2]).powi(2)).sqrt()
}

fn midpoint(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        0.5 * (a[0] + b[0]),
        0.5 * (a[1] + b[1]),
        0.5 * (a[2] + b[2]),
    ]
}

/// The index of the point of `pts` nearest `p`.
fn nearest(pts: &[[f64; 3]], p: [f64; 3]) -> usize {
    (0..pts.len())
        .min_by(|&i, &j| dist(pts[i], p).total_cmp(&dist(pts[j], p)))
        .unwrap()
}

/// Meshes written by gmsh 4.15.2 from gmsh_quad.geo (commands in that file): a 10 mm cube with
/// a spherical cavity of radius 3 mm, 10-node tets whose mid-edge nodes on the sphere lie on
/// it.
#[test]
fn real_quadratic_gmsh_files_in_all_four_encodings_and_vtk() {
    let files = [
        "gmsh_quad_v22.msh",
        "gmsh_quad_v22_bin.msh",
        "gmsh_quad_v41.msh",
        "gmsh_quad_v41_bin.msh",
        "gmsh_quad.vtk",
    ];
    let meshes: Vec<Mesh> = files
        .iter()
        .map(|f| load(&fx(f), LengthUnit::Millimetre).unwrap_or_else(|e| panic!("{f}: {e}")))
        .collect();
    let m = &meshes[0];
    assert!(m.is_quadratic());
    assert_eq!(m.order(), 2);
    let q = m.mid_edges.as_ref().unwrap();
    assert_eq!(q.tets.len(), m.tets.len());
    assert_eq!(q.tris.len(), m.tris.len());
    assert!(m.tets.len() > 100, "{}", m.tets.len());
    assert_eq!(m.tag_name(2, 2), Some("cavity"));
    assert_eq!(m.chamber_tags(), vec![2]);
    let issues = m.validate();
    assert!(
        issues.iter().all(|i| i.severity != Severity::Error),
        "{issues:?}"
    );
    // Every node of the cavity's 6-node triangles lies on the sphere, the mid-edge nodes too
    // (gmsh placed them on the curved surface): a straight-sided midpoint would lie inside.
    let mut inside = 0.0f64;
    for (f, (t, mids)) in m.surface(2).iter().zip(m.surface_mids(2)).enumerate() {
        for &v in t.iter().chain(&mids) {
            let r = dist(m.nodes[v as usize], CENTRE);
            assert!((r - RADIUS).abs() < 1e-6 * RADIUS, "triangle {f}: r = {r}");
        }
        let centres =
            QUAD_TRI_EDGES.map(|e| midpoint(m.nodes[t[e[0]] as usize], m.nodes[t[e[1]] as usize]));
        for (k, c) in centres.iter().enumerate() {
            inside = inside.max(RADIUS - dist(*c, CENTRE));
            // The mid-edge node is nearest its own edge's midpoint.
            assert_eq!(
                nearest(&centres, m.nodes[mids[k] as usize]),
                k,
                "triangle {f}"
            );
        }
    }
    assert!(inside > 0.02 * RADIUS, "{inside}");
    // The same in every tet: each mid-edge node is near the midpoint of its own edge (checks
    // the conversion of gmsh's order, which swaps edges 1-3 and 2-3).
    for e in 0..m.tets.len() {
        let p = element_points(m, e).unwrap();
        let centres = QUAD_TET_EDGES.map(|ed| midpoint(p[ed[0]], p[ed[1]]));
        for k in 0..6 {
            assert_eq!(nearest(&centres, p[4 + k]), k, "element {e}");
        }
        for l in jacobian_check_points() {
            assert!(jacobian_det(&p, l) > 0.0);
        }
    }
    // The isoparametric volume (HRZ masses at ρ = 1) is closer to the exact solid volume
    // than the straight-sided tets' volume, which cuts the sphere's cap off every face.
    let exact = 1e-6 - 4.0 / 3.0 * std::f64::consts::PI * RADIUS.powi(3);
    let pre = Precomputed::with_uniform_density(m, 1.0).unwrap();
    let iso: f64 = pre.mass.iter().sum();
    let lin = m.total_volume();
    assert!(pre.mass.iter().all(|&x| x > 0.0));
    assert!(
        (iso - exact).abs() < 0.1 * (lin - exact).abs(),
        "iso {iso:e}, linear {lin:e}, exact {exact:e}"
    );
    for (f, other) in files.iter().zip(&meshes).skip(1) {
        assert_eq!(other.tets, m.tets, "{f}");
        assert_eq!(other.mid_edges.as_ref().unwrap().tets, q.tets, "{f}");
        assert_eq!(other.nodes.len(), m.nodes.len(), "{f}");
        for (p, r) in other.nodes.iter().zip(&m.nodes) {
            for k in 0..3 {
                assert!((p[k] - r[k]).abs() < 1e-17, "{f}: {p:?} vs {r:?}");
            }
        }
        if !f.ends_with(".vtk") {
            assert_eq!(other.tri_tags, m.tri_tags, "{f}");
            assert_eq!(other.mid_edges.as_ref().unwrap().tris, q.tris, "{f}");
        }
    }
}

/// A straight-sided quadratic Kuhn mesh written as gmsh and read back is the same mesh: nodes
/// bit for bit (coordinates that print exactly), the same corners and mid-edge nodes, tags,
/// names and node sets.
#[test]
fn gmsh_and_vtu_round_trips_of_a_quadratic_mesh_are_exact() {
    let spec = KuhnSpec {
        min: [0.0; 3],
        max: [8.0, 4.0, 4.0],
        cavity_min: [2.0, 1.0, 1.0],
        cavity_max: [6.0, 3.0, 3.0],
        ..KuhnSpec::benchmark(8, 4, 4)
    };
    // In metres, with coordinates on a grid of halves: every value prints exactly.
    let lin = kuhn_grid(&spec, LengthUnit::Metre).unwrap();
    let q = lin.with_mid_edges();
    assert!(q.validate().iter().all(|i| i.severity != Severity::Error));
    let d = tmpdir("rt");
    for ext in ["msh", "vtu"] {
        let path = d.join(format!("q.{ext}"));
        save(&q, &path, LengthUnit::Metre).unwrap();
        let back = load(&path, LengthUnit::Metre).unwrap();
        assert_eq!(back.nodes, q.nodes, "{ext}");
        assert_eq!(back.tets, q.tets, "{ext}");
        assert_eq!(back.tris, q.tris, "{ext}");
        assert_eq!(back.tet_tags, q.tet_tags, "{ext}");
        assert_eq!(back.tri_tags, q.tri_tags, "{ext}");
        assert_eq!(back.mid_edges, q.mid_edges, "{ext}");
        assert_eq!(back.report.reoriented_tets, 0);
        assert_eq!(back.report.reoriented_faces, 0);
        if ext == "msh" {
            assert_eq!(back.names, q.names);
            let text = std::fs::read_to_string(&path).unwrap();
            assert!(
                text.contains(&format!("3 1 11 {}", q.tets.len())),
                "a type-11 block"
            );
            // The first tet in gmsh's order: edge 2-3 before edge 1-3.
            let (t, m) = (q.tets[0], q.mid_edges.as_ref().unwrap().tets[0]);
            let want: Vec<String> = t
                .iter()
                .chain(&[m[0], m[1], m[2], m[3], m[5], m[4]])
                .map(|v| (v + 1).to_string())
                .collect();
            let id = q.tris.len() + 1;
            assert!(
                text.contains(&format!("\n{id} {}\n", want.join(" "))),
                "tet 0 not in gmsh order"
            );
        }
    }
    // Millimetres with unit conversion: not bit for bit the first time (15 significant
    // digits), then stable.
    let mm = kuhn_grid(&KuhnSpec::benchmark(6, 4, 4), LengthUnit::Millimetre)
        .unwrap()
        .with_mid_edges();
    let (p1, p2) = (d.join("a.msh"), d.join("b.msh"));
    save(&mm, &p1, LengthUnit::Millimetre).unwrap();
    let once = load(&p1, LengthUnit::Millimetre).unwrap();
    save(&once, &p2, LengthUnit::Millimetre).unwrap();
    let twice = load(&p2, LengthUnit::Millimetre).unwrap();
    assert_eq!(once.nodes, twice.nodes);
    assert_eq!(once.mid_edges, mm.mid_edges);
    for (p, r) in once.nodes.iter().zip(&mm.nodes) {
        for k in 0..3 {
            assert!((p[k] - r[k]).abs() < 1e-15);
        }
    }
    std::fs::remove_dir_all(&d).unwrap();
}

/// Reorientation permutes the mid-edge nodes with the corners: a quadratic file written with
/// the opposite orientation and winding reads back as the same elements.
#[test]
fn a_reversed_quadratic_file_is_reoriented_with_its_mid_edge_nodes() {
    let q = kuhn_grid(&KuhnSpec::benchmark(6, 4, 4), LengthUnit::Millimetre)
        .unwrap()
        .with_mid_edges();
    let mut rev = q.clone();
    let mids = rev.mid_edges.as_mut().unwrap();
    for (t, m) in rev.tets.iter_mut().zip(&mut mids.tets) {
        t.swap(2, 3);
        *m = softc::mesh::model::swap_mids_23(*m);
    }
    for (t, m) in rev.tris.iter_mut().zip(&mut mids.tris) {
        t.swap(1, 2);
        *m = softc::mesh::model::swap_tri_mids_12(*m);
    }
    let d = tmpdir("rev");
    let path = d.join("rev.msh");
    save(&rev, &path, LengthUnit::Millimetre).unwrap();
    let back = load(&path, LengthUnit::Millimetre).unwrap();
    assert_eq!(back.report.reoriented_tets, q.tets.len());
    assert_eq!(back.report.reoriented_faces, q.tris.len());
    assert_eq!(back.tets, q.tets);
    assert_eq!(back.tris, q.tris);
    assert_eq!(back.mid_edges, q.mid_edges);
    std::fs::remove_dir_all(&d).unwrap();
}

fn refuse(name: &str, content: &str, needles: &[&str]) {
    let d = tmpdir("refuse");
    let p = d.join(name);
    std::fs::write(&p, content).unwrap();
    let e = read(&p, LengthUnit::Millimetre).unwrap_err().to_string();
    for n in needles {
        assert!(e.contains(n), "`{n}` not in: {e}");
    }
    assert!(e.contains(name), "the file is not named: {e}");
    std::fs::remove_dir_all(&d).ok();
}

/// One quadratic tet (nodes 1–10) and, optionally, others, as gmsh 2.2.
fn msh22(extra_nodes: &str, elements: &[&str]) -> String {
    let nodes = "1 0 0 0\n2 1 0 0\n3 0 1 0\n4 0 0 1\n5 0.5 0 0\n6 0.5 0.5 0\n7 0 0.5 0\n\
                 8 0 0 0.5\n9 0 0.5 0.5\n10 0.5 0 0.5\n";
    let n = 10 + extra_nodes.lines().count();
    format!(
        "$MeshFormat\n2.2 0 8\n$EndMeshFormat\n$Nodes\n{n}\n{nodes}{extra_nodes}$EndNodes\n\
         $Elements\n{}\n{}\n$EndElements\n",
        elements.len(),
        elements.join("\n")
    )
}

#[test]
fn files_mixing_element_orders_are_refused_naming_an_element() {
    let quad = "1 11 2 1 1 1 2 3 4 5 6 7 8 9 10";
    // A lone quadratic tet reads, mid-edge nodes in VTK's order.
    let d = tmpdir("one");
    let p = d.join("one.msh");
    std::fs::write(&p, msh22("", &[quad])).unwrap();
    let m = load(&p, LengthUnit::Metre).unwrap();
    // gmsh's nodes 9 (edge 2-3) and 10 (edge 1-3) swap places: VTK lists 1-3 first.
    assert_eq!(m.mid_edges.as_ref().unwrap().tets, vec![[4, 5, 6, 7, 9, 8]]);
    assert!(m.validate().is_empty(), "{:?}", m.validate());
    std::fs::remove_dir_all(&d).ok();
    refuse(
        "mixed_tets.msh",
        &msh22("11 1 1 1\n", &[quad, "2 4 2 1 1 2 3 4 11"]),
        &[
            "element 2 is a 4-node tetrahedron",
            "element 1 has 10 nodes",
            "mixed_tets.msh:21:",
        ],
    );
    refuse(
        "mixed_tris.msh",
        &msh22("", &[quad, "7 2 2 5 5 2 3 4"]),
        &["surface triangle 7 has 3 nodes", "6-node"],
    );
    refuse(
        "six_node_tris_on_linear_tets.msh",
        &msh22("", &["1 4 2 1 1 1 2 3 4", "2 9 2 5 5 2 3 4 6 9 10"]),
        &["surface triangle 2 has 6 nodes", "4"],
    );
}

#[test]
fn vtu_output_of_a_quadratic_mesh_uses_vtk_types_24_and_22() {
    let q = kuhn_grid(&KuhnSpec::benchmark(6, 4, 4), LengthUnit::Millimetre)
        .unwrap()
        .with_mid_edges();
    let disp: Vec<[f64; 3]> = (0..q.nodes.len()).map(|i| [i as f64, 0.0, 0.0]).collect();
    let doc = vtu_document(
        &q,
        LengthUnit::Metre,
        None,
        &[("displacement_m", softc::mesh::writers::Field::Vector(&disp))],
        &[],
        VtuEncoding::Ascii,
    );
    let types = doc
        .split("Name=\"types\" format=\"ascii\">\n")
        .nth(1)
        .unwrap()
        .split("</DataArray>")
        .next()
        .unwrap();
    let types: Vec<&str> = types.split_whitespace().collect();
    assert_eq!(types.len(), q.tets.len() + q.tris.len());
    assert!(types[..q.tets.len()].iter().all(|t| *t == "24"));
    assert!(types[q.tets.len()..].iter().all(|t| *t == "22"));
    assert!(doc.contains(&format!("NumberOfPoints=\"{}\"", q.nodes.len())));
    // The first cell: 4 corners then 6 mid-edge nodes, VTK's order = softc's.
    let (t, m) = (q.tets[0], q.mid_edges.as_ref().unwrap().tets[0]);
    let first: Vec<String> = t.iter().chain(&m).map(|v| v.to_string()).collect();
    assert!(doc.contains(&format!(
        "Name=\"connectivity\" format=\"ascii\">\n{}\n",
        first.join(" ")
    )));
    // Binary and ASCII read back to the same quadratic mesh.
    let d = tmpdir("vtu");
    for enc in [VtuEncoding::Ascii, VtuEncoding::Binary] {
        let p = d.join("q.vtu");
        let doc = vtu_document(&q, LengthUnit::Millimetre, None, &[], &[], enc);
        std::fs::write(&p, doc).unwrap();
        let back = load(&p, LengthUnit::Millimetre).unwrap();
        assert_eq!(back.mid_edges, q.mid_edges, "{enc:?}");
        assert_eq!(back.tets, q.tets, "{enc:?}");
    }
    std::fs::remove_dir_all(&d).unwrap();
    // HRZ masses from the reader's mesh are positive.
    let p = element_points(&q, 0).unwrap();
    assert!(hrz_lumped(&p).iter().all(|&x| x > 0.0));
}
