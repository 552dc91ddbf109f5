//! Validation: each broken-input case is reported with the element, face or node concerned.

use softc::mesh::kuhn::{CAVITY_TAG, KuhnSpec, kuhn_grid};
use softc::mesh::{
    IssueKind, LengthUnit, Mesh, MeshErrorKind, Severity, check_selection, has_errors, load, save,
};

fn bench() -> Mesh {
    kuhn_grid(&KuhnSpec::benchmark(12, 4, 4), LengthUnit::Millimetre).unwrap()
}

fn find(
    issues: &[softc::mesh::MeshIssue],
    pred: impl Fn(&IssueKind) -> bool,
) -> &softc::mesh::MeshIssue {
    issues
        .iter()
        .find(|i| pred(&i.kind))
        .unwrap_or_else(|| panic!("issue not reported; got {issues:#?}"))
}

#[test]
fn clean_mesh_has_no_issues() {
    assert!(bench().validate().is_empty());
}

#[test]
fn inverted_and_degenerate_tets_name_the_element_and_volume() {
    let mut m = bench();
    m.tets[5].swap(0, 1);
    let v = m.tet_volume(5);
    let issues = m.validate();
    let i = find(&issues, |k| {
        matches!(k, IssueKind::InvertedTet { element: 5, .. })
    });
    assert_eq!(i.severity, Severity::Error);
    assert!(
        i.message.contains("element 6") && i.message.contains(&format!("{v:.3e}")),
        "{}",
        i.message
    );
    // One tet against the rest is not a convention: orient_tets leaves it for validation to
    // refuse (issue 20 item 3).
    assert_eq!(m.orient_tets(), 0);
    assert!(has_errors(&m.validate()));

    let mut m = bench();
    let t = m.tets[7];
    m.tets[7] = [t[0], t[1], t[2], t[1]];
    let issues = m.validate();
    let i = find(&issues, |k| {
        matches!(k, IssueKind::DegenerateTet { element: 7, .. })
    });
    assert!(i.message.contains("element 8") && i.message.contains("degenerate"));
}

#[test]
fn flat_tet_in_a_file_is_refused_by_load_naming_the_element() {
    let d = std::env::temp_dir().join(format!("softc-val-flat-{}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    let p = d.join("flat.msh");
    let text = "$MeshFormat\n2.2 0 8\n$EndMeshFormat\n$Nodes\n5\n1 0 0 0\n2 1 0 0\n3 0 1 0\n4 0 0 1\n5 1 1 0\n$EndNodes\n$Elements\n2\n1 4 2 1 1 1 2 3 4\n2 4 2 1 1 1 2 3 5\n$EndElements\n";
    std::fs::write(&p, text).unwrap();
    let e = load(&p, LengthUnit::Millimetre).unwrap_err();
    std::fs::remove_dir_all(&d).unwrap();
    assert_eq!(e.kind, MeshErrorKind::Invalid);
    let s = e.to_string();
    assert!(
        s.contains("flat.msh") && s.contains("element 2 ") && s.contains("degenerate"),
        "{s}"
    );
}

#[test]
fn open_and_non_manifold_chambers() {
    let mut m = bench();
    let k = m.tri_tags.iter().position(|t| *t == CAVITY_TAG).unwrap();
    let removed = m.tris.remove(k);
    m.tri_tags.remove(k);
    let issues = m.validate();
    let i = find(&issues, |k| {
        matches!(k, IssueKind::OpenChamber { tag: 2, .. })
    });
    assert_eq!(i.severity, Severity::Error);
    let IssueKind::OpenChamber { edge, .. } = i.kind else {
        unreachable!()
    };
    assert!(
        edge.iter().all(|n| removed.contains(n)),
        "the open edge belongs to the removed face"
    );
    assert!(
        i.message
            .contains(&format!("nodes {} and {}", edge[0] + 1, edge[1] + 1)),
        "{}",
        i.message
    );

    let mut m = bench();
    let k = m.tri_tags.iter().position(|t| *t == CAVITY_TAG).unwrap();
    let f = m.tris[k];
    // A third triangle on one of its edges, on another boundary face of the cavity wall.
    let other = m
        .tris
        .iter()
        .enumerate()
        .find(|(j, g)| {
            *j != k && m.tri_tags[*j] == CAVITY_TAG && g.contains(&f[0]) && g.contains(&f[1])
        })
        .map(|(_, g)| *g)
        .unwrap();
    m.tris.push(other);
    m.tri_tags.push(CAVITY_TAG);
    let issues = m.validate();
    find(&issues, |k| {
        matches!(
            k,
            IssueKind::NonManifoldChamber {
                tag: 2,
                uses: 3,
                ..
            }
        )
    });
}

#[test]
fn chamber_face_not_on_the_boundary_is_named() {
    let mut m = bench();
    // An interior face: a face of tet 100 shared with a neighbour.
    let t = m.tets[100];
    let interior = m
        .boundary_faces()
        .iter()
        .map(|b| {
            let mut k = b.nodes;
            k.sort_unstable();
            k
        })
        .collect::<std::collections::BTreeSet<_>>();
    let face = softc::mesh::model::TET_FACES
        .iter()
        .map(|f| [t[f[0]], t[f[1]], t[f[2]]])
        .find(|f| {
            let mut k = *f;
            k.sort_unstable();
            !interior.contains(&k)
        })
        .unwrap();
    m.tris.push(face);
    m.tri_tags.push(CAVITY_TAG);
    let fi = m.tris.len() - 1;
    let issues = m.validate();
    let i = find(
        &issues,
        |k| matches!(k, IssueKind::ChamberFaceNotOnBoundary { tag: 2, face, .. } if *face == fi),
    );
    assert_eq!(i.severity, Severity::Error);
    assert!(
        i.message.contains(&format!("surface triangle {}", fi + 1))
            && i.message.contains(&format!("{:?}", face.map(|n| n + 1))),
        "{}",
        i.message
    );
}

#[test]
fn duplicate_unused_nodes_and_disconnected_pieces() {
    let mut m = bench();
    // A copy of node 0 used by no tet: duplicate + unused.
    m.nodes.push(m.nodes[0]);
    let dup = m.nodes.len() - 1;
    let issues = m.validate();
    let i = find(
        &issues,
        |k| matches!(k, IssueKind::DuplicateNodes { first: 0, second } if *second == dup),
    );
    assert!(i.message.contains(&format!("nodes 1 and {}", dup + 1)));
    let i = find(
        &issues,
        |k| matches!(k, IssueKind::UnusedNodes { count: 1, first } if *first == dup),
    );
    assert!(i.message.contains(&format!("node {}", dup + 1)));

    // A detached tet far away: a second piece, named by its element id.
    let mut m = bench();
    let base = m.nodes.len() as u32;
    for p in [
        [1.0, 0.0, 0.0],
        [1.001, 0.0, 0.0],
        [1.0, 0.001, 0.0],
        [1.0, 0.0, 0.001],
    ] {
        m.nodes.push(p);
    }
    m.tets.push([base, base + 1, base + 2, base + 3]);
    m.tet_tags.push(1);
    let e = m.tets.len() - 1;
    let issues = m.validate();
    let i = find(
        &issues,
        |k| matches!(k, IssueKind::DisconnectedPieces { pieces: 2, example_element, .. } if *example_element == e),
    );
    assert!(
        i.message.contains(&format!("element {}", e + 1)),
        "{}",
        i.message
    );
    assert!(has_errors(&issues));
}

#[test]
fn unknown_tags_and_names() {
    let mut m = bench();
    m.tet_tags[3] = 7;
    m.set_name(2, 99, "ghost");
    let issues = m.validate();
    find(&issues, |k| {
        matches!(k, IssueKind::UnnamedTag { dim: 3, tag: 7 })
    });
    let i = find(&issues, |k| {
        matches!(
            k,
            IssueKind::UnusedName {
                dim: 2,
                tag: 99,
                ..
            }
        )
    });
    assert!(i.message.contains("ghost"));
    // Resolving an unknown surface lists what exists.
    let e = m.resolve_surface("chamber9").unwrap_err();
    assert!(e.contains("2 (cavity)") && e.contains("10 (base)"), "{e}");
}

#[test]
fn empty_selection_helper() {
    let m = bench();
    let none = m.nodes_in_box([1.0, 1.0, 1.0], [2.0, 2.0, 2.0]);
    let i = check_selection("clamp", &none).unwrap();
    assert!(matches!(i.kind, IssueKind::EmptySelection { ref name } if name == "clamp"));
    assert!(i.message.contains("clamp") && i.message.contains("units"));
    assert!(check_selection("base", &m.node_sets["base"]).is_none());
}

#[test]
fn non_manifold_faces_bad_nodes_and_wrong_chamber_winding() {
    let mut m = bench();
    m.tets.push(m.tets[0]);
    m.tet_tags.push(1);
    let issues = m.validate();
    find(&issues, |k| {
        matches!(k, IssueKind::NonManifoldFace { tets: 2.., .. })
    });
    // The same face in three tets: duplicate a tet whose face is interior.
    let i = issues
        .iter()
        .find(|i| matches!(i.kind, IssueKind::NonManifoldFace { tets: 3, .. }));
    assert!(i.is_some(), "{issues:#?}");

    let mut m = bench();
    m.nodes[4][1] = f64::NAN;
    let issues = m.validate();
    find(&issues, |k| {
        matches!(k, IssueKind::NonFiniteNode { node: 4 })
    });

    let mut m = bench();
    m.tets[9][2] = 100_000;
    let issues = m.validate();
    let i = find(&issues, |k| {
        matches!(
            k,
            IssueKind::NodeOutOfRange {
                element: 9,
                node: 100_000
            }
        )
    });
    assert!(i.message.contains("element 10") && i.message.contains("node index 100000"));

    let mut m = bench();
    for (f, t) in m.tris.iter_mut().zip(&m.tri_tags) {
        if *t == CAVITY_TAG {
            f.swap(1, 2);
        }
    }
    let issues = m.validate();
    find(&issues, |k| {
        matches!(k, IssueKind::ChamberWrongOrientation { tag: 2, .. })
    });
    // orient_surfaces repairs the winding and counts every flipped triangle.
    let n = m.surface(CAVITY_TAG).len();
    assert_eq!(m.orient_surfaces(), n);
    assert!(m.validate().is_empty());
}

#[test]
fn untagged_cavity_is_a_warning() {
    let mut m = bench();
    let keep: Vec<bool> = m.tri_tags.iter().map(|t| *t != CAVITY_TAG).collect();
    let mut k = keep.iter();
    m.tris.retain(|_| *k.next().unwrap());
    m.tri_tags.retain(|t| *t != CAVITY_TAG);
    m.names.retain(|p| p.tag != CAVITY_TAG);
    let issues = m.validate();
    let i = find(&issues, |k| matches!(k, IssueKind::UntaggedCavity { .. }));
    assert_eq!(i.severity, Severity::Warning);
}

#[test]
fn load_reorients_wrongly_wound_chambers_and_counts_them() {
    let mut m = bench();
    let n = m.surface(CAVITY_TAG).len();
    for (f, t) in m.tris.iter_mut().zip(&m.tri_tags) {
        if *t == CAVITY_TAG {
            f.swap(1, 2);
        }
    }
    let d = std::env::temp_dir().join(format!("softc-val-wind-{}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    let p = d.join("wound.msh");
    save(&m, &p, LengthUnit::Millimetre).unwrap();
    let back = load(&p, LengthUnit::Millimetre).unwrap();
    std::fs::remove_dir_all(&d).unwrap();
    assert_eq!(back.report.reoriented_faces, n);
    assert!(back.enclosed_volume(CAVITY_TAG) > 0.0);
}

#[test]
fn load_refuses_disconnected_mesh_listing_the_issue() {
    let mut m = bench();
    let base = m.nodes.len() as u32;
    for p in [
        [1.0, 0.0, 0.0],
        [1.001, 0.0, 0.0],
        [1.0, 0.001, 0.0],
        [1.0, 0.0, 0.001],
    ] {
        m.nodes.push(p);
    }
    m.tets.push([base, base + 1, base + 2, base + 3]);
    m.tet_tags.push(1);
    let d = std::env::temp_dir().join(format!("softc-val-disc-{}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    let p = d.join("two.msh");
    save(&m, &p, LengthUnit::Millimetre).unwrap();
    let e = load(&p, LengthUnit::Millimetre).unwrap_err();
    std::fs::remove_dir_all(&d).unwrap();
    let s = e.to_string();
    // The detached tet by the file's number: the writer numbers triangles, then tets.
    let id = m.tris.len() + m.tets.len();
    assert!(
        s.contains("two.msh")
            && s.contains("disconnected")
            && s.contains(&format!("element {id} "))
            && s.contains("fix:"),
        "{s}"
    );
}

#[test]
fn pinched_boundary_edge_and_node_are_reported() {
    // Two unit tets sharing only an edge, and two sharing only a node.
    let edge = Mesh::from_tets(
        vec![
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [0.0, 0.0, 1.0],
            [0.0, -1.0, 0.0],
            [0.0, 0.0, -1.0],
        ],
        vec![[0, 1, 2, 3], [0, 1, 5, 4]],
    );
    let issues = edge.validate();
    let i = find(&issues, |k| {
        matches!(
            k,
            IssueKind::NonManifoldBoundaryEdge {
                edge: [0, 1],
                faces: 4
            }
        )
    });
    assert!(i.message.contains("nodes 1 and 2"), "{}", i.message);
    let node = Mesh::from_tets(
        vec![
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [0.0, 0.0, 1.0],
            [-1.0, 0.0, 0.0],
            [0.0, -1.0, 0.0],
            [0.0, 0.0, -1.0],
        ],
        vec![[0, 1, 2, 3], [0, 4, 6, 5]],
    );
    let issues = node.validate();
    let i = find(&issues, |k| {
        matches!(k, IssueKind::NonManifoldBoundaryNode { node: 0, sheets: 2 })
    });
    assert!(i.message.contains("node 1 "), "{}", i.message);
}

/// A 4×4×4 cube of 1 mm Kuhn cells (no cavity), in metres.
fn cube4() -> Mesh {
    let spec = KuhnSpec {
        n: [4, 4, 4],
        min: [0.0; 3],
        max: [4.0; 3],
        cavity_min: [0.0; 3],
        cavity_max: [0.0; 3],
    };
    kuhn_grid(&spec, LengthUnit::Millimetre).unwrap()
}

/// `cube4` with its interior node at (1, 1, 1) mm moved past its neighbour at (2, 1, 1) mm:
/// the tets around it turn inside out (the issue's tangled mesh).
fn tangled() -> (Mesh, Vec<usize>) {
    let mut m = cube4();
    let n = m
        .nodes
        .iter()
        .position(|p| p.iter().all(|c| (c - 1e-3).abs() < 1e-12))
        .unwrap();
    m.nodes[n][0] = 2.6e-3;
    let inverted: Vec<usize> = (0..m.tets.len())
        .filter(|&e| m.tet_volume(e) < 0.0)
        .collect();
    assert!(
        !inverted.is_empty() && inverted.len() < m.tets.len() / 2,
        "{inverted:?}"
    );
    (m, inverted)
}

fn scratch(tag: &str) -> std::path::PathBuf {
    let d = std::env::temp_dir().join(format!("softc-val-{tag}-{}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    d
}

#[test]
fn a_tangled_mesh_is_refused_naming_its_inverted_elements() {
    // Issue 20 item 3: the loader used to reorder the inverted tets one by one, report "valid"
    // and simulate a body 12.5 mm³ too large.
    let (m, inverted) = tangled();
    let d = scratch("tangled");
    let p = d.join("tangled.msh");
    save(&m, &p, LengthUnit::Millimetre).unwrap();
    let e = load(&p, LengthUnit::Millimetre).unwrap_err();
    assert_eq!(e.kind, MeshErrorKind::Invalid);
    let named: Vec<usize> = e
        .issues
        .iter()
        .filter_map(|i| match i.kind {
            IssueKind::InvertedTet { element, .. } => Some(element),
            _ => None,
        })
        .collect();
    assert_eq!(named, inverted, "{e}");
    let s = e.to_string();
    assert!(s.contains("tangled") && s.contains("inverted"), "{s}");
    // `read` (no validation) reorders nothing either.
    let r = softc::mesh::read(&p, LengthUnit::Millimetre).unwrap();
    assert_eq!(r.report.reoriented_tets, 0);
    std::fs::remove_dir_all(&d).ok();
}

#[test]
fn a_tangled_mesh_with_its_corners_reordered_is_refused_as_overlapping() {
    // The same tangle, with the inverted tets' corners swapped in the file so every tet has a
    // positive volume: the tets around the moved node overlap their neighbours.
    let (mut m, inverted) = tangled();
    for &e in &inverted {
        m.tets[e].swap(2, 3);
    }
    assert!((0..m.tets.len()).all(|e| m.tet_volume(e) > 0.0));
    let d = scratch("overlap");
    let p = d.join("overlap.msh");
    save(&m, &p, LengthUnit::Millimetre).unwrap();
    let e = load(&p, LengthUnit::Millimetre).unwrap_err();
    std::fs::remove_dir_all(&d).ok();
    assert_eq!(e.kind, MeshErrorKind::Invalid);
    let i = find(&e.issues, |k| {
        matches!(k, IssueKind::OverlappingTets { .. })
    });
    let IssueKind::OverlappingTets { elements, .. } = i.kind else {
        unreachable!()
    };
    assert!(
        elements.iter().any(|x| inverted.contains(x)),
        "{elements:?} {inverted:?}"
    );
    assert!(i.message.contains("overlap"), "{}", i.message);
}

#[test]
fn a_mesh_written_with_the_other_orientation_is_reordered_whole() {
    let m = cube4();
    let mut flipped = m.clone();
    for t in &mut flipped.tets {
        t.swap(0, 1);
    }
    let d = scratch("flipped");
    let p = d.join("flipped.msh");
    save(&flipped, &p, LengthUnit::Millimetre).unwrap();
    let back = load(&p, LengthUnit::Millimetre).unwrap();
    std::fs::remove_dir_all(&d).ok();
    assert_eq!(back.report.reoriented_tets, m.tets.len());
    assert!((back.total_volume() - 64e-9).abs() < 1e-20);
    assert!(back.validate().is_empty());
}

#[test]
fn messages_name_nodes_and_elements_by_the_files_numbers() {
    // Issue 20 item 17: messages said "element 1" for the file's element 12 (0-based indices).
    let d = scratch("ids");
    let p = d.join("ids.msh");
    let text = "$MeshFormat\n2.2 0 8\n$EndMeshFormat\n$Nodes\n5\n101 0 0 0\n102 1 0 0\n\
                103 0 1 0\n104 0 0 1\n105 1 1 0\n$EndNodes\n$Elements\n2\n\
                11 4 2 1 1 101 102 103 104\n12 4 2 1 1 101 102 103 105\n$EndElements\n";
    std::fs::write(&p, text).unwrap();
    let e = load(&p, LengthUnit::Millimetre).unwrap_err();
    std::fs::remove_dir_all(&d).ok();
    let s = e.to_string();
    assert!(
        s.contains("element 12 (nodes [101, 102, 103, 105]) is degenerate"),
        "{s}"
    );
    // Read without validation, the mesh keeps the numbers; a generated one counts from 1.
    let m = cube4();
    assert_eq!((m.node_id(0), m.tet_id(0), m.tri_id(0)), (1, 1, 1));
}
