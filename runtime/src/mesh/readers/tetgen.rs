//! tetgen `.node` / `.ele` / `.face` reader (given any of the three files). Region attributes
//! of `.ele` become region tags; boundary markers of `.face` (≠ 0) become surface tags.

use std::path::{Path, PathBuf};

use super::{RawElem, RawMesh, parse_float, read_bytes, truncate};
use crate::mesh::error::MeshError;
use crate::mesh::model::{LengthUnit, Mesh};

/// Non-empty lines with `#` comments removed: `(line number, tokens)`.
pub(crate) fn lines(text: &str, comment: char) -> Vec<(usize, Vec<&str>)> {
    text.lines()
        .enumerate()
        .filter_map(|(i, l)| {
            let l = l.split(comment).next().unwrap_or("");
            let toks: Vec<&str> = l.split_whitespace().collect();
            (!toks.is_empty()).then_some((i + 1, toks))
        })
        .collect()
}

struct Tok<'a> {
    path: &'a Path,
}

impl Tok<'_> {
    fn int(&self, toks: &[&str], i: usize, line: usize, what: &str) -> Result<i64, MeshError> {
        let t = toks.get(i).ok_or_else(|| {
            MeshError::parse(format!("missing {what}"))
                .in_file(self.path)
                .at_line(line)
        })?;
        t.parse().map_err(|_| {
            MeshError::parse(format!("expected {what}, found `{}`", truncate(t)))
                .in_file(self.path)
                .at_line(line)
        })
    }
    fn float(&self, toks: &[&str], i: usize, line: usize, what: &str) -> Result<f64, MeshError> {
        let t = toks.get(i).ok_or_else(|| {
            MeshError::parse(format!("missing {what}"))
                .in_file(self.path)
                .at_line(line)
        })?;
        parse_float(t).ok_or_else(|| {
            MeshError::parse(format!("expected {what}, found `{}`", truncate(t)))
                .in_file(self.path)
                .at_line(line)
        })
    }
}

fn text(path: &Path) -> Result<String, MeshError> {
    let b = read_bytes(path)?;
    String::from_utf8(b).map_err(|_| {
        MeshError::parse("the file is not text (invalid UTF-8)")
            .in_file(path)
            .with_fix("tetgen files are plain text")
    })
}

fn count(
    tok: &Tok,
    all: &[(usize, Vec<&str>)],
    path: &Path,
    what: &str,
) -> Result<usize, MeshError> {
    let (line, toks) = all.first().ok_or_else(|| {
        MeshError::parse(format!("empty file, expected the {what} header")).in_file(path)
    })?;
    let n = tok.int(toks, 0, *line, &format!("number of {what}"))?;
    if n < 0 {
        return Err(MeshError::parse(format!("the header declares {n} {what}"))
            .in_file(path)
            .at_line(*line));
    }
    let data = all.len() - 1;
    if n as usize > data {
        // Where the data stops: a file cut short (an interrupted export or copy) is by far the
        // likelier cause than a wrong count.
        let end = all.last().map_or(*line, |l| l.0);
        return Err(MeshError::parse(format!(
            "the file is truncated: it ends at line {end} after {data} of the {n} {what} its \
             header (line {line}) declares"
        ))
        .in_file(path)
        .at_line(end)
        .with_fix(
            "re-export or copy the file again; if it is complete, correct the count on the \
             header line",
        ));
    }
    Ok(n as usize)
}

/// Read `base.node` + `base.ele` (+ `base.face` if present).
pub fn read(path: &Path, unit: LengthUnit) -> Result<Mesh, MeshError> {
    let base: PathBuf = path.with_extension("");
    let node_p = base.with_extension("node");
    let ele_p = base.with_extension("ele");
    let face_p = base.with_extension("face");
    let mut raw = RawMesh::default();
    // .node
    let nt = text(&node_p)?;
    let nl = lines(&nt, '#');
    let tok = Tok { path: &node_p };
    let n = count(&tok, &nl, &node_p, "points")?;
    let (hl, ht) = &nl[0];
    let dim = if ht.len() > 1 {
        tok.int(ht, 1, *hl, "dimension")?
    } else {
        3
    };
    if dim != 3 {
        return Err(
            MeshError::unsupported(format!("dimension {dim}; softc needs 3-D points"))
                .in_file(&node_p)
                .at_line(*hl),
        );
    }
    for (line, t) in nl.iter().skip(1).take(n) {
        let id = tok.int(t, 0, *line, "point number")?;
        let p = [
            tok.float(t, 1, *line, "x coordinate")?,
            tok.float(t, 2, *line, "y coordinate")?,
            tok.float(t, 3, *line, "z coordinate")?,
        ];
        if !p.iter().all(|x| x.is_finite()) {
            return Err(
                MeshError::parse(format!("node {id} has a non-finite coordinate {p:?}"))
                    .in_file(&node_p)
                    .at_line(*line)
                    .with_fix("replace NaN/inf coordinates with real numbers"),
            );
        }
        raw.add_node(id, p, *line);
    }
    // .ele
    let et = text(&ele_p)?;
    let el = lines(&et, '#');
    let tok = Tok { path: &ele_p };
    let ne = count(&tok, &el, &ele_p, "tetrahedra")?;
    let (hl, ht) = &el[0];
    let npt = if ht.len() > 1 {
        tok.int(ht, 1, *hl, "nodes per tetrahedron")?
    } else {
        4
    };
    let nattr = if ht.len() > 2 {
        tok.int(ht, 2, *hl, "number of attributes")?
    } else {
        0
    };
    if npt != 4 {
        return Err(MeshError::unsupported(format!(
            "{npt} nodes per tetrahedron; softc simulates linear (4-node) tets"
        ))
        .in_file(&ele_p)
        .at_line(*hl)
        .with_fix("run tetgen without -o2"));
    }
    for (line, t) in el.iter().skip(1).take(ne) {
        let id = tok.int(t, 0, *line, "tetrahedron number")?;
        let mut nodes = [0i64; 4];
        for (k, v) in nodes.iter_mut().enumerate() {
            *v = tok.int(t, 1 + k, *line, "node number")?;
        }
        let tag = if nattr > 0 {
            tok.float(t, 5, *line, "region attribute")? as i32
        } else {
            1
        };
        raw.tets.push(RawElem {
            id,
            nodes,
            tag,
            line: *line,
        });
    }
    // .face (optional)
    if face_p.exists() {
        let ft = text(&face_p)?;
        let fl = lines(&ft, '#');
        let tok = Tok { path: &face_p };
        let nf = count(&tok, &fl, &face_p, "faces")?;
        let (hl, ht) = &fl[0];
        let markers = if ht.len() > 1 {
            tok.int(ht, 1, *hl, "boundary marker flag")?
        } else {
            0
        };
        if markers != 0 {
            for (line, t) in fl.iter().skip(1).take(nf) {
                let id = tok.int(t, 0, *line, "face number")?;
                let mut nodes = [0i64; 3];
                for (k, v) in nodes.iter_mut().enumerate() {
                    *v = tok.int(t, 1 + k, *line, "node number")?;
                }
                let m = tok.int(t, 4, *line, "boundary marker")? as i32;
                if m != 0 {
                    raw.tris.push(RawElem {
                        id,
                        nodes,
                        tag: m,
                        line: *line,
                    });
                }
            }
        }
    }
    if raw.tets.is_empty() {
        return Err(MeshError::parse("no tetrahedra").in_file(&ele_p));
    }
    raw.finish(&ele_p, unit)
}
