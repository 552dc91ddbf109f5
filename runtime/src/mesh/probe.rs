//! The mesh reader behind `softc check`: lets the compiler check surfaces, tags and selections
//! against the mesh a script loads.

use super::load_scaled;
use softc_compiler::driver::{MeshProbe, MeshSummary};
use std::path::Path;

/// Reads meshes from files with the runtime's loaders (and their validation).
#[derive(Debug, Default, Clone, Copy)]
pub struct FileProbe;

impl MeshProbe for FileProbe {
    fn probe(&self, path: &Path, unit: f64) -> Result<MeshSummary, String> {
        // The file's numbers in the script's unit, validated in metres.
        let mesh = load_scaled(path, unit).map_err(|e| e.to_string())?;
        Ok(summary(&mesh))
    }
}

/// What the checker needs to know of a mesh.
fn summary(mesh: &super::Mesh) -> MeshSummary {
    {
        let nodes = &mesh.nodes;
        let centroids = mesh
            .tets
            .iter()
            .map(|t| {
                let mut c = [0.0; 3];
                for &n in t {
                    for k in 0..3 {
                        c[k] += nodes[n as usize][k] / 4.0;
                    }
                }
                c
            })
            .collect();
        let named = |dim: u8, tags: Vec<i32>| {
            tags.into_iter()
                .map(|t| (t, mesh.tag_name(dim, t).map(str::to_string)))
                .collect::<Vec<_>>()
        };
        MeshSummary {
            surfaces: named(2, mesh.surface_tags()),
            regions: named(3, mesh.region_tags()),
            node_sets: mesh.node_sets.keys().cloned().collect(),
            element_sets: mesh.element_sets.keys().cloned().collect(),
            nodes: mesh.nodes.clone(),
            centroids,
        }
    }
}

/// A probe that keeps the meshes it read: the compile's checks read and validate the mesh, and
/// the scene takes the same one (a run reads its mesh file once).
#[derive(Debug, Default)]
pub struct CachingProbe {
    read: std::sync::Mutex<Vec<(std::path::PathBuf, u64, std::sync::Arc<super::Mesh>)>>,
}

impl CachingProbe {
    /// The mesh at `path` in units of `unit` metres: the one read before, or read now.
    pub fn mesh(
        &self,
        path: &Path,
        unit: f64,
    ) -> Result<std::sync::Arc<super::Mesh>, super::MeshError> {
        let mut read = self.read.lock().unwrap_or_else(|e| e.into_inner());
        if let Some((_, _, m)) = read
            .iter()
            .find(|(p, u, _)| p == path && *u == unit.to_bits())
        {
            return Ok(m.clone());
        }
        let mesh = std::sync::Arc::new(load_scaled(path, unit)?);
        read.push((path.to_path_buf(), unit.to_bits(), mesh.clone()));
        Ok(mesh)
    }
}

impl MeshProbe for CachingProbe {
    fn probe(&self, path: &Path, unit: f64) -> Result<MeshSummary, String> {
        let mesh = self.mesh(path, unit).map_err(|e| e.to_string())?;
        Ok(summary(&mesh))
    }
}

/// The compiler binds a script's selections to a mesh through this view.
impl softc_compiler::driver::MeshView for super::Mesh {
    fn nodes(&self) -> &[[f64; 3]] {
        &self.nodes
    }
    fn tets(&self) -> &[[u32; 4]] {
        &self.tets
    }
    fn tet_tags(&self) -> &[i32] {
        &self.tet_tags
    }
    fn tag_by_name(&self, dim: u8, name: &str) -> Option<i32> {
        super::Mesh::tag_by_name(self, dim, name)
    }
    fn surface(&self, tag: i32) -> Vec<[u32; 3]> {
        super::Mesh::surface(self, tag)
    }
    fn surface_nodes(&self, tag: i32) -> Vec<u32> {
        super::Mesh::surface_nodes(self, tag)
    }
    fn surface_mids(&self, tag: i32) -> Vec<[u32; 3]> {
        super::Mesh::surface_mids(self, tag)
    }
    fn tet_mids(&self) -> &[[u32; 6]] {
        self.mid_edges.as_ref().map_or(&[], |q| q.tets.as_slice())
    }
    fn node_set(&self, name: &str) -> Option<&[u32]> {
        self.node_sets.get(name).map(Vec::as_slice)
    }
    fn element_set(&self, name: &str) -> Option<&[u32]> {
        self.element_sets.get(name).map(Vec::as_slice)
    }
    fn tet_id(&self, e: usize) -> i64 {
        super::Mesh::tet_id(self, e)
    }
}
