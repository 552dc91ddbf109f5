//! The structured benchmark grid of BENCHMARK.md: exact tet counts, conformity, volume,
//! chamber area and orientation.

use softc::mesh::kuhn::{BASE_TAG, CAVITY_TAG, KuhnSpec, TIP_TAG, kuhn_grid};
use softc::mesh::model::{TET_FACES, area_vector};
use softc::mesh::{LengthUnit, Mesh};

fn grid(n: [usize; 3]) -> Mesh {
    kuhn_grid(
        &KuhnSpec::benchmark(n[0], n[1], n[2]),
        LengthUnit::Millimetre,
    )
    .unwrap()
}

/// Cavity cells of the benchmark grid: per axis, the cell index range whose centres lie
/// strictly inside the cavity interval.
fn cavity_cells(n: [usize; 3]) -> [(usize, usize); 3] {
    let (lo, hi, len) = ([5.0, 2.5, 4.0], [55.0, 7.5, 8.0], [60.0, 10.0, 10.0]);
    let mut r = [(0, 0); 3];
    for a in 0..3 {
        let h = len[a] / n[a] as f64;
        let inside: Vec<usize> = (0..n[a])
            .filter(|&i| {
                let c = (i as f64 + 0.5) * h;
                c > lo[a] && c < hi[a]
            })
            .collect();
        r[a] = (inside[0], inside[inside.len() - 1] + 1);
    }
    r
}

#[test]
fn tet_counts_match_the_benchmark_table() {
    for (n, tets) in [
        ([12, 4, 4], 1032),
        ([42, 7, 7], 10512),
        ([72, 12, 12], 51408),
    ] {
        let m = grid(n);
        assert_eq!(m.tets.len(), tets, "{n:?}");
    }
}

#[test]
fn grids_are_conforming_positive_and_valid() {
    for n in [[12, 4, 4], [42, 7, 7]] {
        let m = grid(n);
        for e in 0..m.tets.len() {
            assert!(m.tet_volume(e) > 0.0);
        }
        // Every face is shared by one (boundary) or two (interior) tets.
        let mut faces: Vec<[u32; 3]> = Vec::new();
        for t in &m.tets {
            for f in TET_FACES {
                let mut k = [t[f[0]], t[f[1]], t[f[2]]];
                k.sort_unstable();
                faces.push(k);
            }
        }
        faces.sort_unstable();
        let mut i = 0;
        let mut boundary_area = 0.0;
        let bmap: std::collections::BTreeSet<[u32; 3]> = m
            .boundary_faces()
            .iter()
            .map(|b| {
                let mut k = b.nodes;
                k.sort_unstable();
                boundary_area += norm3(area_vector(
                    m.nodes[b.nodes[0] as usize],
                    m.nodes[b.nodes[1] as usize],
                    m.nodes[b.nodes[2] as usize],
                ));
                k
            })
            .collect();
        while i < faces.len() {
            let mut j = i + 1;
            while j < faces.len() && faces[j] == faces[i] {
                j += 1;
            }
            assert!(j - i <= 2, "face {:?} in {} tets", faces[i], j - i);
            assert_eq!(j - i == 1, bmap.contains(&faces[i]));
            i = j;
        }
        // Boundary = outer box surface + cavity-cell box surface (m²).
        let c = cavity_cells(n);
        let h = [60.0 / n[0] as f64, 10.0 / n[1] as f64, 10.0 / n[2] as f64];
        let d: Vec<f64> = (0..3).map(|a| (c[a].1 - c[a].0) as f64 * h[a]).collect();
        let cav_area = 2.0 * (d[0] * d[1] + d[1] * d[2] + d[0] * d[2]) * 1e-6;
        let box_area = 2.0 * (600.0 + 100.0 + 600.0) * 1e-6;
        assert!(
            (boundary_area - box_area - cav_area).abs() < 1e-12,
            "{boundary_area}"
        );
        let issues = m.validate();
        assert!(issues.is_empty(), "{issues:?}");
    }
}

#[test]
fn volume_is_box_minus_cavity_cells_exactly() {
    for n in [[12, 4, 4], [42, 7, 7], [72, 12, 12]] {
        let m = grid(n);
        let c = cavity_cells(n);
        let ncav: usize = (0..3).map(|a| c[a].1 - c[a].0).product();
        let cell = 6000.0 / (n[0] * n[1] * n[2]) as f64;
        let expect = (6000.0 - ncav as f64 * cell) * 1e-9;
        assert!(
            (m.total_volume() - expect).abs() < 1e-9 * expect,
            "{n:?}: {} vs {expect}",
            m.total_volume()
        );
        // 1k: cavity cells are x∈[5,55], y∈[2.5,7.5], z∈[5,7.5] (20 cells).
        if n == [12, 4, 4] {
            assert_eq!(ncav, 20);
        }
    }
}

#[test]
fn chamber_area_volume_and_orientation() {
    for n in [[12, 4, 4], [42, 7, 7], [72, 12, 12]] {
        let m = grid(n);
        let c = cavity_cells(n);
        let h = [60.0 / n[0] as f64, 10.0 / n[1] as f64, 10.0 / n[2] as f64];
        let d: Vec<f64> = (0..3).map(|a| (c[a].1 - c[a].0) as f64 * h[a]).collect();
        let area = 2.0 * (d[0] * d[1] + d[1] * d[2] + d[0] * d[2]) * 1e-6;
        assert!(
            (m.surface_area(CAVITY_TAG) - area).abs() < 1e-12 * area.max(1.0),
            "{n:?}"
        );
        let vol = d[0] * d[1] * d[2] * 1e-9;
        assert!(
            (m.enclosed_volume(CAVITY_TAG) - vol).abs() < 1e-9 * vol,
            "{n:?}"
        );
        // Each chamber triangle is a boundary face wound opposite to the tet's outward face,
        // i.e. its normal points into the solid.
        let b: std::collections::BTreeMap<[u32; 3], [u32; 3]> = m
            .boundary_faces()
            .iter()
            .map(|f| {
                let mut k = f.nodes;
                k.sort_unstable();
                (k, f.nodes)
            })
            .collect();
        let centre = [30e-3, 5e-3, 6e-3];
        for (f, t) in m.tris.iter().zip(&m.tri_tags) {
            let mut k = *f;
            k.sort_unstable();
            let out = b[&k];
            let n_in = area_vector(
                m.nodes[f[0] as usize],
                m.nodes[f[1] as usize],
                m.nodes[f[2] as usize],
            );
            let n_out = area_vector(
                m.nodes[out[0] as usize],
                m.nodes[out[1] as usize],
                m.nodes[out[2] as usize],
            );
            let dot: f64 = (0..3).map(|a| n_in[a] * n_out[a]).sum();
            assert!(dot < 0.0, "tag {t}: triangle {f:?} points out of the solid");
            if *t == CAVITY_TAG {
                // Into the solid = away from the cavity centre.
                let p = m.nodes[f[0] as usize];
                let away: f64 = (0..3).map(|a| n_in[a] * (p[a] - centre[a])).sum();
                assert!(away > 0.0);
            }
        }
        // Split along the Kuhn diagonal: every chamber triangle is a face of some tet (checked
        // above through the boundary map) — and there are exactly 2 per cavity quad.
        let quads = 2.0
            * (d[0] * d[1] / (h[0] * h[1])
                + d[1] * d[2] / (h[1] * h[2])
                + d[0] * d[2] / (h[0] * h[2]));
        assert_eq!(m.surface(CAVITY_TAG).len(), 2 * quads.round() as usize);
    }
}

#[test]
fn base_and_tip_sets() {
    let m = grid([12, 4, 4]);
    assert_eq!(m.tag_name(2, BASE_TAG), Some("base"));
    assert_eq!(m.tag_name(2, TIP_TAG), Some("tip"));
    assert_eq!(m.tag_name(2, CAVITY_TAG), Some("cavity"));
    assert_eq!(m.chamber_tags(), vec![CAVITY_TAG]);
    assert_eq!(m.node_sets["base"].len(), 25);
    assert_eq!(m.node_sets["tip"].len(), 25);
    for &n in &m.node_sets["tip"] {
        assert!((m.nodes[n as usize][0] - 0.06).abs() < 1e-15);
    }
    assert!((m.surface_area(BASE_TAG) - 1e-4).abs() < 1e-16);
    let sel = m.nodes_in_box([-1.0, -1.0, -1.0], [1e-9, 1.0, 1.0]);
    assert_eq!(sel, m.node_sets["base"]);
}

fn norm3(v: [f64; 3]) -> f64 {
    (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt()
}
