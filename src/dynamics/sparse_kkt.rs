//! The augmented (KKT) system K = [M Aᵀ; A −E] of a large mechanism as a sparse
//! matrix: its pattern and faer's symbolic LU (fill-reducing column order) computed
//! once per mechanism, the numeric LU with partial pivoting at every evaluation.
//!
//! A chain's K has a few nonzeros per row, and the dense LU costs (n + m)³, with
//! the 2n right-hand sides of the dynamics' Jacobians most of a large mechanism's
//! step. The sparse factors cost about as many operations as they have nonzeros,
//! and each right-hand side as many again.

use crate::error::{Error, Result};
use crate::model::Model;
use faer::dyn_stack::{MemBuffer, MemStack};
use faer::linalg::lu::partial_pivoting::factor::PartialPivLuParams;
use faer::sparse::linalg::lu::{factorize_symbolic_lu, LuRef, NumericLu, SymbolicLu};
use faer::sparse::{SparseColMatRef, SymbolicSparseColMatRef};
use faer::{Conj, MatMut, Par, Spec};

/// Unknowns of K (n + active constraints) from which it is factored sparse: the 40
/// four-bar loops (165) and beyond. Below, the dense LU is as fast or faster and its
/// results are kept to the bit.
pub const SPARSE_KKT_FROM: usize = 160;

/// Where a nonzero of K comes from.
#[derive(Debug, Clone, Copy)]
enum Entry {
    /// M[i][j].
    Mass(usize, usize),
    /// Φ_q[k][j] of constraint k (a row of all m).
    Jacobian(usize, usize),
    /// −E[r][r] of active constraint r.
    Regularization(usize),
}

/// K's pattern (compressed columns), where each value comes from, and its symbolic
/// LU.
pub struct KktStructure {
    big: usize,
    col_ptr: Vec<usize>,
    row_idx: Vec<usize>,
    entries: Vec<Entry>,
    symbolic: SymbolicLu<usize>,
}

impl std::fmt::Debug for KktStructure {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("KktStructure")
            .field("unknowns", &self.big)
            .field("nonzeros", &self.row_idx.len())
            .finish()
    }
}

impl KktStructure {
    /// The structure of `model`'s K, if it is large enough to be factored sparse.
    pub fn for_model(model: &Model) -> Option<KktStructure> {
        let (n, ma) = (model.n(), model.active.len());
        let big = n + ma;
        if big < SPARSE_KKT_FROM {
            return None;
        }
        let mut triplets: Vec<(usize, usize, Entry)> = Vec::new();
        for i in 0..n {
            for j in 0..n {
                if model.mass[(i, j)] != 0.0 {
                    triplets.push((j, i, Entry::Mass(i, j)));
                }
            }
        }
        for (r, &k) in model.active.iter().enumerate() {
            let mut touched: Vec<usize> = model.constraints[k].coordinates().collect();
            touched.sort_unstable();
            touched.dedup();
            for j in touched {
                triplets.push((j, n + r, Entry::Jacobian(k, j)));
                triplets.push((n + r, j, Entry::Jacobian(k, j)));
            }
            triplets.push((n + r, n + r, Entry::Regularization(r)));
        }
        // Column-major order: by column, then row.
        triplets.sort_unstable_by_key(|&(col, row, _)| (col, row));
        let mut col_ptr = vec![0; big + 1];
        let (mut row_idx, mut entries) = (Vec::new(), Vec::new());
        for &(col, row, entry) in &triplets {
            col_ptr[col + 1] += 1;
            row_idx.push(row);
            entries.push(entry);
        }
        for c in 0..big {
            col_ptr[c + 1] += col_ptr[c];
        }
        let pattern = SymbolicSparseColMatRef::new_checked(big, big, &col_ptr, None, &row_idx);
        let symbolic = factorize_symbolic_lu(pattern, Default::default()).ok()?;
        Some(KktStructure {
            big,
            col_ptr,
            row_idx,
            entries,
            symbolic,
        })
    }

    /// The numeric LU of K with Φ_q (all m rows, row-major m × n) in `jacobian` and
    /// the regularization E (one entry per active constraint; none: 0).
    pub fn factor(
        &self,
        model: &Model,
        jacobian: &[f64],
        eps: Option<&[f64]>,
    ) -> Result<SparseLu<'_>> {
        let n = model.n();
        let values: Vec<f64> = self
            .entries
            .iter()
            .map(|e| match *e {
                Entry::Mass(i, j) => model.mass[(i, j)],
                Entry::Jacobian(k, j) => jacobian[k * n + j],
                Entry::Regularization(r) => eps.map_or(0.0, |e| -e[r]),
            })
            .collect();
        let pattern = SymbolicSparseColMatRef::new_checked(
            self.big,
            self.big,
            &self.col_ptr,
            None,
            &self.row_idx,
        );
        let matrix = SparseColMatRef::new(pattern, &values);
        let params: Spec<PartialPivLuParams, f64> = Default::default();
        let mut numeric = NumericLu::new();
        let mut memory = MemBuffer::new(
            self.symbolic
                .factorize_numeric_lu_scratch::<f64>(Par::Seq, params),
        );
        self.symbolic
            .factorize_numeric_lu(
                &mut numeric,
                matrix,
                Par::Seq,
                MemStack::new(&mut memory),
                params,
            )
            .map_err(|_| singular())?;
        Ok(SparseLu {
            structure: self,
            numeric,
        })
    }
}

fn singular() -> Error {
    Error::singular(
        "the augmented (KKT) system is singular: a singular configuration or dependent constraints",
    )
}

/// The numeric LU of one K.
pub struct SparseLu<'a> {
    structure: &'a KktStructure,
    numeric: NumericLu<usize, f64>,
}

impl SparseLu<'_> {
    /// B ← K⁻¹B for the row-major big × `cols` right-hand sides in `b`; a solution
    /// that is not finite is a singular K.
    pub fn solve_many(&self, b: &mut [f64], cols: usize) -> Result<()> {
        let big = self.structure.big;
        let lu = LuRef::new_unchecked(&self.structure.symbolic, &self.numeric);
        let mut memory = MemBuffer::new(
            self.structure
                .symbolic
                .solve_in_place_scratch::<f64>(cols, Par::Seq),
        );
        let rhs =
            MatMut::from_column_major_slice_with_stride_mut(&mut b[..big * cols], cols, big, cols)
                .transpose_mut();
        lu.solve_in_place_with_conj(Conj::No, rhs, Par::Seq, MemStack::new(&mut memory));
        if b[..big * cols].iter().all(|v| v.is_finite()) {
            Ok(())
        } else {
            Err(singular())
        }
    }
}
