//! Linear algebra for the implicit solvers: the assembled tangent's sparsity pattern and its
//! sparse direct factorization, restarted GMRES for matrix-free solves, and small dense
//! systems.

pub mod amg;
pub mod dense;
pub mod krylov;
pub mod ordering;
pub mod sparse;
