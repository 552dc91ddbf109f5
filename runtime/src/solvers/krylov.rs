//! Restarted GMRES with right preconditioning: the linear solver of a matrix-free Newton–Krylov
//! solve, where the matrix is known only through its products with vectors (kernels of the
//! compiled scene, run on whatever device holds the state).
//!
//! GMRES rather than CG because the follower-pressure part of a tangent stiffness is not
//! symmetric, and near a limit point the matrix is not definite either; right preconditioning
//! so the residual it minimises is the true one. The Arnoldi basis is orthogonalised by
//! modified Gram–Schmidt and the least-squares problem reduced by Givens rotations. Every sum
//! runs in a fixed order, so a solve is as reproducible as the products it is given.

/// How a solve went.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct KrylovStats {
    /// Products with the matrix (one per iteration, plus one per restart).
    pub products: usize,
    pub iterations: usize,
    /// ‖b − A x‖ / ‖b‖ at the end (computed, not estimated).
    pub relative_residual: f64,
    pub converged: bool,
}

/// Limits of a solve.
#[derive(Clone, Copy, Debug)]
pub struct KrylovLimits {
    /// Stop when ‖b − A x‖ ≤ `rtol`·‖b‖.
    pub rtol: f64,
    /// Basis vectors before a restart.
    pub restart: usize,
    /// Iterations in all.
    pub max_iterations: usize,
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

fn norm(a: &[f64]) -> f64 {
    dot(a, a).sqrt()
}

/// Solve A x = b from x = 0, where `apply(v)` is A v and `precondition(v)` applies an
/// approximate inverse M⁻¹ (the method solves A M⁻¹ y = b, x = M⁻¹ y). An error of `apply`
/// ends the solve. The result is the best iterate found even when the tolerance was not met
/// (`converged` says which).
pub fn gmres(
    b: &[f64],
    mut apply: impl FnMut(&[f64]) -> Result<Vec<f64>, String>,
    precondition: impl Fn(&[f64]) -> Vec<f64>,
    limits: KrylovLimits,
) -> Result<(Vec<f64>, KrylovStats), String> {
    let n = b.len();
    let mut x = vec![0.0; n];
    let b_norm = norm(b);
    let mut stats = KrylovStats::default();
    if b_norm == 0.0 {
        stats.converged = true;
        return Ok((x, stats));
    }
    let target = limits.rtol * b_norm;
    let m = limits.restart.max(1);
    let mut r = b.to_vec();
    let mut r_norm = b_norm;
    while stats.iterations < limits.max_iterations {
        let mut basis: Vec<Vec<f64>> = vec![r.iter().map(|v| v / r_norm).collect()];
        // Hessenberg columns (each j + 2 long), the rotations, and the rotated right-hand side.
        let mut h: Vec<Vec<f64>> = Vec::with_capacity(m);
        let (mut cs, mut sn): (Vec<f64>, Vec<f64>) = (Vec::with_capacity(m), Vec::with_capacity(m));
        let mut g = vec![r_norm];
        for j in 0..m {
            if stats.iterations >= limits.max_iterations {
                break;
            }
            stats.iterations += 1;
            stats.products += 1;
            let mut w = apply(&precondition(&basis[j]))?;
            let mut col = Vec::with_capacity(j + 2);
            for v in &basis {
                let hij = dot(&w, v);
                for (wi, vi) in w.iter_mut().zip(v) {
                    *wi -= hij * vi;
                }
                col.push(hij);
            }
            let w_norm = norm(&w);
            col.push(w_norm);
            for i in 0..j {
                let (a, c) = (col[i], col[i + 1]);
                col[i] = cs[i] * a + sn[i] * c;
                col[i + 1] = -sn[i] * a + cs[i] * c;
            }
            let (a, c) = (col[j], col[j + 1]);
            let d = a.hypot(c);
            let (cj, sj) = if d == 0.0 { (1.0, 0.0) } else { (a / d, c / d) };
            col[j] = d;
            col[j + 1] = 0.0;
            cs.push(cj);
            sn.push(sj);
            let gj = g[j];
            g[j] = cj * gj;
            g.push(-sj * gj);
            h.push(col);
            let breakdown = w_norm <= 1e-14 * r_norm;
            if g[j + 1].abs() <= target || breakdown {
                break;
            }
            basis.push(w.iter().map(|v| v / w_norm).collect());
        }
        // y = H⁻¹ g (upper triangular), x += M⁻¹ (V y).
        let k = h.len();
        let mut y = vec![0.0; k];
        for i in (0..k).rev() {
            let mut s = g[i];
            for (l, yl) in y.iter().enumerate().take(k).skip(i + 1) {
                s -= h[l][i] * yl;
            }
            y[i] = if h[i][i] != 0.0 { s / h[i][i] } else { 0.0 };
        }
        let mut update = vec![0.0; n];
        for (v, yi) in basis.iter().zip(&y) {
            for (u, vi) in update.iter_mut().zip(v) {
                *u += yi * vi;
            }
        }
        for (xi, u) in x.iter_mut().zip(precondition(&update)) {
            *xi += u;
        }
        // The true residual (the recurrence's estimate drifts in finite precision).
        stats.products += 1;
        let ax = apply(&x)?;
        r = b.iter().zip(&ax).map(|(bi, ai)| bi - ai).collect();
        let new_norm = norm(&r);
        let stalled = new_norm >= r_norm;
        r_norm = new_norm;
        if r_norm <= target || stalled || !r_norm.is_finite() {
            break;
        }
    }
    stats.relative_residual = r_norm / b_norm;
    stats.converged = r_norm <= target;
    Ok((x, stats))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A non-symmetric, diagonally dominant tridiagonal matrix.
    fn matrix(n: usize) -> Vec<Vec<f64>> {
        let mut a = vec![vec![0.0; n]; n];
        for i in 0..n {
            a[i][i] = 4.0 + (i % 3) as f64;
            if i + 1 < n {
                a[i][i + 1] = -1.5;
                a[i + 1][i] = -0.5;
            }
        }
        a
    }

    fn mul(a: &[Vec<f64>], v: &[f64]) -> Vec<f64> {
        a.iter().map(|row| dot(row, v)).collect()
    }

    #[test]
    fn solves_a_nonsymmetric_system_across_restarts() {
        let n = 60;
        let a = matrix(n);
        let x_true: Vec<f64> = (0..n).map(|i| ((i * 7 % 11) as f64) - 5.0).collect();
        let b = mul(&a, &x_true);
        let jacobi: Vec<f64> = (0..n).map(|i| 1.0 / a[i][i]).collect();
        let limits = KrylovLimits {
            rtol: 1e-12,
            restart: 5,
            max_iterations: 500,
        };
        let (x, stats) = gmres(
            &b,
            |v| Ok(mul(&a, v)),
            |v| v.iter().zip(&jacobi).map(|(a, b)| a * b).collect(),
            limits,
        )
        .unwrap();
        assert!(stats.converged, "{stats:?}");
        assert!(stats.iterations > 5, "needed restarts: {stats:?}");
        let err = x
            .iter()
            .zip(&x_true)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        assert!(err < 1e-10, "{err}");
        // Reproducible: the same solve gives the same bits.
        let (again, _) = gmres(&b, |v| Ok(mul(&a, v)), |v| v.to_vec(), limits).unwrap();
        let (twice, _) = gmres(&b, |v| Ok(mul(&a, v)), |v| v.to_vec(), limits).unwrap();
        assert_eq!(again, twice);
    }

    #[test]
    fn reports_a_solve_that_runs_out_of_iterations() {
        let n = 40;
        let a = matrix(n);
        let b = vec![1.0; n];
        let limits = KrylovLimits {
            rtol: 1e-14,
            restart: 3,
            max_iterations: 4,
        };
        let (_, stats) = gmres(&b, |v| Ok(mul(&a, v)), |v| v.to_vec(), limits).unwrap();
        assert!(!stats.converged);
        assert!(stats.relative_residual < 1.0, "{stats:?}");
        assert_eq!(stats.iterations, 4);
    }

    #[test]
    fn a_product_error_ends_the_solve() {
        let b = vec![1.0; 4];
        let limits = KrylovLimits {
            rtol: 1e-10,
            restart: 3,
            max_iterations: 10,
        };
        let err = gmres(&b, |_| Err("device lost".into()), |v| v.to_vec(), limits).unwrap_err();
        assert_eq!(err, "device lost");
    }
}
