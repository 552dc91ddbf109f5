//! The extruded mesher: bodies whose cross-section is constant along one axis (a cylinder or box
//! body with cylinder or box cavities parallel to it, such as a multi-chamber endoscope or a
//! bellows-free bending actuator), meshed boundary-conforming. The cross-section is triangulated
//! with every cavity outline as a constraint (constrained Delaunay with Ruppert refinement, by
//! `spade`), so walls get as many elements through them as `wall` asks, graded to `interior`
//! away from the outlines; the triangles are extruded through layers whose planes include every
//! cavity's ends, and each prism is split into three tetrahedra by the global vertex order (so
//! neighbouring prisms split a shared face the same way). Outline vertices lie on the exact
//! circles; with `order = 2` the mid-edge nodes of outline chords are put on the exact arcs too.

use spade::{
    AngleLimit, ConstrainedDelaunayTriangulation, Point2, RefinementParameters, Triangulation,
};

use super::Shape;
use crate::mesh::error::MeshError;

/// The `[extrude]` section of a spec.
#[derive(Debug, Clone, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ExtrudeSection {
    /// Edge length along every outline of the cross-section (cavity walls, the outer surface).
    pub wall: f64,
    /// Largest edge length inside the cross-section, away from the outlines (default 2·wall).
    pub interior: Option<f64>,
    /// Layer thickness along the axis (default: `interior`).
    pub layer: Option<f64>,
    /// Edge length at the corners of box cavities (default `wall`): smaller grades the
    /// outline towards the re-entrant edges, where the stress is singular.
    pub corner: Option<f64>,
    /// Layer thickness at every end plane (body and cavity ends; default `layer`): smaller
    /// grades the layers towards them.
    pub end_layer: Option<f64>,
}

/// Growth of graded pieces: each is at most this much longer than the one before.
const GROWTH: f64 = 1.3;

/// Positions subdividing [0, len]: pieces `h_end` long at both ends, growing by [`GROWTH`]
/// towards the middle up to `h_max`, the middle evenly at most `h_max`.
fn graded(len: f64, h_end: f64, h_max: f64) -> Vec<f64> {
    let mut side = Vec::new();
    let (mut at, mut h) = (0.0, h_end.min(h_max));
    while h < h_max && at + h <= 0.5 * len - 0.5 * h {
        side.push(h);
        at += h;
        h = (h * GROWTH).min(h_max);
    }
    let gap = len - 2.0 * at;
    let m = ((gap / h_max).ceil() as usize).max(1);
    let pieces = side
        .iter()
        .copied()
        .chain(std::iter::repeat_n(gap / m as f64, m))
        .chain(side.iter().rev().copied());
    let mut out = vec![0.0];
    for p in pieces {
        out.push(out.last().unwrap() + p);
    }
    *out.last_mut().unwrap() = len;
    out
}

/// A cross-section outline: a closed polygon (counter-clockwise) in the section's 2-D
/// coordinates, and the exact circle it is inscribed in (None for boxes).
struct Outline {
    points: Vec<[f64; 2]>,
    circle: Option<([f64; 2], f64)>,
    /// Extent along the axis.
    span: [f64; 2],
}

/// What the extrusion produced, in spec units.
pub struct Extruded {
    pub nodes: Vec<[f64; 3]>,
    pub tets: Vec<[u32; 4]>,
    /// Per node, the circle whose outline vertex it is (an index into `circles`), if any.
    pub on_circle: Vec<Option<u32>>,
    /// The circles: 2-D centre and radius.
    pub circles: Vec<([f64; 2], f64)>,
    /// Per node on a circle, its position along the circle's outline (which chords are arcs).
    pub circle_slot: Vec<u32>,
    /// Per circle, its outline's vertex count.
    pub circle_len: Vec<u32>,
    pub axis: usize,
}

/// The two in-section axes of extrusion axis `a`.
fn plane_axes(a: usize) -> [usize; 2] {
    [(a + 1) % 3, (a + 2) % 3]
}

/// The extrusion axis of an axis-aligned cylinder, None otherwise.
fn cylinder_axis(a: [f64; 3], b: [f64; 3]) -> Option<usize> {
    let d = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
    let len = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
    (0..3).find(|&k| (d[k].abs() - len).abs() <= 1e-12 * len)
}

fn outline_of(
    shape: &Shape,
    axis: usize,
    wall: f64,
    corner: f64,
    what: &str,
) -> Result<Outline, MeshError> {
    let [u, v] = plane_axes(axis);
    match shape {
        Shape::Cylinder { a, b, r } => {
            if cylinder_axis(*a, *b) != Some(axis) {
                return Err(MeshError::spec(format!(
                    "{what}: [extrude] needs cylinders parallel to the extrusion axis"
                )));
            }
            let n = ((2.0 * std::f64::consts::PI * r / wall).ceil() as usize).max(8);
            let c = [a[u], a[v]];
            let points = (0..n)
                .map(|i| {
                    let t = 2.0 * std::f64::consts::PI * i as f64 / n as f64;
                    [c[0] + r * t.cos(), c[1] + r * t.sin()]
                })
                .collect();
            Ok(Outline {
                points,
                circle: Some((c, *r)),
                span: [a[axis].min(b[axis]), a[axis].max(b[axis])],
            })
        }
        Shape::Box { min, max } => {
            let corners = [
                [min[u], min[v]],
                [max[u], min[v]],
                [max[u], max[v]],
                [min[u], max[v]],
            ];
            Ok(Outline {
                points: polygon_points(&corners, corner, wall),
                circle: None,
                span: [min[axis], max[axis]],
            })
        }
        Shape::Prism {
            axis: along,
            span,
            outline,
        } => {
            if *along != axis {
                return Err(MeshError::spec(format!(
                    "{what}: [extrude] needs prisms along the extrusion axis"
                )));
            }
            // The outline's coordinates are in x, y, z order; the section's in (u, v).
            let mut corners: Vec<[f64; 2]> = outline
                .iter()
                .map(|&q| if axis == 1 { [q[1], q[0]] } else { q })
                .collect();
            if super::sdf::twice_area(&corners) < 0.0 {
                corners.reverse();
            }
            Ok(Outline {
                points: polygon_points(&corners, corner, wall),
                circle: None,
                span: *span,
            })
        }
        _ => Err(MeshError::spec(format!(
            "{what}: [extrude] meshes cylinders, boxes and prisms only (use the stuffing mesher \
             for spheres and STL surfaces)"
        ))),
    }
}

/// The points of a polygon's outline: its corners and each side divided into pieces of at most
/// `wall`, graded down to `corner` at both ends.
fn polygon_points(corners: &[[f64; 2]], corner: f64, wall: f64) -> Vec<[f64; 2]> {
    let mut points = Vec::new();
    for k in 0..corners.len() {
        let (p, q) = (corners[k], corners[(k + 1) % corners.len()]);
        let len = ((q[0] - p[0]).powi(2) + (q[1] - p[1]).powi(2)).sqrt();
        let at = graded(len, corner, wall);
        for a in &at[..at.len() - 1] {
            let s = a / len;
            points.push([p[0] + s * (q[0] - p[0]), p[1] + s * (q[1] - p[1])]);
        }
    }
    points
}

/// Winding-number test of a point against a closed polygon.
fn inside(poly: &[[f64; 2]], p: [f64; 2]) -> bool {
    let mut inside = false;
    let n = poly.len();
    for i in 0..n {
        let (a, b) = (poly[i], poly[(i + 1) % n]);
        if (a[1] > p[1]) != (b[1] > p[1]) {
            let x = a[0] + (p[1] - a[1]) / (b[1] - a[1]) * (b[0] - a[0]);
            if p[0] < x {
                inside = !inside;
            }
        }
    }
    inside
}

/// Layer planes along the axis: every outline end, and uniform layers of at most `layer`
/// between them.
fn layer_planes(ends: &mut Vec<f64>, layer: f64, end_layer: f64) -> Vec<f64> {
    ends.sort_by(f64::total_cmp);
    ends.dedup_by(|a, b| (*a - *b).abs() <= 1e-9 * (1.0 + b.abs()));
    let mut planes = vec![ends[0]];
    for w in ends.windows(2) {
        let at = graded(w[1] - w[0], end_layer, layer);
        planes.extend(at[1..at.len() - 1].iter().map(|a| w[0] + a));
        planes.push(w[1]);
    }
    planes
}

/// Mesh `body` minus `cavities` by extrusion along the body's axis (`box_axis` for a box body).
pub fn extrude(
    body: &Shape,
    cavities: &[&Shape],
    box_axis: usize,
    section: &ExtrudeSection,
    scale: f64,
) -> Result<Extruded, MeshError> {
    let positive = |x: f64| x > 0.0 && x.is_finite();
    let wall = section.wall * scale;
    let interior = section.interior.map_or(2.0 * wall, |x| x * scale);
    let layer = section.layer.map_or(interior, |x| x * scale);
    let corner = section.corner.map_or(wall, |x| x * scale);
    let end_layer = section.end_layer.map_or(layer, |x| x * scale);
    if ![wall, interior, layer, corner, end_layer]
        .into_iter()
        .all(positive)
    {
        return Err(MeshError::spec(
            "[extrude]: wall, interior, layer, corner and end_layer must be > 0",
        ));
    }
    let axis = match body {
        Shape::Cylinder { a, b, .. } => cylinder_axis(*a, *b).ok_or_else(|| {
            MeshError::spec("[extrude]: the body cylinder must be parallel to x, y or z")
        })?,
        Shape::Prism { axis, .. } => *axis,
        _ => box_axis,
    };
    // The body's corners are convex (no singularity): only cavities are graded.
    let outer = outline_of(body, axis, wall, wall, "body")?;
    let mut holes = Vec::new();
    for (i, c) in cavities.iter().enumerate() {
        let what = format!("cavity {}", i + 1);
        let o = outline_of(c, axis, wall, corner, &what)?;
        // Outlines may neither touch nor cross: each cavity lies strictly inside the body and
        // apart from the others (a wall of zero thickness has no mesh).
        let clear = o.points.iter().all(|&p| {
            inside(&outer.points, p) && holes.iter().all(|h: &Outline| !inside(&h.points, p))
        }) && holes
            .iter()
            .all(|h| h.points.iter().all(|&p| !inside(&o.points, p)));
        if !clear || o.span[0] < outer.span[0] || o.span[1] > outer.span[1] {
            return Err(MeshError::spec(format!(
                "{what}: [extrude] needs every cavity strictly inside the body and apart from \
                 the other cavities"
            )));
        }
        holes.push(o);
    }
    // The cross-section: every outline as constraint edges.
    let mut cdt = ConstrainedDelaunayTriangulation::<Point2<f64>>::new();
    let mut circles = Vec::new();
    let mut vertex_circle: Vec<(u32, u32, u32)> = Vec::new(); // (2-D vertex, circle, slot)
    let mut vertex_outline: Vec<(u32, u32)> = Vec::new(); // (2-D vertex, outline)
    for (k, o) in std::iter::once(&outer).chain(&holes).enumerate() {
        let mut handles = Vec::with_capacity(o.points.len());
        for p in &o.points {
            let h = cdt
                .insert(Point2::new(p[0], p[1]))
                .map_err(|e| MeshError::spec(format!("[extrude]: cross-section: {e:?}")))?;
            handles.push(h);
            vertex_outline.push((h.index() as u32, k as u32));
        }
        for i in 0..handles.len() {
            cdt.add_constraint(handles[i], handles[(i + 1) % handles.len()]);
        }
        if let Some(c) = o.circle {
            for (slot, h) in handles.iter().enumerate() {
                vertex_circle.push((h.index() as u32, circles.len() as u32, slot as u32));
            }
            circles.push((c, o.points.len() as u32));
        }
    }
    let max_area = 3f64.sqrt() / 4.0 * interior * interior;
    let params = || {
        RefinementParameters::<f64>::new()
            .keep_constraint_edges()
            .with_angle_limit(AngleLimit::from_deg(25.0))
            .with_max_allowed_area(max_area)
            .with_max_additional_vertices(2_000_000)
    };
    // Ruppert's refinement grades by angle and area only, so a wall narrower than about three
    // `wall` edges may keep triangles that reach across it. Split those (at their centroid)
    // and refine again until no triangle joins two outlines: every wall gets at least two
    // elements through it.
    let outline_of_vertex = |cdt: &ConstrainedDelaunayTriangulation<Point2<f64>>| {
        let mut of = vec![u32::MAX; cdt.num_vertices()];
        for &(vtx, o) in &vertex_outline {
            of[vtx as usize] = o;
        }
        of
    };
    let mut complete = cdt.refine(params()).refinement_complete;
    for _ in 0..50 {
        let of = outline_of_vertex(&cdt);
        let spans: Vec<Point2<f64>> = cdt
            .inner_faces()
            .filter(|f| {
                let o = f.vertices().map(|v| of[v.fix().index()]);
                let on: Vec<u32> = o.into_iter().filter(|&x| x != u32::MAX).collect();
                on.iter().any(|&x| x != on[0])
            })
            .map(|f| f.center())
            .collect();
        if spans.is_empty() {
            break;
        }
        for p in spans {
            cdt.insert(p)
                .map_err(|e| MeshError::spec(format!("[extrude]: cross-section: {e:?}")))?;
        }
        complete &= cdt.refine(params()).refinement_complete;
    }
    if !complete {
        return Err(MeshError::spec(
            "[extrude]: the cross-section's refinement did not finish; use a larger `wall`",
        ));
    }
    let section_points: Vec<[f64; 2]> = cdt
        .vertices()
        .map(|v| {
            let p = v.position();
            [p.x, p.y]
        })
        .collect();
    // Each triangle of the body's section (a non-convex outline leaves triangles of the
    // convex hull outside it): which cavity it lies in (None: solid in every layer).
    let triangles: Vec<([u32; 3], Option<usize>)> = cdt
        .inner_faces()
        .filter_map(|f| {
            let vs = f.vertices().map(|v| v.fix().index() as u32);
            let c = vs.iter().fold([0.0; 2], |acc, &v| {
                let p = section_points[v as usize];
                [acc[0] + p[0] / 3.0, acc[1] + p[1] / 3.0]
            });
            inside(&outer.points, c).then(|| (vs, holes.iter().position(|h| inside(&h.points, c))))
        })
        .collect();
    let mut ends: Vec<f64> = std::iter::once(&outer)
        .chain(&holes)
        .flat_map(|o| o.span)
        .collect();
    let planes = layer_planes(&mut ends, layer, end_layer);
    let nv = section_points.len();
    let [u, v] = plane_axes(axis);
    let mut nodes = Vec::with_capacity(nv * planes.len());
    for &x in &planes {
        for p in &section_points {
            let mut q = [0.0; 3];
            q[axis] = x;
            q[u] = p[0];
            q[v] = p[1];
            nodes.push(q);
        }
    }
    let mut tets = Vec::new();
    for (j, w) in planes.windows(2).enumerate() {
        let mid = 0.5 * (w[0] + w[1]);
        for (t, hole) in &triangles {
            if hole.is_some_and(|h| holes[h].span[0] < mid && mid < holes[h].span[1]) {
                continue;
            }
            let mut s = *t;
            s.sort_unstable();
            let b = s.map(|x| (j * nv) as u32 + x);
            let top = s.map(|x| ((j + 1) * nv) as u32 + x);
            // The lower-numbered bottom vertex joins the higher-numbered top vertex on every
            // side face, so the prisms on either side of it split it alike.
            for mut tet in [
                [b[0], b[1], b[2], top[2]],
                [b[0], b[1], top[1], top[2]],
                [b[0], top[0], top[1], top[2]],
            ] {
                if signed_volume(&nodes, tet) < 0.0 {
                    tet.swap(2, 3);
                }
                tets.push(tet);
            }
        }
    }
    // Drop nodes no tet uses (section vertices inside a cavity between its end planes).
    let mut used = vec![u32::MAX; nodes.len()];
    let mut count = 0u32;
    for t in &mut tets {
        for n in t.iter_mut() {
            if used[*n as usize] == u32::MAX {
                used[*n as usize] = count;
                count += 1;
            }
            *n = used[*n as usize];
        }
    }
    let mut kept = vec![[0.0; 3]; count as usize];
    let mut on_circle = vec![None; count as usize];
    let mut circle_slot = vec![0; count as usize];
    let mut circle_of_vertex = vec![None; nv];
    for &(vtx, c, slot) in &vertex_circle {
        circle_of_vertex[vtx as usize] = Some((c, slot));
    }
    for (old, &new) in used.iter().enumerate() {
        if new != u32::MAX {
            kept[new as usize] = nodes[old];
            if let Some((c, slot)) = circle_of_vertex[old % nv] {
                on_circle[new as usize] = Some(c);
                circle_slot[new as usize] = slot;
            }
        }
    }
    Ok(Extruded {
        nodes: kept,
        tets,
        on_circle,
        circle_len: circles.iter().map(|c| c.1).collect(),
        circles: circles.into_iter().map(|c| c.0).collect(),
        circle_slot,
        axis,
    })
}

fn signed_volume(nodes: &[[f64; 3]], t: [u32; 4]) -> f64 {
    let p = t.map(|n| nodes[n as usize]);
    let d = |i: usize| [p[i][0] - p[0][0], p[i][1] - p[0][1], p[i][2] - p[0][2]];
    let (a, b, c) = (d(1), d(2), d(3));
    a[0] * (b[1] * c[2] - b[2] * c[1]) - a[1] * (b[0] * c[2] - b[2] * c[0])
        + a[2] * (b[0] * c[1] - b[1] * c[0])
}

impl Extruded {
    /// Where the mid-edge node of the edge `a`–`b` belongs on the exact geometry: on the arc
    /// when both ends are neighbouring vertices of one circle's outline (a chord of the
    /// circle, whether within one section plane or across a layer), None otherwise (keep it
    /// at the chord's midpoint).
    pub fn arc_midpoint(&self, a: u32, b: u32, mid: [f64; 3]) -> Option<[f64; 3]> {
        let (ca, cb) = (self.on_circle[a as usize]?, self.on_circle[b as usize]?);
        if ca != cb {
            return None;
        }
        let n = self.circle_len[ca as usize];
        let (sa, sb) = (self.circle_slot[a as usize], self.circle_slot[b as usize]);
        if (sa + 1) % n != sb && (sb + 1) % n != sa {
            return None;
        }
        let ([cu, cv], r) = self.circles[ca as usize];
        let [u, v] = plane_axes(self.axis);
        let (du, dv) = (mid[u] - cu, mid[v] - cv);
        let d = (du * du + dv * dv).sqrt();
        let mut p = mid;
        p[u] = cu + du * r / d;
        p[v] = cv + dv * r / d;
        Some(p)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn layer_planes_include_every_end() {
        let planes = layer_planes(&mut vec![0.0, 100.0, 4.0, 96.0, 4.0], 2.5, 2.5);
        assert_eq!(planes.first(), Some(&0.0));
        assert_eq!(planes.last(), Some(&100.0));
        assert!(planes.contains(&4.0) && planes.contains(&96.0));
        assert!(
            planes
                .windows(2)
                .all(|w| w[1] > w[0] && w[1] - w[0] <= 2.5 + 1e-12)
        );
    }

    #[test]
    fn graded_pieces_grow_from_both_ends_and_cover_the_interval() {
        let at = graded(10.0, 0.1, 1.0);
        assert_eq!((at[0], *at.last().unwrap()), (0.0, 10.0));
        let pieces: Vec<f64> = at.windows(2).map(|w| w[1] - w[0]).collect();
        assert!((pieces[0] - 0.1).abs() < 1e-12 && (pieces.last().unwrap() - 0.1).abs() < 1e-12);
        assert!(pieces.iter().all(|&p| p <= 1.0 + 1e-12));
        assert!(pieces.windows(2).all(|w| w[1] <= GROWTH * w[0] + 1e-12));
        // Symmetric.
        for (a, b) in pieces.iter().zip(pieces.iter().rev()) {
            assert!((a - b).abs() < 1e-12);
        }
        // Ungraded: even pieces.
        assert_eq!(graded(10.0, 1.0, 1.0).len(), 11);
    }

    #[test]
    fn point_in_polygon() {
        let square = [[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]];
        assert!(inside(&square, [0.5, 0.5]));
        assert!(!inside(&square, [1.5, 0.5]));
    }
}
