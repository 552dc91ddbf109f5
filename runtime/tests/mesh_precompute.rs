//! Precomputed kernel data: volumes, Dm⁻¹, lumped masses, CSR adjacency, edges, surfaces.

#![allow(clippy::needless_range_loop)]

use softc::mesh::kuhn::{CAVITY_TAG, KuhnSpec, kuhn_grid};
use softc::mesh::{LengthUnit, Precomputed};

#[test]
fn masses_sum_to_density_times_volume_and_follow_element_densities() {
    let m = kuhn_grid(&KuhnSpec::benchmark(12, 4, 4), LengthUnit::Millimetre).unwrap();
    let p = Precomputed::with_uniform_density(&m, 1070.0).unwrap();
    let total: f64 = p.mass.iter().sum();
    let v = m.total_volume();
    assert!(
        (total - 1070.0 * v).abs() < 1e-12 * total,
        "{total} vs {}",
        1070.0 * v
    );
    assert!(p.mass.iter().all(|x| *x > 0.0));
    // Per-element densities: node masses are ρ_e V_e / 4 summed over adjacent tets.
    let rho: Vec<f64> = (0..m.tets.len()).map(|e| 1000.0 + e as f64).collect();
    let p = Precomputed::new(&m, &rho).unwrap();
    let mut expect = vec![0.0; m.nodes.len()];
    for (e, t) in m.tets.iter().enumerate() {
        for &n in t {
            expect[n as usize] += rho[e] * m.tet_volume(e) / 4.0;
        }
    }
    for (a, b) in p.mass.iter().zip(&expect) {
        assert!((a - b).abs() <= 1e-15 * b);
    }
    assert!(Precomputed::new(&m, &rho[1..]).is_err());
}

#[test]
fn dm_inverse_and_rest_volumes() {
    let m = kuhn_grid(&KuhnSpec::benchmark(12, 4, 4), LengthUnit::Millimetre).unwrap();
    let p = Precomputed::with_uniform_density(&m, 1.0).unwrap();
    for e in 0..m.tets.len() {
        let x = m.tet_points(e);
        let dm: Vec<[f64; 3]> = (1..4)
            .map(|c| [x[c][0] - x[0][0], x[c][1] - x[0][1], x[c][2] - x[0][2]])
            .collect();
        // (Dm⁻¹ · Dm)_ij = Σ_k inv[i][k] · Dm[k][j], Dm[k][j] = column j component k.
        for i in 0..3 {
            for j in 0..3 {
                let s: f64 = (0..3).map(|k| p.dm_inv[e][i][k] * dm[j][k]).sum();
                let id = if i == j { 1.0 } else { 0.0 };
                assert!((s - id).abs() < 1e-9, "tet {e}: ({i},{j}) = {s}");
            }
        }
        assert_eq!(p.rest_volume[e], m.tet_volume(e));
    }
}

#[test]
fn csr_adjacency_is_consistent_and_ordered() {
    let m = kuhn_grid(&KuhnSpec::benchmark(42, 7, 7), LengthUnit::Millimetre).unwrap();
    let p = Precomputed::with_uniform_density(&m, 1.0).unwrap();
    let csr = &p.node_elements;
    assert_eq!(csr.offsets.len(), m.nodes.len() + 1);
    assert_eq!(csr.entries.len(), 4 * m.tets.len());
    let mut seen = 0;
    for n in 0..m.nodes.len() {
        let list = csr.of(n);
        assert!(!list.is_empty());
        for w in list.windows(2) {
            assert!(w[0] < w[1], "sorted by (element, corner)");
        }
        for &(e, c) in list {
            assert_eq!(m.tets[e as usize][c as usize] as usize, n);
            seen += 1;
        }
    }
    assert_eq!(seen, 4 * m.tets.len());
}

#[test]
fn edges_and_surfaces() {
    let m = kuhn_grid(&KuhnSpec::benchmark(12, 4, 4), LengthUnit::Millimetre).unwrap();
    let p = Precomputed::with_uniform_density(&m, 1.0).unwrap();
    // Euler characteristic of a solid with one cavity: V − E + F − T = χ = 2 (ball minus ball:
    // χ = 1 − (−1)... for a 3-manifold with boundary, χ = χ(∂M)/2 = (2 + 2)/2 = 2).
    let nf = {
        let mut f: Vec<[u32; 3]> = Vec::new();
        for t in &m.tets {
            for l in softc::mesh::model::TET_FACES {
                let mut k = [t[l[0]], t[l[1]], t[l[2]]];
                k.sort_unstable();
                f.push(k);
            }
        }
        f.sort_unstable();
        f.dedup();
        f.len() as i64
    };
    let chi = m.nodes.len() as i64 - p.edges.len() as i64 + nf - m.tets.len() as i64;
    assert_eq!(chi, 2);
    for w in p.edges.windows(2) {
        assert!(w[0].nodes < w[1].nodes);
    }
    // Each tet contributes its volume to its 6 edges.
    let sum: f64 = p.edges.iter().map(|e| e.volume).sum();
    assert!((sum - 6.0 * m.total_volume()).abs() < 1e-12 * sum);
    for e in &p.edges {
        let a = m.nodes[e.nodes[0] as usize];
        let b = m.nodes[e.nodes[1] as usize];
        let l = ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt();
        assert_eq!(e.rest_length, l);
    }
    let cav = p.surface(CAVITY_TAG).unwrap();
    assert!(cav.chamber);
    assert_eq!(cav.name.as_deref(), Some("cavity"));
    assert_eq!(cav.tris, m.surface(CAVITY_TAG));
    assert!(!p.surface(10).unwrap().chamber);
}

#[test]
fn min_altitude_is_the_shortest_height() {
    // Corner tet of the unit cube: the height over the slanted face is 1/√3.
    let m = softc::mesh::Mesh::from_tets(
        vec![
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [0.0, 0.0, 1.0],
        ],
        vec![[0, 1, 2, 3]],
    );
    let p = Precomputed::with_uniform_density(&m, 1.0).unwrap();
    assert!((p.min_altitude[0] - 1.0 / 3f64.sqrt()).abs() < 1e-15);
    let m = kuhn_grid(&KuhnSpec::benchmark(12, 4, 4), LengthUnit::Millimetre).unwrap();
    let p = Precomputed::with_uniform_density(&m, 1.0).unwrap();
    let p2 = Precomputed::with_uniform_density(&m, 1.0).unwrap();
    assert_eq!(p, p2, "deterministic");
    for e in 0..m.tets.len() {
        let x = m.tet_points(e);
        let shortest = softc::mesh::model::TET_EDGES
            .iter()
            .map(|ed| {
                let d = [0, 1, 2].map(|k| x[ed[0]][k] - x[ed[1]][k]);
                (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt()
            })
            .fold(f64::INFINITY, f64::min);
        assert!(p.min_altitude[e] > 0.0 && p.min_altitude[e] <= shortest);
    }
}
