//! softc runtime: meshes (I/O, meshing, validation), devices, the time loop, optimizers and
//! outputs, plus the `softc` command line.

pub mod cli;
pub mod devices;
pub mod embed;
pub mod engine;
pub mod files;
pub mod lsp;
pub mod mesh;
pub mod optim;
pub mod outputs;
pub mod reference;
pub mod session;
pub mod solvers;
pub mod text;
