//! Binding a resolved program to a mesh: the script's selections and regions evaluated at the
//! mesh's nodes and element centroids, materials assigned to elements (and the elements put in
//! kernel order, grouped by material), chamber triangles, fixed nodes, the per-element params'
//! elements, the param and input slots, and the loss lowered over the node sets it reduces.
//! The compiler does not read meshes: the caller provides one through [`MeshView`].

use super::Resolved;
use super::loss::{LossKernels, SensorKernels, lower_loss, lower_sensors};
use super::plan::uniform_name;
use crate::ir::{Domain, KernelBuilder, interp};
use crate::lower::expr::{Env, ExprLowerer, LVal, Program};
use crate::lower::scene::SceneModule;
use crate::sema::ParamInfo;
use crate::sema::hir::DeclKind;
use crate::sema::mesh_probe::{MeshRefs, Selector, Shape, SurfaceRef};
use crate::sema::types::Len;
use std::collections::BTreeMap;
use std::ops::Range;

/// What binding needs of a mesh (in metres, 0-based indices).
pub trait MeshView {
    fn nodes(&self) -> &[[f64; 3]];
    fn tets(&self) -> &[[u32; 4]];
    /// Region tag per tet.
    fn tet_tags(&self) -> &[i32];
    /// The tag of a physical name of dimension `dim` (2 surfaces, 3 regions).
    fn tag_by_name(&self, dim: u8, name: &str) -> Option<i32>;
    /// The triangles of a tagged surface, wound so their normals point into the solid.
    fn surface(&self, tag: i32) -> Vec<[u32; 3]>;
    /// The nodes of a tagged surface, sorted, unique.
    fn surface_nodes(&self, tag: i32) -> Vec<u32>;
    /// The mid-edge nodes (edges 0-1, 1-2, 2-0) of [`MeshView::surface`]'s triangles, in its
    /// order; empty for a linear mesh.
    fn surface_mids(&self, _tag: i32) -> Vec<[u32; 3]> {
        Vec::new()
    }
    /// The mid-edge nodes of each tet of a quadratic mesh (empty for a linear one).
    fn tet_mids(&self) -> &[[u32; 6]] {
        &[]
    }
    fn node_set(&self, name: &str) -> Option<&[u32]>;
    fn element_set(&self, name: &str) -> Option<&[u32]>;
    /// The mesh file's number of tet `e`, what messages call it (default: `e + 1`).
    fn tet_id(&self, e: usize) -> i64 {
        e as i64 + 1
    }
}

/// What a param or input slot range belongs to.
#[derive(Debug, Clone, PartialEq)]
pub enum SlotKind {
    /// A scalar or array param.
    Param,
    /// A per-element param: one entry per element of the set.
    Field {
        set: String,
    },
    Input,
}

/// One declared param or input and its entries' uniforms, in row-major (slot) order.
#[derive(Debug, Clone)]
pub struct ParamSlots {
    pub name: String,
    pub kind: SlotKind,
    /// Fixed lengths of the declared shape (a field: its number of elements).
    pub shape: Vec<usize>,
    /// The uniform of each entry (`param.w.1.2`), in row-major order.
    pub uniforms: Vec<String>,
    pub lower: Option<f64>,
    pub upper: Option<f64>,
}

/// A per-element param (`param mu: pressure[soft_part]`): entry `i` is the uniform
/// `param.NAME.i`, the value at the set's `i`-th element; the kernels read it from the element
/// buffer `param.NAME`.
#[derive(Debug, Clone)]
pub struct FieldSlots {
    pub name: String,
    /// The element set.
    pub set: String,
    /// The position in the kernels' element order of each entry's element.
    pub elements: Vec<u32>,
}

/// A resolved program bound to a mesh.
#[derive(Debug, Clone)]
pub struct Bound {
    /// Kernel element order: entry `k` is the mesh element (file order) the kernels see at
    /// position `k`. Elements are grouped by material, stably.
    pub order: Vec<usize>,
    /// Element range of each material (kernel order).
    pub material_ranges: Vec<Range<usize>>,
    /// The material of each element, in kernel order.
    pub material_of: Vec<usize>,
    /// Chamber triangles per chamber, in kernel order.
    pub chamber_tris: Vec<Vec<[u32; 3]>>,
    /// Quadratic scenes: the mid-edge nodes of each chamber's triangles (empty lists for a
    /// linear one).
    pub chamber_mids: Vec<Vec<[u32; 3]>>,
    pub fixed: Vec<bool>,
    /// Every declared node set with its nodes.
    pub node_sets: Vec<(String, Vec<u32>)>,
    /// Every declared element set with its elements, as indices of the mesh file's element
    /// order, in the set's order.
    pub element_sets: Vec<(String, Vec<u32>)>,
    pub fields: Vec<FieldSlots>,
    /// The params (source order), then the inputs.
    pub slots: Vec<ParamSlots>,
    pub loss: Option<LossKernels>,
    /// Closed-loop control's sensors, one per scalar (uniform `sensor.I.C`).
    pub sensors: Vec<SensorKernels>,
    /// Per `contact` statement: its nodes and their boundary areas.
    pub contacts: Vec<crate::lower::contact::ContactNodes>,
}

impl Bound {
    /// The slots of a param or input by name.
    pub fn slots_of(&self, name: &str) -> Option<&ParamSlots> {
        self.slots.iter().find(|s| s.name == name)
    }
}

type Fail<T> = Result<T, String>;

impl Resolved {
    /// Bind the program to a mesh (elements in file order).
    pub fn bind(&self, kernels: &SceneModule, mesh: &dyn MeshView) -> Fail<Bound> {
        let program = &self.program;
        let places = Places {
            program,
            refs: &self.mesh_refs,
        };
        let material_of = assign_materials(&places, mesh, kernels)?;
        let (chamber_tris, chamber_mids): (Vec<_>, Vec<_>) =
            chambers(&self.mesh_refs.surfaces, mesh, kernels)?
                .into_iter()
                .unzip();
        let fixed = fixed_nodes(&places, mesh)?;
        let node_sets = all_sets(&places, mesh, false)?;
        let element_sets = all_sets(&places, mesh, true)?;
        let slots = self.slots(&element_sets)?;
        let fields = fields(&self.params, kernels, mesh, &material_of, &element_sets)?;
        // Group elements by material, so each element kernel runs over a range, and within a
        // group by their lowest node, so that the kernels' element order follows the node
        // order whatever order the file lists elements in: the node kernel, walking the nodes,
        // then reads its incident elements' force rows from a sliding window, and the element
        // kernel reads corner positions from one. (50k benchmark, f32: with the tets shuffled
        // in the file, ~1,420 steps/s in file order, ~2,050 in this one, the same as the
        // generator's own order. A Morton curve through the centroids measured ~1,750: it
        // does not follow the node order. Nodes keep the file's numbering; a random one costs
        // about a third.)
        let tets = mesh.tets();
        let mut order: Vec<usize> = (0..tets.len()).collect();
        order.sort_by_key(|&e| (material_of[e], tets[e].iter().min().copied()));
        let sorted: Vec<usize> = order.iter().map(|&e| material_of[e]).collect();
        let mut position = vec![0u32; order.len()];
        for (new, &old) in order.iter().enumerate() {
            position[old] = new as u32;
        }
        let fields = fields
            .into_iter()
            .map(|f| FieldSlots {
                elements: f.elements.iter().map(|&e| position[e as usize]).collect(),
                ..f
            })
            .collect();
        let material_ranges = (0..kernels.materials.len())
            .map(|m| {
                let start = sorted.partition_point(|&x| x < m);
                let end = sorted.partition_point(|&x| x <= m);
                start..end
            })
            .collect();
        // Area weights only where a reduction asks for them (a face table of the mesh).
        let node_weights = if self.source.contains("area_mean") {
            super::area::area_weights(mesh, &node_sets)
        } else {
            Default::default()
        };
        let contacts =
            super::area::contact_nodes(mesh, &crate::lower::contact::bodies(program), &node_sets);
        let loss = lower_loss(
            program,
            &node_sets,
            &element_sets,
            &node_weights,
            &contacts,
            mesh,
        )?;
        let sensors = lower_sensors(
            program,
            &kernels.sensors,
            &node_sets,
            &element_sets,
            &node_weights,
        )?;
        Ok(Bound {
            order,
            material_ranges,
            material_of: sorted,
            chamber_tris,
            chamber_mids,
            fixed,
            node_sets,
            element_sets,
            fields,
            slots,
            loss,
            sensors,
            contacts,
        })
    }

    /// The param and input slots; a field has one entry per element of its set.
    fn slots(&self, element_sets: &[(String, Vec<u32>)]) -> Fail<Vec<ParamSlots>> {
        let mut out = Vec::new();
        for p in &self.params {
            if let [Len::PerElement(set)] = p.ty.shape() {
                let n = element_sets
                    .iter()
                    .find(|(name, _)| name == set)
                    .map_or(0, |(_, e)| e.len());
                if n == 0 {
                    return Err(format!(
                        "the per-element param `{}` has no entries: the element set `{set}` is empty",
                        p.name
                    ));
                }
                if p.init.len() != 1 {
                    return Err(format!(
                        "the per-element param `{}` needs one initial value for every element",
                        p.name
                    ));
                }
                out.push(ParamSlots {
                    name: p.name.clone(),
                    kind: SlotKind::Field { set: set.clone() },
                    shape: vec![n],
                    uniforms: (0..n).map(|i| format!("param.{}.{i}", p.name)).collect(),
                    lower: p.lower,
                    upper: p.upper,
                });
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
            out.push(ParamSlots {
                name: p.name.clone(),
                kind: SlotKind::Param,
                uniforms: (0..n.max(1))
                    .map(|i| format!("param.{}", uniform_name(&p.name, &shape, i)))
                    .collect(),
                shape,
                lower: p.lower,
                upper: p.upper,
            });
        }
        for input in &self.inputs {
            out.push(ParamSlots {
                name: input.name.clone(),
                kind: SlotKind::Input,
                shape: input.shape.clone(),
                uniforms: (0..input.first.len())
                    .map(|i| uniform_name(&format!("input.{}", input.name), &input.shape, i))
                    .collect(),
                lower: None,
                upper: None,
            });
        }
        Ok(out)
    }

    /// The values of every param and input uniform: initial values, or `--set NAME=…` /
    /// `--set NAME.i=…` overrides (SI; `--params` expands to such names; one entry's override
    /// wins over the whole param's), and the first scene of each input.
    pub fn initial_uniforms(
        &self,
        bound: &Bound,
        overrides: &[(String, f64)],
    ) -> BTreeMap<String, f64> {
        let given = |name: &str| overrides.iter().find(|(n, _)| n == name).map(|(_, v)| *v);
        let mut out = BTreeMap::new();
        for (slots, p) in bound.slots.iter().zip(&self.params) {
            let whole = given(&p.name);
            for (i, uniform) in slots.uniforms.iter().enumerate() {
                let entry = &uniform["param.".len()..];
                let init = if p.init.len() == 1 {
                    p.init[0]
                } else {
                    p.init.get(i).copied().unwrap_or(0.0)
                };
                let v = given(entry).or(whole).unwrap_or(init);
                out.insert(uniform.clone(), v);
            }
        }
        for (slots, input) in bound.slots[self.params.len()..].iter().zip(&self.inputs) {
            // `--set NAME=VALUE` on an input runs that one scene (every entry of an array input).
            let whole = given(&input.name);
            for (uniform, v) in slots.uniforms.iter().zip(&input.first) {
                out.insert(uniform.clone(), whole.unwrap_or(*v));
            }
        }
        out
    }
}

/// The geometry of region `name`, as the checker evaluated it.
fn region<'a>(regions: &'a BTreeMap<String, Shape>, name: &str) -> Fail<&'a Shape> {
    regions
        .get(name)
        .ok_or_else(|| format!("unknown region `{name}`"))
}

/// What binding reads of the checked program: the sets' selectors and the regions' geometry
/// as the checker evaluated them, and the selection conditions it lowers.
struct Places<'a> {
    program: &'a Program,
    refs: &'a MeshRefs,
}

/// Indices selected by the declared set `name`: nodes, or elements (tested at their
/// centroids) when `elements`.
fn selection(places: &Places, mesh: &dyn MeshView, name: &str, elements: bool) -> Fail<Vec<u32>> {
    let set = places
        .refs
        .sets
        .iter()
        .find(|s| s.name == name)
        .ok_or_else(|| {
            format!(
                "unknown {} set `{name}`",
                if elements { "element" } else { "node" }
            )
        })?;
    let nodes = mesh.nodes();
    let tets = mesh.tets();
    let tags = mesh.tet_tags();
    let points: Vec<[f64; 3]> = if elements {
        tets.iter()
            .map(|t| {
                let p = t.map(|n| nodes[n as usize]);
                [0, 1, 2].map(|k| (p[0][k] + p[1][k] + p[2][k] + p[3][k]) / 4.0)
            })
            .collect()
    } else {
        nodes.to_vec()
    };
    let tagged = |tag: i32| -> Vec<u32> {
        let elems: Vec<u32> = (0..tets.len() as u32)
            .filter(|&e| tags[e as usize] == tag)
            .collect();
        if elements {
            elems
        } else {
            nodes_of(tets, mesh.tet_mids(), &elems)
        }
    };
    Ok(match &set.selector {
        Selector::Condition => {
            // The condition is lowered to a kernel function of x, y, z and evaluated at each
            // point.
            let value = match places.program.find(name).map(|(_, d)| &d.kind) {
                Some(DeclKind::Nodes(v) | DeclKind::Elements(v)) => v,
                _ => return Err(format!("unknown selection `{name}`")),
            };
            let cond = value
                .builtin_call()
                .and_then(|(_, args)| args.get(1))
                .map(|a| &a.value)
                .ok_or("`select` needs a condition")?;
            let mut k = KernelBuilder::new("select", Domain::Node, "selection");
            let mut env = Env::new();
            for c in ["x", "y", "z"] {
                env.insert(c.to_string(), LVal::S(k.uniform(c)));
            }
            let mut lw = ExprLowerer::new(places.program);
            let v = lw
                .lower(&mut k, &env, cond)
                .and_then(|v| v.scalar())
                .map_err(|e| e.to_string())?;
            k.b.func.outputs.push(v);
            let (srcs, mut func) = k.into_parts();
            func.n_args = srcs.sources.len() as u32;
            let idx: Vec<usize> = srcs
                .sources
                .iter()
                .map(|s| match srcs.uniform_name(s) {
                    Some(n) => ["x", "y", "z"].iter().position(|c| *c == n).unwrap_or(0),
                    None => 0,
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
        Selector::Inside(r) => {
            let shape = region(&places.refs.regions, r)?;
            points
                .iter()
                .enumerate()
                .filter(|(_, p)| shape.contains(**p))
                .map(|(i, _)| i as u32)
                .collect()
        }
        Selector::Tagged(tag) => tagged(*tag),
        Selector::Named(name) => {
            if let Some(t) = mesh.tag_by_name(3, name) {
                tagged(t)
            } else if let Some(t) = mesh.tag_by_name(2, name) {
                if elements {
                    return Err(format!(
                        "\"{name}\" is a surface; element sets need a region"
                    ));
                }
                mesh.surface_nodes(t)
            } else if let Some(set) = mesh.node_set(name).filter(|_| !elements) {
                set.to_vec()
            } else if let Some(set) = mesh.element_set(name).filter(|_| elements) {
                set.to_vec()
            } else {
                return Err(format!("the mesh has no part named \"{name}\""));
            }
        }
    })
}

/// The nodes of elements `elems`: their corners and any mid-edge nodes.
fn nodes_of(tets: &[[u32; 4]], mids: &[[u32; 6]], elems: &[u32]) -> Vec<u32> {
    let mut n: Vec<u32> = elems.iter().flat_map(|&e| tets[e as usize]).collect();
    n.extend(elems.iter().filter_map(|&e| mids.get(e as usize)).flatten());
    n.sort_unstable();
    n.dedup();
    n
}

fn assign_materials(
    places: &Places,
    mesh: &dyn MeshView,
    kernels: &SceneModule,
) -> Fail<Vec<usize>> {
    let mut of = vec![usize::MAX; mesh.tets().len()];
    let uses = &places.refs.uses;
    if uses.is_empty() {
        of.iter_mut().for_each(|m| *m = 0);
    }
    for (material, set) in uses {
        let m = kernels
            .materials
            .iter()
            .position(|x| x == material)
            .expect("lowered materials include every used one");
        match set {
            None => of.iter_mut().for_each(|x| *x = m),
            Some(s) => {
                for e in selection(places, mesh, s, true)? {
                    of[e as usize] = m;
                }
            }
        }
    }
    if let Some(e) = of.iter().position(|&m| m == usize::MAX) {
        return Err(format!(
            "element {} has no material: add `use NAME` for the whole mesh before the `use NAME in SET` lines",
            mesh.tet_id(e)
        ));
    }
    Ok(of)
}

/// A chamber's triangles (corners) and, for quadratic elements, their mid-edge nodes.
type ChamberTriangles = (Vec<[u32; 3]>, Vec<[u32; 3]>);

fn chambers(
    surfaces: &BTreeMap<String, SurfaceRef>,
    mesh: &dyn MeshView,
    kernels: &SceneModule,
) -> Fail<Vec<ChamberTriangles>> {
    let quadratic = kernels.module.order == crate::ir::ElementOrder::Quadratic;
    kernels
        .chambers
        .iter()
        .map(|c| {
            let tag = match surfaces.get(c) {
                Some(SurfaceRef::Name(name)) => mesh
                    .tag_by_name(2, name)
                    .ok_or_else(|| format!("the mesh has no surface named \"{name}\""))?,
                Some(SurfaceRef::Tag(t)) => *t,
                None => return Err(format!("chamber `{c}` names no surface")),
            };
            let tris = mesh.surface(tag);
            let mids = if quadratic {
                mesh.surface_mids(tag)
            } else {
                Vec::new()
            };
            if quadratic && mids.len() != tris.len() {
                return Err(format!(
                    "chamber `{c}`: the mesh has no mid-edge nodes on its triangles; a \
                     quadratic scene (`order: 2`) needs a mesh with them"
                ));
            }
            Ok((tris, mids))
        })
        .collect()
}

fn fixed_nodes(places: &Places, mesh: &dyn MeshView) -> Fail<Vec<bool>> {
    let mut fixed = vec![false; mesh.nodes().len()];
    for target in &places.refs.fixed {
        if target.region {
            let shape = region(&places.refs.regions, &target.name)?;
            for (i, p) in mesh.nodes().iter().enumerate() {
                if shape.contains(*p) {
                    fixed[i] = true;
                }
            }
        } else {
            for i in selection(places, mesh, &target.name, false)? {
                fixed[i as usize] = true;
            }
        }
    }
    Ok(fixed)
}

/// Every declared node set (or element set, `elements`) with what it selects, in source order.
fn all_sets(places: &Places, mesh: &dyn MeshView, elements: bool) -> Fail<Vec<(String, Vec<u32>)>> {
    places
        .refs
        .sets
        .iter()
        .filter(|s| s.elements == elements)
        .map(|s| {
            let mut selected = selection(places, mesh, &s.name, elements)?;
            if elements {
                // A named set from the mesh file may list an element twice: keep the first.
                let mut seen = vec![false; mesh.tets().len()];
                selected.retain(|&e| !std::mem::replace(&mut seen[e as usize], true));
            }
            Ok((s.name.clone(), selected))
        })
        .collect()
}

/// The per-element params with their elements (mesh-file indices, the set's order), after
/// checking that every material reading one is applied only to elements of its set.
fn fields(
    params: &[ParamInfo],
    kernels: &SceneModule,
    mesh: &dyn MeshView,
    material_of: &[usize],
    element_sets: &[(String, Vec<u32>)],
) -> Fail<Vec<FieldSlots>> {
    let n_elements = mesh.tets().len();
    let mut out = Vec::new();
    for p in params {
        let [Len::PerElement(set)] = p.ty.shape() else {
            continue;
        };
        let elements = element_sets
            .iter()
            .find(|(n, _)| n == set)
            .map(|(_, e)| e.clone())
            .ok_or_else(|| format!("unknown element set `{set}`"))?;
        let mut member = vec![false; n_elements];
        for &e in &elements {
            member[e as usize] = true;
        }
        for (m, reads) in kernels.material_fields.iter().enumerate() {
            if !reads.contains(&p.name) {
                continue;
            }
            if let Some(e) = (0..n_elements).find(|&e| material_of[e] == m && !member[e]) {
                let material = &kernels.materials[m];
                return Err(format!(
                    "material `{material}` takes `{}` per element of `{}`, but it is applied to \
                     element {e}, which is not in `{}`: apply `{material}` only there (`use \
                     {material} in {}`, after a `use` of another material for the rest of the \
                     mesh)",
                    p.name, set, set, set
                ));
            }
        }
        out.push(FieldSlots {
            name: p.name.clone(),
            set: set.clone(),
            elements,
        });
    }
    Ok(out)
}
