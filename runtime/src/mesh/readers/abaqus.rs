//! Abaqus `.inp` reader: `*NODE`, `*ELEMENT, TYPE=C3D4` (element sets on the keyword line
//! become regions), `*ELSET`, `*NSET` (with `GENERATE`), `*SURFACE, TYPE=ELEMENT` (element
//! faces S1–S4 become tagged triangles). Other keywords are skipped; other solid element
//! types are refused.

use std::collections::BTreeMap;
use std::path::Path;

use super::{RawElem, RawMesh, parse_float, read_bytes, truncate};
use crate::mesh::error::MeshError;
use crate::mesh::model::{LengthUnit, Mesh, PhysicalName};

/// C3D4 faces S1..S4 as 0-based corner triples (Abaqus manual, "three-dimensional solid
/// element library").
const C3D4_FACES: [[usize; 3]; 4] = [[0, 1, 2], [0, 3, 1], [1, 3, 2], [2, 3, 0]];

fn params(line: &str) -> (String, BTreeMap<String, String>) {
    let mut parts = line.trim_start_matches('*').split(',');
    let kw = parts.next().unwrap_or("").trim().to_ascii_uppercase();
    let mut map = BTreeMap::new();
    for p in parts {
        let mut kv = p.splitn(2, '=');
        let k = kv.next().unwrap_or("").trim().to_ascii_uppercase();
        let v = kv.next().unwrap_or("").trim().to_string();
        if !k.is_empty() {
            map.insert(k, v);
        }
    }
    (kw, map)
}

/// Read an Abaqus input file.
pub fn read(path: &Path, unit: LengthUnit) -> Result<Mesh, MeshError> {
    let bytes = read_bytes(path)?;
    let text = String::from_utf8(bytes)
        .map_err(|_| MeshError::parse("the file is not text (invalid UTF-8)").in_file(path))?;
    let err = |line: usize, msg: String| MeshError::parse(msg).in_file(path).at_line(line);
    let mut raw = RawMesh::default();
    let mut region_names: Vec<String> = Vec::new();
    let mut elsets: BTreeMap<String, Vec<i64>> = BTreeMap::new();
    let mut nsets: BTreeMap<String, Vec<i64>> = BTreeMap::new();
    // (surface name, [(elset name or element id, face number, line)])
    type Entries = Vec<(String, usize, usize)>;
    let mut surfaces: Vec<(String, Entries)> = Vec::new();
    enum Mode {
        Skip,
        Node,
        Elem { tag: i32, elset: Option<String> },
        Elset { name: String, generate: bool },
        Nset { name: String, generate: bool },
        Surface,
    }
    let mut mode = Mode::Skip;
    let ints = |line: usize, toks: &[&str]| -> Result<Vec<i64>, MeshError> {
        toks.iter()
            .filter(|t| !t.is_empty())
            .map(|t| {
                t.parse::<i64>().map_err(|_| {
                    err(
                        line,
                        format!("expected an integer, found `{}`", truncate(t)),
                    )
                })
            })
            .collect()
    };
    for (i, l) in text.lines().enumerate() {
        let line = i + 1;
        let l = l.trim();
        if l.is_empty() || l.starts_with("**") {
            continue;
        }
        if l.starts_with('*') {
            let (kw, p) = params(l);
            mode = match kw.as_str() {
                "NODE" => Mode::Node,
                "ELEMENT" => {
                    let ty = p
                        .get("TYPE")
                        .cloned()
                        .unwrap_or_default()
                        .to_ascii_uppercase();
                    if ty == "C3D4" || ty == "C3D4H" {
                        let name = p.get("ELSET").cloned().unwrap_or_else(|| "solid".into());
                        let tag = match region_names.iter().position(|n| *n == name) {
                            Some(k) => k as i32 + 1,
                            None => {
                                region_names.push(name.clone());
                                region_names.len() as i32
                            }
                        };
                        Mode::Elem {
                            tag,
                            elset: Some(name),
                        }
                    } else if ty.starts_with("C3D") {
                        return Err(err(line, format!(
                            "element type {ty} is not supported; softc reads 4-node tets (C3D4) \
                             from Abaqus files"
                        ))
                        .with_fix(
                            "mesh with C3D4 elements (then `softc mesh convert --order 2` for \
                             10-node tets), or export 10-node tets as gmsh .msh or VTK",
                        ));
                    } else {
                        *raw.ignored.entry(format!("abaqus {ty}")).or_insert(0) += 1;
                        Mode::Skip
                    }
                }
                "ELSET" => Mode::Elset {
                    name: p.get("ELSET").cloned().unwrap_or_default(),
                    generate: p.contains_key("GENERATE"),
                },
                "NSET" => Mode::Nset {
                    name: p.get("NSET").cloned().unwrap_or_default(),
                    generate: p.contains_key("GENERATE"),
                },
                "SURFACE" => {
                    let ty = p.get("TYPE").cloned().unwrap_or_else(|| "ELEMENT".into());
                    if !ty.eq_ignore_ascii_case("ELEMENT") {
                        Mode::Skip
                    } else {
                        surfaces.push((p.get("NAME").cloned().unwrap_or_default(), Vec::new()));
                        Mode::Surface
                    }
                }
                _ => Mode::Skip,
            };
            continue;
        }
        let toks: Vec<&str> = l
            .split(',')
            .map(str::trim)
            .filter(|t| !t.is_empty())
            .collect();
        let is_n = matches!(mode, Mode::Nset { .. });
        match &mut mode {
            Mode::Skip => {}
            Mode::Node => {
                if toks.len() < 4 {
                    return Err(err(line, "a *NODE line needs `id, x, y, z`".into()));
                }
                let id: i64 = toks[0]
                    .parse()
                    .map_err(|_| err(line, format!("bad node id `{}`", truncate(toks[0]))))?;
                let mut p = [0.0; 3];
                for k in 0..3 {
                    p[k] = parse_float(toks[1 + k]).ok_or_else(|| {
                        err(line, format!("bad coordinate `{}`", truncate(toks[1 + k])))
                    })?;
                }
                raw.add_node(id, p, line);
            }
            Mode::Elem { tag, elset } => {
                let v = ints(line, &toks)?;
                if v.len() != 5 {
                    return Err(err(
                        line,
                        format!(
                            "a C3D4 element needs `id, n1, n2, n3, n4`, found {} numbers",
                            v.len()
                        ),
                    ));
                }
                raw.tets.push(RawElem {
                    id: v[0],
                    nodes: [v[1], v[2], v[3], v[4]],
                    tag: *tag,
                    line,
                });
                if let Some(n) = elset {
                    elsets.entry(n.clone()).or_default().push(v[0]);
                }
            }
            Mode::Elset { name, generate } | Mode::Nset { name, generate } => {
                let v = ints(line, &toks)?;
                let ids: Vec<i64> = if *generate {
                    if v.len() < 2 {
                        return Err(err(line, "GENERATE needs `first, last[, step]`".into()));
                    }
                    let step = v.get(2).copied().unwrap_or(1);
                    if step <= 0 || v[1] < v[0] || (v[1] - v[0]) / step > 100_000_000 {
                        return Err(err(line, "bad GENERATE range".into()));
                    }
                    (v[0]..=v[1]).step_by(step as usize).collect()
                } else {
                    v
                };
                let map = if is_n { &mut nsets } else { &mut elsets };
                map.entry(name.clone()).or_default().extend(ids);
            }
            Mode::Surface => {
                if toks.len() < 2 {
                    return Err(err(
                        line,
                        "a *SURFACE line needs `element or elset, S1..S4`".into(),
                    ));
                }
                let face = match toks[1].to_ascii_uppercase().as_str() {
                    "S1" => 0,
                    "S2" => 1,
                    "S3" => 2,
                    "S4" => 3,
                    other => {
                        return Err(err(
                            line,
                            format!("unknown face `{}` (use S1..S4)", truncate(other)),
                        ));
                    }
                };
                if let Some(s) = surfaces.last_mut() {
                    s.1.push((toks[0].to_string(), face, line));
                }
            }
        }
    }
    if raw.tets.is_empty() {
        return Err(MeshError::parse("no C3D4 elements found")
            .in_file(path)
            .with_fix("the file needs *ELEMENT, TYPE=C3D4 blocks"));
    }
    for (k, n) in region_names.iter().enumerate() {
        raw.names.push(PhysicalName {
            dim: 3,
            tag: k as i32 + 1,
            name: n.clone(),
        });
    }
    // Surfaces → triangles on element faces.
    let by_id: BTreeMap<i64, usize> = raw
        .tets
        .iter()
        .enumerate()
        .map(|(i, t)| (t.id, i))
        .collect();
    for (si, (name, entries)) in surfaces.iter().enumerate() {
        let tag = si as i32 + 1;
        raw.names.push(PhysicalName {
            dim: 2,
            tag,
            name: name.clone(),
        });
        for (target, face, line) in entries {
            let elems: Vec<i64> = match target.parse::<i64>() {
                Ok(id) => vec![id],
                Err(_) => elsets.get(target).cloned().ok_or_else(|| {
                    err(
                        *line,
                        format!("surface `{name}` refers to unknown element set `{target}`"),
                    )
                })?,
            };
            for e in elems {
                let t = by_id.get(&e).ok_or_else(|| {
                    err(
                        *line,
                        format!("surface `{name}` refers to element {e}, which is not a C3D4"),
                    )
                })?;
                let tn = raw.tets[*t].nodes;
                let f = C3D4_FACES[*face];
                // Abaqus face nodes wind with the outward normal; softc stores surfaces with
                // normals into the solid (finish() re-checks against the tets anyway).
                raw.tris.push(RawElem {
                    id: e,
                    nodes: [tn[f[0]], tn[f[2]], tn[f[1]]],
                    tag,
                    line: *line,
                });
            }
        }
    }
    raw.node_sets = nsets;
    raw.elem_sets = elsets;
    raw.finish(path, unit)
}
