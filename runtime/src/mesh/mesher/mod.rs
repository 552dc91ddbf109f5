//! The built-in tetrahedral mesher: a closed body (box, cylinder, sphere or closed STL surface) minus
//! closed cavities (each a chamber with its own surface tag), meshed by isosurface stuffing;
//! or the structured Kuhn grid of the benchmark. Driven by a TOML spec:
//!
//! ```toml
//! unit = "mm"            # unit of every length in this file and of the STL files
//! resolution = 2.0       # lattice spacing h
//! [region]               # optional, default tag 1 "solid"
//! tag = 1
//! name = "solid"
//! [body]
//! shape = "box"          # or "cylinder" (start, end, radius), "sphere" (center, radius),
//!                        # "prism" (axis, span = [from, to], outline = [[a, b], …]: a
//!                        # polygon across the axis, its other two coordinates in x, y, z
//!                        # order, extruded over span) or "stl" (path)
//! min = [0, 0, 0]
//! max = [60, 10, 10]
//! [[cavity]]
//! name = "cavity"
//! tag = 2
//! shape = "box"
//! min = [5, 2.5, 4]
//! max = [55, 7.5, 8]
//! [base]                 # optional: body faces on the plane x = min x of the body
//! axis = "x"             # or "y", "z" (base: min plane, tip: max plane of that axis)
//! tag = 10
//! name = "base"
//! [tip]                  # optional: body faces on the plane x = max x of the body
//! tag = 11
//! name = "tip"
//! [[subregion]]          # optional, any number: tets whose centroid is inside get this
//! tag = 2                # region tag (a second material); later entries win
//! name = "stiff"
//! shape = "box"
//! min = [0, 0, 0]
//! max = [10, 10, 10]
//! # [kuhn] n = [12, 4, 4]  → structured Kuhn grid instead (box body, ≤ 1 box cavity);
//! #   a resolution override h then sets n = round(extent / h) per axis
//! # [extrude] wall = 0.75, interior = 1.5, layer = 2.0 → boundary-conforming extrusion
//! #   (cylinder/box body and cavities parallel to one axis), optionally graded towards box
//! #   cavities' corners (corner = 0.1) and every end plane (end_layer = 0.15); a resolution
//! #   override sets wall = h and scales every other length alike
//! # order = 2 → 10-node tets; mid-edge nodes of curved boundaries on the exact surface
//! ```

pub mod extrude;
pub mod sdf;
pub mod stuffing;

use std::path::{Path, PathBuf};
use std::time::Instant;

use serde::Deserialize;

use super::error::MeshError;
use super::kuhn::{KuhnSpec, kuhn_grid};
use super::model::{LengthUnit, Mesh};
pub use sdf::{Shape, TriSurface};

/// A shape in a spec.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ShapeSpec {
    pub shape: String,
    pub min: Option<[f64; 3]>,
    pub max: Option<[f64; 3]>,
    pub start: Option<[f64; 3]>,
    pub end: Option<[f64; 3]>,
    /// Sphere only: its centre (with `radius`).
    pub center: Option<[f64; 3]>,
    pub radius: Option<f64>,
    pub path: Option<PathBuf>,
    /// Prism only: its axis ("x", "y" or "z"), its extent along it and its cross-section (the
    /// two other coordinates of each corner, in x, y, z order).
    pub axis: Option<String>,
    pub span: Option<[f64; 2]>,
    pub outline: Option<Vec<[f64; 2]>>,
    /// Cavities only: surface tag and name.
    pub tag: Option<i32>,
    pub name: Option<String>,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TagSpec {
    pub tag: i32,
    pub name: String,
    /// `[base]`/`[tip]` only: the axis whose min (base) or max (tip) plane of the body's
    /// bounding box selects the faces: "x" (default), "y" or "z".
    #[serde(default)]
    pub axis: Option<String>,
}

impl TagSpec {
    fn axis_index(&self) -> Result<usize, MeshError> {
        match self.axis.as_deref().unwrap_or("x") {
            "x" => Ok(0),
            "y" => Ok(1),
            "z" => Ok(2),
            a => Err(MeshError::spec(format!(
                "[base]/[tip] `{}`: axis `{a}` must be x, y or z",
                self.name
            ))),
        }
    }
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct KuhnSection {
    pub n: [usize; 3],
}

/// A mesh generation spec (TOML).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MeshSpec {
    #[serde(default)]
    pub unit: Option<String>,
    /// Lattice spacing h (spec units). Required unless `[kuhn]` is given.
    pub resolution: Option<f64>,
    pub region: Option<TagSpec>,
    pub body: ShapeSpec,
    #[serde(default)]
    pub cavity: Vec<ShapeSpec>,
    pub base: Option<TagSpec>,
    pub tip: Option<TagSpec>,
    pub kuhn: Option<KuhnSection>,
    /// Boundary-conforming extrusion instead of isosurface stuffing.
    pub extrude: Option<extrude::ExtrudeSection>,
    /// Element order: 1 (4-node tets, the default) or 2 (10-node tets).
    pub order: Option<u32>,
    /// Parts of the solid with their own region tag (materials): tets whose centroid lies
    /// inside the shape get `tag`; later entries win.
    #[serde(default)]
    pub subregion: Vec<ShapeSpec>,
}

/// A generated mesh with what is known about its input geometry.
#[derive(Debug, Clone)]
pub struct Generated {
    pub mesh: Mesh,
    /// Exact volume of the input solid (body − cavities), m³.
    pub reference_volume: f64,
    /// Exact volume of each cavity `(tag, m³)`.
    pub cavity_volumes: Vec<(i32, f64)>,
    /// Wall time of meshing, seconds.
    pub seconds: f64,
}

impl MeshSpec {
    pub fn from_toml(text: &str, path: &Path) -> Result<MeshSpec, MeshError> {
        toml::from_str(text).map_err(|e| {
            MeshError::spec(format!("invalid mesh spec: {}", e.message().trim()))
                .in_file(path)
                .with_fix("see `softc mesh generate --help` and meshes/README.md for the format")
        })
    }

    pub fn from_file(path: &Path) -> Result<MeshSpec, MeshError> {
        let text = crate::files::read_regular_text(path).map_err(|e| MeshError::io(path, &e))?;
        Self::from_toml(&text, path)
    }

    pub fn unit(&self) -> Result<LengthUnit, MeshError> {
        match &self.unit {
            None => Ok(LengthUnit::Millimetre),
            Some(u) => u.parse().map_err(MeshError::spec),
        }
    }
}

fn shape_of(
    s: &ShapeSpec,
    what: &str,
    base_dir: &Path,
    unit: LengthUnit,
) -> Result<Shape, MeshError> {
    let need = |v: Option<[f64; 3]>, field: &str| {
        v.ok_or_else(|| MeshError::spec(format!("{what}: shape `{}` needs `{field}`", s.shape)))
    };
    let finite = |v: [f64; 3], field: &str| {
        if v.iter().all(|x| x.is_finite()) {
            Ok(v)
        } else {
            Err(MeshError::spec(format!("{what}: `{field}` is not finite")))
        }
    };
    match s.shape.as_str() {
        "box" => {
            let min = finite(need(s.min, "min")?, "min")?;
            let max = finite(need(s.max, "max")?, "max")?;
            if (0..3).any(|k| max[k] <= min[k]) {
                return Err(MeshError::spec(format!(
                    "{what}: box needs max > min on every axis"
                )));
            }
            Ok(Shape::Box { min, max })
        }
        "cylinder" => {
            let a = finite(need(s.start, "start")?, "start")?;
            let b = finite(need(s.end, "end")?, "end")?;
            let r = s
                .radius
                .filter(|r| *r > 0.0 && r.is_finite())
                .ok_or_else(|| MeshError::spec(format!("{what}: cylinder needs `radius` > 0")))?;
            if a == b {
                return Err(MeshError::spec(format!(
                    "{what}: cylinder start equals end"
                )));
            }
            Ok(Shape::Cylinder { a, b, r })
        }
        "sphere" => {
            let c = finite(need(s.center, "center")?, "center")?;
            let r = s
                .radius
                .filter(|r| *r > 0.0 && r.is_finite())
                .ok_or_else(|| MeshError::spec(format!("{what}: sphere needs `radius` > 0")))?;
            Ok(Shape::Sphere { c, r })
        }
        "stl" => {
            let p = s
                .path
                .as_ref()
                .ok_or_else(|| MeshError::spec(format!("{what}: shape `stl` needs `path`")))?;
            let full = if p.is_absolute() {
                p.clone()
            } else {
                base_dir.join(p)
            };
            let (verts, tris) = super::readers::stl::read_closed(&full)?;
            let _ = unit;
            let surf = TriSurface::new(verts, tris);
            if surf.volume() <= 0.0 {
                return Err(MeshError::spec(format!(
                    "{what}: the STL surface encloses no volume (inward-facing normals?)"
                ))
                .in_file(&full)
                .with_fix("flip the triangle winding so normals point outwards"));
            }
            Ok(Shape::Surface(surf))
        }
        "prism" => prism_of(s, what),
        other => Err(MeshError::spec(format!(
            "{what}: unknown shape `{other}` (use box, cylinder, sphere, prism or stl)"
        ))),
    }
}

/// A `prism` shape: a simple polygon of at least three corners, extruded over a positive span.
fn prism_of(s: &ShapeSpec, what: &str) -> Result<Shape, MeshError> {
    let axis = match s.axis.as_deref() {
        Some("x") => 0,
        Some("y") => 1,
        Some("z") => 2,
        _ => {
            return Err(MeshError::spec(format!(
                "{what}: prism needs `axis` = \"x\", \"y\" or \"z\""
            )));
        }
    };
    let span = s
        .span
        .filter(|[a, b]| a.is_finite() && b.is_finite() && b > a)
        .ok_or_else(|| {
            MeshError::spec(format!(
                "{what}: prism needs `span` = [from, to], from < to"
            ))
        })?;
    let outline = s.outline.clone().unwrap_or_default();
    if outline.len() < 3 || outline.iter().flatten().any(|x| !x.is_finite()) {
        return Err(MeshError::spec(format!(
            "{what}: prism needs an `outline` of at least three finite corners"
        )));
    }
    let n = outline.len();
    if (0..n).any(|i| outline[i] == outline[(i + 1) % n]) {
        return Err(MeshError::spec(format!(
            "{what}: the prism's `outline` repeats a corner: list each corner once"
        )));
    }
    let crosses = |i: usize, j: usize| {
        let (a, b, c, d) = (
            outline[i],
            outline[(i + 1) % n],
            outline[j],
            outline[(j + 1) % n],
        );
        let side = |p: [f64; 2], q: [f64; 2], r: [f64; 2]| {
            (q[0] - p[0]) * (r[1] - p[1]) - (q[1] - p[1]) * (r[0] - p[0])
        };
        let (s1, s2, s3, s4) = (side(a, b, c), side(a, b, d), side(c, d, a), side(c, d, b));
        if s1 == 0.0 && s2 == 0.0 {
            // Collinear: they cross where their extents along the line overlap.
            let k = if (b[0] - a[0]).abs() >= (b[1] - a[1]).abs() {
                0
            } else {
                1
            };
            let (lo1, hi1) = (a[k].min(b[k]), a[k].max(b[k]));
            let (lo2, hi2) = (c[k].min(d[k]), c[k].max(d[k]));
            return lo1 <= hi2 && lo2 <= hi1;
        }
        s1 * s2 <= 0.0 && s3 * s4 <= 0.0
    };
    let adjacent = |i: usize, j: usize| j == i + 1 || (i == 0 && j == n - 1);
    let simple = (0..n).all(|i| (i + 1..n).all(|j| adjacent(i, j) || !crosses(i, j)));
    if !simple || sdf::twice_area(&outline).abs() <= 0.0 {
        return Err(MeshError::spec(format!(
            "{what}: the prism's `outline` crosses itself or encloses no area: list its corners \
             in order around it"
        )));
    }
    Ok(Shape::Prism {
        axis,
        span,
        outline,
    })
}

/// Generate the mesh a spec describes. `resolution` overrides the spec's. `base_dir` resolves
/// relative STL paths. Coordinates of the result are in metres.
pub fn generate(
    spec: &MeshSpec,
    resolution: Option<f64>,
    base_dir: &Path,
) -> Result<Generated, MeshError> {
    let unit = spec.unit()?;
    let s = unit.to_metres();
    let t0 = Instant::now();
    let region = spec.region.clone().unwrap_or(TagSpec {
        tag: 1,
        name: "solid".into(),
        axis: None,
    });
    let quadratic = match spec.order.unwrap_or(1) {
        1 => false,
        2 => true,
        o => return Err(MeshError::spec(format!("order {o} must be 1 or 2"))),
    };
    let base_axis = spec.base.as_ref().map(TagSpec::axis_index).transpose()?;
    let tip_axis = spec.tip.as_ref().map(TagSpec::axis_index).transpose()?;
    let body = shape_of(&spec.body, "body", base_dir, unit)?;
    let mut cavities = Vec::new();
    for (i, c) in spec.cavity.iter().enumerate() {
        let what = format!("cavity {}", i + 1);
        let shape = shape_of(c, &what, base_dir, unit)?;
        let tag = c.tag.unwrap_or(2 + i as i32);
        if tag <= 0 {
            return Err(MeshError::spec(format!("{what}: tag must be ≥ 1")));
        }
        let name = c.name.clone().unwrap_or_else(|| format!("chamber{tag}"));
        cavities.push((shape, tag, name));
    }
    let mut subregions = Vec::new();
    for (i, r) in spec.subregion.iter().enumerate() {
        let what = format!("subregion {}", i + 1);
        let shape = shape_of(r, &what, base_dir, unit)?;
        let tag = r
            .tag
            .ok_or_else(|| MeshError::spec(format!("{what}: needs a `tag`")))?;
        if tag <= 0 {
            return Err(MeshError::spec(format!("{what}: tag must be ≥ 1")));
        }
        let name = r.name.clone().unwrap_or_else(|| format!("region{tag}"));
        subregions.push((shape, tag, name));
    }
    let reference_volume =
        (body.volume() - cavities.iter().map(|c| c.0.volume()).sum::<f64>()) * s * s * s;
    // Per tag: cavities that share one (a PneuNet's chambers) are one chamber.
    let mut cavity_volumes: Vec<(i32, f64)> = Vec::new();
    for c in &cavities {
        let v = c.0.volume() * s * s * s;
        match cavity_volumes.iter_mut().find(|(t, _)| *t == c.1) {
            Some((_, total)) => *total += v,
            None => cavity_volumes.push((c.1, v)),
        }
    }
    if let Some(k) = &spec.kuhn {
        let (Shape::Box { min, max }, true) = (&body, cavities.len() <= 1) else {
            return Err(MeshError::spec(
                "[kuhn] needs a box body and at most one box cavity",
            ));
        };
        let (cmin, cmax) = match cavities.first() {
            Some((Shape::Box { min, max }, _, _)) => (*min, *max),
            Some(_) => return Err(MeshError::spec("[kuhn] cavity must be a box")),
            None => ([f64::NAN; 3], [f64::NAN; 3]),
        };
        // A resolution override sets the cell size: n = round(extent / h) per axis.
        let n = match resolution {
            Some(h) if h > 0.0 && h.is_finite() => {
                [0, 1, 2].map(|a| (((max[a] - min[a]) / h).round() as usize).max(1))
            }
            Some(h) => return Err(MeshError::spec(format!("resolution {h} must be > 0"))),
            None => k.n,
        };
        let mut mesh = kuhn_grid(
            &KuhnSpec {
                n,
                min: *min,
                max: *max,
                cavity_min: cmin,
                cavity_max: cmax,
            },
            unit,
        )?;
        let mut map = Vec::new();
        if let Some((_, tag, name)) = cavities.first() {
            map.push((super::kuhn::CAVITY_TAG, *tag, name.clone()));
        }
        if let Some(b) = &spec.base {
            map.push((super::kuhn::BASE_TAG, b.tag, b.name.clone()));
        }
        if let Some(b) = &spec.tip {
            map.push((super::kuhn::TIP_TAG, b.tag, b.name.clone()));
        }
        retag_all(&mut mesh, &map);
        retag_region(&mut mesh, &region);
        apply_subregions(&mut mesh, &subregions, s);
        if quadratic {
            mesh = mesh.with_mid_edges();
        }
        return Ok(Generated {
            mesh,
            reference_volume,
            cavity_volumes,
            seconds: t0.elapsed().as_secs_f64(),
        });
    }
    if let (Some(h), Some(x)) = (spec.resolution, &spec.extrude) {
        // It would be silently ignored: the extrusion's lengths are its own.
        return Err(MeshError::spec(format!(
            "`resolution = {h}` has no effect beside [extrude], whose `wall` ({}) sets the edge \
             length: remove it (to refine, lower `wall`, or pass --resolution to scale every length)",
            x.wall
        )));
    }
    let (mut mesh, extruded, h) = if let Some(x) = &spec.extrude {
        // A resolution override is the new wall edge; interior and layer scale with it.
        let scale = match resolution {
            Some(h) if h > 0.0 && h.is_finite() => h / x.wall,
            Some(h) => return Err(MeshError::spec(format!("resolution {h} must be > 0"))),
            None => 1.0,
        };
        let shapes: Vec<&Shape> = cavities.iter().map(|c| &c.0).collect();
        let ex = extrude::extrude(&body, &shapes, base_axis.unwrap_or(0), x, scale)?;
        let mesh = Mesh::from_tets(ex.nodes.clone(), ex.tets.clone());
        (mesh, Some(ex), x.wall * scale)
    } else {
        let h = resolution.or(spec.resolution).ok_or_else(|| {
            MeshError::spec("no `resolution` (lattice spacing) in the spec or on the command line")
        })?;
        let (lo, hi) = body.bbox();
        let ext = (0..3).map(|k| hi[k] - lo[k]).fold(0.0, f64::max);
        if !(h > 0.0 && h.is_finite()) || ext / h > 2000.0 {
            return Err(MeshError::spec(format!(
                "resolution {h} is not usable for a body of size {ext} (need 0 < h and size/h ≤ 2000)"
            )));
        }
        let f = |p: [f64; 3]| {
            let mut d = body.sdf(p);
            for (c, _, _) in &cavities {
                d = d.max(-c.sdf(p));
            }
            d
        };
        let st = stuffing::stuff(&f, lo, hi, h);
        (Mesh::from_tets(st.nodes, st.tets), None, h)
    };
    mesh.tet_tags = vec![region.tag; mesh.tets.len()];
    mesh.set_name(3, region.tag, &region.name);
    let shapes: Vec<(&Shape, i32)> = cavities.iter().map(|(c, t, _)| (c, *t)).collect();
    let planes = [
        spec.base.as_ref().map(|b| (b.tag, base_axis.unwrap_or(0))),
        spec.tip.as_ref().map(|t| (t.tag, tip_axis.unwrap_or(0))),
    ];
    tag_boundary(&mut mesh, &body, &shapes, planes, 1e-6 * h);
    if quadratic {
        mesh = mesh.with_mid_edges();
        let tol = 1e-4 * h;
        let nodes = mesh.nodes.clone();
        curve_boundary_mids(&mut mesh, &|a, b, mid| match &extruded {
            Some(ex) => ex.arc_midpoint(a, b, mid),
            None => std::iter::once(&body)
                .chain(cavities.iter().map(|c| &c.0))
                .find_map(|sh| sh.arc_point(nodes[a as usize], nodes[b as usize], mid, tol)),
        });
    }
    for (_, tag, name) in &cavities {
        mesh.set_name(2, *tag, name);
    }
    if let Some(b) = &spec.base {
        mesh.set_name(2, b.tag, &b.name);
    }
    if let Some(b) = &spec.tip {
        mesh.set_name(2, b.tag, &b.name);
    }
    mesh.scale(s);
    apply_subregions(&mut mesh, &subregions, s);
    for sel in [&spec.base, &spec.tip].into_iter().flatten() {
        let nodes = mesh.surface_nodes(sel.tag);
        mesh.node_sets.insert(sel.name.clone(), nodes);
    }
    Ok(Generated {
        mesh,
        reference_volume,
        cavity_volumes,
        seconds: t0.elapsed().as_secs_f64(),
    })
}

/// Tag the boundary faces of a linear mesh (spec units): each face goes to the closest of the
/// body and the cavities at its centroid; a cavity's faces get its tag (wound into the solid),
/// the body's faces on the base or tip plane (`(tag, axis)`: the min or max plane of the body's
/// bounding box along the axis) get that tag, other body faces none.
fn tag_boundary(
    mesh: &mut Mesh,
    body: &Shape,
    cavities: &[(&Shape, i32)],
    planes: [Option<(i32, usize)>; 2],
    tol: f64,
) {
    let (lo, hi) = body.bbox();
    for bf in mesh.boundary_faces() {
        let p = bf.nodes.map(|n| mesh.nodes[n as usize]);
        let c = [0, 1, 2].map(|k| (p[0][k] + p[1][k] + p[2][k]) / 3.0);
        let mut best = (body.sdf(c).abs(), 0i32);
        for (cs, tag) in cavities {
            let d = cs.sdf(c).abs();
            if d < best.0 {
                best = (d, *tag);
            }
        }
        let on_plane = |(tag, a): (i32, usize), at: f64| {
            p.iter().all(|q| (q[a] - at).abs() < tol).then_some(tag)
        };
        let tag = if best.1 != 0 {
            Some(best.1)
        } else {
            planes[0]
                .and_then(|b| on_plane(b, lo[b.1]))
                .or_else(|| planes[1].and_then(|t| on_plane(t, hi[t.1])))
        };
        if let Some(t) = tag {
            mesh.tris.push([bf.nodes[0], bf.nodes[2], bf.nodes[1]]);
            mesh.tri_tags.push(t);
        }
    }
}

/// Move the mid-edge nodes of boundary edges of a quadratic mesh to where `place(a, b, mid)`
/// says the edge `a`–`b` runs on the exact geometry (None: keep the straight edge).
fn curve_boundary_mids(mesh: &mut Mesh, place: &dyn Fn(u32, u32, [f64; 3]) -> Option<[f64; 3]>) {
    let Some(mids) = mesh.mid_edges.as_ref() else {
        return;
    };
    let mut moves = Vec::new();
    for bf in mesh.boundary_faces() {
        let (tet, tm) = (mesh.tets[bf.tet as usize], mids.tets[bf.tet as usize]);
        for (k, e) in super::model::QUAD_TET_EDGES.iter().enumerate() {
            let (a, b) = (tet[e[0]], tet[e[1]]);
            if bf.nodes.contains(&a) && bf.nodes.contains(&b) {
                let m = tm[k];
                if let Some(p) = place(a, b, mesh.nodes[m as usize]) {
                    moves.push((m, p));
                }
            }
        }
    }
    for (m, p) in moves {
        mesh.nodes[m as usize] = p;
    }
}

/// Replace surface tags `from → (to, name)` all at once (no collisions between old and new).
fn retag_all(mesh: &mut Mesh, map: &[(i32, i32, String)]) {
    let old_names: Vec<(i32, Option<String>)> = map
        .iter()
        .map(|(f, _, _)| (*f, mesh.tag_name(2, *f).map(str::to_string)))
        .collect();
    for t in &mut mesh.tri_tags {
        if let Some((_, to, _)) = map.iter().find(|(f, _, _)| f == t) {
            *t = *to;
        }
    }
    mesh.names
        .retain(|p| !(p.dim == 2 && map.iter().any(|(f, _, _)| *f == p.tag)));
    for (from, to, name) in map {
        mesh.set_name(2, *to, name);
        if let Some((_, Some(old))) = old_names.iter().find(|(f, _)| f == from)
            && mesh.node_sets.remove(old).is_some()
        {
            let nodes = mesh.surface_nodes(*to);
            mesh.node_sets.insert(name.clone(), nodes);
        }
    }
}

/// Give tets whose centroid (metres) lies inside a subregion shape (spec units, scale `s`
/// metres per unit) that subregion's tag and name.
fn apply_subregions(mesh: &mut Mesh, subs: &[(Shape, i32, String)], s: f64) {
    for (shape, tag, name) in subs {
        let mut any = false;
        for e in 0..mesh.tets.len() {
            let p = mesh.tet_points(e);
            let c = [0, 1, 2].map(|k| (p[0][k] + p[1][k] + p[2][k] + p[3][k]) / (4.0 * s));
            if shape.sdf(c) < 0.0 {
                mesh.tet_tags[e] = *tag;
                any = true;
            }
        }
        if any {
            mesh.set_name(3, *tag, name);
        }
    }
    let used = mesh.region_tags();
    mesh.names.retain(|p| p.dim != 3 || used.contains(&p.tag));
}

fn retag_region(mesh: &mut Mesh, region: &TagSpec) {
    for t in &mut mesh.tet_tags {
        *t = region.tag;
    }
    mesh.names.retain(|p| p.dim != 3);
    mesh.set_name(3, region.tag, &region.name);
}
