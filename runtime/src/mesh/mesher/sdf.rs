//! Signed distance functions (negative inside) of the mesher's shapes.

use crate::mesh::model::{cross, dot, norm, sub};

/// A closed shape with a signed distance (negative inside), in file units.
#[derive(Debug, Clone)]
pub enum Shape {
    Box {
        min: [f64; 3],
        max: [f64; 3],
    },
    /// Capped cylinder from `a` to `b` with radius `r`.
    Cylinder {
        a: [f64; 3],
        b: [f64; 3],
        r: f64,
    },
    /// Sphere of centre `c` and radius `r`.
    Sphere {
        c: [f64; 3],
        r: f64,
    },
    /// A closed triangle surface (e.g. from STL).
    Surface(TriSurface),
    /// A prism: the simple polygon `outline` in the plane across `axis` (its points' two other
    /// coordinates in x, y, z order: (y, z) for x, (x, z) for y, (x, y) for z), extruded from
    /// `span[0]` to `span[1]` along the axis. Any polygon: a U-shaped gripper's palm and
    /// fingers, a finger's side profile.
    Prism {
        axis: usize,
        span: [f64; 2],
        outline: Vec<[f64; 2]>,
    },
}

/// The two coordinates of a point across `axis`, in x, y, z order.
pub fn across(axis: usize, p: [f64; 3]) -> [f64; 2] {
    let [a, b] = across_axes(axis);
    [p[a], p[b]]
}

/// The two axes across `axis`, in x, y, z order.
pub fn across_axes(axis: usize) -> [usize; 2] {
    match axis {
        0 => [1, 2],
        1 => [0, 2],
        _ => [0, 1],
    }
}

/// Signed distance from `p` to the simple polygon `poly` in the plane (negative inside).
fn polygon_distance(poly: &[[f64; 2]], p: [f64; 2]) -> f64 {
    let mut d2 = f64::INFINITY;
    let mut inside = false;
    for i in 0..poly.len() {
        let (a, b) = (poly[i], poly[(i + 1) % poly.len()]);
        let e = [b[0] - a[0], b[1] - a[1]];
        let w = [p[0] - a[0], p[1] - a[1]];
        let t = ((w[0] * e[0] + w[1] * e[1]) / (e[0] * e[0] + e[1] * e[1])).clamp(0.0, 1.0);
        let r = [w[0] - t * e[0], w[1] - t * e[1]];
        d2 = d2.min(r[0] * r[0] + r[1] * r[1]);
        if (a[1] > p[1]) != (b[1] > p[1]) && p[0] < a[0] + (p[1] - a[1]) / (b[1] - a[1]) * e[0] {
            inside = !inside;
        }
    }
    if inside { -d2.sqrt() } else { d2.sqrt() }
}

/// Twice the signed area of a polygon (positive counter-clockwise).
pub fn twice_area(poly: &[[f64; 2]]) -> f64 {
    (0..poly.len())
        .map(|i| {
            let (a, b) = (poly[i], poly[(i + 1) % poly.len()]);
            a[0] * b[1] - b[0] * a[1]
        })
        .sum()
}

/// A closed, consistently wound triangle surface.
#[derive(Debug, Clone)]
pub struct TriSurface {
    pub verts: Vec<[f64; 3]>,
    pub tris: Vec<[u32; 3]>,
    lo: [f64; 3],
    hi: [f64; 3],
}

impl TriSurface {
    pub fn new(verts: Vec<[f64; 3]>, tris: Vec<[u32; 3]>) -> Self {
        let mut lo = [f64::INFINITY; 3];
        let mut hi = [f64::NEG_INFINITY; 3];
        for p in &verts {
            for k in 0..3 {
                lo[k] = lo[k].min(p[k]);
                hi[k] = hi[k].max(p[k]);
            }
        }
        TriSurface {
            verts,
            tris,
            lo,
            hi,
        }
    }

    /// Enclosed volume (positive for outward winding).
    pub fn volume(&self) -> f64 {
        self.tris
            .iter()
            .map(|t| {
                let (a, b, c) = (
                    self.verts[t[0] as usize],
                    self.verts[t[1] as usize],
                    self.verts[t[2] as usize],
                );
                dot(a, cross(b, c)) / 6.0
            })
            .sum()
    }

    /// Generalized winding number (≈1 inside, ≈0 outside) — robust to winding errors of the
    /// sign test, exact for closed surfaces.
    fn winding(&self, p: [f64; 3]) -> f64 {
        let mut w = 0.0;
        for t in &self.tris {
            let a = sub(self.verts[t[0] as usize], p);
            let b = sub(self.verts[t[1] as usize], p);
            let c = sub(self.verts[t[2] as usize], p);
            let (la, lb, lc) = (norm(a), norm(b), norm(c));
            let num = dot(a, cross(b, c));
            let den = la * lb * lc + dot(a, b) * lc + dot(b, c) * la + dot(c, a) * lb;
            w += 2.0 * num.atan2(den);
        }
        w / (4.0 * std::f64::consts::PI)
    }

    fn dist(&self, p: [f64; 3]) -> f64 {
        let mut best = f64::INFINITY;
        for t in &self.tris {
            let d = point_triangle_dist2(
                p,
                self.verts[t[0] as usize],
                self.verts[t[1] as usize],
                self.verts[t[2] as usize],
            );
            best = best.min(d);
        }
        let d = best.sqrt();
        if self.winding(p).abs() > 0.5 { -d } else { d }
    }
}

/// Squared distance from `p` to triangle `(a, b, c)` (Ericson, Real-Time Collision Detection
/// §5.1.5).
fn point_triangle_dist2(p: [f64; 3], a: [f64; 3], b: [f64; 3], c: [f64; 3]) -> f64 {
    let ab = sub(b, a);
    let ac = sub(c, a);
    let ap = sub(p, a);
    let d1 = dot(ab, ap);
    let d2 = dot(ac, ap);
    let closest = |q: [f64; 3]| {
        let d = sub(p, q);
        dot(d, d)
    };
    let lerp =
        |o: [f64; 3], d: [f64; 3], t: f64| [o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2]];
    if d1 <= 0.0 && d2 <= 0.0 {
        return closest(a);
    }
    let bp = sub(p, b);
    let d3 = dot(ab, bp);
    let d4 = dot(ac, bp);
    if d3 >= 0.0 && d4 <= d3 {
        return closest(b);
    }
    let vc = d1 * d4 - d3 * d2;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        return closest(lerp(a, ab, d1 / (d1 - d3)));
    }
    let cp = sub(p, c);
    let d5 = dot(ab, cp);
    let d6 = dot(ac, cp);
    if d6 >= 0.0 && d5 <= d6 {
        return closest(c);
    }
    let vb = d5 * d2 - d1 * d6;
    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        return closest(lerp(a, ac, d2 / (d2 - d6)));
    }
    let va = d3 * d6 - d5 * d4;
    if va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0 {
        return closest(lerp(b, sub(c, b), (d4 - d3) / ((d4 - d3) + (d5 - d6))));
    }
    let den = 1.0 / (va + vb + vc);
    let v = vb * den;
    let w = vc * den;
    closest([
        a[0] + ab[0] * v + ac[0] * w,
        a[1] + ab[1] * v + ac[1] * w,
        a[2] + ab[2] * v + ac[2] * w,
    ])
}

impl Shape {
    /// Signed distance, negative inside.
    pub fn sdf(&self, p: [f64; 3]) -> f64 {
        match self {
            Shape::Box { min, max } => {
                let mut q = [0.0; 3];
                for k in 0..3 {
                    let c = 0.5 * (min[k] + max[k]);
                    let e = 0.5 * (max[k] - min[k]);
                    q[k] = (p[k] - c).abs() - e;
                }
                let outside = norm([q[0].max(0.0), q[1].max(0.0), q[2].max(0.0)]);
                let inside = q[0].max(q[1]).max(q[2]).min(0.0);
                outside + inside
            }
            Shape::Cylinder { a, b, r } => {
                let ax = sub(*b, *a);
                let len = norm(ax);
                let u = [ax[0] / len, ax[1] / len, ax[2] / len];
                let ap = sub(p, *a);
                let t = dot(ap, u);
                let radial = norm(sub(ap, [u[0] * t, u[1] * t, u[2] * t]));
                let dr = radial - r;
                let da = (t - len).max(-t);
                let outside = norm([dr.max(0.0), da.max(0.0), 0.0]);
                outside + dr.max(da).min(0.0)
            }
            Shape::Sphere { c, r } => norm(sub(p, *c)) - r,
            Shape::Surface(s) => s.dist(p),
            Shape::Prism {
                axis,
                span,
                outline,
            } => {
                let dr = polygon_distance(outline, across(*axis, p));
                let da = (p[*axis] - span[1]).max(span[0] - p[*axis]);
                let outside = norm([dr.max(0.0), da.max(0.0), 0.0]);
                outside + dr.max(da).min(0.0)
            }
        }
    }

    /// Bounding box.
    pub fn bbox(&self) -> ([f64; 3], [f64; 3]) {
        match self {
            Shape::Box { min, max } => (*min, *max),
            Shape::Cylinder { a, b, r } => {
                let ax = sub(*b, *a);
                let len = norm(ax);
                let mut lo = [0.0; 3];
                let mut hi = [0.0; 3];
                for k in 0..3 {
                    // Extent of a disc of radius r with normal u along axis k: r·sqrt(1−u_k²).
                    let uk = ax[k] / len;
                    let e = r * (1.0 - uk * uk).max(0.0).sqrt();
                    lo[k] = a[k].min(b[k]) - e;
                    hi[k] = a[k].max(b[k]) + e;
                }
                (lo, hi)
            }
            Shape::Sphere { c, r } => (c.map(|x| x - r), c.map(|x| x + r)),
            Shape::Surface(s) => (s.lo, s.hi),
            Shape::Prism {
                axis,
                span,
                outline,
            } => {
                let (mut lo, mut hi) = ([span[0]; 3], [span[1]; 3]);
                for (k, &a) in across_axes(*axis).iter().enumerate() {
                    lo[a] = outline.iter().map(|q| q[k]).fold(f64::INFINITY, f64::min);
                    hi[a] = outline
                        .iter()
                        .map(|q| q[k])
                        .fold(f64::NEG_INFINITY, f64::max);
                }
                (lo, hi)
            }
        }
    }

    /// Where the mid-edge node `mid` of a boundary edge `p`–`q` belongs on this shape's exact
    /// surface: on a sphere, or on a cylinder's curved side, when both ends lie on it (within
    /// `tol`) and the edge spans at most 60° around the centre or axis (a longer edge is a
    /// chord across a face, not a piece of the curve). None for flat faces, which straight
    /// edges already follow.
    pub fn arc_point(&self, p: [f64; 3], q: [f64; 3], mid: [f64; 3], tol: f64) -> Option<[f64; 3]> {
        let close = |a: [f64; 3], b: [f64; 3]| dot(a, b) >= 0.5 * norm(a) * norm(b);
        match self {
            Shape::Sphere { c, r } => {
                let (dp, dq, dm) = (sub(p, *c), sub(q, *c), sub(mid, *c));
                let on = |d: [f64; 3]| (norm(d) - r).abs() <= tol;
                (on(dp) && on(dq) && close(dp, dq)).then(|| {
                    let k = r / norm(dm);
                    [c[0] + dm[0] * k, c[1] + dm[1] * k, c[2] + dm[2] * k]
                })
            }
            Shape::Cylinder { a, b, r } => {
                let ax = sub(*b, *a);
                let len = norm(ax);
                let u = [ax[0] / len, ax[1] / len, ax[2] / len];
                // The radial part of a point and its position along the axis.
                let radial = |x: [f64; 3]| {
                    let d = sub(x, *a);
                    let t = dot(d, u);
                    (sub(d, [u[0] * t, u[1] * t, u[2] * t]), t)
                };
                let ((rp, tp), (rq, tq), (rm, tm)) = (radial(p), radial(q), radial(mid));
                let on = |rad: [f64; 3], t: f64| {
                    (norm(rad) - r).abs() <= tol && t >= -tol && t <= len + tol
                };
                (on(rp, tp) && on(rq, tq) && close(rp, rq) && norm(rm) > 0.0).then(|| {
                    let k = r / norm(rm);
                    [0, 1, 2].map(|i| a[i] + u[i] * tm + rm[i] * k)
                })
            }
            Shape::Box { .. } | Shape::Surface(_) | Shape::Prism { .. } => None,
        }
    }

    /// Exact enclosed volume.
    pub fn volume(&self) -> f64 {
        match self {
            Shape::Box { min, max } => (0..3).map(|k| max[k] - min[k]).product(),
            Shape::Cylinder { a, b, r } => std::f64::consts::PI * r * r * norm(sub(*b, *a)),
            Shape::Sphere { r, .. } => 4.0 / 3.0 * std::f64::consts::PI * r * r * r,
            Shape::Surface(s) => s.volume(),
            Shape::Prism { span, outline, .. } => {
                0.5 * twice_area(outline).abs() * (span[1] - span[0])
            }
        }
    }
}
