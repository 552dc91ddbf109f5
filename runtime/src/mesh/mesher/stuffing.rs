//! Isosurface stuffing (Labelle & Shewchuk, SIGGRAPH 2007) on a body-centred cubic lattice.
//!
//! The lattice holds the corners of a cubic grid of spacing `h` and the cube centres. Its
//! tets each join two axis-adjacent cube centres with one edge of the square face they share
//! (4 per face, 12 per cube). Lattice vertices closer to the surface than `α·edge` along a
//! crossing edge are warped onto the surface (α = 0.24999 on the axis-parallel "long" edges of
//! length h, α = 0.41189 on the "short" diagonal edges of length √3/2·h, the paper's values).
//! Each lattice tet is then clipped to the inside with stencils: whole tet, one tet, a
//! pyramid (two tets) or a prism (three tets). Quadrilaterals shared by neighbouring tets are
//! split along the diagonal through their smallest-id vertex, which keeps the mesh conforming
//! and always yields a valid prism split.
//!
//! Difference from the paper: it chooses quad diagonals by a parity rule on the lattice's
//! edge colours to prove the dihedral bounds [10.7°, 164.8°]; softc uses the smallest-id rule,
//! so those bounds are not guaranteed here; the angles actually reached are measured and
//! reported (see the tests and `softc mesh info`).

use std::collections::HashMap;

/// Warp threshold on long (axis-parallel, length h) lattice edges.
pub const ALPHA_LONG: f64 = 0.24999;
/// Warp threshold on short (diagonal, length √3/2·h) lattice edges.
pub const ALPHA_SHORT: f64 = 0.41189;

/// Receives each output tet with the current node list and the tet list.
type Emit<'a> = dyn FnMut([u32; 4], &[[f64; 3]], &mut Vec<[u32; 4]>) + 'a;

/// Output of stuffing: nodes and positively oriented tets in the input units.
pub struct Stuffed {
    pub nodes: Vec<[f64; 3]>,
    pub tets: Vec<[u32; 4]>,
}

struct Lattice {
    n: [usize; 3],
    origin: [f64; 3],
    h: f64,
}

impl Lattice {
    fn ncorners(&self) -> usize {
        (self.n[0] + 1) * (self.n[1] + 1) * (self.n[2] + 1)
    }
    fn corner(&self, i: usize, j: usize, k: usize) -> u32 {
        (i + (self.n[0] + 1) * (j + (self.n[1] + 1) * k)) as u32
    }
    fn center(&self, i: usize, j: usize, k: usize) -> u32 {
        (self.ncorners() + i + self.n[0] * (j + self.n[1] * k)) as u32
    }
    fn position(&self, v: u32) -> [f64; 3] {
        let v = v as usize;
        let nc = self.ncorners();
        if v < nc {
            let i = v % (self.n[0] + 1);
            let j = (v / (self.n[0] + 1)) % (self.n[1] + 1);
            let k = v / ((self.n[0] + 1) * (self.n[1] + 1));
            [
                self.origin[0] + i as f64 * self.h,
                self.origin[1] + j as f64 * self.h,
                self.origin[2] + k as f64 * self.h,
            ]
        } else {
            let c = v - nc;
            let i = c % self.n[0];
            let j = (c / self.n[0]) % self.n[1];
            let k = c / (self.n[0] * self.n[1]);
            [
                self.origin[0] + (i as f64 + 0.5) * self.h,
                self.origin[1] + (j as f64 + 0.5) * self.h,
                self.origin[2] + (k as f64 + 0.5) * self.h,
            ]
        }
    }
}

/// Root of `f` on the segment `a` (f<0) → `b` (f>0) by the Illinois method.
fn root(f: &dyn Fn([f64; 3]) -> f64, a: [f64; 3], fa: f64, b: [f64; 3], fb: f64, tol: f64) -> f64 {
    let (mut t0, mut f0, mut t1, mut f1) = (0.0f64, fa, 1.0f64, fb);
    let mut side = 0;
    let mut t = 0.5;
    let len = super::super::model::norm(super::super::model::sub(b, a));
    for _ in 0..60 {
        t = (t0 * f1 - t1 * f0) / (f1 - f0);
        if !t.is_finite() {
            t = 0.5 * (t0 + t1);
        }
        let p = [
            a[0] + t * (b[0] - a[0]),
            a[1] + t * (b[1] - a[1]),
            a[2] + t * (b[2] - a[2]),
        ];
        let ft = f(p);
        if ft.abs() < tol || (t1 - t0) * len < tol {
            break;
        }
        if ft < 0.0 {
            t0 = t;
            f0 = ft;
            if side == -1 {
                f1 *= 0.5;
            }
            side = -1;
        } else {
            t1 = t;
            f1 = ft;
            if side == 1 {
                f0 *= 0.5;
            }
            side = 1;
        }
    }
    t.clamp(0.0, 1.0)
}

/// Stuff the domain `{p : f(p) < 0}` inside the box `[lo, hi]` with lattice spacing `h`. The
/// lattice corners start at `lo − h`, so box faces at `lo + k·h` coincide with lattice planes.
pub fn stuff(f: &dyn Fn([f64; 3]) -> f64, lo: [f64; 3], hi: [f64; 3], h: f64) -> Stuffed {
    let mut n = [0usize; 3];
    for k in 0..3 {
        n[k] = ((hi[k] - lo[k]) / h - 1e-9).ceil().max(1.0) as usize + 2;
    }
    let lat = Lattice {
        n,
        origin: [lo[0] - h, lo[1] - h, lo[2] - h],
        h,
    };
    let nv = lat.ncorners() + n[0] * n[1] * n[2];
    let mut pos: Vec<[f64; 3]> = (0..nv as u32).map(|v| lat.position(v)).collect();
    let mut val: Vec<f64> = pos.iter().map(|p| f(*p)).collect();
    let tol = 1e-10 * h;
    for v in val.iter_mut() {
        if v.abs() < tol {
            *v = 0.0;
        }
    }
    // Lattice edges: long (corner–corner, centre–centre along axes) and short (centre–corner).
    let mut edges: Vec<(u32, u32, bool)> = Vec::new();
    for k in 0..=n[2] {
        for j in 0..=n[1] {
            for i in 0..=n[0] {
                let v = lat.corner(i, j, k);
                if i < n[0] {
                    edges.push((v, lat.corner(i + 1, j, k), true));
                }
                if j < n[1] {
                    edges.push((v, lat.corner(i, j + 1, k), true));
                }
                if k < n[2] {
                    edges.push((v, lat.corner(i, j, k + 1), true));
                }
                if i < n[0] && j < n[1] && k < n[2] {
                    let c = lat.center(i, j, k);
                    if i + 1 < n[0] {
                        edges.push((c, lat.center(i + 1, j, k), true));
                    }
                    if j + 1 < n[1] {
                        edges.push((c, lat.center(i, j + 1, k), true));
                    }
                    if k + 1 < n[2] {
                        edges.push((c, lat.center(i, j, k + 1), true));
                    }
                    for d in 0..8 {
                        edges.push((
                            c,
                            lat.corner(i + (d & 1), j + ((d >> 1) & 1), k + ((d >> 2) & 1)),
                            false,
                        ));
                    }
                }
            }
        }
    }
    // Warping: each violated vertex moves to its closest violating cut point.
    let mut warp: Vec<Option<(f64, [f64; 3])>> = vec![None; nv];
    for &(u, w, long) in &edges {
        let (fu, fw) = (val[u as usize], val[w as usize]);
        if !((fu < 0.0 && fw > 0.0) || (fu > 0.0 && fw < 0.0)) {
            continue;
        }
        let (a, fa, b, fb, a_is_u) = if fu < 0.0 {
            (pos[u as usize], fu, pos[w as usize], fw, true)
        } else {
            (pos[w as usize], fw, pos[u as usize], fu, false)
        };
        let t = root(f, a, fa, b, fb, tol);
        let c = [
            a[0] + t * (b[0] - a[0]),
            a[1] + t * (b[1] - a[1]),
            a[2] + t * (b[2] - a[2]),
        ];
        let alpha = if long { ALPHA_LONG } else { ALPHA_SHORT };
        // Distance from u along the edge, as a fraction.
        let tu = if a_is_u { t } else { 1.0 - t };
        for (v, frac) in [(u, tu), (w, 1.0 - tu)] {
            if frac < alpha {
                let slot = &mut warp[v as usize];
                if slot.is_none_or(|(d, _)| frac < d) {
                    *slot = Some((frac, c));
                }
            }
        }
    }
    for v in 0..nv {
        if let Some((_, c)) = warp[v] {
            pos[v] = c;
            val[v] = 0.0;
        }
    }
    // Stencils.
    let mut out_nodes: Vec<[f64; 3]> = Vec::new();
    let mut lattice_id: Vec<u32> = vec![u32::MAX; nv];
    let mut cut_id: HashMap<(u32, u32), u32> = HashMap::new();
    let mut tets: Vec<[u32; 4]> = Vec::new();
    let mut get_v = |v: u32, out_nodes: &mut Vec<[f64; 3]>| -> u32 {
        let s = &mut lattice_id[v as usize];
        if *s == u32::MAX {
            *s = out_nodes.len() as u32;
            out_nodes.push(pos[v as usize]);
        }
        *s
    };
    let mut emit = |t: [u32; 4], nodes: &[[f64; 3]], tets: &mut Vec<[u32; 4]>| {
        let p = t.map(|i| nodes[i as usize]);
        let v = super::super::model::signed_volume(p);
        if v > 0.0 {
            tets.push(t);
        } else if v < 0.0 {
            tets.push([t[0], t[1], t[3], t[2]]);
        } else {
            // Exactly flat: keep it (removing it would open a crack); validation flags it.
            tets.push(t);
        }
    };
    for k in 0..n[2] {
        for j in 0..n[1] {
            for i in 0..n[0] {
                let c1 = lat.center(i, j, k);
                for a in 0..3 {
                    let mut d = [i, j, k];
                    d[a] += 1;
                    if d[a] >= n[a] {
                        continue;
                    }
                    let c2 = lat.center(d[0], d[1], d[2]);
                    // The shared face is at corner plane d[a] along axis a.
                    let (u, w) = ((a + 1) % 3, (a + 2) % 3);
                    let corner = |du: usize, dw: usize| {
                        let mut q = d;
                        q[u] += du;
                        q[w] += dw;
                        lat.corner(q[0], q[1], q[2])
                    };
                    let sq = [corner(0, 0), corner(1, 0), corner(1, 1), corner(0, 1)];
                    for e in 0..4 {
                        let tet = [c1, c2, sq[e], sq[(e + 1) % 4]];
                        stencil(
                            tet,
                            f,
                            &pos,
                            &val,
                            tol,
                            &mut out_nodes,
                            &mut get_v,
                            &mut cut_id,
                            &mut tets,
                            &mut emit,
                        );
                    }
                }
            }
        }
    }
    Stuffed {
        nodes: out_nodes,
        tets,
    }
}

#[allow(clippy::too_many_arguments)]
fn stencil(
    tet: [u32; 4],
    f: &dyn Fn([f64; 3]) -> f64,
    pos: &[[f64; 3]],
    val: &[f64],
    tol: f64,
    out: &mut Vec<[f64; 3]>,
    get_v: &mut dyn FnMut(u32, &mut Vec<[f64; 3]>) -> u32,
    cut_id: &mut HashMap<(u32, u32), u32>,
    tets: &mut Vec<[u32; 4]>,
    emit: &mut Emit,
) {
    let mut neg = Vec::with_capacity(4);
    let mut zer = Vec::with_capacity(4);
    let mut posv = Vec::with_capacity(4);
    for &v in &tet {
        let x = val[v as usize];
        if x < 0.0 {
            neg.push(v);
        } else if x > 0.0 {
            posv.push(v);
        } else {
            zer.push(v);
        }
    }
    if neg.is_empty() {
        if zer.len() == 4 {
            let c = centroid(tet.map(|v| pos[v as usize]));
            if f(c) < 0.0 {
                let t = tet.map(|v| get_v(v, out));
                emit(t, out, tets);
            }
        }
        return;
    }
    if posv.is_empty() {
        let t = tet.map(|v| get_v(v, out));
        emit(t, out, tets);
        return;
    }
    let mut cut = |a: u32, b: u32, out: &mut Vec<[f64; 3]>| -> u32 {
        let key = (a.min(b), a.max(b));
        if let Some(&id) = cut_id.get(&key) {
            return id;
        }
        // a inside (f<0), b outside.
        let (pa, pb) = (pos[a as usize], pos[b as usize]);
        let t = root(f, pa, val[a as usize], pb, val[b as usize], tol);
        let id = out.len() as u32;
        out.push([
            pa[0] + t * (pb[0] - pa[0]),
            pa[1] + t * (pb[1] - pa[1]),
            pa[2] + t * (pb[2] - pa[2]),
        ]);
        cut_id.insert(key, id);
        id
    };
    match (neg.len(), zer.len(), posv.len()) {
        (1, _, _) => {
            let a = get_v(neg[0], out);
            let mut t = vec![a];
            for &z in &zer {
                t.push(get_v(z, out));
            }
            for &p in &posv {
                t.push(cut(neg[0], p, out));
            }
            emit([t[0], t[1], t[2], t[3]], out, tets);
        }
        (2, 1, 1) => {
            let a = get_v(neg[0], out);
            let b = get_v(neg[1], out);
            let z = get_v(zer[0], out);
            let ca = cut(neg[0], posv[0], out);
            let cb = cut(neg[1], posv[0], out);
            // Quad (a, b, cb, ca); apex z.
            let m = a.min(b).min(ca).min(cb);
            if m == a || m == cb {
                emit([a, b, cb, z], out, tets);
                emit([a, cb, ca, z], out, tets);
            } else {
                emit([a, b, ca, z], out, tets);
                emit([b, cb, ca, z], out, tets);
            }
        }
        (2, 0, 2) => {
            let a = get_v(neg[0], out);
            let b = get_v(neg[1], out);
            let cap = cut(neg[0], posv[0], out);
            let caq = cut(neg[0], posv[1], out);
            let cbp = cut(neg[1], posv[0], out);
            let cbq = cut(neg[1], posv[1], out);
            prism([a, cap, caq, b, cbp, cbq], out, tets, emit);
        }
        (3, 0, 1) => {
            let a = get_v(neg[0], out);
            let b = get_v(neg[1], out);
            let c = get_v(neg[2], out);
            let ca = cut(neg[0], posv[0], out);
            let cb = cut(neg[1], posv[0], out);
            let cc = cut(neg[2], posv[0], out);
            prism([a, b, c, ca, cb, cc], out, tets, emit);
        }
        _ => unreachable!("sign pattern covered above"),
    }
}

fn centroid(p: [[f64; 3]; 4]) -> [f64; 3] {
    let mut c = [0.0; 3];
    for q in p {
        for k in 0..3 {
            c[k] += 0.25 * q[k];
        }
    }
    c
}

/// Split the prism with triangles (v0,v1,v2), (v3,v4,v5) (v_i joined to v_{i+3}) into three
/// tets, every quad split along the diagonal through its smallest vertex id.
fn prism(v: [u32; 6], out: &[[f64; 3]], tets: &mut Vec<[u32; 4]>, emit: &mut Emit) {
    let mi = (0..6).min_by_key(|&i| v[i]).unwrap_or(0);
    // Bring the minimum to position 0 (swap top/bottom, then rotate).
    let mut w = if mi >= 3 {
        [v[3], v[4], v[5], v[0], v[1], v[2]]
    } else {
        v
    };
    let r = mi % 3;
    w = [
        w[r],
        w[(r + 1) % 3],
        w[(r + 2) % 3],
        w[3 + r],
        w[3 + (r + 1) % 3],
        w[3 + (r + 2) % 3],
    ];
    let m = w[1].min(w[2]).min(w[4]).min(w[5]);
    if m == w[1] || m == w[5] {
        emit([w[0], w[1], w[2], w[5]], out, tets);
        emit([w[0], w[1], w[5], w[4]], out, tets);
        emit([w[0], w[4], w[5], w[3]], out, tets);
    } else {
        emit([w[0], w[1], w[2], w[4]], out, tets);
        emit([w[0], w[4], w[2], w[5]], out, tets);
        emit([w[0], w[4], w[5], w[3]], out, tets);
    }
}
