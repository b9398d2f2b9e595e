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
use crate::factors::{Euler, Trapezoidal};
use crate::graph::{Factor, Key, StackReq, VarKind, Workspace};
use crate::model::Model;
use nalgebra::{DMatrix, DVector};
use std::sync::Arc;

/// Singular values of the row-normalized Φ_q below this (relative to the largest)
/// count as a lost rank: the direction is not projected out.
const RANK_TOLERANCE: f64 = 1e-10;

/// The integration rule the projected residual e comes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Rule {
    /// e = x_t − x_{t−1} − Δt/2 (ẋ_{t−1} + ẋ_t).
    Trapezoidal,
    /// e = x_t − x_{t−1} − Δt ẋ_{t−1}.
    Euler,
}

/// The row space of Φ_q at q, from the active rows (redundant constraints left out:
/// on the manifold they add no direction) normalized, Â = D Φ_q,active: the
/// projector P = I − Â⁺Â onto the null space (n × n) and Φ_q⁺ = Â⁺D (n × m over all
/// m constraints, zero columns for the redundant ones), Â⁺ restricted to Â's rank.
struct RowSpace {
    p: DMatrix<f64>,
    pinv: DMatrix<f64>,
}

fn row_space(model: &Model, q: &[f64]) -> Result<RowSpace> {
    let (m, n) = (model.m(), model.n());
    let mut all = vec![0.0; m * n];
    model.jacobian_into(q, &mut all);
    if all.iter().any(|v| !v.is_finite()) {
        return Err(Error::singular("Φ_q is not finite at the step's positions"));
    }
    let rows = &model.active;
    let mut a = DMatrix::zeros(rows.len(), n);
    let mut d = vec![0.0; rows.len()];
    for (i, &k) in rows.iter().enumerate() {
        let row = &all[k * n..(k + 1) * n];
        let norm = row.iter().map(|v| v * v).sum::<f64>().sqrt();
        if norm > 0.0 {
            d[i] = 1.0 / norm;
            for (j, v) in row.iter().enumerate() {
                a[(i, j)] = v * d[i];
            }
        }
    }
    // Â⁺ = Âᵀ(ÂÂᵀ)⁻¹ by Cholesky while the Gram matrix is well conditioned (the
    // usual case), the SVD otherwise: near a singular configuration the Gram matrix
    // squares a large condition number.
    let pinv_hat = match (&a * a.transpose()).cholesky() {
        Some(ch) if well_conditioned(&ch.l()) => a.transpose() * ch.inverse(),
        _ => svd_pseudo_inverse(&a),
    };
    let mut p = -(&pinv_hat * &a);
    for i in 0..n {
        p[(i, i)] += 1.0;
    }
    let mut pinv = DMatrix::zeros(n, m);
    for (i, &k) in rows.iter().enumerate() {
        pinv.set_column(k, &(pinv_hat.column(i) * d[i]));
    }
    Ok(RowSpace { p, pinv })
}

/// The Gram matrix's Cholesky factor is trusted while its diagonal stays within this
/// ratio (Â's rows far from dependent; with unit rows, L's diagonal bounds the
/// distance of each row from the span of the ones before).
const GRAM_DIAGONAL_RATIO: f64 = 1e-2;

fn well_conditioned(l: &DMatrix<f64>) -> bool {
    let diagonal = l.diagonal();
    let largest = diagonal.iter().cloned().fold(0.0, f64::max);
    diagonal.iter().all(|&v| v > GRAM_DIAGONAL_RATIO * largest)
}

/// Â⁺ from the SVD, singular values below RANK_TOLERANCE of the largest dropped.
fn svd_pseudo_inverse(a: &DMatrix<f64>) -> DMatrix<f64> {
    let svd = a.clone().svd(true, true);
    let largest = svd.singular_values.iter().cloned().fold(0.0, f64::max);
    svd.pseudo_inverse(RANK_TOLERANCE * largest)
        .unwrap_or_else(|_| DMatrix::zeros(a.ncols(), a.nrows()))
}

/// Subtracts d(P e)/dq at fixed e, −P (Σₖ λₖ Φᵏ_qq) − Φ_q⁺ (Φ_qq u) with
/// λ = (Φ_q⁺)ᵀe and u = P e, from the row-major n × n `block`.
fn subtract_projector_derivative(
    model: &Model,
    q: &[f64],
    rows: &RowSpace,
    e: &DVector<f64>,
    u: &DVector<f64>,
    block: &mut [f64],
) {
    let (m, n) = (model.m(), model.n());
    let lambda = rows.pinv.tr_mul(e);
    let mut w = vec![0.0; n * n];
    model.add_all_weighted_hessians(q, lambda.as_slice(), &mut w);
    let w = DMatrix::from_row_slice(n, n, &w);
    let mut jw = vec![0.0; m * n];
    model.jacobian_derivative_into(q, u.as_slice(), &mut jw);
    let jw = DMatrix::from_row_slice(m, n, &jw);
    let dp = &rows.p * w + &rows.pinv * jw;
    for i in 0..n {
        for k in 0..n {
            block[i * n + k] -= dp[(i, k)];
        }
    }
}

/// An integrator factor of dependent coordinates (n rows) projected onto the tangent
/// space at the step's positions: P(q_t) e, for the trapezoidal rule and Euler
/// ([`Projected::integrator`]) and for the Hermite–Simpson factors
/// ([`crate::collocation`]).
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

    /// The integration of `dx` into `x` (q or q̇) by `rule`, projected: the
    /// `--dc-integrators tangent` factors.
    pub fn integrator(model: Arc<Model>, x: VarKind, dx: VarKind, rule: Rule, dt: f64) -> Self {
        let n = model.n();
        let inner: Box<dyn Factor> = match rule {
            Rule::Trapezoidal => Box::new(Trapezoidal::new(x, dx, n, dt)),
            Rule::Euler => Box::new(Euler::new(x, dx, n, dt)),
        };
        Projected::new(model, inner)
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
        self.inner.scratch()
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
        let mut e = DVector::zeros(n);
        let rows = row_space(&self.model, q)?;
        let Some(j) = jac else {
            self.inner
                .evaluate(t, &x[..inner_keys], e.as_mut_slice(), None, ws)?;
            r.copy_from_slice((&rows.p * &e).as_slice());
            return Ok(());
        };
        self.inner.evaluate(
            t,
            &x[..inner_keys],
            e.as_mut_slice(),
            Some(&mut j[..inner_keys]),
            ws,
        )?;
        let u = &rows.p * &e;
        r.copy_from_slice(u.as_slice());
        for block in j[..inner_keys].iter_mut() {
            let cols = block.len() / n;
            let inner = DMatrix::from_row_slice(n, cols, block);
            let projected = &rows.p * inner;
            for i in 0..n {
                for k in 0..cols {
                    block[i * cols + k] = projected[(i, k)];
                }
            }
        }
        if self.q_key >= inner_keys {
            j[self.q_key].fill(0.0);
        }
        subtract_projector_derivative(&self.model, q, &rows, &e, &u, &mut j[self.q_key]);
        Ok(())
    }
}
