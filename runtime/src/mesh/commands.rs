//! The work behind `softc mesh ...` (the clap layer is `crate::cli::mesh`). Each command
//! returns its exit code (0 ok, 1 bad input, 2 a file that cannot be read or written) and
//! writes messages to the given sinks, so it can be tested without a process.

use std::io::Write;
use std::path::Path;

use serde_json::json;

use super::error::MeshError;
use super::kuhn::{KuhnSpec, kuhn_grid};
use super::mesher::{MeshSpec, generate as gen_mesh};
use super::model::{LengthUnit, Mesh};
use super::validate::{Severity, has_errors};

/// Report `e`: a file that cannot be opened, read or written is a usage error (2), as the
/// exit-status table (docs/src/reference/exit-status.md) says; a bad mesh or spec is bad input (1).
fn fail(err: &mut dyn Write, e: &MeshError) -> i32 {
    let _ = writeln!(err, "error: {e}");
    match e.kind {
        super::error::MeshErrorKind::Io => 2,
        _ => 1,
    }
}

/// `softc mesh generate SPEC -o OUT [--resolution H]`.
pub fn generate(
    spec_path: &Path,
    output: &Path,
    resolution: Option<f64>,
    out: &mut dyn Write,
    err: &mut dyn Write,
) -> i32 {
    let spec = match MeshSpec::from_file(spec_path) {
        Ok(s) => s,
        Err(e) => return fail(err, &e),
    };
    let unit = match spec.unit() {
        Ok(u) => u,
        Err(e) => return fail(err, &e.in_file(spec_path)),
    };
    let base = spec_path.parent().unwrap_or(Path::new("."));
    let g = match gen_mesh(&spec, resolution, base) {
        Ok(g) => g,
        Err(e) => return fail(err, &e.in_file(spec_path)),
    };
    let issues = g.mesh.validate();
    for i in &issues {
        let _ = writeln!(err, "{}: {i}", spec_path.display());
    }
    if has_errors(&issues) {
        let _ = writeln!(
            err,
            "error: {}: the generated mesh is invalid; try a finer resolution (features thinner \
             than about two lattice cells are not resolved)",
            spec_path.display()
        );
        return 1;
    }
    if let Err(e) = super::save(&g.mesh, output, unit) {
        return fail(err, &e);
    }
    let q = g.mesh.quality(Some(g.reference_volume));
    let _ = writeln!(
        out,
        "wrote {}: {} nodes, {} tets in {:.3} s ({:.0} tets/s)",
        output.display(),
        q.nodes,
        q.tets,
        g.seconds,
        q.tets as f64 / g.seconds.max(1e-9)
    );
    let _ = writeln!(
        out,
        "dihedral angles [{:.2}°, {:.2}°], worst aspect ratio R/(3r) {:.3}, volume error {:+.4} %",
        q.min_dihedral_deg,
        q.max_dihedral_deg,
        q.worst_aspect_ratio,
        100.0 * q.volume_error.unwrap_or(0.0)
    );
    for (tag, v) in &g.cavity_volumes {
        let mv = g.mesh.enclosed_volume(*tag);
        let _ = writeln!(
            out,
            "chamber {tag} ({}): volume {:.6e} m³, exact {:.6e} m³ ({:+.3} %)",
            g.mesh.tag_name(2, *tag).unwrap_or(""),
            mv,
            v,
            100.0 * (mv - v) / v
        );
    }
    0
}

/// The `info` report as JSON (SI units).
pub fn info_json(mesh: &Mesh, file: &Path) -> serde_json::Value {
    let q = mesh.quality(None);
    let issues = mesh.validate();
    let chambers = mesh.chamber_tags();
    let regions: Vec<_> = mesh
        .region_tags()
        .into_iter()
        .map(|t| {
            let vol: f64 = (0..mesh.tets.len())
                .filter(|e| mesh.tet_tags[*e] == t)
                .map(|e| mesh.element_volume(e))
                .sum();
            json!({
                "tag": t,
                "name": mesh.tag_name(3, t),
                "tets": mesh.tet_tags.iter().filter(|x| **x == t).count(),
                "volume": vol,
            })
        })
        .collect();
    let surfaces: Vec<_> = mesh
        .surface_tags()
        .into_iter()
        .map(|t| {
            json!({
                "tag": t,
                "name": mesh.tag_name(2, t),
                "triangles": mesh.tri_tags.iter().filter(|x| **x == t).count(),
                "area": mesh.surface_area(t),
                "chamber": chambers.contains(&t),
            })
        })
        .collect();
    let ch: Vec<_> = chambers
        .iter()
        .map(|&t| {
            json!({
                "tag": t,
                "name": mesh.tag_name(2, t).map(str::to_string).unwrap_or_else(|| format!("tag{t}")),
                "volume": mesh.enclosed_volume(t),
                "area": mesh.surface_area(t),
            })
        })
        .collect();
    let (lo, hi) = mesh.bounding_box();
    json!({
        "file": file.display().to_string(),
        "nodes": q.nodes,
        "tets": q.tets,
        "order": mesh.order(),
        "mid_edge_nodes": mesh.mid_edge_node_count(),
        "node_span": super::renumber::span(mesh),
        "volume": q.volume,
        "bounding_box": {"min": lo, "max": hi},
        "regions": regions,
        "surfaces": surfaces,
        "chambers": ch,
        "node_sets": mesh.node_sets.iter().map(|(k, v)| json!({"name": k, "nodes": v.len()})).collect::<Vec<_>>(),
        "min_dihedral_deg": q.min_dihedral_deg,
        "max_dihedral_deg": q.max_dihedral_deg,
        "worst_aspect_ratio": q.worst_aspect_ratio,
        "worst_dihedral_tet": mesh.tet_id(q.worst_dihedral_element),
        "worst_aspect_tet": mesh.tet_id(q.worst_aspect_element),
        "aspect_ratio_definition": "circumradius / (3 * inradius), 1 for a regular tet",
        "min_edge": q.min_edge,
        "max_edge": q.max_edge,
        "reoriented_tets": mesh.report.reoriented_tets,
        "reoriented_faces": mesh.report.reoriented_faces,
        "ignored_elements": mesh.report.ignored_elements,
        "valid": !has_errors(&issues),
        "issues": issues.iter().map(|i| json!({
            "severity": if i.severity == Severity::Error { "error" } else { "warning" },
            "message": i.message,
        })).collect::<Vec<_>>(),
    })
}

/// The element order in words, for `info` and `convert`.
fn order_line(mesh: &Mesh) -> String {
    if mesh.is_quadratic() {
        format!(
            "elements: quadratic (10-node tets, {} mid-edge nodes)",
            mesh.mid_edge_node_count()
        )
    } else {
        "elements: linear (4-node tets)".to_string()
    }
}

/// A node span above this (a structured mesh's is ~0.1, a random numbering's ~0.75) makes
/// `softc mesh info` suggest `convert --renumber`.
const SCATTERED_SPAN: f64 = 0.25;

/// `softc mesh info FILE [--json] [--unit mm]`: exit 1 if the file cannot be read or the
/// mesh has validation errors.
pub fn info(
    file: &Path,
    unit: LengthUnit,
    as_json: bool,
    out: &mut dyn Write,
    err: &mut dyn Write,
) -> i32 {
    let mesh = match super::read(file, unit) {
        Ok(m) => m,
        Err(e) => return fail(err, &e),
    };
    let issues = mesh.validate();
    if as_json {
        let _ = writeln!(
            out,
            "{}",
            serde_json::to_string_pretty(&info_json(&mesh, file)).unwrap_or_default()
        );
    } else {
        let q = mesh.quality(None);
        let mm3 = 1e9;
        let _ = writeln!(
            out,
            "{}: {} nodes, {} tets, volume {:.6} mm³ (read in {unit})",
            file.display(),
            q.nodes,
            q.tets,
            q.volume * mm3
        );
        let _ = writeln!(out, "{}", order_line(&mesh));
        let (lo, hi) = mesh.bounding_box();
        let _ = writeln!(
            out,
            "bounding box [{:.4}, {:.4}, {:.4}] – [{:.4}, {:.4}, {:.4}] mm",
            lo[0] * 1e3,
            lo[1] * 1e3,
            lo[2] * 1e3,
            hi[0] * 1e3,
            hi[1] * 1e3,
            hi[2] * 1e3
        );
        let span = super::renumber::span(&mesh);
        let _ = writeln!(
            out,
            "node span {:.1} % (an element's node numbers apart, over the node count, on average){}",
            100.0 * span,
            if span > SCATTERED_SPAN {
                format!(
                    ": scattered numbering slows the kernels by up to a third; `softc mesh \
                     convert --renumber {} OUT` writes a renumbered copy",
                    file.display()
                )
            } else {
                String::new()
            }
        );
        for t in mesh.region_tags() {
            let n = mesh.tet_tags.iter().filter(|x| **x == t).count();
            let _ = writeln!(
                out,
                "region {t} {}: {n} tets",
                mesh.tag_name(3, t)
                    .map(|s| format!("\"{s}\""))
                    .unwrap_or_default()
            );
        }
        let chambers = mesh.chamber_tags();
        for t in mesh.surface_tags() {
            let n = mesh.tri_tags.iter().filter(|x| **x == t).count();
            let name = mesh
                .tag_name(2, t)
                .map(|s| format!("\"{s}\""))
                .unwrap_or_default();
            if chambers.contains(&t) {
                let _ = writeln!(
                    out,
                    "chamber {t} {name}: {n} triangles, enclosed volume {:.6} mm³, area {:.6} mm²",
                    mesh.enclosed_volume(t) * mm3,
                    mesh.surface_area(t) * 1e6
                );
            } else {
                let _ = writeln!(
                    out,
                    "surface {t} {name}: {n} triangles, area {:.6} mm²",
                    mesh.surface_area(t) * 1e6
                );
            }
        }
        let _ = writeln!(
            out,
            "dihedral angles [{:.2}°, {:.2}°] (worst tet {}), worst aspect ratio R/(3r) {:.3} (tet {})",
            q.min_dihedral_deg,
            q.max_dihedral_deg,
            mesh.tet_id(q.worst_dihedral_element),
            q.worst_aspect_ratio,
            mesh.tet_id(q.worst_aspect_element)
        );
        if mesh.report.reoriented_tets > 0 || mesh.report.reoriented_faces > 0 {
            let _ = writeln!(
                out,
                "reoriented on load: {} tets, {} surface triangles",
                mesh.report.reoriented_tets, mesh.report.reoriented_faces
            );
        }
        for (k, n) in &mesh.report.ignored_elements {
            let _ = writeln!(out, "ignored {n} element(s) of kind {k}");
        }
        for i in &issues {
            let _ = writeln!(out, "{i}");
        }
        if issues.is_empty() {
            let _ = writeln!(out, "valid: no issues");
        }
    }
    if has_errors(&issues) {
        let _ = writeln!(
            err,
            "error: {}: the mesh is invalid (see the issues above)",
            file.display()
        );
        return 1;
    }
    0
}

/// `softc mesh convert IN OUT`: any readable format to `.msh` or `.vtu`. `order` 2 inserts a
/// straight-sided mid-edge node on every edge ([`Mesh::with_mid_edges`]), 1 drops them
/// ([`Mesh::without_mid_edges`]); `None` keeps the file's order.
pub fn convert(
    input: &Path,
    output: &Path,
    unit: LengthUnit,
    renumber: bool,
    order: Option<u8>,
    out: &mut dyn Write,
    err: &mut dyn Write,
) -> i32 {
    let mut mesh = match super::load(input, unit) {
        Ok(m) => m,
        Err(e) => return fail(err, &e),
    };
    match order {
        None => {}
        Some(1) => mesh = mesh.without_mid_edges(),
        Some(2) => mesh = mesh.with_mid_edges(),
        Some(o) => {
            let _ = writeln!(err, "error: --order {o}: softc meshes are of order 1 or 2");
            return 2;
        }
    }
    if renumber {
        let before = super::renumber::span(&mesh);
        let order = super::renumber::locality_order(&mesh);
        mesh.renumber_nodes(&order);
        let _ = writeln!(
            out,
            "renumbered the nodes: node span {:.1} % -> {:.1} %",
            100.0 * before,
            100.0 * super::renumber::span(&mesh)
        );
    }
    if let Err(e) = super::save(&mesh, output, unit) {
        return fail(err, &e);
    }
    let _ = writeln!(
        out,
        "wrote {}: {} nodes, {} tets; {}",
        output.display(),
        mesh.nodes.len(),
        mesh.tets.len(),
        order_line(&mesh)
    );
    0
}

/// `softc mesh kuhn NX NY NZ -o OUT`: the benchmark scene of BENCHMARK.md.
pub fn kuhn(
    n: [usize; 3],
    order: u8,
    output: &Path,
    out: &mut dyn Write,
    err: &mut dyn Write,
) -> i32 {
    let mesh = match kuhn_grid(
        &KuhnSpec::benchmark(n[0], n[1], n[2]),
        LengthUnit::Millimetre,
    ) {
        Ok(m) if order == 2 => m.with_mid_edges(),
        Ok(m) => m,
        Err(e) => return fail(err, &e.in_file(output)),
    };
    if let Err(e) = super::save(&mesh, output, LengthUnit::Millimetre) {
        return fail(err, &e);
    }
    let _ = writeln!(
        out,
        "wrote {}: {} nodes, {} tets",
        output.display(),
        mesh.nodes.len(),
        mesh.tets.len()
    );
    0
}
