//! The mesh reader behind `softc check`: lets the compiler check surfaces, tags and selections
//! against the mesh a script loads.

use super::load_scaled;
use softc_compiler::sema::mesh_probe::{MeshProbe, MeshSummary};
use std::path::Path;

/// Reads meshes from files with the runtime's loaders (and their validation).
#[derive(Debug, Default, Clone, Copy)]
pub struct FileProbe;

impl MeshProbe for FileProbe {
    fn probe(&self, path: &Path, unit: f64) -> Result<MeshSummary, String> {
        // The file's numbers in the script's unit, validated in metres.
        let mesh = load_scaled(path, unit).map_err(|e| e.to_string())?;
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
        Ok(MeshSummary {
            surfaces: named(2, mesh.surface_tags()),
            regions: named(3, mesh.region_tags()),
            node_sets: mesh.node_sets.keys().cloned().collect(),
            element_sets: mesh.element_sets.keys().cloned().collect(),
            nodes: mesh.nodes.clone(),
            centroids,
        })
    }
}
