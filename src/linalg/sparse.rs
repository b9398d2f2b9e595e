//! Sparse factorizations (faer) for a large mechanism: a square solve with an
//! estimate of its condition number, the pivots of a Cholesky factorization in the
//! given order, and the trace of an inverse by selected inversion. The dense versions cost
//! n³; a chain's matrices have a few nonzeros per row and these cost about as many
//! operations as their factors have nonzeros.

use faer::dyn_stack::{MemBuffer, MemStack};
use faer::linalg::cholesky::llt::factor::LltRegularization;
use faer::linalg::solvers::SolveCore;
use faer::sparse::linalg::cholesky::{
    factorize_symbolic_cholesky, CholeskySymbolicParams, SymbolicCholesky, SymbolicCholeskyRaw,
    SymmetricOrdering,
};
use faer::sparse::linalg::SupernodalThreshold;
use faer::sparse::{SparseColMat, SparseColMatRef, SymbolicSparseColMatRef, Triplet};
use faer::{Conj, MatMut, Par, Side};

/// A compressed-column pattern and, for each entry an assembly emits (in its
/// fixed order), where it adds up: the values of matrices of one structure,
/// assembled entry by entry, without building triplets each time.
#[derive(Debug, Clone)]
pub struct Pattern {
    pub size: usize,
    pub col_ptr: Vec<usize>,
    pub row_idx: Vec<usize>,
    pub slots: Vec<usize>,
}

impl Pattern {
    /// The pattern of the (row, column) pairs in emission order.
    pub fn new(size: usize, emitted: &[(usize, usize)]) -> Pattern {
        let mut order: Vec<usize> = (0..emitted.len()).collect();
        order.sort_unstable_by_key(|&t| (emitted[t].1, emitted[t].0));
        let mut col_ptr = vec![0; size + 1];
        let mut row_idx = Vec::new();
        let mut slots = vec![0; emitted.len()];
        let mut last = None;
        for &t in &order {
            let (row, col) = emitted[t];
            if last != Some((row, col)) {
                row_idx.push(row);
                col_ptr[col + 1] += 1;
                last = Some((row, col));
            }
            slots[t] = row_idx.len() - 1;
        }
        for c in 0..size {
            col_ptr[c + 1] += col_ptr[c];
        }
        Pattern {
            size,
            col_ptr,
            row_idx,
            slots,
        }
    }

    pub fn symbolic(&self) -> SymbolicSparseColMatRef<'_, usize> {
        SymbolicSparseColMatRef::new_checked(
            self.size,
            self.size,
            &self.col_ptr,
            None,
            &self.row_idx,
        )
    }
}

/// Solves the square system A x = b given by the triplets (row, column, value;
/// repeated positions add up) and `b` in `x`. Returns the estimate of A's 1-norm
/// condition number, or `None` when the factorization fails or the solution is not
/// finite.
pub fn solve_square(size: usize, triplets: &[(usize, usize, f64)], x: &mut [f64]) -> Option<f64> {
    let entries: Vec<Triplet<usize, usize, f64>> = triplets
        .iter()
        .map(|&(row, col, val)| Triplet::new(row, col, val))
        .collect();
    let a = SparseColMat::<usize, f64>::try_new_from_triplets(size, size, &entries).ok()?;
    let lu = a.sp_lu().ok()?;
    lu.solve_in_place_with_conj(Conj::No, MatMut::from_column_major_slice_mut(x, size, 1));
    if !x.iter().all(|v| v.is_finite()) {
        return None;
    }
    let norm = (0..size)
        .map(|j| a.val_of_col(j).iter().map(|v| v.abs()).sum::<f64>())
        .fold(0.0, f64::max);
    let inverse_norm = inverse_norm_estimate(size, |v, transpose| {
        let rhs = MatMut::from_column_major_slice_mut(v, size, 1);
        if transpose {
            lu.solve_transpose_in_place_with_conj(Conj::No, rhs);
        } else {
            lu.solve_in_place_with_conj(Conj::No, rhs);
        }
    });
    let condition = norm * inverse_norm;
    condition.is_finite().then_some(condition)
}

/// Hager's estimate of ‖A⁻¹‖₁ (the method of LAPACK's condition estimators) from a
/// few solves with A and Aᵀ; `solve(v, transpose)` overwrites v with A⁻¹v or A⁻ᵀv.
/// A lower bound, usually within a small factor of the true norm.
fn inverse_norm_estimate(size: usize, mut solve: impl FnMut(&mut [f64], bool)) -> f64 {
    if size == 0 {
        return 0.0;
    }
    let mut x = vec![1.0 / size as f64; size];
    let mut estimate = 0.0;
    let mut last = usize::MAX;
    for _ in 0..5 {
        solve(&mut x, false);
        let norm: f64 = x.iter().map(|v| v.abs()).sum();
        if !norm.is_finite() {
            return f64::INFINITY;
        }
        if norm <= estimate {
            break;
        }
        estimate = norm;
        for v in x.iter_mut() {
            *v = if *v >= 0.0 { 1.0 } else { -1.0 };
        }
        solve(&mut x, true);
        let (j, top) = x.iter().enumerate().fold((0, 0.0f64), |(bj, bv), (j, v)| {
            if v.abs() > bv {
                (j, v.abs())
            } else {
                (bj, bv)
            }
        });
        if j == last || !top.is_finite() {
            break;
        }
        last = j;
        x.fill(0.0);
        x[j] = 1.0;
    }
    estimate
}

/// The simplicial symbolic Cholesky analysis of a symmetric pattern: simplicial
/// because the callers read its factor's columns (pivots, selected inversion).
pub fn simplicial_symbolic(
    pattern: SymbolicSparseColMatRef<'_, usize>,
    side: Side,
    ordering: SymmetricOrdering<'_, usize>,
) -> Option<SymbolicCholesky<usize>> {
    factorize_symbolic_cholesky(
        pattern,
        side,
        ordering,
        CholeskySymbolicParams {
            supernodal_flop_ratio_threshold: SupernodalThreshold::FORCE_SIMPLICIAL,
            ..Default::default()
        },
    )
    .ok()
}

/// A simplicial factor L (A = L Lᵀ) of the symmetric matrix whose lower triangle
/// the triplets give (row ≥ column; repeated positions add up), eliminated in the
/// given order: L's column pointers, row indices (each column's diagonal first) and
/// values. `None` when A is not positive definite to working precision.
fn simplicial_llt(
    size: usize,
    lower: &[(usize, usize, f64)],
) -> Option<(Vec<usize>, Vec<usize>, Vec<f64>)> {
    // Without a reordering faer's symbolic analysis reads the upper triangle.
    let entries: Vec<Triplet<usize, usize, f64>> = lower
        .iter()
        .map(|&(row, col, val)| Triplet::new(col, row, val))
        .collect();
    let a = SparseColMat::<usize, f64>::try_new_from_triplets(size, size, &entries).ok()?;
    let symbolic = simplicial_symbolic(a.symbolic(), Side::Upper, SymmetricOrdering::Identity)?;
    let mut factor = vec![0.0; symbolic.len_val()];
    let mut memory =
        MemBuffer::new(symbolic.factorize_numeric_llt_scratch::<f64>(Par::Seq, Default::default()));
    symbolic
        .factorize_numeric_llt(
            &mut factor,
            SparseColMatRef::new(a.symbolic(), a.val()),
            Side::Upper,
            LltRegularization::default(),
            Par::Seq,
            MemStack::new(&mut memory),
            Default::default(),
        )
        .ok()?;
    let SymbolicCholeskyRaw::Simplicial(l) = symbolic.raw() else {
        return None;
    };
    Some((l.col_ptr().to_vec(), l.row_idx().to_vec(), factor))
}

/// The diagonal of the Cholesky factor L (A = L Lᵀ) of the symmetric matrix whose
/// lower triangle the triplets give (row ≥ column; repeated positions add up),
/// eliminated in the given order (no reordering: L_kk is then the part of the k-th
/// row or column not explained by the earlier ones). `None` when A is not positive
/// definite to working precision.
pub fn cholesky_pivots(size: usize, lower: &[(usize, usize, f64)]) -> Option<Vec<f64>> {
    let (col_ptr, row_idx, factor) = simplicial_llt(size, lower)?;
    (0..size)
        .map(|j| {
            let start = col_ptr[j];
            (row_idx.get(start) == Some(&j) && factor[start] > 0.0 && factor[start].is_finite())
                .then_some(factor[start])
        })
        .collect()
}

/// tr (LLᵀ)⁻¹ of the sparse lower-triangular L (compressed columns, each column's
/// diagonal first, rows ascending) by selected inversion (Takahashi's equations):
/// the entries of Z = (LLᵀ)⁻¹ on L's pattern, last column first, each from the ones
/// after it, in as many operations as Σⱼ (nonzeros of column j)². `None` where L
/// is not laid out so.
pub fn selected_inverse_trace(
    col_ptr: &[usize],
    row_idx: &[usize],
    l: &[f64],
    z: &mut [f64],
) -> Option<f64> {
    let size = col_ptr.len() - 1;
    // Z's entry (i, k), i ≥ k, on L's pattern (closed under the elimination tree,
    // so every entry the recurrence reads is there).
    let find = |i: usize, k: usize| -> Option<usize> {
        let (row, col) = if i >= k { (i, k) } else { (k, i) };
        let range = col_ptr[col]..col_ptr[col + 1];
        row_idx[range.clone()]
            .binary_search(&row)
            .ok()
            .map(|p| range.start + p)
    };
    let mut trace = 0.0;
    for j in (0..size).rev() {
        let (start, end) = (col_ptr[j], col_ptr[j + 1]);
        if row_idx.get(start) != Some(&j) || !(l[start] > 0.0) {
            return None;
        }
        let diagonal = l[start];
        for e in (start + 1..end).rev() {
            let i = row_idx[e];
            let mut sum = 0.0;
            for f in start + 1..end {
                sum += l[f] * z[find(i, row_idx[f])?];
            }
            z[e] = -sum / diagonal;
        }
        let sum: f64 = (start + 1..end).map(|f| l[f] * z[f]).sum();
        z[start] = (1.0 / diagonal - sum) / diagonal;
        trace += z[start];
    }
    Some(trace)
}

/// tr A⁻¹ of the symmetric positive definite matrix whose lower triangle the
/// triplets give (row ≥ column; repeated positions add up): see [`InverseTrace`].
/// `None` when A is not positive definite to working precision. 1 / tr A⁻¹ bounds
/// A's smallest eigenvalue from below.
pub fn spd_inverse_trace(size: usize, lower: &[(usize, usize, f64)]) -> Option<f64> {
    let pairs: Vec<(usize, usize)> = lower.iter().map(|&(i, j, _)| (i, j)).collect();
    let values: Vec<f64> = lower.iter().map(|e| e.2).collect();
    InverseTrace::new(size, &pairs)?.trace(&values)
}

/// tr A⁻¹ of symmetric positive definite matrices of one pattern: the sparse
/// Cholesky factor (fill-reducing order; the trace does not depend on it) and the
/// selected inversion of [`selected_inverse_trace`], the pattern's symbolic
/// analysis made once (a long chain's is most of the work of one trace).
pub struct InverseTrace {
    pattern: Pattern,
    cholesky: SymbolicCholesky<usize>,
    values: Vec<f64>,
    factor: Vec<f64>,
    /// (LLᵀ)⁻¹ on L's pattern.
    inverse: Vec<f64>,
    memory: MemBuffer,
}

impl InverseTrace {
    /// For matrices whose lower triangle has the entries `lower` (row ≥ column, in
    /// the order [`InverseTrace::trace`] is given their values; repeated positions
    /// add up); `None` where the analysis fails.
    pub fn new(size: usize, lower: &[(usize, usize)]) -> Option<InverseTrace> {
        let pattern = Pattern::new(size, lower);
        let cholesky =
            simplicial_symbolic(pattern.symbolic(), Side::Lower, SymmetricOrdering::Amd)?;
        let len = cholesky.len_val();
        let memory = MemBuffer::new(
            cholesky.factorize_numeric_llt_scratch::<f64>(Par::Seq, Default::default()),
        );
        Some(InverseTrace {
            values: vec![0.0; pattern.row_idx.len()],
            pattern,
            cholesky,
            factor: vec![0.0; len],
            inverse: vec![0.0; len],
            memory,
        })
    }

    /// tr A⁻¹ of the matrix with these values of the entries given at
    /// [`InverseTrace::new`]; `None` when it is not positive definite to working
    /// precision.
    pub fn trace(&mut self, lower: &[f64]) -> Option<f64> {
        self.values.fill(0.0);
        for (value, &slot) in lower.iter().zip(&self.pattern.slots) {
            self.values[slot] += value;
        }
        let matrix = SparseColMatRef::new(self.pattern.symbolic(), &self.values);
        self.cholesky
            .factorize_numeric_llt(
                &mut self.factor,
                matrix,
                Side::Lower,
                LltRegularization::default(),
                Par::Seq,
                MemStack::new(&mut self.memory),
                Default::default(),
            )
            .ok()?;
        let SymbolicCholeskyRaw::Simplicial(l) = self.cholesky.raw() else {
            return None;
        };
        selected_inverse_trace(l.col_ptr(), l.row_idx(), &self.factor, &mut self.inverse)
    }

    /// max (A⁻¹)ᵢᵢ of the matrix of the last [`InverseTrace::trace`] (read after one
    /// that succeeded: the diagonal it left). Like 1 / tr A⁻¹, its inverse brackets
    /// A's smallest eigenvalue λ (from λ to size·λ), but it is not summed over
    /// eigenvectors on disjoint rows: it tells how near the nearest part of the matrix
    /// is to singular, whatever the number of such parts.
    pub fn largest_diagonal(&self) -> f64 {
        let SymbolicCholeskyRaw::Simplicial(l) = self.cholesky.raw() else {
            return f64::INFINITY;
        };
        let columns = l.col_ptr();
        columns[..columns.len() - 1]
            .iter()
            .map(|&p| self.inverse[p])
            .fold(0.0, f64::max)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{DMatrix, DVector};

    /// A tridiagonal test matrix with an off-diagonal coupling, as triplets and dense.
    fn chain(size: usize, shift: f64) -> (Vec<(usize, usize, f64)>, DMatrix<f64>) {
        let mut dense = DMatrix::zeros(size, size);
        for i in 0..size {
            dense[(i, i)] = 2.0 + shift * i as f64;
            if i + 1 < size {
                dense[(i + 1, i)] = -1.0;
                dense[(i, i + 1)] = -0.5;
            }
        }
        dense[(size - 1, 0)] = 0.25;
        let triplets = (0..size)
            .flat_map(|c| (0..size).map(move |r| (r, c)))
            .filter(|&(r, c)| dense[(r, c)] != 0.0)
            .map(|(r, c)| (r, c, dense[(r, c)]))
            .collect();
        (triplets, dense)
    }

    #[test]
    fn square_solve_matches_dense_and_estimates_the_condition_number() {
        let (triplets, dense) = chain(40, 0.1);
        let b = DVector::from_fn(40, |i, _| (i as f64 * 0.7).sin());
        let mut x = b.as_slice().to_vec();
        let condition = solve_square(40, &triplets, &mut x).unwrap();
        let exact = dense.clone().lu().solve(&b).unwrap();
        for (a, e) in x.iter().zip(exact.iter()) {
            assert!((a - e).abs() <= 1e-12 * exact.amax(), "{a} vs {e}");
        }
        let inverse = dense.clone().try_inverse().unwrap();
        let norm1 = |m: &DMatrix<f64>| {
            (0..m.ncols())
                .map(|j| m.column(j).iter().map(|v| v.abs()).sum::<f64>())
                .fold(0.0, f64::max)
        };
        let true_condition = norm1(&dense) * norm1(&inverse);
        assert!(
            condition <= true_condition * (1.0 + 1e-12) && condition >= 0.3 * true_condition,
            "estimate {condition} against {true_condition}"
        );
    }

    #[test]
    fn a_singular_square_system_is_refused_or_flagged() {
        // Two equal rows.
        let triplets = vec![
            (0, 0, 1.0),
            (0, 1, 2.0),
            (1, 0, 1.0),
            (1, 1, 2.0),
            (2, 2, 1.0),
        ];
        let mut x = vec![1.0, 1.0, 1.0];
        match solve_square(3, &triplets, &mut x) {
            None => {}
            Some(condition) => assert!(condition > 1e14, "condition {condition}"),
        }
    }

    #[test]
    fn cholesky_pivots_and_inverse_trace_match_the_dense_factorization() {
        let size = 30;
        let (_, a) = chain(size, 0.2);
        let spd = &a * a.transpose() + DMatrix::identity(size, size) * 1e-3;
        let lower: Vec<(usize, usize, f64)> = (0..size)
            .flat_map(|c| (c..size).map(move |r| (r, c)))
            .filter(|&(r, c)| spd[(r, c)] != 0.0)
            .map(|(r, c)| (r, c, spd[(r, c)]))
            .collect();
        let pivots = cholesky_pivots(size, &lower).unwrap();
        let dense = spd.clone().cholesky().unwrap().l();
        for (k, p) in pivots.iter().enumerate() {
            assert!(
                (p - dense[(k, k)]).abs() <= 1e-12 * dense[(k, k)],
                "{k}: {p}"
            );
        }
        let trace = spd_inverse_trace(size, &lower).unwrap();
        let exact = spd.clone().try_inverse().unwrap().trace();
        assert!((trace - exact).abs() <= 1e-10 * exact, "{trace} vs {exact}");
        // Not positive definite: refused.
        let mut indefinite = lower.clone();
        indefinite.push((size - 1, size - 1, -1e3));
        assert!(cholesky_pivots(size, &indefinite).is_none());
        assert!(spd_inverse_trace(size, &indefinite).is_none());
    }

    /// One analysis serves every matrix of its pattern, and a matrix that is not
    /// positive definite does not spoil the next.
    #[test]
    fn an_inverse_trace_is_reused_across_values() {
        let size = 30;
        let (_, a) = chain(size, 0.2);
        let base = &a * a.transpose();
        let entries: Vec<(usize, usize)> = (0..size)
            .flat_map(|c| (c..size).map(move |r| (r, c)))
            .filter(|&(r, c)| base[(r, c)] != 0.0)
            .collect();
        let mut trace = InverseTrace::new(size, &entries).unwrap();
        for shift in [1e-3, -1e3, 0.5, 2.0] {
            let spd = &base + DMatrix::identity(size, size) * shift;
            let values: Vec<f64> = entries.iter().map(|&(r, c)| spd[(r, c)]).collect();
            let got = trace.trace(&values);
            if shift < 0.0 {
                assert!(got.is_none(), "indefinite: {got:?}");
                continue;
            }
            let inverse = spd.try_inverse().unwrap();
            let exact = inverse.trace();
            let got = got.unwrap();
            assert!(
                (got - exact).abs() <= 1e-10 * exact,
                "shift {shift}: {got} vs {exact}"
            );
            let largest = inverse.diagonal().max();
            assert!(
                (trace.largest_diagonal() - largest).abs() <= 1e-10 * largest,
                "shift {shift}: {} vs {largest}",
                trace.largest_diagonal()
            );
        }
    }

    /// Two blocks near singular on disjoint rows: tr A⁻¹ adds them up, the largest
    /// diagonal entry of A⁻¹ sees one, as it would alone.
    #[test]
    fn the_largest_inverse_diagonal_does_not_add_up_disjoint_parts() {
        let block = |eps: f64| DMatrix::from_row_slice(2, 2, &[1.0, 1.0 - eps, 1.0 - eps, 1.0]);
        let one = block(1e-6);
        let mut two = DMatrix::zeros(4, 4);
        two.view_mut((0, 0), (2, 2)).copy_from(&one);
        two.view_mut((2, 2), (2, 2)).copy_from(&one);
        let lower = |a: &DMatrix<f64>| -> (Vec<(usize, usize)>, Vec<f64>) {
            let size = a.nrows();
            (0..size)
                .flat_map(|c| (c..size).map(move |r| (r, c)))
                .filter(|&(r, c)| a[(r, c)] != 0.0)
                .map(|(r, c)| ((r, c), a[(r, c)]))
                .unzip()
        };
        let measure = |a: &DMatrix<f64>| {
            let (entries, values) = lower(a);
            let mut trace = InverseTrace::new(a.nrows(), &entries).unwrap();
            let t = trace.trace(&values).unwrap();
            (t, trace.largest_diagonal())
        };
        let (t1, d1) = measure(&one);
        let (t2, d2) = measure(&two);
        assert!((t2 / t1 - 2.0).abs() < 1e-6, "traces {t1} {t2}");
        assert!((d2 / d1 - 1.0).abs() < 1e-6, "diagonals {d1} {d2}");
    }
}
