//! The LU factors of a step system's Jacobian: faer's sparse LU, its symbolic
//! analysis made once per mechanism. (At the four-bar's 21 unknowns a dense LU is
//! no faster: cheaper to factor, dearer to solve with, and a step solves several
//! times per factorization.)

use crate::linalg::sparse::Pattern;
use faer::dyn_stack::{MemBuffer, MemStack};
use faer::linalg::lu::partial_pivoting::factor::PartialPivLuParams;
use faer::sparse::linalg::lu::{factorize_symbolic_lu, LuRef, NumericLu, SymbolicLu};
use faer::sparse::SparseColMatRef;
use faer::{Conj, MatMut, Par, Spec};

/// The factors of the Jacobian last factored, with their scratch.
pub(super) struct Factors {
    symbolic: SymbolicLu<usize>,
    numeric: NumericLu<usize, f64>,
    lu_memory: MemBuffer,
    solve_memory: MemBuffer,
}

impl Factors {
    /// Factors for Jacobians of `pattern`; `None` where its symbolic analysis fails.
    pub(super) fn new(pattern: &Pattern) -> Option<Factors> {
        let symbolic = factorize_symbolic_lu(pattern.symbolic(), Default::default()).ok()?;
        let params: Spec<PartialPivLuParams, f64> = Default::default();
        let lu_memory =
            MemBuffer::new(symbolic.factorize_numeric_lu_scratch::<f64>(Par::Seq, params));
        let solve_memory = MemBuffer::new(symbolic.solve_in_place_scratch::<f64>(1, Par::Seq));
        Some(Factors {
            symbolic,
            numeric: NumericLu::new(),
            lu_memory,
            solve_memory,
        })
    }

    /// Factors for Jacobians of the same pattern, from this one's symbolic analysis.
    pub(super) fn like(&self) -> Factors {
        let params: Spec<PartialPivLuParams, f64> = Default::default();
        let symbolic = self.symbolic.clone();
        let lu_memory =
            MemBuffer::new(symbolic.factorize_numeric_lu_scratch::<f64>(Par::Seq, params));
        let solve_memory = MemBuffer::new(symbolic.solve_in_place_scratch::<f64>(1, Par::Seq));
        Factors {
            symbolic,
            numeric: NumericLu::new(),
            lu_memory,
            solve_memory,
        }
    }

    /// Factors the Jacobian with `values` on `pattern`; `None` where the LU fails.
    pub(super) fn factor(&mut self, pattern: &Pattern, values: &[f64]) -> Option<()> {
        let matrix = SparseColMatRef::new(pattern.symbolic(), values);
        let params: Spec<PartialPivLuParams, f64> = Default::default();
        self.symbolic
            .factorize_numeric_lu(
                &mut self.numeric,
                matrix,
                Par::Seq,
                MemStack::new(&mut self.lu_memory),
                params,
            )
            .ok()
            .map(|_| ())
    }

    /// Overwrites `rhs` with the solution of J x = rhs for the Jacobian factored last.
    pub(super) fn solve_in_place(&mut self, rhs: &mut [f64]) {
        let lu = LuRef::new_unchecked(&self.symbolic, &self.numeric);
        let size = rhs.len();
        let rhs = MatMut::from_column_major_slice_mut(rhs, size, 1);
        lu.solve_in_place_with_conj(
            Conj::No,
            rhs,
            Par::Seq,
            MemStack::new(&mut self.solve_memory),
        );
    }
}
