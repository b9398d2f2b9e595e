//! Linear algebra kernels for the solver's hot loop: small dense factorizations in
//! place, the block-tridiagonal Cholesky of time-chained normal equations, and the
//! sparse factorizations of a large mechanism's set-up.

pub mod banded;
pub mod dense;
pub mod nullspace;
pub mod sparse;
