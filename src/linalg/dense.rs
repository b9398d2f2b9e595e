//! Small dense kernels that work in place on row-major slices, for the hot loops of
//! the solver and the dynamics factors, where nalgebra's owning decompositions would
//! allocate on every call.
//!
//! The Cholesky and LU factorizations are hand-written below [`FAER_CHOLESKY_FROM`]
//! and [`FAER_LU_FROM`] unknowns and faer's blocked in-place kernels from there on,
//! on the same row-major buffers: `benches/linalg.rs` (groups `cholesky` and `lu`)
//! times both at the sizes a step has, and the hand-written ones are kept only where
//! they are faster. (Over 800 lines for that reason: each kernel stands beside its
//! faer counterpart and the switch between them, as the benchmark compares them.)

use faer::dyn_stack::{MemBuffer, MemStack, StackReq};
use faer::linalg::cholesky::llt;
use faer::linalg::lu::partial_pivoting as plu;
use faer::linalg::triangular_solve;
use faer::{MatMut, MatRef, Par};
use std::mem::MaybeUninit;

/// Order from which [`cholesky`] and its strided variants call faer: the hand-written
/// loop is as fast or faster up to 70 unknowns, faer from 85 on (`benches/linalg.rs`,
/// group `cholesky`: faer/hand 1.05–1.45 at 4–70, 0.66 at 85, 0.63 at 96, 0.59 at
/// 120).
pub const FAER_CHOLESKY_FROM: usize = 80;

/// Order from which [`lu`], [`lu_solve`] and [`lu_solve_many`] call faer: the
/// hand-written loops win up to 16 unknowns, faer from 32 on (`benches/linalg.rs`,
/// group `lu`: faer/hand 2.1, 1.8, 1.35 at 4, 8, 16, 0.78 at 32, 0.6 at 48–70).
pub const FAER_LU_FROM: usize = 32;

/// Runs `f` with a scratch stack of at least `req`: on the call stack when it is
/// small (every size a step has), on the heap otherwise.
fn with_scratch<R>(req: StackReq, f: impl FnOnce(&mut MemStack) -> R) -> R {
    let mut local = [MaybeUninit::<u8>::uninit(); 4096];
    if req.unaligned_bytes_required() <= local.len() {
        f(MemStack::new(&mut local))
    } else {
        let mut heap = MemBuffer::new(req);
        f(MemStack::new(&mut heap))
    }
}

/// A dense factorization failed.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum DenseError {
    /// Cholesky met a non-positive pivot at this row.
    NotPositiveDefinite(usize),
    /// LU met a (numerically) zero pivot at this column.
    Singular(usize),
}

/// How the sums of products in the kernels here are taken.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Summation {
    /// One running sum, in order (the default; the forward runs' results are pinned
    /// to it).
    #[default]
    Sequential,
    /// Four interleaved partial sums, added pairwise at the end: a running sum
    /// waits on each addition (a dot product of length L takes ~4L cycles), four
    /// independent ones overlap. Another rounding than `Sequential`, as accurate.
    Lanes,
}

/// Σ aᵢbᵢ over the shorter length, summed as `how` says.
#[inline(always)]
pub fn dot(a: &[f64], b: &[f64], how: Summation) -> f64 {
    match how {
        Summation::Sequential => a.iter().zip(b).map(|(x, y)| x * y).sum(),
        Summation::Lanes => {
            let len = a.len().min(b.len());
            let (a, b) = (&a[..len], &b[..len]);
            let mut acc = [0.0f64; 4];
            let (xa, xb) = (a.chunks_exact(4), b.chunks_exact(4));
            let (ra, rb) = (xa.remainder(), xb.remainder());
            for (x, y) in xa.zip(xb) {
                acc[0] += x[0] * y[0];
                acc[1] += x[1] * y[1];
                acc[2] += x[2] * y[2];
                acc[3] += x[3] * y[3];
            }
            let tail: f64 = ra.iter().zip(rb).map(|(x, y)| x * y).sum();
            (acc[0] + acc[1]) + (acc[2] + acc[3]) + tail
        }
    }
}

/// In-place lower Cholesky of the symmetric positive definite n×n matrix `a`
/// (row-major, lower triangle read): afterwards a = L (upper triangle zeroed).
pub fn cholesky(a: &mut [f64], n: usize) -> Result<(), DenseError> {
    cholesky_strided(a, n, n)
}

/// [`cholesky`] of the leading n×n part of a matrix stored with row stride `ld`.
pub fn cholesky_strided(a: &mut [f64], n: usize, ld: usize) -> Result<(), DenseError> {
    cholesky_strided_with(a, n, ld, Summation::Sequential)
}

/// [`cholesky_strided`] with its sums taken as `how` says (from
/// [`FAER_CHOLESKY_FROM`] on, faer's blocked kernel takes them its own way).
pub fn cholesky_strided_with(
    a: &mut [f64],
    n: usize,
    ld: usize,
    how: Summation,
) -> Result<(), DenseError> {
    if n >= FAER_CHOLESKY_FROM {
        cholesky_faer(a, n, ld)
    } else {
        cholesky_by_hand(a, n, ld, how)
    }
}

/// faer's LLᵀ of the leading n×n part (row stride `ld`), read and written where
/// [`cholesky_by_hand`] reads and writes.
pub fn cholesky_faer(a: &mut [f64], n: usize, ld: usize) -> Result<(), DenseError> {
    if n == 0 {
        return Ok(());
    }
    let len = (n - 1) * ld + n;
    let req = llt::factor::cholesky_in_place_scratch::<f64>(n, Par::Seq, faer::Spec::default());
    let factored = with_scratch(req, |stack| {
        // The row-major view, as the transpose of the column-major one (faer 0.24's
        // `from_row_major_slice_with_stride_mut` lays the strides out column-major).
        let m = MatMut::from_column_major_slice_with_stride_mut(&mut a[..len], n, n, ld)
            .transpose_mut();
        llt::factor::cholesky_in_place(
            m,
            Default::default(),
            Par::Seq,
            stack,
            faer::Spec::default(),
        )
    });
    if let Err(llt::factor::LltError::NonPositivePivot { index }) = factored {
        return Err(DenseError::NotPositiveDefinite(index));
    }
    // faer accepts what the hand-written loop refuses: a non-finite pivot.
    if let Some(j) = (0..n).find(|&j| !a[j * ld + j].is_finite()) {
        return Err(DenseError::NotPositiveDefinite(j));
    }
    for j in 0..n {
        a[j * ld + j + 1..j * ld + n].fill(0.0);
    }
    Ok(())
}

/// The hand-written Cholesky (left-looking, one dot product per entry), as
/// [`cholesky_strided_with`] describes it.
pub fn cholesky_by_hand(
    a: &mut [f64],
    n: usize,
    ld: usize,
    how: Summation,
) -> Result<(), DenseError> {
    for j in 0..n {
        let rj = &a[j * ld..j * ld + j];
        let mut d = a[j * ld + j] - dot(rj, rj, how);
        if !(d > 0.0) || !d.is_finite() {
            return Err(DenseError::NotPositiveDefinite(j));
        }
        d = d.sqrt();
        a[j * ld + j] = d;
        for i in j + 1..n {
            let (top, bottom) = a.split_at_mut(i * ld);
            let rj = &top[j * ld..j * ld + j];
            let ri = &mut bottom[..j + 1];
            let sum = dot(&ri[..j], rj, how);
            ri[j] = (ri[j] - sum) / d;
        }
        a[j * ld + j + 1..j * ld + n].fill(0.0);
    }
    Ok(())
}

/// Solves L y = b in place (L lower, from [`cholesky`]).
pub fn solve_lower(l: &[f64], n: usize, b: &mut [f64]) {
    solve_lower_strided(l, n, n, b)
}

/// [`solve_lower`] with L stored with row stride `ld`.
pub fn solve_lower_strided(l: &[f64], n: usize, ld: usize, b: &mut [f64]) {
    solve_lower_strided_with(l, n, ld, b, Summation::Sequential)
}

/// [`solve_lower_strided`] with its sums taken as `how` says.
pub fn solve_lower_strided_with(l: &[f64], n: usize, ld: usize, b: &mut [f64], how: Summation) {
    for i in 0..n {
        let row = &l[i * ld..i * ld + i];
        let sum = dot(row, &b[..i], how);
        b[i] = (b[i] - sum) / l[i * ld + i];
    }
}

/// Solves Lᵀ x = y in place.
pub fn solve_lower_transpose(l: &[f64], n: usize, b: &mut [f64]) {
    solve_lower_transpose_strided(l, n, n, b)
}

/// [`solve_lower_transpose`] with L stored with row stride `ld`.
pub fn solve_lower_transpose_strided(l: &[f64], n: usize, ld: usize, b: &mut [f64]) {
    for i in (0..n).rev() {
        let xi = b[i] / l[i * ld + i];
        b[i] = xi;
        // Column i of Lᵀ x: subtract L[i][k]·x_i from the rows above.
        for k in 0..i {
            b[k] -= l[i * ld + k] * xi;
        }
    }
}

/// Solves (L Lᵀ) x = b in place.
pub fn cholesky_solve(l: &[f64], n: usize, b: &mut [f64]) {
    solve_lower(l, n, b);
    solve_lower_transpose(l, n, b);
}

/// Solves (L Lᵀ) X = B in place for the `cols` columns of B (n × cols, row-major),
/// each column by [`cholesky_solve`]'s operations in its order (the same bits), a
/// row of B at a time.
pub fn cholesky_solve_columns(l: &[f64], n: usize, b: &mut [f64], cols: usize) {
    for i in 0..n {
        let (done, rest) = b.split_at_mut(i * cols);
        for (j, bij) in rest[..cols].iter_mut().enumerate() {
            let sum: f64 = (0..i).map(|k| l[i * n + k] * done[k * cols + j]).sum();
            *bij = (*bij - sum) / l[i * n + i];
        }
    }
    for i in (0..n).rev() {
        let (above, rest) = b.split_at_mut(i * cols);
        let row = &mut rest[..cols];
        for v in row.iter_mut() {
            *v /= l[i * n + i];
        }
        for k in 0..i {
            let lik = l[i * n + k];
            for (o, xi) in above[k * cols..(k + 1) * cols].iter_mut().zip(row.iter()) {
                *o -= lik * xi;
            }
        }
    }
}

/// In-place LU with partial pivoting of the n×n matrix `a` (row-major): P a = L U
/// with unit-diagonal L below and U on and above the diagonal; `perm[i]` is the
/// original row now at row i. A pivot below 1e-14 × the largest entry is singular.
pub fn lu(a: &mut [f64], n: usize, perm: &mut [usize]) -> Result<(), DenseError> {
    if n >= FAER_LU_FROM {
        lu_faer(a, n, perm)
    } else {
        lu_by_hand(a, n, perm)
    }
}

/// faer's LU with partial pivoting, with [`lu`]'s storage, permutation and pivot test.
pub fn lu_faer(a: &mut [f64], n: usize, perm: &mut [usize]) -> Result<(), DenseError> {
    let tol = 1e-14 * a[..n * n].iter().fold(0.0f64, |m, v| m.max(v.abs()));
    let req = plu::factor::lu_in_place_scratch::<usize, f64>(n, n, Par::Seq, faer::Spec::default())
        .and(StackReq::new::<usize>(n));
    with_scratch(req, |stack| {
        let (mut inverse, stack) = stack.make_with(n, |_| 0usize);
        let m = MatMut::from_row_major_slice_mut(&mut a[..n * n], n, n);
        plu::factor::lu_in_place(
            m,
            &mut perm[..n],
            &mut inverse,
            Par::Seq,
            stack,
            faer::Spec::default(),
        );
    });
    match (0..n).find(|&k| !(a[k * n + k].abs() > tol)) {
        Some(k) => Err(DenseError::Singular(k)),
        None => Ok(()),
    }
}

/// The hand-written LU (right-looking, row by row), as [`lu`] describes it.
pub fn lu_by_hand(a: &mut [f64], n: usize, perm: &mut [usize]) -> Result<(), DenseError> {
    let scale = a[..n * n].iter().fold(0.0f64, |m, v| m.max(v.abs()));
    let tol = 1e-14 * scale;
    for (i, p) in perm.iter_mut().enumerate().take(n) {
        *p = i;
    }
    for k in 0..n {
        let mut piv = k;
        let mut best = a[k * n + k].abs();
        for i in k + 1..n {
            let v = a[i * n + k].abs();
            if v > best {
                best = v;
                piv = i;
            }
        }
        if !(best > tol) {
            return Err(DenseError::Singular(k));
        }
        let (top, bottom) = a[..n * n].split_at_mut((k + 1) * n);
        let pivot = &mut top[k * n..];
        if piv != k {
            pivot.swap_with_slice(&mut bottom[(piv - k - 1) * n..(piv - k) * n]);
            perm.swap(k, piv);
        }
        let d = pivot[k];
        for row in bottom.chunks_exact_mut(n) {
            let f = row[k] / d;
            row[k] = f;
            if f != 0.0 {
                for (x, p) in row[k + 1..].iter_mut().zip(&pivot[k + 1..]) {
                    *x -= f * p;
                }
            }
        }
    }
    Ok(())
}

/// Solves A x = b with the factors of [`lu`]; `tmp` has length n.
pub fn lu_solve(lu: &[f64], n: usize, perm: &[usize], b: &mut [f64], tmp: &mut [f64]) {
    if n >= FAER_LU_FROM {
        return lu_solve_faer(lu, n, perm, b, 1, tmp);
    }
    for i in 0..n {
        tmp[i] = b[perm[i]];
    }
    for i in 0..n {
        let mut s = tmp[i];
        for k in 0..i {
            s -= lu[i * n + k] * tmp[k];
        }
        tmp[i] = s;
    }
    for i in (0..n).rev() {
        let mut s = tmp[i];
        for k in i + 1..n {
            s -= lu[i * n + k] * tmp[k];
        }
        tmp[i] = s / lu[i * n + i];
    }
    b[..n].copy_from_slice(&tmp[..n]);
}

/// Solves A X = B with the factors of [`lu`] for the row-major n × k B in place
/// (`tmp` holds n × k): the same substitutions as [`lu_solve`], a whole row of
/// right-hand sides at a time, so the inner loops run along contiguous rows.
pub fn lu_solve_many(
    lu: &[f64],
    n: usize,
    perm: &[usize],
    b: &mut [f64],
    k: usize,
    tmp: &mut [f64],
) {
    if n >= FAER_LU_FROM {
        lu_solve_faer(lu, n, perm, b, k, tmp)
    } else {
        lu_solve_many_by_hand(lu, n, perm, b, k, tmp)
    }
}

/// [`lu_solve_many`] with faer's triangular solves on the permuted right-hand sides.
pub fn lu_solve_faer(
    lu: &[f64],
    n: usize,
    perm: &[usize],
    b: &mut [f64],
    k: usize,
    tmp: &mut [f64],
) {
    let (b, x) = (&mut b[..n * k], &mut tmp[..n * k]);
    permute_rows(b, &perm[..n], k, x);
    let f = MatRef::from_row_major_slice(&lu[..n * n], n, n);
    let mut rhs = MatMut::from_row_major_slice_mut(x, n, k);
    triangular_solve::solve_unit_lower_triangular_in_place(f, rhs.as_mut(), Par::Seq);
    triangular_solve::solve_upper_triangular_in_place(f, rhs.as_mut(), Par::Seq);
    b.copy_from_slice(x);
}

/// Row i of `x` (n × k, row-major) = row perm[i] of `b`.
fn permute_rows(b: &[f64], perm: &[usize], k: usize, x: &mut [f64]) {
    for (i, &p) in perm.iter().enumerate() {
        x[i * k..(i + 1) * k].copy_from_slice(&b[p * k..(p + 1) * k]);
    }
}

/// The hand-written substitutions of [`lu_solve_many`].
pub fn lu_solve_many_by_hand(
    lu: &[f64],
    n: usize,
    perm: &[usize],
    b: &mut [f64],
    k: usize,
    tmp: &mut [f64],
) {
    let (b, x) = (&mut b[..n * k], &mut tmp[..n * k]);
    permute_rows(b, &perm[..n], k, x);
    for i in 0..n {
        let (done, rest) = x.split_at_mut(i * k);
        let row = &mut rest[..k];
        for (l, prev) in lu[i * n..i * n + i].iter().zip(done.chunks_exact(k)) {
            if *l != 0.0 {
                for (r, p) in row.iter_mut().zip(prev) {
                    *r -= l * p;
                }
            }
        }
    }
    for i in (0..n).rev() {
        let (head, later) = x.split_at_mut((i + 1) * k);
        let row = &mut head[i * k..];
        for (u, next) in lu[i * n + i + 1..(i + 1) * n]
            .iter()
            .zip(later.chunks_exact(k))
        {
            if *u != 0.0 {
                for (r, p) in row.iter_mut().zip(next) {
                    *r -= u * p;
                }
            }
        }
        let d = lu[i * n + i];
        for r in row.iter_mut() {
            *r /= d;
        }
    }
    b.copy_from_slice(x);
}

/// Size (unknowns of a step, s) from which the dense products of the priors and of
/// the marginal (the s × s information against the null-space basis, the Schur
/// complement's YᵀY, s × s × dim each) go through faer's blocked kernels
/// ([`multiply`], [`solve_lower_rows`], [`gram_lower`]) instead of the loops beside
/// them: the 10 four-bar loops (69 unknowns a step in DC) and beyond. faer is the
/// faster at every size (`docs/benchmarks.md`), but it sums in another order: below
/// this size the loops are kept, operation for operation, so that the results the
/// reports and the regression table pin stay the same to the bit.
pub const FAER_PRODUCTS_FROM: usize = 64;

/// Dense columns of a null-space basis from which its products with an s × s
/// information matrix go through faer (with [`FAER_PRODUCTS_FROM`] unknowns): a
/// chain of loops with one degree of freedom has 2 a step (the rest are unit
/// vectors, which the loops skip and a dense product would not); an n-link
/// pendulum 2n.
pub const FAER_DENSE_COLUMNS_FROM: usize = 16;

/// Whether the products of an s × s information matrix with a null-space basis of
/// `q` dense columns are faster by faer's blocked kernels than by the loops.
pub fn blocked_products(s: usize, q: usize) -> bool {
    s >= FAER_PRODUCTS_FROM && q >= FAER_DENSE_COLUMNS_FROM
}

/// The row-major `rows` × `cols` matrix in `v` with row stride `ld`.
pub fn rows(v: &[f64], rows: usize, cols: usize, ld: usize) -> MatRef<'_, f64> {
    let len = if rows == 0 { 0 } else { (rows - 1) * ld + cols };
    MatRef::from_row_major_slice_with_stride(&v[..len], rows, cols, ld)
}

/// [`rows`], writable. (As the transpose of a column-major view: faer 0.24.4's
/// `from_row_major_slice_with_stride_mut` lays the slice out column by column.)
pub fn rows_mut(v: &mut [f64], rows: usize, cols: usize, ld: usize) -> MatMut<'_, f64> {
    let len = if rows == 0 { 0 } else { (rows - 1) * ld + cols };
    MatMut::from_column_major_slice_with_stride_mut(&mut v[..len], cols, rows, ld).transpose_mut()
}

/// C ← A B, or C += A B with `add`, by faer's blocked product.
pub fn multiply(c: MatMut<'_, f64>, add: bool, a: MatRef<'_, f64>, b: MatRef<'_, f64>) {
    let accum = if add {
        faer::Accum::Add
    } else {
        faer::Accum::Replace
    };
    faer::linalg::matmul::matmul(c, accum, a, b, 1.0, Par::Seq);
}

/// The lower triangle (diagonal included) of C ← AᵀA, A row-major k × n, C n × n
/// row-major (its upper triangle not written): by loops below
/// [`FAER_PRODUCTS_FROM`] columns, by faer from there on (`benches/linalg.rs`,
/// group `gram`).
pub fn gram_lower(a: &[f64], k: usize, n: usize, c: &mut [f64]) {
    if n >= FAER_PRODUCTS_FROM {
        gram_lower_faer(rows_mut(c, n, n, n), rows(a, k, n, n));
    } else {
        gram_lower_by_hand(a, k, n, c);
    }
}

/// [`gram_lower`] by loops: summed over the rows of A in order.
pub fn gram_lower_by_hand(a: &[f64], k: usize, n: usize, c: &mut [f64]) {
    for i in 0..n {
        c[i * n..=i * n + i].fill(0.0);
    }
    for row in a.chunks_exact(n).take(k) {
        for (i, &ri) in row.iter().enumerate() {
            for (o, rj) in c[i * n..=i * n + i].iter_mut().zip(row) {
                *o += ri * rj;
            }
        }
    }
}

/// [`gram_lower`] by faer's blocked kernel, on views.
pub fn gram_lower_faer(c: MatMut<'_, f64>, a: MatRef<'_, f64>) {
    use faer::linalg::matmul::triangular::{matmul, BlockStructure};
    matmul(
        c,
        BlockStructure::TriangularLower,
        faer::Accum::Replace,
        a.transpose(),
        BlockStructure::Rectangular,
        a,
        BlockStructure::Rectangular,
        1.0,
        Par::Seq,
    );
}

/// B ← L⁻¹ B for the lower-triangular L (its upper part not read), by faer.
pub fn solve_lower_rows(l: MatRef<'_, f64>, b: MatMut<'_, f64>) {
    triangular_solve::solve_lower_triangular_in_place(l, b, Par::Seq);
}

/// The lower triangle of the Gram matrix G_ij = rᵢ·rⱼ (row-major `count` × `count`
/// in `g`) of the rows `row(i)`, each sum over the columns where both rows can be
/// nonzero: a large mechanism's equations touch a few coordinates each, and the
/// sums, in the order of the whole rows', lose only exact zeros at their ends (the
/// same values to the bit). `spans` receives each row's nonzero columns
/// [start, end), `first` each row of G's first nonzero column (where the rows of its
/// Cholesky factor start too).
pub fn sparse_gram<'a>(
    count: usize,
    row: impl Fn(usize) -> &'a [f64],
    spans: &mut [[usize; 2]],
    first: &mut [usize],
    g: &mut [f64],
) {
    for (i, span) in spans[..count].iter_mut().enumerate() {
        let r = row(i);
        let start = r.iter().position(|v| *v != 0.0).unwrap_or(r.len());
        let end = r.iter().rposition(|v| *v != 0.0).map_or(start, |e| e + 1);
        *span = [start, end];
    }
    for i in 0..count {
        let ri = row(i);
        first[i] = i;
        for j in 0..=i {
            let rj = row(j);
            let (a, b) = (spans[i][0].max(spans[j][0]), spans[i][1].min(spans[j][1]));
            let v: f64 = if a < b {
                ri[a..b].iter().zip(&rj[a..b]).map(|(x, y)| x * y).sum()
            } else {
                0.0
            };
            if v != 0.0 && first[i] == i {
                first[i] = j;
            }
            g[i * count + j] = v;
        }
    }
}

/// tr G⁻¹ = ‖L⁻¹‖_F² from the lower Cholesky factor L of G (row-major ma × ma): L⁻¹
/// column by column, each by forward substitution of a column of I
/// ([`solve_lower`]) in `column` (length ma), or from [`FAER_PRODUCTS_FROM`] rows by
/// faer's blocked triangular inverse, and kept in the lower triangle of `linv` where
/// one is given. `first` (length ma) receives each row's first
/// nonzero column.
pub fn inverse_trace(
    l: &[f64],
    ma: usize,
    column: &mut [f64],
    first: &mut [usize],
    mut linv: Option<&mut [f64]>,
) -> f64 {
    let column = &mut column[..ma];
    for (i, f) in first[..ma].iter_mut().enumerate() {
        *f = l[i * ma..i * ma + i]
            .iter()
            .position(|v| *v != 0.0)
            .unwrap_or(i);
    }
    if ma >= FAER_PRODUCTS_FROM {
        // faer's blocked triangular inverse (the sums in its order), into `linv`
        // where one is given.
        let mut own = Vec::new();
        let inverse = match linv {
            Some(linv) => &mut linv[..ma * ma],
            None => {
                own.resize(ma * ma, 0.0);
                &mut own[..]
            }
        };
        faer::linalg::triangular_inverse::invert_lower_triangular(
            rows_mut(inverse, ma, ma, ma),
            rows(l, ma, ma, ma),
            Par::Seq,
        );
        let mut trace = 0.0;
        for i in 0..ma {
            for v in &inverse[i * ma..=i * ma + i] {
                trace += v * v;
            }
        }
        return trace;
    }
    let mut trace = 0.0;
    for j in 0..ma {
        // L⁻¹eⱼ is 0 above row j and row i of L before first[i]: each sum starts
        // where both can be nonzero (it loses only leading zeros, so the same value
        // to the bit as the whole row's).
        column.fill(0.0);
        column[j] = 1.0;
        for i in j..ma {
            let start = j.max(first[i]).min(i);
            let sum = dot(
                &l[i * ma + start..i * ma + i],
                &column[start..i],
                Summation::Sequential,
            );
            column[i] = (column[i] - sum) / l[i * ma + i];
        }
        for i in j..ma {
            let v = column[i];
            if let Some(linv) = linv.as_deref_mut() {
                linv[i * ma + j] = v;
            }
            trace += v * v;
        }
    }
    trace
}

#[cfg(test)]
mod tests {
    use super::*;

    /// tr G⁻¹ and L⁻¹ by the loops (small) and by faer (from FAER_PRODUCTS_FROM rows)
    /// against G⁻¹'s diagonal from Cholesky solves and L L⁻¹ = I.
    #[test]
    fn inverse_trace_at_both_sizes() {
        for ma in [12, FAER_PRODUCTS_FROM + 16] {
            let mut g = vec![0.0; ma * ma];
            for i in 0..ma {
                for j in 0..ma {
                    g[i * ma + j] = ((i * 7 + j * 3) as f64 * 0.31).sin() * 0.1;
                }
            }
            for i in 0..ma {
                for j in 0..i {
                    let v = 0.5 * (g[i * ma + j] + g[j * ma + i]);
                    g[i * ma + j] = v;
                    g[j * ma + i] = v;
                }
                g[i * ma + i] += 2.0 + i as f64 * 0.01;
            }
            let mut l = g.clone();
            cholesky(&mut l, ma).unwrap();
            let (mut column, mut first) = (vec![0.0; ma], vec![0; ma]);
            let mut linv = vec![0.0; ma * ma];
            let trace = inverse_trace(&l, ma, &mut column, &mut first, Some(&mut linv));
            let mut want = 0.0;
            for i in 0..ma {
                let mut e = vec![0.0; ma];
                e[i] = 1.0;
                cholesky_solve(&l, ma, &mut e);
                want += e[i];
            }
            assert!(
                (trace - want).abs() < 1e-12 * want,
                "ma = {ma}: {trace} vs {want}"
            );
            for i in 0..ma {
                for j in 0..=i {
                    let lli: f64 = (j..=i).map(|k| l[i * ma + k] * linv[k * ma + j]).sum();
                    let want = if i == j { 1.0 } else { 0.0 };
                    assert!(
                        (lli - want).abs() < 1e-12,
                        "ma = {ma}: (L L⁻¹)[{i}, {j}] = {lli}"
                    );
                }
            }
        }
    }

    /// The row-major views address row i, column j at i·ld + j, also when written
    /// through, and the blocked solve and product agree with their definitions.
    #[test]
    fn row_major_views_and_blocked_products() {
        let (d, s) = (5, 7);
        let mut l = vec![0.0; d * s];
        for i in 0..d {
            for j in 0..=i {
                l[i * s + j] = 1.0 + (i * 3 + j) as f64 * 0.1;
            }
        }
        let b0: Vec<f64> = (0..d * s).map(|i| (i as f64 * 0.37).sin()).collect();
        let mut b = b0.clone();
        {
            let mut view = rows_mut(&mut b, d, s, s);
            for i in 0..d {
                for j in 0..s {
                    assert_eq!(view[(i, j)], b0[i * s + j]);
                }
            }
            view[(1, 2)] = 42.0;
        }
        assert_eq!(b[s + 2], 42.0);
        b[s + 2] = b0[s + 2];
        solve_lower_rows(rows(&l, d, d, s), rows_mut(&mut b, d, s, s));
        for i in 0..d {
            for j in 0..s {
                let lb: f64 = (0..=i).map(|k| l[i * s + k] * b[k * s + j]).sum();
                assert!((lb - b0[i * s + j]).abs() < 1e-12, "(L B)[{i}, {j}]");
            }
        }
        let mut c = vec![1.0; s * s];
        let bv = rows(&b, d, s, s);
        multiply(rows_mut(&mut c, s, s, s), true, bv.transpose(), bv);
        let (mut lower, mut by_hand) = (vec![7.0; s * s], vec![7.0; s * s]);
        gram_lower_faer(rows_mut(&mut lower, s, s, s), bv);
        gram_lower_by_hand(&b, d, s, &mut by_hand);
        for i in 0..s {
            for j in 0..s {
                let want = if j <= i { c[i * s + j] - 1.0 } else { 7.0 };
                assert!((lower[i * s + j] - want).abs() < 1e-12, "lower[{i}, {j}]");
                assert!(
                    (by_hand[i * s + j] - want).abs() < 1e-12,
                    "by hand [{i}, {j}]"
                );
            }
        }
        for i in 0..s {
            for j in 0..s {
                let btb: f64 = (0..d).map(|k| b[k * s + i] * b[k * s + j]).sum();
                assert!(
                    (1.0 + btb - c[i * s + j]).abs() < 1e-12,
                    "(1 + BᵀB)[{i}, {j}]"
                );
            }
        }
    }
    use nalgebra::DMatrix;

    #[test]
    fn faer_kernels_match_the_hand_written_ones() {
        for n in [1, 5, 33, 80] {
            let r = random(n, 40 + n as u64);
            let spd = row_major(&(&r * r.transpose() + DMatrix::identity(n, n)));
            // Strided: the leading n × n of an (n + 3)-wide buffer.
            let ld = n + 3;
            let mut wide = vec![7.0; n * ld];
            for i in 0..n {
                wide[i * ld..i * ld + n].copy_from_slice(&spd[i * n..(i + 1) * n]);
            }
            let mut by_faer = wide.clone();
            cholesky_by_hand(&mut wide, n, ld, Summation::Sequential).unwrap();
            cholesky_faer(&mut by_faer, n, ld).unwrap();
            for (x, y) in wide.iter().zip(&by_faer) {
                assert!((x - y).abs() < 1e-10 * (1.0 + x.abs()), "cholesky at {n}");
            }
            let a = row_major(&(r + DMatrix::identity(n, n)));
            let k = 3;
            let b: Vec<f64> = (0..n * k).map(|i| (i as f64 * 0.21).sin()).collect();
            let (mut f1, mut f2) = (a.clone(), a.clone());
            let (mut p1, mut p2) = (vec![0; n], vec![0; n]);
            lu_by_hand(&mut f1, n, &mut p1).unwrap();
            lu_faer(&mut f2, n, &mut p2).unwrap();
            let (mut x1, mut x2) = (b.clone(), b.clone());
            let mut tmp = vec![0.0; n * k];
            lu_solve_many_by_hand(&f1, n, &p1, &mut x1, k, &mut tmp);
            lu_solve_faer(&f2, n, &p2, &mut x2, k, &mut tmp);
            for (x, y) in x1.iter().zip(&x2) {
                assert!((x - y).abs() < 1e-9 * (1.0 + x.abs()), "lu at {n}");
            }
        }
        let mut bad = vec![1.0, 2.0, 2.0, 1.0];
        assert_eq!(
            cholesky_faer(&mut bad, 2, 2),
            Err(DenseError::NotPositiveDefinite(1))
        );
        let mut singular = vec![1.0, 2.0, 2.0, 4.0];
        let mut perm = vec![0; 2];
        assert!(matches!(
            lu_faer(&mut singular, 2, &mut perm),
            Err(DenseError::Singular(_))
        ));
    }

    fn random(n: usize, seed: u64) -> DMatrix<f64> {
        let mut s = seed;
        DMatrix::from_fn(n, n, |_, _| {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((s >> 11) as f64 / (1u64 << 53) as f64) - 0.5
        })
    }

    fn row_major(m: &DMatrix<f64>) -> Vec<f64> {
        m.transpose().as_slice().to_vec()
    }

    #[test]
    fn dot_in_lanes_matches_the_running_sum() {
        for len in [0, 1, 3, 4, 5, 8, 13, 40] {
            let a: Vec<f64> = (0..len).map(|i| (i as f64 * 0.7).sin()).collect();
            let b: Vec<f64> = (0..len).map(|i| (i as f64 * 1.3).cos()).collect();
            let (x, y) = (
                dot(&a, &b, Summation::Sequential),
                dot(&a, &b, Summation::Lanes),
            );
            assert!((x - y).abs() <= 1e-14 * (1.0 + x.abs()), "length {len}");
            let plain: f64 = a.iter().zip(&b).map(|(p, q)| p * q).sum();
            assert_eq!(
                x.to_bits(),
                plain.to_bits(),
                "sequential is the running sum"
            );
        }
    }

    #[test]
    fn cholesky_solve_columns_is_cholesky_solve_per_column() {
        let (n, cols) = (7, 5);
        let r = random(n, 3);
        let a = &r * r.transpose() + DMatrix::identity(n, n);
        let mut l = row_major(&a);
        cholesky(&mut l, n).unwrap();
        let b: Vec<f64> = (0..n * cols)
            .map(|i| ((i * 13) as f64 * 0.37).sin())
            .collect();
        let mut x = b.clone();
        cholesky_solve_columns(&l, n, &mut x, cols);
        for j in 0..cols {
            let mut column: Vec<f64> = (0..n).map(|i| b[i * cols + j]).collect();
            cholesky_solve(&l, n, &mut column);
            for i in 0..n {
                assert_eq!(x[i * cols + j].to_bits(), column[i].to_bits(), "({i}, {j})");
            }
        }
    }

    #[test]
    fn cholesky_matches_nalgebra() {
        for n in [1, 3, 12, 30] {
            let r = random(n, n as u64);
            let a = &r * r.transpose() + DMatrix::identity(n, n);
            let mut l = row_major(&a);
            cholesky(&mut l, n).unwrap();
            let b: Vec<f64> = (0..n).map(|i| i as f64 - 1.5).collect();
            let mut x = b.clone();
            cholesky_solve(&l, n, &mut x);
            let expect = a
                .clone()
                .cholesky()
                .unwrap()
                .solve(&nalgebra::DVector::from_vec(b));
            for i in 0..n {
                assert!((x[i] - expect[i]).abs() < 1e-10 * expect.amax().max(1.0));
            }
        }
        let mut bad = vec![1.0, 2.0, 2.0, 1.0];
        assert_eq!(
            cholesky(&mut bad, 2),
            Err(DenseError::NotPositiveDefinite(1))
        );
    }

    #[test]
    fn lu_solves_general_systems() {
        for n in [1, 4, 7, 25] {
            let a = random(n, 100 + n as u64);
            let mut f = row_major(&a);
            let mut perm = vec![0; n];
            lu(&mut f, n, &mut perm).unwrap();
            let b: Vec<f64> = (0..n).map(|i| (i as f64).sin()).collect();
            let mut x = b.clone();
            let mut tmp = vec![0.0; n];
            lu_solve(&f, n, &perm, &mut x, &mut tmp);
            let r = &a * nalgebra::DVector::from_vec(x) - nalgebra::DVector::from_vec(b);
            assert!(r.amax() < 1e-10, "n = {n}: residual {}", r.amax());
        }
        // Several right-hand sides at once agree with one at a time.
        let n = 9;
        let a = random(n, 7);
        let mut f = row_major(&a);
        let mut perm = vec![0; n];
        lu(&mut f, n, &mut perm).unwrap();
        let k = 4;
        let mut many: Vec<f64> = (0..n * k).map(|i| (i as f64 * 0.37).cos()).collect();
        let mut tmp = vec![0.0; n * k];
        let mut one = vec![0.0; n];
        let mut t1 = vec![0.0; n];
        let expect: Vec<Vec<f64>> = (0..k)
            .map(|c| {
                for i in 0..n {
                    one[i] = many[i * k + c];
                }
                lu_solve(&f, n, &perm, &mut one, &mut t1);
                one.clone()
            })
            .collect();
        lu_solve_many(&f, n, &perm, &mut many, k, &mut tmp);
        for c in 0..k {
            for i in 0..n {
                assert!((many[i * k + c] - expect[c][i]).abs() < 1e-12);
            }
        }
        let mut singular = vec![1.0, 2.0, 2.0, 4.0];
        let mut perm = vec![0; 2];
        assert!(matches!(
            lu(&mut singular, 2, &mut perm),
            Err(DenseError::Singular(_))
        ));
    }
}
