//! Linear algebra kernels for the solver's hot loop: small dense factorizations in
//! place and the block-tridiagonal Cholesky of time-chained normal equations.

pub mod banded;
pub mod dense;
pub mod nullspace;
