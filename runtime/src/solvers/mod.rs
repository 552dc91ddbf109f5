//! Linear algebra for the implicit solvers: the assembled tangent's sparsity pattern and its
//! sparse direct factorization, and restarted GMRES for matrix-free solves.

pub mod krylov;
pub mod sparse;
