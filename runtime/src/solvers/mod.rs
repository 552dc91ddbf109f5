//! Linear algebra for the implicit solvers: the assembled tangent's sparsity pattern and its
//! sparse direct factorization.

pub mod sparse;
