//! `stretch(e)` in the loss (SPEC §7): the largest principal stretch of element e, from its
//! corners' current positions (the uniforms `state.x.N.d` the host fills, as `x[n]` reads them)
//! and its rest shape (constants), so that a loss can hold a strain limit
//! (`sum(e in walls) max(stretch(e) - 1.3, 0)^2`) and be differentiated like the rest of it.
//!
//! F = Ds·Dm⁻¹ (Dm, Ds the rest and current edge matrices of the corners), C = FᵀF, and the
//! stretch is √λ with λ the largest root of C's characteristic polynomial
//! p(λ) = λ³ − I₁λ² + I₂λ − I₃. Newton on p starts at the upper bound
//! λ₀ = I₁/3 + √(2/3)·‖dev C‖ (the largest eigenvalue of a traceless symmetric matrix is at
//! most √(2/3) times its norm; equality when the two others are equal, as in uniaxial
//! stretch), right of the largest root, where p is increasing and convex: the iterates
//! decrease monotonically onto it. A quadratic element's stretch is its corners' (the linear
//! part of its motion).

use super::LowerError;
use crate::ir::{BinOp, CmpOp, KernelBuilder, UnOp, V};

/// Newton iterations on the characteristic polynomial (unrolled in the loss's IR).
pub const NEWTON_ITERATIONS: usize = 8;

/// The largest principal stretch of the tet whose corners are `corners` (node indices) at
/// rest positions `rest`.
pub fn largest_stretch(
    k: &mut KernelBuilder,
    corners: [u32; 4],
    rest: [[f64; 3]; 4],
) -> Result<V, LowerError> {
    let dm: [[f64; 3]; 3] =
        std::array::from_fn(|r| std::array::from_fn(|c| rest[c + 1][r] - rest[0][r]));
    let inv = inverse(dm).ok_or_else(|| {
        LowerError::new(format!(
            "`stretch`: the element with corners {corners:?} has no volume at rest"
        ))
    })?;
    let x: Vec<[V; 3]> = corners
        .iter()
        .map(|n| [0, 1, 2].map(|d| k.uniform(&format!("state.x.{n}.{d}"))))
        .collect();
    let b = &mut k.b;
    let ds: [[V; 3]; 3] =
        std::array::from_fn(|r| std::array::from_fn(|c| b.sub(x[c + 1][r], x[0][r])));
    // F = Ds·Dm⁻¹.
    let f: [[V; 3]; 3] = std::array::from_fn(|r| {
        std::array::from_fn(|c| {
            let terms: Vec<V> = (0..3).map(|m| b.scale(inv[m][c], ds[r][m])).collect();
            b.sum(&terms)
        })
    });
    // C = FᵀF (symmetric: the upper triangle).
    let mut cm = [[b.constant(0.0); 3]; 3];
    for i in 0..3 {
        for j in i..3 {
            let terms: Vec<V> = (0..3).map(|a| b.mul(f[a][i], f[a][j])).collect();
            cm[i][j] = b.sum(&terms);
            cm[j][i] = cm[i][j];
        }
    }
    let i1 = b.sum(&[cm[0][0], cm[1][1], cm[2][2]]);
    let minor = |b: &mut crate::ir::Builder, i: usize, j: usize| {
        let d = b.mul(cm[i][i], cm[j][j]);
        let o = b.mul(cm[i][j], cm[i][j]);
        b.sub(d, o)
    };
    let m01 = minor(b, 0, 1);
    let m12 = minor(b, 1, 2);
    let m02 = minor(b, 0, 2);
    let i2 = b.sum(&[m01, m12, m02]);
    // det C along the first row.
    let c12 = {
        let p = b.mul(cm[1][0], cm[2][2]);
        let q = b.mul(cm[1][2], cm[2][0]);
        b.sub(p, q)
    };
    let c13 = {
        let p = b.mul(cm[1][0], cm[2][1]);
        let q = b.mul(cm[1][1], cm[2][0]);
        b.sub(p, q)
    };
    let t0 = b.mul(cm[0][0], m12);
    let t1 = b.mul(cm[0][1], c12);
    let t2 = b.mul(cm[0][2], c13);
    let i3 = b.sub(t0, t1);
    let i3 = b.add(i3, t2);
    // ‖dev C‖² = tr(C²) − I₁²/3, tr(C²) = I₁² − 2 I₂.
    let i1_sq = b.mul(i1, i1);
    let two_i2 = b.scale(2.0, i2);
    let tr_c2 = b.sub(i1_sq, two_i2);
    let third = b.scale(1.0 / 3.0, i1_sq);
    let dev2 = b.sub(tr_c2, third);
    let zero = b.constant(0.0);
    let dev2 = b.bin(BinOp::Max, dev2, zero);
    let dev = b.un(UnOp::Sqrt, dev2);
    let spread = b.scale((2.0f64 / 3.0).sqrt(), dev);
    let mean = b.scale(1.0 / 3.0, i1);
    let mut lambda = b.add(mean, spread);
    let tiny = b.constant(1e-30);
    for _ in 0..NEWTON_ITERATIONS {
        // p and p' by Horner.
        let p = b.sub(lambda, i1);
        let p = b.mul(p, lambda);
        let p = b.add(p, i2);
        let p = b.mul(p, lambda);
        let p = b.sub(p, i3);
        let dp = b.scale(3.0, lambda);
        let two_i1 = b.scale(2.0, i1);
        let dp = b.sub(dp, two_i1);
        let dp = b.mul(dp, lambda);
        let dp = b.add(dp, i2);
        // At a triple root (rest, or pure dilation) the start is the root and p' = 0: stay.
        let steep = b.cmp(CmpOp::Gt, dp, tiny);
        let safe = b.select(steep, dp, tiny);
        let step = b.div(p, safe);
        let step = b.select(steep, step, zero);
        lambda = b.sub(lambda, step);
    }
    Ok(b.un(UnOp::Sqrt, lambda))
}

/// The inverse of a 3×3 matrix, or `None` where it is singular.
fn inverse(m: [[f64; 3]; 3]) -> Option<[[f64; 3]; 3]> {
    let cof = |r: usize, c: usize| {
        let (r1, r2) = ((r + 1) % 3, (r + 2) % 3);
        let (c1, c2) = ((c + 1) % 3, (c + 2) % 3);
        m[r1][c1] * m[r2][c2] - m[r1][c2] * m[r2][c1]
    };
    let det = m[0][0] * cof(0, 0) + m[0][1] * cof(0, 1) + m[0][2] * cof(0, 2);
    let scale = m.iter().flatten().fold(0.0f64, |a, x| a.max(x.abs()));
    // Also refuses a NaN determinant.
    if det.abs().partial_cmp(&(1e-12 * scale.powi(3))) != Some(std::cmp::Ordering::Greater) {
        return None;
    }
    Some(std::array::from_fn(|r| {
        std::array::from_fn(|c| cof(c, r) / det)
    }))
}

#[cfg(test)]
mod tests {
    use super::inverse;

    #[test]
    fn inverse_of_a_rest_shape() {
        let m = [[2.0, 0.5, 0.0], [0.0, 1.0, 0.3], [0.1, 0.0, 3.0]];
        let inv = inverse(m).unwrap();
        for (r, row) in m.iter().enumerate() {
            for c in 0..3 {
                let e: f64 = row.iter().zip(&inv).map(|(a, i)| a * i[c]).sum();
                assert!((e - if r == c { 1.0 } else { 0.0 }).abs() < 1e-14);
            }
        }
        assert!(inverse([[1.0, 2.0, 3.0], [2.0, 4.0, 6.0], [0.0, 0.0, 1.0]]).is_none());
    }
}
