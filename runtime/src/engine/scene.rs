//! A scene ready to simulate: the checked script, its mesh with elements grouped by material,
//! chamber triangles, fixed nodes, node sets, masses, the time step and the values of params
//! and inputs. Everything here is data; the physics lives in the kernels (and, for testing,
//! in the reference simulator).
//!
//! Constant expressions (the mesh unit, region geometry, `dt`, selections at each node) are
//! evaluated by lowering them to kernel IR and folding or interpreting it, so the scene uses
//! the same expression semantics as the kernels.

use crate::mesh::{Mesh, Precomputed};
use softc_compiler::diag::SourceFile;
use softc_compiler::front::ast::*;
use softc_compiler::ir::{ArgSource, Domain, KernelBuilder, interp};
use softc_compiler::lower::expr::{Env, ExprLowerer, LVal, Program, flatten};
use softc_compiler::lower::fem::material_density;
use softc_compiler::lower::scene::{SceneModule, lower_scene};
use softc_compiler::sema::CheckOptions;
use std::collections::BTreeMap;
use std::ops::Range;
use std::path::{Path, PathBuf};

/// Why a scene could not be built; the message is ready to print.
#[derive(Debug)]
pub struct SceneError(pub String);

impl std::fmt::Display for SceneError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

fn err<T>(msg: impl Into<String>) -> Result<T, SceneError> {
    Err(SceneError(msg.into()))
}

/// Node → incident entity adjacency in CSR form, entries `(entity, corner)` in entity order.
#[derive(Debug, Clone, Default)]
pub struct Csr {
    pub offsets: Vec<u32>,
    pub entries: Vec<(u32, u8)>,
}

impl Csr {
    pub fn build(n_nodes: usize, entities: impl Iterator<Item = impl AsRef<[u32]>>) -> Csr {
        let mut lists: Vec<Vec<(u32, u8)>> = vec![Vec::new(); n_nodes];
        for (e, nodes) in entities.enumerate() {
            for (c, &n) in nodes.as_ref().iter().enumerate() {
                lists[n as usize].push((e as u32, c as u8));
            }
        }
        let mut offsets = Vec::with_capacity(n_nodes + 1);
        let mut entries = Vec::new();
        offsets.push(0);
        for l in lists {
            entries.extend(l);
            offsets.push(entries.len() as u32);
        }
        Csr { offsets, entries }
    }

    pub fn of(&self, node: usize) -> &[(u32, u8)] {
        &self.entries[self.offsets[node] as usize..self.offsets[node + 1] as usize]
    }
}

/// A per-element param (`param mu: pressure[soft_part]`): entry `i` is the uniform
/// `param.NAME.i` (in [`Scene::uniforms`] and the gradients), the value at the set's `i`-th
/// element; the kernels read it from the element buffer `param.NAME`.
#[derive(Debug, Clone)]
pub struct FieldParam {
    pub name: String,
    /// The element set.
    pub set: String,
    /// The position in the kernels' element order (the mesh grouped by material) of each
    /// entry's element.
    pub elements: Vec<u32>,
}

/// How the time step was chosen.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum DtChoice {
    Given(f64),
    /// `dt = auto(safety: s)`: s × the estimated largest stable step.
    Auto {
        safety: f64,
    },
}

#[derive(Debug)]
pub struct Scene {
    pub script: PathBuf,
    pub source: String,
    pub ast: Script,
    pub lowered: SceneModule,
    /// Nodes in metres, tets grouped by material (kernel order).
    pub mesh: Mesh,
    pub pre: Precomputed,
    /// Element range of each material, in `lowered.materials` order.
    pub material_ranges: Vec<Range<usize>>,
    /// Chamber triangles, concatenated in `lowered.chambers` order.
    pub tris: Vec<[u32; 3]>,
    pub chamber_ranges: Vec<Range<usize>>,
    pub node_elements: Csr,
    pub node_tris: Csr,
    pub fixed: Vec<bool>,
    /// Every declared node set with its nodes (for outputs).
    pub node_sets: Vec<(String, Vec<u32>)>,
    /// Every declared element set with its elements, as indices of the mesh file's element
    /// order (before the grouping by material), in the set's order.
    pub element_sets: Vec<(String, Vec<u32>)>,
    /// The per-element params: where each entry's element is in the kernels' element order.
    pub fields: Vec<FieldParam>,
    pub dt: DtChoice,
    pub steps: Option<u64>,
    pub duration: Option<f64>,
    /// Values of the uniforms `param.*` and `input.*` (first scene of a batch).
    pub uniforms: BTreeMap<String, f64>,
    /// The declared params with their bounds, in source order.
    pub params: Vec<softc_compiler::sema::ParamInfo>,
}

impl Scene {
    /// Check, lower and set up the scene of a script. `overrides` are `--set NAME=VALUE` param
    /// values in SI units.
    pub fn load(path: &Path, overrides: &[(String, f64)]) -> Result<Scene, SceneError> {
        let bytes = std::fs::read(path)
            .map_err(|e| SceneError(format!("cannot read `{}`: {e}", path.display())))?;
        let dir = path
            .parent()
            .filter(|p| !p.as_os_str().is_empty())
            .unwrap_or(Path::new("."))
            .to_path_buf();
        let options = CheckOptions {
            base_dir: Some(dir.clone()),
            mesh_probe: Some(std::sync::Arc::new(crate::mesh::probe::FileProbe)),
        };
        let (text, checked) = softc_compiler::check_bytes(&bytes, &options);
        let name = path.display().to_string();
        if checked.has_errors() {
            let file = SourceFile::new(&name, &text);
            let msgs: Vec<String> = checked
                .diagnostics
                .iter()
                .filter(|d| d.is_error())
                .map(|d| file.render(d))
                .collect();
            return err(msgs.join("\n"));
        }
        let source = text.into_owned();
        let ast = softc_compiler::front::parse(&source)
            .map_err(|d| SceneError(SourceFile::new(&name, &source).render(&d)))?;
        let checked_script = checked.script.unwrap_or_default();
        let (
            mesh,
            lowered,
            material_of,
            chamber_tris,
            fixed,
            node_sets,
            element_sets,
            uniforms,
            dt,
            steps,
        ) = {
            let program = Program::new(&ast, softc_compiler::sema::prelude_ast());
            let lowered =
                lower_scene(&program, &ast).map_err(|e| SceneError(format!("{name}: {e}")))?;
            let mesh = load_mesh(&program, &ast, &dir)?;
            let material_of = assign_materials(&program, &ast, &mesh, &lowered)?;
            let chamber_tris = chambers(&program, &ast, &mesh, &lowered)?;
            let fixed = fixed_nodes(&program, &ast, &mesh)?;
            let node_sets = all_node_sets(&program, &ast, &mesh)?;
            let element_sets = all_element_sets(&program, &ast, &mesh)?;
            let uniforms =
                uniform_values(&program, &ast, &checked_script, &element_sets, overrides)?;
            let (dt, steps) = time_settings(&program, &ast)?;
            (
                mesh,
                lowered,
                material_of,
                chamber_tris,
                fixed,
                node_sets,
                element_sets,
                uniforms,
                dt,
                steps,
            )
        };
        let fields = fields(&ast, &lowered, &mesh, &material_of, &element_sets)?;
        // Group elements by material (stable), so each element kernel runs over a range.
        let mut order: Vec<usize> = (0..mesh.tets.len()).collect();
        order.sort_by_key(|&e| material_of[e]);
        let mut mesh = mesh;
        mesh.tets = order.iter().map(|&e| mesh.tets[e]).collect();
        mesh.tet_tags = order.iter().map(|&e| mesh.tet_tags[e]).collect();
        let sorted_mat: Vec<usize> = order.iter().map(|&e| material_of[e]).collect();
        // The fields' elements in kernel order.
        let mut position = vec![0u32; order.len()];
        for (new, &old) in order.iter().enumerate() {
            position[old] = new as u32;
        }
        let fields: Vec<FieldParam> = fields
            .into_iter()
            .map(|f| FieldParam {
                elements: f.elements.iter().map(|&e| position[e as usize]).collect(),
                ..f
            })
            .collect();
        let material_ranges: Vec<Range<usize>> = (0..lowered.materials.len())
            .map(|m| {
                let start = sorted_mat.partition_point(|&x| x < m);
                let end = sorted_mat.partition_point(|&x| x <= m);
                start..end
            })
            .collect();
        let program = Program::new(&ast, softc_compiler::sema::prelude_ast());
        let densities: Vec<f64> = lowered
            .materials
            .iter()
            .map(|m| material_density(&program, m).map_err(|e| SceneError(e.to_string())))
            .collect::<Result<_, _>>()?;
        let rho: Vec<f64> = sorted_mat.iter().map(|&m| densities[m]).collect();
        let mut pre = Precomputed::new(&mesh, &rho).map_err(|e| SceneError(e.to_string()))?;
        let scaling = setting_value(&program, &ast, "mass_scaling")?.unwrap_or(1.0);
        for m in &mut pre.mass {
            *m *= scaling;
        }
        let mut tris = Vec::new();
        let mut chamber_ranges = Vec::new();
        for t in chamber_tris {
            let start = tris.len();
            tris.extend(t);
            chamber_ranges.push(start..tris.len());
        }
        let node_elements = Csr::build(mesh.nodes.len(), mesh.tets.iter());
        let node_tris = Csr::build(mesh.nodes.len(), tris.iter());
        let duration = checked_script.duration;
        Ok(Scene {
            script: path.to_path_buf(),
            source,
            ast,
            lowered,
            mesh,
            pre,
            material_ranges,
            tris,
            chamber_ranges,
            node_elements,
            node_tris,
            fixed,
            node_sets,
            element_sets,
            fields,
            dt,
            steps,
            duration,
            uniforms,
            params: checked_script.params.clone(),
        })
    }

    /// `precision = f32|f64` from the sim block, if given.
    pub fn precision_setting(&self) -> Option<&str> {
        match &self.ast.sim_setting("precision").map(|e| &e.kind) {
            Some(ExprKind::Name(n)) => Some(n.name.as_str()),
            _ => None,
        }
    }

    pub fn program(&self) -> Program<'_> {
        Program::new(&self.ast, softc_compiler::sema::prelude_ast())
    }

    /// The number of steps for a time step `dt`.
    pub fn steps_for(&self, dt: f64) -> u64 {
        match (self.steps, self.duration) {
            (Some(n), _) => n,
            (None, Some(d)) => (d / dt - 1e-9).ceil().max(1.0) as u64,
            _ => 1,
        }
    }
}

/// Evaluate a constant expression (SI values, flattened).
pub fn const_values(program: &Program, e: &Expr) -> Result<Vec<f64>, SceneError> {
    let mut k = KernelBuilder::new("const", Domain::Single, "constant");
    let mut lw = ExprLowerer::new(program);
    let v = lw
        .lower(&mut k, &Env::new(), e)
        .map_err(|e| SceneError(e.to_string()))?;
    flatten(&v)
        .into_iter()
        .map(|x| {
            k.b.func
                .constant(x)
                .ok_or_else(|| SceneError("expected a constant".into()))
        })
        .collect()
}

fn const_scalar(program: &Program, e: &Expr) -> Result<f64, SceneError> {
    const_values(program, e)?
        .first()
        .copied()
        .ok_or_else(|| SceneError("expected a number".into()))
}

fn setting_value(program: &Program, ast: &Script, name: &str) -> Result<Option<f64>, SceneError> {
    ast.sim_setting(name)
        .map(|e| const_scalar(program, e))
        .transpose()
}

fn time_settings(program: &Program, ast: &Script) -> Result<(DtChoice, Option<u64>), SceneError> {
    let dt = match ast.sim_setting("dt") {
        None => return err("the sim block has no `dt`"),
        Some(e) => match &e.kind {
            ExprKind::Name(n) if n.name == "auto" => DtChoice::Auto { safety: 0.9 },
            ExprKind::Call { callee, args } if matches!(&callee.kind, ExprKind::Name(n) if n.name == "auto") => {
                DtChoice::Auto {
                    safety: const_scalar(program, &args[0].value)?,
                }
            }
            _ => DtChoice::Given(const_scalar(program, e)?),
        },
    };
    let steps = setting_value(program, ast, "steps")?.map(|s| s as u64);
    Ok((dt, steps))
}

fn decl<'a>(ast: &'a Script, name: &str) -> Option<(&'a DeclKind, &'a Expr)> {
    ast.items.iter().find_map(|i| match &i.kind {
        ItemKind::Decl {
            kind,
            name: n,
            value,
        } if n.name == name => Some((kind, value)),
        _ => None,
    })
}

fn call_parts(e: &Expr) -> Option<(&str, &[Arg])> {
    match &e.kind {
        ExprKind::Call { callee, args } => match &callee.kind {
            ExprKind::Name(n) => Some((n.name.as_str(), args.as_slice())),
            _ => None,
        },
        _ => None,
    }
}

/// The argument named `name`, or the positional one at `pos`.
fn arg<'a>(args: &'a [Arg], name: &str, pos: usize) -> Option<&'a Expr> {
    args.iter()
        .find(|a| a.name.as_ref().is_some_and(|n| n.name == name))
        .or_else(|| args.get(pos).filter(|a| a.name.is_none()))
        .map(|a| &a.value)
}

fn string_arg(e: &Expr) -> Option<&str> {
    match &e.kind {
        ExprKind::Str(s) => Some(s),
        _ => None,
    }
}

fn load_mesh(program: &Program, ast: &Script, dir: &Path) -> Result<Mesh, SceneError> {
    let value = ast
        .items
        .iter()
        .find_map(|i| match &i.kind {
            ItemKind::Decl {
                kind: DeclKind::Mesh,
                value,
                ..
            } => Some(value),
            _ => None,
        })
        .ok_or_else(|| SceneError("the script declares no mesh".into()))?;
    let (_, args) = call_parts(value).ok_or_else(|| SceneError("the mesh is not loaded".into()))?;
    let path = arg(args, "path", 0)
        .and_then(string_arg)
        .ok_or_else(|| SceneError("the mesh path is not a string".into()))?;
    let unit = match arg(args, "unit", 1) {
        Some(u) => const_scalar(program, u)?,
        None => 1e-3,
    };
    let full = dir.join(path);
    crate::mesh::load_scaled(&full, unit).map_err(|e| SceneError(e.to_string()))
}

/// Whether a point lies in a region.
type PointTest = Box<dyn Fn([f64; 3]) -> bool>;

/// Region geometry from `box(…)`, `sphere(…)`, `cylinder(…)`.
fn region_contains(program: &Program, e: &Expr) -> Result<PointTest, SceneError> {
    let (f, args) =
        call_parts(e).ok_or_else(|| SceneError("a region is a box, sphere or cylinder".into()))?;
    let v = |name: &str, pos: usize| -> Result<Vec<f64>, SceneError> {
        const_values(
            program,
            arg(args, name, pos).ok_or_else(|| SceneError(format!("missing `{name}`")))?,
        )
    };
    const EPS: f64 = 1e-9;
    Ok(match f {
        "box" => {
            let (lo, hi) = (v("min", 0)?, v("max", 1)?);
            Box::new(move |p| (0..3).all(|k| p[k] >= lo[k] - EPS && p[k] <= hi[k] + EPS))
        }
        "sphere" => {
            let (c, r) = (v("center", 0)?, v("radius", 1)?[0]);
            Box::new(move |p| {
                (0..3).map(|k| (p[k] - c[k]).powi(2)).sum::<f64>() <= (r + EPS).powi(2)
            })
        }
        "cylinder" => {
            let (a, b, r) = (v("start", 0)?, v("end", 1)?, v("radius", 2)?[0]);
            Box::new(move |p| {
                let ab: Vec<f64> = (0..3).map(|k| b[k] - a[k]).collect();
                let ap: Vec<f64> = (0..3).map(|k| p[k] - a[k]).collect();
                let l2: f64 = ab.iter().map(|x| x * x).sum();
                let s = ab.iter().zip(&ap).map(|(x, y)| x * y).sum::<f64>() / l2;
                let d2: f64 = (0..3).map(|k| (ap[k] - s * ab[k]).powi(2)).sum();
                (-EPS..=1.0 + EPS).contains(&s) && d2 <= (r + EPS).powi(2)
            })
        }
        other => return err(format!("`{other}` is not a region")),
    })
}

/// Indices selected by a `nodes` (points = nodes) or `elements` (points = centroids) value.
fn selection(
    program: &Program,
    ast: &Script,
    mesh: &Mesh,
    e: &Expr,
    elements: bool,
) -> Result<Vec<u32>, SceneError> {
    let (f, args) = call_parts(e).ok_or_else(|| SceneError("a selection is a call".into()))?;
    let points: Vec<[f64; 3]> = if elements {
        mesh.tets
            .iter()
            .map(|t| {
                let p = t.map(|n| mesh.nodes[n as usize]);
                [0, 1, 2].map(|k| (p[0][k] + p[1][k] + p[2][k] + p[3][k]) / 4.0)
            })
            .collect()
    } else {
        mesh.nodes.clone()
    };
    let second = args.get(1).map(|a| &a.value);
    Ok(match f {
        "select" => {
            let cond = second.ok_or_else(|| SceneError("`select` needs a condition".into()))?;
            let mut k = KernelBuilder::new("select", Domain::Node, "selection");
            let mut env = Env::new();
            for c in ["x", "y", "z"] {
                env.insert(c.to_string(), LVal::S(k.uniform(c)));
            }
            let mut lw = ExprLowerer::new(program);
            let v = lw
                .lower(&mut k, &env, cond)
                .map_err(|e| SceneError(e.to_string()))?
                .scalar()
                .map_err(|e| SceneError(e.to_string()))?;
            k.b.func.outputs.push(v);
            let (srcs, mut func) = k.into_parts();
            func.n_args = srcs.len() as u32;
            let idx: Vec<usize> = srcs
                .iter()
                .map(|s| match s {
                    ArgSource::Uniform(n) => {
                        ["x", "y", "z"].iter().position(|c| c == n).unwrap_or(0)
                    }
                    _ => 0,
                })
                .collect();
            points
                .iter()
                .enumerate()
                .filter(|(_, p)| {
                    let args: Vec<f64> = idx.iter().map(|&i| p[i]).collect();
                    interp::eval(&func, &args)[0] != 0.0
                })
                .map(|(i, _)| i as u32)
                .collect()
        }
        "inside" => {
            let Some(ExprKind::Name(r)) = second.map(|e| &e.kind) else {
                return err("`inside` needs a region name");
            };
            let (_, region) = decl(ast, &r.name)
                .ok_or_else(|| SceneError(format!("unknown region `{}`", r.name)))?;
            let contains = region_contains(program, region)?;
            points
                .iter()
                .enumerate()
                .filter(|(_, p)| contains(**p))
                .map(|(i, _)| i as u32)
                .collect()
        }
        "tagged" => {
            let tag = const_scalar(
                program,
                second.ok_or_else(|| SceneError("`tagged` needs a tag".into()))?,
            )? as i32;
            let elems: Vec<u32> = (0..mesh.tets.len() as u32)
                .filter(|&e| mesh.tet_tags[e as usize] == tag)
                .collect();
            if elements {
                elems
            } else {
                nodes_of(mesh, &elems)
            }
        }
        "named" => {
            let name = second
                .and_then(string_arg)
                .ok_or_else(|| SceneError("`named` needs a name".into()))?;
            if let Some(t) = mesh.tag_by_name(3, name) {
                let elems: Vec<u32> = (0..mesh.tets.len() as u32)
                    .filter(|&e| mesh.tet_tags[e as usize] == t)
                    .collect();
                if elements {
                    elems
                } else {
                    nodes_of(mesh, &elems)
                }
            } else if let Some(t) = mesh.tag_by_name(2, name) {
                if elements {
                    return err(format!(
                        "\"{name}\" is a surface; element sets need a region"
                    ));
                }
                mesh.surface_nodes(t)
            } else if let Some(set) = mesh.node_sets.get(name).filter(|_| !elements) {
                set.clone()
            } else if let Some(set) = mesh.element_sets.get(name).filter(|_| elements) {
                set.clone()
            } else {
                return err(format!("the mesh has no part named \"{name}\""));
            }
        }
        other => return err(format!("`{other}` is not a selection")),
    })
}

fn nodes_of(mesh: &Mesh, elems: &[u32]) -> Vec<u32> {
    let mut n: Vec<u32> = elems.iter().flat_map(|&e| mesh.tets[e as usize]).collect();
    n.sort_unstable();
    n.dedup();
    n
}

fn assign_materials(
    program: &Program,
    ast: &Script,
    mesh: &Mesh,
    lowered: &SceneModule,
) -> Result<Vec<usize>, SceneError> {
    let mut of = vec![usize::MAX; mesh.tets.len()];
    let uses: Vec<(&Ident, Option<&Ident>)> = ast
        .sim_block()
        .iter()
        .filter_map(|s| match &s.kind {
            StmtKind::Use { material, set } => Some((material, set.as_ref())),
            _ => None,
        })
        .collect();
    if uses.is_empty() {
        of.iter_mut().for_each(|m| *m = 0);
    }
    for (material, set) in uses {
        let m = lowered
            .materials
            .iter()
            .position(|x| *x == material.name)
            .expect("lowered materials include every used one");
        match set {
            None => of.iter_mut().for_each(|x| *x = m),
            Some(s) => {
                let (_, value) = decl(ast, &s.name)
                    .ok_or_else(|| SceneError(format!("unknown element set `{}`", s.name)))?;
                for e in selection(program, ast, mesh, value, true)? {
                    of[e as usize] = m;
                }
            }
        }
    }
    if let Some(e) = of.iter().position(|&m| m == usize::MAX) {
        return err(format!(
            "element {e} has no material: add `use NAME` for the whole mesh before the `use NAME in SET` lines"
        ));
    }
    Ok(of)
}

fn chambers(
    program: &Program,
    ast: &Script,
    mesh: &Mesh,
    lowered: &SceneModule,
) -> Result<Vec<Vec<[u32; 3]>>, SceneError> {
    lowered
        .chambers
        .iter()
        .map(|c| {
            let (_, value) =
                decl(ast, c).ok_or_else(|| SceneError(format!("unknown chamber `{c}`")))?;
            let (_, args) =
                call_parts(value).ok_or_else(|| SceneError("a chamber is `surface(…)`".into()))?;
            let tag = match (
                arg(args, "name", 1).and_then(string_arg),
                arg(args, "tag", 99),
            ) {
                (Some(name), _) => mesh.tag_by_name(2, name).ok_or_else(|| {
                    SceneError(format!("the mesh has no surface named \"{name}\""))
                })?,
                (None, Some(t)) => const_scalar(program, t)? as i32,
                (None, None) => match args.get(1) {
                    Some(a) => const_scalar(program, &a.value)? as i32,
                    None => return err(format!("chamber `{c}` names no surface")),
                },
            };
            Ok(mesh.surface(tag))
        })
        .collect()
}

fn fixed_nodes(program: &Program, ast: &Script, mesh: &Mesh) -> Result<Vec<bool>, SceneError> {
    let mut fixed = vec![false; mesh.nodes.len()];
    for s in ast.sim_block() {
        let StmtKind::Fix(names) = &s.kind else {
            continue;
        };
        for n in names {
            let mut name = n.name.clone();
            // A let may alias a region or node set.
            for _ in 0..8 {
                match ast.items.iter().find_map(|i| match &i.kind {
                    ItemKind::Let(l) if l.name.name == name => Some(&l.value),
                    _ => None,
                }) {
                    Some(Expr {
                        kind: ExprKind::Name(id),
                        ..
                    }) => name = id.name.clone(),
                    _ => break,
                }
            }
            let (kind, value) =
                decl(ast, &name).ok_or_else(|| SceneError(format!("unknown region `{name}`")))?;
            match kind {
                DeclKind::Region => {
                    let contains = region_contains(program, value)?;
                    for (i, p) in mesh.nodes.iter().enumerate() {
                        if contains(*p) {
                            fixed[i] = true;
                        }
                    }
                }
                DeclKind::Nodes => {
                    for i in selection(program, ast, mesh, value, false)? {
                        fixed[i as usize] = true;
                    }
                }
                _ => return err(format!("`{name}` cannot be fixed")),
            }
        }
    }
    Ok(fixed)
}

/// The `nodes` (or `elements`) declarations of a script: name and selection.
fn declared_sets(ast: &Script, kind: DeclKind) -> impl Iterator<Item = (&Ident, &Expr)> {
    ast.items.iter().filter_map(move |i| match &i.kind {
        ItemKind::Decl {
            kind: k,
            name,
            value,
        } if *k == kind => Some((name, value)),
        _ => None,
    })
}

fn all_node_sets(
    program: &Program,
    ast: &Script,
    mesh: &Mesh,
) -> Result<Vec<(String, Vec<u32>)>, SceneError> {
    declared_sets(ast, DeclKind::Nodes)
        .map(|(name, value)| {
            Ok((
                name.name.clone(),
                selection(program, ast, mesh, value, false)?,
            ))
        })
        .collect()
}

fn all_element_sets(
    program: &Program,
    ast: &Script,
    mesh: &Mesh,
) -> Result<Vec<(String, Vec<u32>)>, SceneError> {
    declared_sets(ast, DeclKind::Elements)
        .map(|(name, value)| {
            // A named set from the mesh file may list an element twice: keep the first.
            let mut seen = vec![false; mesh.tets.len()];
            let elements = selection(program, ast, mesh, value, true)?
                .into_iter()
                .filter(|&e| !std::mem::replace(&mut seen[e as usize], true))
                .collect();
            Ok((name.name.clone(), elements))
        })
        .collect()
}

/// The per-element params with their elements (mesh-file indices, the set's order), after
/// checking that every material reading one is applied only to elements of its set.
fn fields(
    ast: &Script,
    lowered: &SceneModule,
    mesh: &Mesh,
    material_of: &[usize],
    element_sets: &[(String, Vec<u32>)],
) -> Result<Vec<FieldParam>, SceneError> {
    let mut out = Vec::new();
    for item in &ast.items {
        let ItemKind::Param(p) = &item.kind else {
            continue;
        };
        let Some(set) = softc_compiler::lower::expr::field_set(item) else {
            continue;
        };
        let elements = element_sets
            .iter()
            .find(|(n, _)| *n == set.name)
            .map(|(_, e)| e.clone())
            .ok_or_else(|| SceneError(format!("unknown element set `{}`", set.name)))?;
        let mut member = vec![false; mesh.tets.len()];
        for &e in &elements {
            member[e as usize] = true;
        }
        for (m, reads) in lowered.material_fields.iter().enumerate() {
            if !reads.contains(&p.name.name) {
                continue;
            }
            if let Some(e) = (0..mesh.tets.len()).find(|&e| material_of[e] == m && !member[e]) {
                let material = &lowered.materials[m];
                return err(format!(
                    "material `{material}` takes `{}` per element of `{}`, but it is applied to \
                     element {e}, which is not in `{}`: apply `{material}` only there (`use \
                     {material} in {}`, after a `use` of another material for the rest of the \
                     mesh)",
                    p.name.name, set.name, set.name, set.name
                ));
            }
        }
        out.push(FieldParam {
            name: p.name.name.clone(),
            set: set.name.clone(),
            elements,
        });
    }
    Ok(out)
}

/// `param.NAME[.i…]` and `input.NAME[.i…]` values: initial values (or `--set` overrides) and
/// the first scene of each input batch (or its `--set` override). A per-element param has one entry per element of its
/// set, `param.NAME.i`, all starting at its (scalar) initial value.
fn uniform_values(
    program: &Program,
    ast: &Script,
    checked: &softc_compiler::sema::CheckedScript,
    element_sets: &[(String, Vec<u32>)],
    overrides: &[(String, f64)],
) -> Result<BTreeMap<String, f64>, SceneError> {
    use softc_compiler::sema::types::Len;
    let mut out = BTreeMap::new();
    // `--set NAME=…` / `--set NAME.i=…` (and `--params`, which expands to such names).
    let given = |name: &str| overrides.iter().find(|(n, _)| n == name).map(|(_, v)| *v);
    for p in &checked.params {
        if let [Len::PerElement(set)] = p.ty.shape() {
            let n = element_sets
                .iter()
                .find(|(name, _)| name == set)
                .map_or(0, |(_, e)| e.len());
            if n == 0 {
                return err(format!(
                    "the per-element param `{}` has no entries: the element set `{set}` is empty",
                    p.name
                ));
            }
            let [init] = p.init[..] else {
                return err(format!(
                    "the per-element param `{}` needs one initial value for every element",
                    p.name
                ));
            };
            let whole = given(&p.name).unwrap_or(init);
            for i in 0..n {
                // One entry (`--set mu.7=…`) before the whole field.
                let entry = format!("{}.{i}", p.name);
                out.insert(format!("param.{entry}"), given(&entry).unwrap_or(whole));
            }
            continue;
        }
        let shape: Vec<usize> =
            p.ty.shape()
                .iter()
                .map(|l| match l {
                    Len::Fixed(n) => *n,
                    _ => 0,
                })
                .collect();
        let n: usize = shape.iter().product();
        for i in 0..n.max(1) {
            // One entry (`--set beta.3=…`, `--set w.0.2=…`) before the whole param.
            let entry = uniform_name(&p.name, &shape, i);
            let init = if p.init.len() == 1 {
                p.init[0]
            } else {
                p.init.get(i).copied().unwrap_or(0.0)
            };
            let v = given(&entry).or_else(|| given(&p.name)).unwrap_or(init);
            out.insert(format!("param.{entry}"), v);
        }
    }
    for item in &ast.items {
        let ItemKind::Input(input) = &item.kind else {
            continue;
        };
        let first = match &input.source.kind {
            ExprKind::Array { .. } => {
                let all = const_values(program, &input.source)?;
                let n = match &input.source.kind {
                    ExprKind::Array { items, .. } => items.len().max(1),
                    _ => 1,
                };
                all[..all.len() / n].to_vec()
            }
            // Generators (circle_quadrants) sample per iteration; a plain run uses the centre.
            _ => vec![0.0; shape_of(&input.ty).iter().product::<usize>().max(1)],
        };
        let shape = shape_of(&input.ty);
        // `--set NAME=VALUE` on an input runs that one scene (every entry of an array input).
        let whole = given(&input.name.name);
        for (i, v) in first.iter().enumerate() {
            out.insert(
                uniform_name(&format!("input.{}", input.name.name), &shape, i),
                whole.unwrap_or(*v),
            );
        }
    }
    Ok(out)
}

pub(crate) fn shape_of(ty: &TypeExpr) -> Vec<usize> {
    ty.shape
        .iter()
        .map(|s| match s {
            ShapeItem::Len(n, _) => n.parse().unwrap_or(0),
            _ => 0,
        })
        .collect()
}

/// `prefix.i.j` for the flat index of a row-major array of the given shape.
pub(crate) fn uniform_name(prefix: &str, shape: &[usize], flat: usize) -> String {
    let mut name = prefix.to_string();
    let mut rest = flat;
    let mut strides: Vec<usize> = shape
        .iter()
        .rev()
        .scan(1, |acc, &n| {
            let s = *acc;
            *acc *= n;
            Some(s)
        })
        .collect();
    strides.reverse();
    for s in strides {
        name.push_str(&format!(".{}", rest / s));
        rest %= s;
    }
    name
}
