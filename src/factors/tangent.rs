//! Integrator factors projected onto the constraint manifold's tangent space, for
//! dependent coordinates.
//!
//! In dependent coordinates the paper's integrators, e = x_t − x_{t−1} − Δt/2
//! (ẋ_{t−1} + ẋ_t), ask n equations of a step whose positions and velocities have only
//! n − m free directions each (the hard constraints fix the rest). Together with
//! f_dyn's n equations on q̈ that is 2m more equations than unknowns per step: the
//! soft factors can not all hold, and each solve settles on a compromise weighted by
//! the σ's. Over a long window or a batch, the compromise is a least-squares problem
//! with a nonzero residual whose minimum is ill-determined along slow directions (a
//! drift of the whole motion costs almost nothing), and Gauss–Newton converges
//! linearly or not at all.
//!
//! Here the residual is P(q_t) e, with P = I − Φ_q⁺Φ_q the orthogonal projector onto
//! the null space of Φ_q at the step's positions: the integrator is asked only along
//! the directions the constraints leave free, as in a projected (GGL-type) index-2
//! integration, where x_t − x_{t−1} − Δt/2 (ẋ_{t−1} + ẋ_t) = Φ_qᵀμ with a
//! multiplier μ. Each step then has as many soft equations as unknowns, they hold
//! exactly, and every window length (and the batch) has the same solution as N_w = 1.
//!
//! **Jacobian.** With u = Pe and λ = (Φ_q⁺)ᵀe, for a direction δ of q_t (rank
//! constant): d(Pe) = −Φ_q⁺ (Φ_qq u) δ − P (Σₖ λₖ Φᵏ_qq) δ; the other keys enter
//! through e only (P ∂e/∂x). Rows of Φ_q are normalized first (row space and
//! projector are unchanged) so that rank is judged relative to each row's size.

use crate::error::{Error, Result};
use crate::graph::{zeros, Factor, Key, StackReq, VarKind, Workspace};
use crate::linalg::dense;
use crate::model::Model;
use faer::dyn_stack::PodStack;
use nalgebra::DMatrix;
use std::cell::RefCell;
use std::sync::Arc;

/// Singular values of the row-normalized Φ_q below this (relative to the largest)
/// count as a lost rank: the direction is not projected out.
const RANK_TOLERANCE: f64 = 1e-10;

/// The row space of Φ_q at q, from the active rows (redundant constraints left out:
/// on the manifold they add no direction) normalized, Â = D Φ_q,active: the
/// projector P = I − Â⁺Â onto the null space (row-major n × n) and Φ_q⁺ = Â⁺D
/// (row-major n × m over all m constraints, zero columns for the redundant ones),
/// Â⁺ restricted to Â's rank. Carved from the factor's workspace, with the scratch
/// of their computation.
struct RowSpace<'a> {
    p: &'a mut [f64],
    pinv: &'a mut [f64],
}

/// The scratch of [`row_space`] and of the products after it, for `cols` columns
/// at most in a Jacobian block.
fn row_space_scratch(model: &Model, cols: usize) -> StackReq {
    let (m, n, ma) = (model.m(), model.n(), model.active.len());
    let reals = [n * n, n * m, m * n, ma * n, ma, ma * ma, ma * n, n * ma];
    let products = [n, m, n * n, m * n, n * n, n * n, n * cols.max(n)];
    StackReq::all_of(&reals.map(StackReq::new::<f64>))
        .and(StackReq::all_of(&products.map(StackReq::new::<f64>)))
}

/// The last row space made on this thread: its model's identity, the bits of its q,
/// and P and Φ_q⁺. A step's projected integrators (one per integrated variable) all project
/// at the same q_t.
#[derive(Default)]
struct LastRowSpace {
    model: u64,
    q: Vec<u64>,
    p: Vec<f64>,
    pinv: Vec<f64>,
}

thread_local! {
    static LAST: RefCell<LastRowSpace> = RefCell::new(LastRowSpace::default());
}

/// [`row_space_at`], or the last one made on this thread where it was made for
/// the same model at the same bits of q: the same values.
fn row_space<'a>(
    model: &Model,
    q: &[f64],
    stack: &'a mut PodStack,
) -> Result<(RowSpace<'a>, &'a mut PodStack)> {
    let key = model.identity.get();
    let hit = LAST.with_borrow(|last| {
        last.model == key
            && last.q.len() == q.len()
            && last.q.iter().zip(q).all(|(a, b)| *a == b.to_bits())
    });
    if hit {
        let (n, m) = (model.n(), model.m());
        let (p, stack) = zeros(stack, n * n);
        let (pinv, stack) = zeros(stack, n * m);
        LAST.with_borrow(|last| {
            p.copy_from_slice(&last.p);
            pinv.copy_from_slice(&last.pinv);
        });
        return Ok((RowSpace { p, pinv }, stack));
    }
    let (rows, stack) = row_space_at(model, q, stack)?;
    LAST.with_borrow_mut(|last| {
        last.model = key;
        last.q.clear();
        last.q.extend(q.iter().map(|v| v.to_bits()));
        last.p.clear();
        last.p.extend_from_slice(rows.p);
        last.pinv.clear();
        last.pinv.extend_from_slice(rows.pinv);
    });
    Ok((rows, stack))
}

fn row_space_at<'a>(
    model: &Model,
    q: &[f64],
    stack: &'a mut PodStack,
) -> Result<(RowSpace<'a>, &'a mut PodStack)> {
    let (m, n, ma) = (model.m(), model.n(), model.active.len());
    let (p, stack) = zeros(stack, n * n);
    let (pinv, stack) = zeros(stack, n * m);
    let (all, stack) = zeros(stack, m * n);
    let (a, stack) = zeros(stack, ma * n);
    let (d, stack) = zeros(stack, ma);
    let (gram, stack) = zeros(stack, ma * ma);
    let (x, stack) = zeros(stack, ma * n);
    let (pinv_hat, stack) = zeros(stack, n * ma);
    model.jacobian_into(q, all);
    if all.iter().any(|v| !v.is_finite()) {
        return Err(Error::singular("Φ_q is not finite at the step's positions"));
    }
    for (i, &k) in model.active.iter().enumerate() {
        let row = &all[k * n..(k + 1) * n];
        let norm = row.iter().map(|v| v * v).sum::<f64>().sqrt();
        if norm > 0.0 {
            d[i] = 1.0 / norm;
            for (o, v) in a[i * n..(i + 1) * n].iter_mut().zip(row) {
                *o = v * d[i];
            }
        }
    }
    // Â⁺ = Âᵀ(ÂÂᵀ)⁻¹ by Cholesky while the Gram matrix is well conditioned (the
    // usual case), the SVD otherwise: near a singular configuration the Gram matrix
    // squares a large condition number.
    // Over row i's nonzeros (a few: each constraint involves a few coordinates), in
    // ascending order as the dense dot product: the same sums.
    for i in 0..ma {
        let row = &a[i * n..(i + 1) * n];
        for j in 0..=i {
            let other = &a[j * n..(j + 1) * n];
            let g: f64 = row
                .iter()
                .zip(other)
                .filter(|(x, _)| **x != 0.0)
                .map(|(x, y)| x * y)
                .sum();
            gram[i * ma + j] = g;
            gram[j * ma + i] = g;
        }
    }
    if dense::cholesky(gram, ma).is_ok() && well_conditioned(gram, ma) {
        // X = (ÂÂᵀ)⁻¹Â, Â⁺ = Xᵀ: every column at once.
        x.copy_from_slice(a);
        dense::cholesky_solve_columns(gram, ma, x, n);
        for i in 0..n {
            for k in 0..ma {
                pinv_hat[i * ma + k] = x[k * n + i];
            }
        }
    } else {
        svd_pseudo_inverse(a, ma, n, pinv_hat);
    }
    // P = I − Â⁺Â, Â⁺Â over Â's nonzeros in ascending k as the dense sums.
    for k in 0..ma {
        for (j, &akj) in a[k * n..(k + 1) * n].iter().enumerate() {
            if akj != 0.0 {
                for i in 0..n {
                    p[i * n + j] += pinv_hat[i * ma + k] * akj;
                }
            }
        }
    }
    for i in 0..n {
        for j in 0..n {
            p[i * n + j] = f64::from(u8::from(i == j)) - p[i * n + j];
        }
    }
    for (i, &k) in model.active.iter().enumerate() {
        for r in 0..n {
            pinv[r * m + k] = pinv_hat[r * ma + i] * d[i];
        }
    }
    Ok((RowSpace { p, pinv }, stack))
}

/// The Gram matrix's Cholesky factor is trusted while its diagonal stays within this
/// ratio (Â's rows far from dependent; with unit rows, L's diagonal bounds the
/// distance of each row from the span of the ones before).
const GRAM_DIAGONAL_RATIO: f64 = 1e-2;

/// Whether the Cholesky factor L (row-major k × k) is trusted.
fn well_conditioned(l: &[f64], k: usize) -> bool {
    let diagonal = (0..k).map(|i| l[i * k + i]);
    let largest = diagonal.clone().fold(0.0, f64::max);
    diagonal
        .into_iter()
        .all(|v| v > GRAM_DIAGONAL_RATIO * largest)
}

/// Â⁺ (row-major n × k) of the row-major k × n `a` from the SVD, singular values
/// below RANK_TOLERANCE of the largest dropped (near a singular configuration only:
/// this allocates).
fn svd_pseudo_inverse(a: &[f64], k: usize, n: usize, out: &mut [f64]) {
    let a = DMatrix::from_row_slice(k, n, &a[..k * n]);
    let svd = a.svd(true, true);
    let largest = svd.singular_values.iter().cloned().fold(0.0, f64::max);
    let pinv = svd
        .pseudo_inverse(RANK_TOLERANCE * largest)
        .unwrap_or_else(|_| DMatrix::zeros(n, k));
    for i in 0..n {
        for j in 0..k {
            out[i * k + j] = pinv[(i, j)];
        }
    }
}

/// out ← A b for the row-major `rows` × `cols` A.
fn multiply_vector(a: &[f64], rows: usize, cols: usize, b: &[f64], out: &mut [f64]) {
    for (o, row) in out[..rows].iter_mut().zip(a.chunks_exact(cols)) {
        *o = row.iter().zip(b).map(|(x, y)| x * y).sum();
    }
}

/// Subtracts d(P e)/dq at fixed e, −P (Σₖ λₖ Φᵏ_qq) − Φ_q⁺ (Φ_qq u) with
/// λ = (Φ_q⁺)ᵀe and u = P e, from the row-major n × n `block`.
fn subtract_projector_derivative(
    model: &Model,
    q: &[f64],
    rows: &RowSpace,
    (e, u): (&[f64], &[f64]),
    block: &mut [f64],
    stack: &mut PodStack,
) {
    let (m, n) = (model.m(), model.n());
    let (lambda, stack) = zeros(stack, m);
    let (w, stack) = zeros(stack, n * n);
    let (jw, stack) = zeros(stack, m * n);
    let (pw, stack) = zeros(stack, n * n);
    let (gj, _) = zeros(stack, n * n);
    for (k, l) in lambda.iter_mut().enumerate() {
        *l = (0..n).map(|i| rows.pinv[i * m + k] * e[i]).sum();
    }
    model.add_all_weighted_hessians(q, lambda, w);
    model.jacobian_derivative_into(q, u, jw);
    // P W + Φ_q⁺ Jw over the nonzeros of W and Jw (a few per row: each constraint
    // involves a few coordinates), in ascending k as the dense sums: the same value.
    let add = |a: &[f64], b: &[f64], inner: usize, sum: &mut [f64]| {
        for k in 0..inner {
            for (j, &bkj) in b[k * n..(k + 1) * n].iter().enumerate() {
                if bkj != 0.0 {
                    for i in 0..n {
                        sum[i * n + j] += a[i * inner + k] * bkj;
                    }
                }
            }
        }
    };
    add(rows.p, w, n, pw);
    add(rows.pinv, jw, m, gj);
    for ((b, p), g) in block.iter_mut().zip(pw.iter()).zip(gj.iter()) {
        *b -= p + g;
    }
}

/// An integrator factor of dependent coordinates (n rows) projected onto the tangent
/// space at the step's positions: P(q_t) e, for every integrator's factors (the
/// `--dc-integrators tangent` ones, made by [`super::Integrator::factors`] with
/// [`super::Form::Tangent`]).
pub struct Projected {
    model: Arc<Model>,
    inner: Box<dyn Factor>,
    name: String,
    /// The inner factor's keys, then q_t where the inner factor does not touch it.
    keys: Vec<Key>,
    /// Index in `keys` of q_t (the positions P is taken at).
    q_key: usize,
}

impl Projected {
    /// Projects `inner`, whose residual has one row per coordinate of q.
    pub fn new(model: Arc<Model>, inner: Box<dyn Factor>) -> Self {
        assert_eq!(inner.dim(), model.n(), "a projected factor has n rows");
        let mut keys = inner.keys().to_vec();
        let q_key = match keys.iter().position(|k| *k == Key::now(VarKind::Q)) {
            Some(k) => k,
            None => {
                keys.push(Key::now(VarKind::Q));
                keys.len() - 1
            }
        };
        Projected {
            name: format!("P {}", inner.name()),
            model,
            inner,
            keys,
            q_key,
        }
    }
}

impl Factor for Projected {
    fn name(&self) -> &str {
        &self.name
    }
    fn keys(&self) -> &[Key] {
        &self.keys
    }
    /// The inner factor's sizes, then n for a q_t the inner factor does not touch.
    fn size(&self, key: usize) -> usize {
        if key < self.inner.keys().len() {
            self.inner.size(key)
        } else {
            self.model.n()
        }
    }
    fn dim(&self) -> usize {
        self.inner.dim()
    }
    fn scratch(&self) -> StackReq {
        let cols = (0..self.keys.len())
            .map(|k| self.size(k))
            .max()
            .unwrap_or(0);
        // The inner factor runs first, then the projection carves its own.
        self.inner
            .scratch()
            .or(row_space_scratch(&self.model, cols))
    }
    fn evaluate(
        &self,
        t: f64,
        x: &[&[f64]],
        r: &mut [f64],
        jac: Option<&mut [Vec<f64>]>,
        ws: &mut Workspace,
    ) -> Result<()> {
        let n = self.model.n();
        let q = x[self.q_key];
        let inner_keys = self.inner.keys().len();
        // e into r, projected at the end.
        let mut jac = jac;
        match jac.as_deref_mut() {
            Some(j) => {
                self.inner
                    .evaluate(t, &x[..inner_keys], r, Some(&mut j[..inner_keys]), ws)?
            }
            None => self.inner.evaluate(t, &x[..inner_keys], r, None, ws)?,
        }
        let (rows, stack) = row_space(&self.model, q, ws.stack())?;
        let (u, stack) = zeros(stack, n);
        multiply_vector(rows.p, n, n, r, u);
        if let Some(j) = jac {
            let (product, stack) = zeros(stack, j.iter().map(Vec::len).max().unwrap_or(0));
            for (a, block) in j[..inner_keys].iter_mut().enumerate() {
                let cols = block.len() / n;
                if self.inner.diagonal_jacobian(a) && cols == n {
                    // P diag(d): P's columns scaled (the dense product's only
                    // nonzero term).
                    for (out, p_row) in product[..n * n]
                        .chunks_exact_mut(n)
                        .zip(rows.p.chunks_exact(n))
                    {
                        for (k, (o, p)) in out.iter_mut().zip(p_row).enumerate() {
                            *o = p * block[k * n + k];
                        }
                    }
                } else {
                    for i in 0..n {
                        for k in 0..cols {
                            product[i * cols + k] = (0..n)
                                .map(|l| rows.p[i * n + l] * block[l * cols + k])
                                .sum();
                        }
                    }
                }
                let len = block.len();
                block.copy_from_slice(&product[..len]);
            }
            if self.q_key >= inner_keys {
                j[self.q_key].fill(0.0);
            }
            subtract_projector_derivative(&self.model, q, &rows, (r, u), &mut j[self.q_key], stack);
        }
        r.copy_from_slice(u);
        Ok(())
    }
}
