//! VTK XML unstructured grid (`.vtu`) reader: `DataArray`s in `ascii`, inline `binary`
//! (base64, uncompressed) or raw `appended` format, UInt32/UInt64 headers, either byte order.
//! Tags as in the legacy reader. Hand-written (≈250 lines) instead of `vtkio`, which pulls a
//! large dependency tree into the runtime for one file format.

use std::collections::BTreeMap;
use std::path::Path;

use super::vtk::{TAG_NAMES, assemble};
use super::{Cursor, parse_float, read_bytes};
use crate::mesh::error::MeshError;
use crate::mesh::model::{LengthUnit, Mesh};

fn attrs(tag: &str) -> BTreeMap<String, String> {
    let mut m = BTreeMap::new();
    let mut rest = tag;
    while let Some(eq) = rest.find('=') {
        let key = rest[..eq]
            .split_whitespace()
            .last()
            .unwrap_or("")
            .to_string();
        let after = rest[eq + 1..].trim_start();
        let Some(q) = after.chars().next().filter(|c| *c == '"' || *c == '\'') else {
            break;
        };
        let body = &after[1..];
        let Some(end) = body.find(q) else { break };
        m.insert(key, body[..end].to_string());
        rest = &body[end + 1..];
    }
    m
}

fn b64_decode(s: &str) -> Option<Vec<u8>> {
    let val = |c: u8| -> Option<u32> {
        Some(match c {
            b'A'..=b'Z' => (c - b'A') as u32,
            b'a'..=b'z' => (c - b'a' + 26) as u32,
            b'0'..=b'9' => (c - b'0' + 52) as u32,
            b'+' => 62,
            b'/' => 63,
            _ => return None,
        })
    };
    let clean: Vec<u8> = s.bytes().filter(|b| !b.is_ascii_whitespace()).collect();
    if !clean.len().is_multiple_of(4) {
        return None;
    }
    let mut out = Vec::with_capacity(clean.len() / 4 * 3);
    for g in clean.chunks(4) {
        let pad = g.iter().rev().take_while(|&&b| b == b'=').count();
        if pad > 2 {
            return None;
        }
        let mut n = 0u32;
        for &b in &g[..4 - pad] {
            n = (n << 6) | val(b)?;
        }
        n <<= 6 * pad as u32;
        let bytes = [(n >> 16) as u8, (n >> 8) as u8, n as u8];
        out.extend_from_slice(&bytes[..3 - pad]);
    }
    Some(out)
}

struct Ctx<'a> {
    path: &'a Path,
    little: bool,
    header64: bool,
    appended: Option<&'a [u8]>,
}

fn type_size(t: &str) -> Option<usize> {
    Some(match t {
        "Int8" | "UInt8" => 1,
        "Int16" | "UInt16" => 2,
        "Int32" | "UInt32" | "Float32" => 4,
        "Int64" | "UInt64" | "Float64" => 8,
        _ => return None,
    })
}

fn decode_bin(ctx: &Ctx, ty: &str, bytes: &[u8]) -> Vec<f64> {
    let sz = type_size(ty).unwrap_or(8);
    bytes
        .chunks_exact(sz)
        .map(|ch| {
            let mut b = [0u8; 8];
            if ctx.little {
                b[..sz].copy_from_slice(ch);
            } else {
                for (k, x) in ch.iter().rev().enumerate() {
                    b[k] = *x;
                }
            }
            let u = u64::from_le_bytes(b);
            match ty {
                "Int8" => u as u8 as i8 as f64,
                "UInt8" => u as u8 as f64,
                "Int16" => u as u16 as i16 as f64,
                "UInt16" => u as u16 as f64,
                "Int32" => u as u32 as i32 as f64,
                "UInt32" => u as u32 as f64,
                "Int64" => u as i64 as f64,
                "UInt64" => u as f64,
                "Float32" => f32::from_bits(u as u32) as f64,
                _ => f64::from_bits(u),
            }
        })
        .collect()
}

fn strip_header(ctx: &Ctx, bytes: &[u8], name: &str) -> Result<Vec<u8>, MeshError> {
    let hs = if ctx.header64 { 8 } else { 4 };
    if bytes.len() < hs {
        return Err(
            MeshError::parse(format!("binary array `{name}` is truncated")).in_file(ctx.path),
        );
    }
    let mut b = [0u8; 8];
    if ctx.little {
        b[..hs].copy_from_slice(&bytes[..hs]);
    } else {
        for (k, x) in bytes[..hs].iter().rev().enumerate() {
            b[k] = *x;
        }
    }
    let n = u64::from_le_bytes(b) as usize;
    if bytes.len() - hs < n {
        return Err(MeshError::parse(format!(
            "binary array `{name}` declares {n} bytes but holds {}",
            bytes.len() - hs
        ))
        .in_file(ctx.path)
        .with_fix("the file is truncated; re-export it"));
    }
    Ok(bytes[hs..hs + n].to_vec())
}

/// Values of one `<DataArray ...>content</DataArray>`.
fn array_values(ctx: &Ctx, head: &str, content: &str, line: usize) -> Result<Vec<f64>, MeshError> {
    let a = attrs(head);
    let name = a.get("Name").cloned().unwrap_or_default();
    let ty = a.get("type").cloned().unwrap_or_else(|| "Float64".into());
    if type_size(&ty).is_none() {
        return Err(
            MeshError::unsupported(format!("DataArray `{name}` has type {ty}"))
                .in_file(ctx.path)
                .at_line(line),
        );
    }
    let err = |m: String| MeshError::parse(m).in_file(ctx.path).at_line(line);
    match a.get("format").map(String::as_str).unwrap_or("ascii") {
        "ascii" => content
            .split_whitespace()
            .map(|t| {
                parse_float(t).ok_or_else(|| err(format!("bad number `{t}` in array `{name}`")))
            })
            .collect(),
        "binary" => {
            let bytes = b64_decode(content)
                .ok_or_else(|| err(format!("array `{name}` is not valid base64")))?;
            Ok(decode_bin(ctx, &ty, &strip_header(ctx, &bytes, &name)?))
        }
        "appended" => {
            let app = ctx
                .appended
                .ok_or_else(|| err("appended array but no raw <AppendedData>".into()))?;
            let off: usize = a
                .get("offset")
                .and_then(|o| o.parse().ok())
                .ok_or_else(|| err(format!("appended array `{name}` has no offset")))?;
            if off > app.len() {
                return Err(err(format!(
                    "appended array `{name}` offset {off} is past the data"
                )));
            }
            Ok(decode_bin(
                ctx,
                &ty,
                &strip_header(ctx, &app[off..], &name)?,
            ))
        }
        f => Err(err(format!("DataArray format `{f}` is not supported"))),
    }
}

/// Read a `.vtu` file.
pub fn read(path: &Path, unit: LengthUnit) -> Result<Mesh, MeshError> {
    let data = read_bytes(path)?;
    let cur = Cursor::new(&data, path);
    // Split off raw appended data (binary) before treating the rest as text.
    let (xml_bytes, appended) = match find(&data, b"<AppendedData") {
        Some(k) => {
            let tag_end = data[k..].iter().position(|&b| b == b'>').map(|e| k + e + 1);
            let Some(te) = tag_end else {
                return Err(MeshError::parse("unterminated <AppendedData> tag").in_file(path));
            };
            let head = String::from_utf8_lossy(&data[k..te]).into_owned();
            let enc = attrs(&head).get("encoding").cloned().unwrap_or_default();
            if enc != "raw" {
                return Err(
                    MeshError::unsupported(format!("appended data encoding `{enc}`"))
                        .in_file(path)
                        .with_fix("save the .vtu with raw appended data, inline binary or ascii"),
                );
            }
            let us = data[te..]
                .iter()
                .position(|&b| b == b'_')
                .map(|u| te + u + 1);
            (&data[..k], us.map(|u| &data[u..]))
        }
        None => (&data[..], None),
    };
    let xml = std::str::from_utf8(xml_bytes)
        .map_err(|_| MeshError::parse("the XML part of the file is not UTF-8").in_file(path))?;
    if !xml.contains("UnstructuredGrid") {
        return Err(MeshError::parse("not a VTK UnstructuredGrid XML file")
            .in_file(path)
            .with_fix("softc reads .vtu unstructured grids"));
    }
    // Every writer closes the root element last (after any appended data): without it the
    // file was cut short, and a missing element further down would be the wrong diagnosis.
    if find(&data, b"</VTKFile>").is_none() {
        let end = cur.line_at(data.len().saturating_sub(1));
        return Err(MeshError::parse(format!(
            "the file is truncated: it ends at line {end} without `</VTKFile>`"
        ))
        .in_file(path)
        .at_line(end)
        .with_fix("re-export or copy the file again"));
    }
    if let Some(k) = xml.find("<VTKFile") {
        let end = xml[k..].find('>').map(|e| k + e).unwrap_or(xml.len());
        let a = attrs(&xml[k..end]);
        if a.contains_key("compressor") {
            return Err(MeshError::unsupported("compressed .vtu data")
                .in_file(path)
                .with_fix(
                    "save the .vtu uncompressed (ParaView: Data Mode ascii/binary, no compression)",
                ));
        }
    }
    let vtk_attrs = xml
        .find("<VTKFile")
        .map(|k| attrs(&xml[k..k + xml[k..].find('>').unwrap_or(0)]))
        .unwrap_or_default();
    let ctx = Ctx {
        path,
        little: vtk_attrs.get("byte_order").map(String::as_str) != Some("BigEndian"),
        header64: vtk_attrs.get("header_type").map(String::as_str) == Some("UInt64"),
        appended,
    };
    let section = |name: &str| -> Option<(usize, &str)> {
        let open = format!("<{name}");
        let close = format!("</{name}>");
        let s = xml.find(&open)?;
        let e = xml[s..].find(&close)? + s;
        Some((s, &xml[s..e]))
    };
    let arrays = |sec: Option<(usize, &str)>| -> Result<Vec<(String, usize, Vec<f64>)>, MeshError> {
        let mut out = Vec::new();
        let Some((base, text)) = sec else {
            return Ok(out);
        };
        let mut rest = 0;
        while let Some(k) = text[rest..].find("<DataArray") {
            let s = rest + k;
            let he = text[s..]
                .find('>')
                .map(|e| s + e)
                .ok_or_else(|| MeshError::parse("unterminated <DataArray> tag").in_file(path))?;
            let head = &text[s..he];
            let line = cur.line_at(base + s);
            let a = attrs(head);
            let name = a.get("Name").cloned().unwrap_or_default();
            let ncomp: usize = a
                .get("NumberOfComponents")
                .and_then(|n| n.parse().ok())
                .unwrap_or(1);
            let (content, next) = if head.ends_with('/') {
                ("", he + 1)
            } else {
                let ce = text[he..]
                    .find("</DataArray>")
                    .map(|e| he + e)
                    .ok_or_else(|| {
                        MeshError::parse(format!("DataArray `{name}` is not closed"))
                            .in_file(path)
                            .at_line(line)
                            .with_fix("the file is truncated; re-export it")
                    })?;
                (&text[he + 1..ce], ce + 12)
            };
            let vals = array_values(&ctx, head, content, line)?;
            out.push((name, ncomp, vals));
            rest = next;
        }
        Ok(out)
    };
    let piece =
        section("Piece").ok_or_else(|| MeshError::parse("no <Piece> element").in_file(path))?;
    let pa = attrs(&piece.1[..piece.1.find('>').unwrap_or(0)]);
    let npts: usize = pa
        .get("NumberOfPoints")
        .and_then(|n| n.parse().ok())
        .unwrap_or(0);
    let ncells: usize = pa
        .get("NumberOfCells")
        .and_then(|n| n.parse().ok())
        .unwrap_or(0);
    let pts = arrays(section("Points"))?;
    let (_, _, pv) = pts
        .first()
        .ok_or_else(|| MeshError::parse("no point coordinates").in_file(path))?;
    if pv.len() != 3 * npts {
        return Err(MeshError::parse(format!(
            "<Points> holds {} values for {npts} points (need 3 per point)",
            pv.len()
        ))
        .in_file(path));
    }
    let points: Vec<[f64; 3]> = pv.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect();
    let cells_arr = arrays(section("Cells"))?;
    let get = |n: &str| {
        cells_arr
            .iter()
            .find(|a| a.0 == n)
            .map(|a| a.2.clone())
            .ok_or_else(|| MeshError::parse(format!("<Cells> has no `{n}` array")).in_file(path))
    };
    let conn = get("connectivity")?;
    let offs = get("offsets")?;
    let types = get("types")?;
    if offs.len() != ncells || types.len() != ncells {
        return Err(MeshError::parse(format!(
            "NumberOfCells is {ncells} but there are {} offsets and {} types",
            offs.len(),
            types.len()
        ))
        .in_file(path));
    }
    let mut cells = Vec::with_capacity(ncells);
    let mut prev = 0usize;
    for (i, &o) in offs.iter().enumerate() {
        let o = o as usize;
        if o < prev || o > conn.len() {
            return Err(MeshError::parse(format!(
                "cell {i}: offset {o} is out of order or past the connectivity"
            ))
            .in_file(path));
        }
        cells.push(conn[prev..o].iter().map(|x| *x as i64).collect());
        prev = o;
    }
    let cd = arrays(section("CellData"))?;
    let mut tags = None;
    for n in TAG_NAMES {
        if let Some(a) = cd.iter().find(|a| a.0.eq_ignore_ascii_case(n) && a.1 == 1) {
            tags = Some(a.2.iter().map(|x| *x as i64).collect());
            break;
        }
    }
    let raw = assemble(
        &cur,
        points,
        cells,
        types.iter().map(|x| *x as i64).collect(),
        tags,
    )?;
    raw.finish(path, unit)
}

fn find(hay: &[u8], needle: &[u8]) -> Option<usize> {
    hay.windows(needle.len()).position(|w| w == needle)
}
