//! STL surfaces (ASCII and binary) for the mesher. Vertices are welded by exact position.
//! Written by hand (≈80 lines) rather than with `stl_io`, to weld, check closedness and give
//! errors with line numbers in one place.

use std::collections::HashMap;
use std::path::Path;

use super::{Cursor, read_bytes};
use crate::mesh::error::MeshError;

/// Welded vertices and triangles of a surface.
pub type Surface = (Vec<[f64; 3]>, Vec<[u32; 3]>);

/// Read an STL file into welded vertices and triangles (file units).
pub fn read(path: &Path) -> Result<Surface, MeshError> {
    let data = read_bytes(path)?;
    let mut soup: Vec<[[f64; 3]; 3]> = Vec::new();
    let is_binary = data.len() >= 84 && {
        let n = u32::from_le_bytes([data[80], data[81], data[82], data[83]]) as usize;
        n.checked_mul(50).and_then(|x| x.checked_add(84)) == Some(data.len())
    };
    if is_binary {
        let n = (data.len() - 84) / 50;
        for i in 0..n {
            let base = 84 + 50 * i + 12;
            let mut t = [[0.0; 3]; 3];
            for (v, tv) in t.iter_mut().enumerate() {
                for (k, c) in tv.iter_mut().enumerate() {
                    let o = base + 12 * v + 4 * k;
                    *c =
                        f32::from_le_bytes([data[o], data[o + 1], data[o + 2], data[o + 3]]) as f64;
                }
            }
            soup.push(t);
        }
    } else {
        let mut c = Cursor::new(&data, path);
        if c.token() != Some("solid") {
            return Err(c
                .err("not an STL file: neither binary (size ≠ 84 + 50·count) nor ASCII (`solid`)")
                .with_fix("export the surface as STL"));
        }
        c.rest_of_line();
        loop {
            match c.token() {
                Some("facet") => {
                    // normal nx ny nz (ignored: winding defines orientation)
                    for _ in 0..4 {
                        c.need("facet normal")?;
                    }
                    if c.need("outer")? != "outer" || c.need("loop")? != "loop" {
                        return Err(c.err("expected `outer loop`"));
                    }
                    let mut t = [[0.0; 3]; 3];
                    for tv in t.iter_mut() {
                        if c.need("vertex")? != "vertex" {
                            return Err(c.err("expected `vertex` (only triangles are allowed)"));
                        }
                        for x in tv.iter_mut() {
                            *x = c.float("vertex coordinate")?;
                        }
                    }
                    if c.need("endloop")? != "endloop" || c.need("endfacet")? != "endfacet" {
                        return Err(
                            c.err("expected `endloop endfacet` (only triangles are allowed)")
                        );
                    }
                    soup.push(t);
                }
                Some("endsolid") => break,
                Some(t) => return Err(c.err(format!("unexpected `{t}` in ASCII STL"))),
                None => {
                    return Err(c
                        .err("unexpected end of file (no `endsolid`)")
                        .with_fix("the file is truncated; re-export it"));
                }
            }
        }
    }
    let mut index: HashMap<[u64; 3], u32> = HashMap::new();
    let mut verts = Vec::new();
    let mut tris = Vec::with_capacity(soup.len());
    for (i, t) in soup.iter().enumerate() {
        let mut ids = [0u32; 3];
        for (k, p) in t.iter().enumerate() {
            if !p.iter().all(|x| x.is_finite()) {
                return Err(
                    MeshError::parse(format!("triangle {i} has a non-finite vertex")).in_file(path),
                );
            }
            let key = p.map(|x| (x + 0.0).to_bits());
            ids[k] = *index.entry(key).or_insert_with(|| {
                verts.push(*p);
                (verts.len() - 1) as u32
            });
        }
        if ids[0] != ids[1] && ids[1] != ids[2] && ids[0] != ids[2] {
            tris.push(ids);
        }
    }
    if tris.is_empty() {
        return Err(MeshError::parse("the STL file holds no triangles").in_file(path));
    }
    Ok((verts, tris))
}

/// Read an STL surface and check it is closed and manifold (every edge in exactly two
/// triangles, traversed once in each direction).
pub fn read_closed(path: &Path) -> Result<Surface, MeshError> {
    let (v, t) = read(path)?;
    let mut edges: Vec<(u32, u32, i32)> = Vec::new();
    for f in &t {
        for k in 0..3 {
            let (a, b) = (f[k], f[(k + 1) % 3]);
            edges.push((a.min(b), a.max(b), if a < b { 1 } else { -1 }));
        }
    }
    edges.sort_unstable();
    let mut i = 0;
    while i < edges.len() {
        let mut j = i + 1;
        let mut sum = edges[i].2;
        while j < edges.len() && edges[j].0 == edges[i].0 && edges[j].1 == edges[i].1 {
            sum += edges[j].2;
            j += 1;
        }
        let (a, b) = (v[edges[i].0 as usize], v[edges[i].1 as usize]);
        if j - i != 2 {
            return Err(MeshError::parse(format!(
                "the STL surface is {}: the edge {a:?}–{b:?} belongs to {} triangle(s)",
                if j - i == 1 { "open" } else { "non-manifold" },
                j - i
            ))
            .in_file(path)
            .with_fix(
                "the mesher needs closed, watertight surfaces; repair the STL (e.g. close holes)",
            ));
        }
        if sum != 0 {
            return Err(MeshError::parse(format!(
                "the STL surface is not consistently wound at edge {a:?}–{b:?}"
            ))
            .in_file(path)
            .with_fix("make all triangle normals point outwards"));
        }
        i = j;
    }
    Ok((v, t))
}

/// Write a surface as ASCII STL (for fixtures and debugging).
pub fn to_ascii(verts: &[[f64; 3]], tris: &[[u32; 3]]) -> String {
    use std::fmt::Write as _;
    let mut o = String::from("solid softc\n");
    for t in tris {
        let p = t.map(|i| verts[i as usize]);
        let n = crate::mesh::model::cross(
            crate::mesh::model::sub(p[1], p[0]),
            crate::mesh::model::sub(p[2], p[0]),
        );
        let _ = writeln!(o, "facet normal {} {} {}\n outer loop", n[0], n[1], n[2]);
        for q in p {
            let _ = writeln!(o, "  vertex {} {} {}", q[0], q[1], q[2]);
        }
        o.push_str(" endloop\nendfacet\n");
    }
    o.push_str("endsolid softc\n");
    o
}
