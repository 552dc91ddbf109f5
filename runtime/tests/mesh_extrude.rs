//! The extruded mesher (`[extrude]`) and quadratic mesh generation (`order = 2`): conforming,
//! positive, reproducible meshes whose chamber walls get the elements asked for, outline
//! vertices and (order 2) mid-edge nodes on the exact curved surfaces, clear spec errors.

use std::path::Path;

use softc::mesh::mesher::{Generated, MeshSpec, Shape, generate};
use softc::mesh::{Mesh, has_errors};

/// A short soft-endoscope section (mm): radius 9, three chambers of radius 2.5 whose axes lie
/// 5 from the body axis (1.5 mm outer walls), x in [0, 20], chambers x in [2, 18].
fn endoscope_spec(wall: f64, order: u32) -> String {
    let mut s = format!(
        "unit = \"mm\"\norder = {order}\n[extrude]\nwall = {wall}\ninterior = {}\nlayer = {}\n\
         [body]\nshape = \"cylinder\"\nstart = [0, 0, 0]\nend = [20, 0, 0]\nradius = 9\n",
        2.0 * wall,
        2.0 * wall
    );
    for (k, deg) in [30.0f64, 150.0, 270.0].iter().enumerate() {
        let (y, z) = (5.0 * deg.to_radians().cos(), 5.0 * deg.to_radians().sin());
        s += &format!(
            "[[cavity]]\nname = \"c{}\"\ntag = {}\nshape = \"cylinder\"\nstart = [2, {y}, {z}]\n\
             end = [18, {y}, {z}]\nradius = 2.5\n",
            k + 1,
            k + 1
        );
    }
    s + "[base]\ntag = 10\nname = \"base\"\n[tip]\ntag = 11\nname = \"tip\"\n"
}

fn generate_text(text: &str, resolution: Option<f64>) -> Result<Generated, String> {
    let spec = MeshSpec::from_toml(text, Path::new("test.toml")).map_err(|e| e.to_string())?;
    generate(&spec, resolution, Path::new(".")).map_err(|e| e.to_string())
}

/// Chamber `k`'s exact cylinder, in metres.
fn chamber(k: usize) -> Shape {
    let deg = [30.0f64, 150.0, 270.0][k].to_radians();
    let (y, z) = (5e-3 * deg.cos(), 5e-3 * deg.sin());
    Shape::Cylinder {
        a: [2e-3, y, z],
        b: [18e-3, y, z],
        r: 2.5e-3,
    }
}

fn body() -> Shape {
    Shape::Cylinder {
        a: [0.0; 3],
        b: [20e-3, 0.0, 0.0],
        r: 9e-3,
    }
}

/// Nodes of the boundary faces that lie on the body's curved outer surface.
fn outer_nodes(m: &Mesh) -> std::collections::BTreeSet<u32> {
    m.boundary_faces()
        .iter()
        .flat_map(|f| f.nodes)
        .filter(|&n| {
            let p = m.nodes[n as usize];
            ((p[1] * p[1] + p[2] * p[2]).sqrt() - 9e-3).abs() < 1e-9
        })
        .collect()
}

#[test]
fn an_extruded_endoscope_is_conforming_with_two_elements_through_every_wall() {
    let g = generate_text(&endoscope_spec(0.75, 1), None).unwrap();
    let m = &g.mesh;
    let issues = m.validate();
    assert!(!has_errors(&issues), "{issues:?}");
    for e in 0..m.tets.len() {
        assert!(m.tet_volume(e) > 0.0, "tet {e} is not positive");
    }
    // Watertight: every boundary edge joins exactly two boundary faces.
    let mut edges: Vec<(u32, u32)> = m
        .boundary_faces()
        .iter()
        .flat_map(|f| (0..3).map(move |k| (f.nodes[k], f.nodes[(k + 1) % 3])))
        .map(|(a, b)| (a.min(b), a.max(b)))
        .collect();
    edges.sort_unstable();
    for w in edges.chunks(2) {
        assert!(
            w.len() == 2 && w[0] == w[1],
            "boundary edge {:?} is open",
            w[0]
        );
    }
    assert_eq!(m.chamber_tags(), vec![1, 2, 3]);
    // Every chamber vertex lies on its exact cylinder (side or cap).
    for k in 0..3 {
        let c = chamber(k);
        for n in m.surface_nodes(k as i32 + 1) {
            let d = c.sdf(m.nodes[n as usize]).abs();
            assert!(d < 1e-12, "c{}: node {n} is {d} m off the cylinder", k + 1);
        }
    }
    // Inscribed polygons: the solid is slightly larger than the exact one, the chambers
    // slightly smaller (by the chords' sagitta, under 1.5 % at 0.75 mm on a 2.5 mm radius).
    let q = m.quality(Some(g.reference_volume));
    let err = q.volume_error.unwrap();
    assert!(err > 0.0 && err < 0.005, "solid volume error {err}");
    for (tag, exact) in &g.cavity_volumes {
        let e = (m.enclosed_volume(*tag) - exact) / exact;
        assert!(e < 0.0 && e > -0.015, "chamber {tag} volume error {e}");
    }
    // Two elements through each 1.5 mm outer wall: no tet touches both a chamber and the
    // outer surface.
    let outer = outer_nodes(m);
    for k in 1..=3 {
        let inner: std::collections::BTreeSet<u32> = m.surface_nodes(k).into_iter().collect();
        for t in &m.tets {
            assert!(
                !(t.iter().any(|n| inner.contains(n)) && t.iter().any(|n| outer.contains(n))),
                "tet {t:?} spans the wall of c{k}"
            );
        }
    }
    // The base and tip planes are tagged and named node sets.
    assert!(
        m.node_sets["base"]
            .iter()
            .all(|&n| m.nodes[n as usize][0] == 0.0)
    );
    assert!(
        m.node_sets["tip"]
            .iter()
            .all(|&n| m.nodes[n as usize][0] == 20e-3)
    );
    // Reproducible to the bit.
    let again = generate_text(&endoscope_spec(0.75, 1), None).unwrap().mesh;
    assert_eq!(again.nodes, m.nodes);
    assert_eq!(again.tets, m.tets);
    assert_eq!(again.tris, m.tris);
}

#[test]
fn a_resolution_override_refines_the_walls() {
    let fine = generate_text(&endoscope_spec(0.75, 1), Some(0.5)).unwrap();
    let coarse = generate_text(&endoscope_spec(0.75, 1), Some(1.5)).unwrap();
    let base = generate_text(&endoscope_spec(0.75, 1), None).unwrap();
    assert!(fine.mesh.tets.len() > 2 * base.mesh.tets.len());
    assert!(coarse.mesh.tets.len() * 4 < base.mesh.tets.len());
    // Finer outlines: closer chamber volumes.
    let err = |g: &Generated| {
        let (tag, exact) = g.cavity_volumes[0];
        (g.mesh.enclosed_volume(tag) - exact).abs() / exact
    };
    assert!(err(&fine) < err(&base) && err(&base) < err(&coarse));
    assert!(!has_errors(&coarse.mesh.validate()));
}

#[test]
fn quadratic_generation_puts_curved_mid_edge_nodes_on_the_exact_surfaces() {
    let g = generate_text(&endoscope_spec(1.0, 2), None).unwrap();
    let m = &g.mesh;
    assert!(m.is_quadratic());
    let issues = m.validate();
    assert!(!has_errors(&issues), "{issues:?}");
    // Every node of every chamber triangle, corners and mid-edge nodes, on its cylinder: the
    // chords of the outline are arcs now.
    for k in 0..3 {
        let c = chamber(k);
        let tris = m.surface_mids(k as i32 + 1);
        assert!(!tris.is_empty());
        for n in tris.iter().flatten() {
            let d = c.sdf(m.nodes[*n as usize]).abs();
            assert!(
                d < 1e-12,
                "c{}: mid-edge node {n} is {d} m off the cylinder",
                k + 1
            );
        }
    }
    // The outer surface's mid-edge nodes too (the untagged body surface).
    let mids = m.mid_edges.as_ref().unwrap();
    let outer = outer_nodes(m);
    let b = body();
    let mut curved = 0;
    for (t, tm) in m.tets.iter().zip(&mids.tets) {
        for (e, &mid) in softc::mesh::QUAD_TET_EDGES.iter().zip(tm) {
            let (p, q) = (t[e[0]], t[e[1]]);
            let (pp, qq) = (m.nodes[p as usize], m.nodes[q as usize]);
            // An outline chord of the outer circle: both ends on it, in one or two sections,
            // less than 10° apart.
            let angle = |x: [f64; 3]| x[2].atan2(x[1]);
            if outer.contains(&p)
                && outer.contains(&q)
                && (angle(pp) - angle(qq)).abs() < 10f64.to_radians()
                && angle(pp) != angle(qq)
            {
                let d = b.sdf(m.nodes[mid as usize]).abs();
                assert!(
                    d < 1e-12,
                    "outer mid-edge node {mid} is {d} m off the cylinder"
                );
                curved += 1;
            }
        }
    }
    assert!(curved > 100, "{curved} curved outer edges");
    // The chambers' volumes, enclosed by the curved 6-node triangles, are within 0.1 % of the
    // cylinders' (the inscribed polygons alone lack 2.6 % at 1 mm on a 2.5 mm radius).
    for (tag, exact) in &g.cavity_volumes {
        let e = (m.enclosed_volume(*tag) - exact) / exact;
        assert!(e.abs() < 1e-3, "chamber {tag}: volume error {e}");
    }
    // Straight-sided interior edges keep their midpoints.
    let interior = m
        .tets
        .iter()
        .zip(&mids.tets)
        .flat_map(|(t, tm)| {
            softc::mesh::QUAD_TET_EDGES
                .iter()
                .zip(tm)
                .map(move |(e, &n)| (t[e[0]], t[e[1]], n))
        })
        .filter(|(p, q, _)| !outer.contains(p) || !outer.contains(q))
        .filter(|(p, q, n)| {
            let (a, b, c) = (
                m.nodes[*p as usize],
                m.nodes[*q as usize],
                m.nodes[*n as usize],
            );
            (0..3).all(|k: usize| (0.5 * (a[k] + b[k]) - c[k]).abs() < 1e-15f64)
        })
        .count();
    assert!(
        interior > m.tets.len(),
        "{interior} straight interior edges"
    );
}

#[test]
fn quadratic_stuffed_spheres_have_their_chamber_mid_edge_nodes_on_the_sphere() {
    let g = generate_text(
        "resolution = 2.5\norder = 2\n[body]\nshape = \"sphere\"\ncenter = [0, 0, 0]\nradius = 10\n\
         [[cavity]]\nname = \"inner\"\ntag = 2\nshape = \"sphere\"\ncenter = [0, 0, 0]\nradius = 5\n",
        None,
    )
    .unwrap();
    let m = &g.mesh;
    assert!(m.is_quadratic());
    assert!(!has_errors(&m.validate()));
    let inner = Shape::Sphere {
        c: [0.0; 3],
        r: 5e-3,
    };
    let mids = m.surface_mids(2);
    assert!(!mids.is_empty());
    for n in mids.iter().flatten() {
        let d = inner.sdf(m.nodes[*n as usize]).abs();
        assert!(d < 1e-9, "mid-edge node {n} is {d} m off the sphere");
    }
}

#[test]
fn extrusion_refuses_what_it_cannot_mesh_with_a_clear_message() {
    // A chamber that cuts through the outer wall.
    let crossing = endoscope_spec(0.75, 1).replace("radius = 2.5", "radius = 4.5");
    let e = generate_text(&crossing, None).unwrap_err();
    assert!(e.contains("strictly inside the body"), "{e}");
    // A sphere cannot be extruded.
    let sphere =
        "[extrude]\nwall = 1\n[body]\nshape = \"sphere\"\ncenter = [0, 0, 0]\nradius = 10\n";
    let e = generate_text(sphere, None).unwrap_err();
    assert!(e.contains("cylinders, boxes and prisms only"), "{e}");
    // A cavity askew to the axis.
    let askew = "[extrude]\nwall = 1\n[body]\nshape = \"cylinder\"\nstart = [0, 0, 0]\n\
                 end = [20, 0, 0]\nradius = 9\n[[cavity]]\nshape = \"cylinder\"\n\
                 start = [2, 0, 0]\nend = [18, 1, 0]\nradius = 2\n";
    let e = generate_text(askew, None).unwrap_err();
    assert!(e.contains("parallel"), "{e}");
    // Order 3 does not exist.
    let e = generate_text(&endoscope_spec(0.75, 3), None).unwrap_err();
    assert!(e.contains("order 3 must be 1 or 2"), "{e}");
    let e = generate_text(
        &endoscope_spec(0.75, 1).replace("wall = 0.75", "wall = 0"),
        None,
    )
    .unwrap_err();
    assert!(e.contains("must be > 0"), "{e}");
    // A `resolution` key would be ignored beside [extrude]: it is refused, naming the fix.
    let e = generate_text(
        &format!("resolution = 2.0\n{}", endoscope_spec(0.75, 1)),
        None,
    )
    .unwrap_err();
    assert!(
        e.contains("no effect beside [extrude]") && e.contains("`wall`"),
        "{e}"
    );
}

/// A box body with a box cavity, graded towards the cavity's edges: outline pieces `corner`
/// long at its corners and layers `end_layer` thick at every end plane, growing by at most
/// 1.3 per piece; the cavity is exact (its faces are planes).
#[test]
fn a_box_cavity_is_graded_towards_its_edges() {
    let text = "unit = \"mm\"\n[extrude]\nwall = 1\ninterior = 2\nlayer = 2\ncorner = 0.2\n\
                end_layer = 0.25\n[body]\nshape = \"box\"\nmin = [0, 0, 0]\nmax = [20, 10, 10]\n\
                [[cavity]]\nname = \"cavity\"\ntag = 2\nshape = \"box\"\nmin = [5, 2.5, 4]\n\
                max = [15, 7.5, 8]\n[base]\ntag = 10\nname = \"base\"\n";
    let g = generate_text(text, None).unwrap();
    let m = &g.mesh;
    assert!(!has_errors(&m.validate()));
    let (_, exact) = g.cavity_volumes[0];
    assert!(((m.enclosed_volume(2) - exact) / exact).abs() < 1e-12);
    // Layer planes: x coordinates of the nodes.
    let mut xs: Vec<f64> = m.nodes.iter().map(|p| p[0] * 1e3).collect();
    xs.sort_by(f64::total_cmp);
    xs.dedup_by(|a, b| (*a - *b).abs() < 1e-9);
    for end in [0.0, 5.0, 15.0, 20.0] {
        let i = xs.iter().position(|x| (x - end).abs() < 1e-9).unwrap();
        let next = [i.checked_sub(1), Some(i + 1)]
            .into_iter()
            .flatten()
            .filter_map(|j| xs.get(j))
            .map(|x| (x - end).abs())
            .fold(f64::INFINITY, f64::min);
        assert!(
            (next - 0.25).abs() < 1e-9,
            "layer next to x = {end}: {next}"
        );
    }
    assert!(xs.windows(2).all(|w| w[1] - w[0] <= 2.0 + 1e-9));
    // The cavity's corner edges in a section plane: its shortest outline pieces are 0.2 mm.
    let corner = [5e-3, 2.5e-3, 4e-3];
    let near: f64 = m
        .surface(2)
        .iter()
        .flat_map(|t| (0..3).map(move |k| (t[k], t[(k + 1) % 3])))
        .filter(|&(a, b)| {
            let (p, q) = (m.nodes[a as usize], m.nodes[b as usize]);
            p[0] == corner[0] && q[0] == corner[0] && (p == corner || q == corner)
        })
        .map(|(a, b)| {
            let (p, q) = (m.nodes[a as usize], m.nodes[b as usize]);
            ((p[1] - q[1]).powi(2) + (p[2] - q[2]).powi(2)).sqrt()
        })
        .fold(f64::INFINITY, f64::min);
    assert!(
        (near - 0.2e-3).abs() < 1e-12,
        "shortest piece at the corner: {near}"
    );
}

/// `meshes/gripper.toml`: a U-shaped prism body (a palm and two fingers) extruded along y,
/// seven box chambers per finger sharing one tag, a strain-limiting subregion. The notch between
/// the fingers (outside the non-convex outline, inside its convex hull) stays empty, the
/// solid's volume is exact, the chambers' tagged faces enclose their exact volume per finger.
#[test]
fn the_gripper_prism_meshes_its_palm_fingers_and_chambers_exactly() {
    let spec_path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../meshes/gripper.toml");
    let spec = MeshSpec::from_file(&spec_path).unwrap();
    let g = generate(&spec, None, spec_path.parent().unwrap()).unwrap();
    let m = &g.mesh;
    let issues = m.validate();
    assert!(!has_errors(&issues), "{issues:?}");
    let mut volume = 0.0;
    for e in 0..m.tets.len() {
        let v = m.tet_volume(e);
        assert!(v > 0.0, "tet {e} is not positive");
        volume += v;
        let c = m.tets[e].iter().fold([0.0; 3], |acc, &n| {
            let p = m.nodes[n as usize];
            [0, 1, 2].map(|d| acc[d] + p[d] / 4.0)
        });
        let in_notch = c[0] > 10e-3 && c[0] < 34e-3 && c[2] > 6e-3;
        assert!(
            !in_notch,
            "tet {e} at {c:?} fills the gap between the fingers"
        );
    }
    // Palm 44 × 6, fingers 2 × 10 × 54, all 12 wide, less 14 chambers of 6 × 9 × 5 (mm³).
    let exact = (44.0 * 6.0 + 2.0 * 10.0 * 54.0) * 12.0 - 14.0 * 6.0 * 9.0 * 5.0;
    assert!(
        (g.reference_volume / 1e-9 - exact).abs() < 1e-6,
        "{}",
        g.reference_volume
    );
    assert!((volume / g.reference_volume - 1.0).abs() < 1e-9, "{volume}");
    // One entry per chamber tag, each finger's seven cavities together.
    assert_eq!(g.cavity_volumes.len(), 2, "{:?}", g.cavity_volumes);
    for (tag, v) in &g.cavity_volumes {
        assert!((v / 1e-9 - 7.0 * 270.0).abs() < 1e-6, "chamber {tag}: {v}");
        // Its faces, wound into the solid (out of the chamber), enclose the same volume.
        let enclosed: f64 = (m.tris.iter().zip(&m.tri_tags))
            .filter(|(_, t)| *t == tag)
            .map(|(tri, _)| {
                let [a, b, c] = tri.map(|n| m.nodes[n as usize]);
                let (u, w) = (
                    [0, 1, 2].map(|d| b[d] - a[d]),
                    [0, 1, 2].map(|d| c[d] - a[d]),
                );
                let cross = [
                    u[1] * w[2] - u[2] * w[1],
                    u[2] * w[0] - u[0] * w[2],
                    u[0] * w[1] - u[1] * w[0],
                ];
                (0..3).map(|d| a[d] * cross[d]).sum::<f64>() / 6.0
            })
            .sum();
        assert!(
            (enclosed / v - 1.0).abs() < 1e-9,
            "chamber {tag}: {enclosed} vs {v}"
        );
    }
    // The shipped mesh is this spec's (regenerate it with `softc mesh generate`).
    let shipped = std::fs::read_to_string(spec_path.with_extension("msh")).unwrap();
    let unit = spec.unit().unwrap();
    let written = softc::mesh::readers::gmsh::to_string(m, unit).unwrap();
    assert!(
        shipped == written,
        "meshes/gripper.msh differs from meshes/gripper.toml's mesh: regenerate it with \
         `softc mesh generate meshes/gripper.toml -o meshes/gripper.msh`"
    );
    // The strain-limiting layers and the palm's underside.
    let limit = m.tet_tags.iter().filter(|&&t| t == 2).count();
    assert!(limit > 0 && limit < m.tets.len() / 4, "{limit}");
    let base = m.node_sets.get("base").expect("base");
    assert!(!base.is_empty() && base.iter().all(|&n| m.nodes[n as usize][2].abs() < 1e-12));
}

#[test]
fn a_prism_outline_must_be_a_simple_polygon() {
    let prism = |outline: &str| {
        format!(
            "[extrude]\nwall = 1\n[body]\nshape = \"prism\"\naxis = \"z\"\nspan = [0, 5]\n\
             outline = {outline}\n"
        )
    };
    // An L-shaped plate meshes, and the same outline listed clockwise too.
    for l in [
        "[[0, 0], [10, 0], [10, 4], [4, 4], [4, 10], [0, 10]]",
        "[[0, 10], [4, 10], [4, 4], [10, 4], [10, 0], [0, 0]]",
    ] {
        let g = generate_text(&prism(l), None).unwrap();
        assert!((g.reference_volume / 1e-9 - 64.0 * 5.0).abs() < 1e-6);
        let v: f64 = (0..g.mesh.tets.len()).map(|e| g.mesh.tet_volume(e)).sum();
        assert!((v / g.reference_volume - 1.0).abs() < 1e-9, "{v}");
    }
    // A bow tie crosses itself; two points enclose nothing.
    for bad in [
        "[[0, 0], [10, 10], [10, 0], [0, 10]]",
        "[[0, 0], [10, 0]]",
        "[[0, 0], [10, 0], [10, 0], [0, 10]]",
    ] {
        let e = generate_text(&prism(bad), None).unwrap_err();
        assert!(e.contains("outline"), "{e}");
    }
    let e = generate_text(
        &prism("[[0, 0], [1, 0], [0, 1]]").replace("axis = \"z\"\n", ""),
        None,
    )
    .unwrap_err();
    assert!(e.contains("needs `axis`"), "{e}");
    // Stuffing meshes a prism too (its signed distance is exact): an L at resolution 0.5.
    let stuffed = prism("[[0, 0], [10, 0], [10, 4], [4, 4], [4, 10], [0, 10]]")
        .replace("[extrude]\nwall = 1\n", "resolution = 0.5\n");
    let g = generate_text(&stuffed, None).unwrap();
    let v: f64 = (0..g.mesh.tets.len()).map(|e| g.mesh.tet_volume(e)).sum();
    assert!((v / g.reference_volume - 1.0).abs() < 0.02, "{v}");
}
