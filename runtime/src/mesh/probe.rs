//! The mesh reader behind `softc check`: lets the compiler check surfaces, tags and selections
//! against the mesh a script loads.

use super::{LengthUnit, load};
use softc_compiler::sema::mesh_probe::{MeshProbe, MeshSummary};
use std::path::Path;

/// Reads meshes from files with the runtime's loaders (and their validation).
#[derive(Debug, Default, Clone, Copy)]
pub struct FileProbe;

impl MeshProbe for FileProbe {
    fn probe(&self, path: &Path, unit: f64) -> Result<MeshSummary, String> {
        // Read the file's numbers as they are, then apply the script's unit.
        let mesh = load(path, LengthUnit::Metre).map_err(|e| e.to_string())?;
        let nodes: Vec<[f64; 3]> = mesh
            .nodes
            .iter()
            .map(|p| [p[0] * unit, p[1] * unit, p[2] * unit])
            .collect();
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
            nodes,
            centroids,
        })
    }
}
