//! The evaluation of the [`DynamicsKernel`]: q̈(q, q̇, t) from the augmented system
//! without allocating, its exact Jacobians ∂q̈/∂q and ∂q̈/∂q̇, and ∂q̈/∂Q, with the
//! scratch they share.

use super::kernel::DynamicsKernel;
use super::regularization::{mass_scale, MeasureLayout};
use crate::error::{Error, Result};
use crate::linalg::dense;
use crate::model::Model;

/// Where the kernel's scratch lives inside `ws.reals`: the augmented system and its
/// right-hand sides, then the singularity measure's scratch ([`MeasureLayout`]).
pub(super) struct KernelLayout {
    pub(super) n: usize,
    pub(super) ma: usize,
    pub(super) sol: usize,
    pub(super) tmp: usize,
    pub(super) mat: usize,
    pub(super) kq: usize,
    pub(super) kv: usize,
    pub(super) cols: usize,
    pub(super) c: usize,
    pub(super) measure: usize,
    pub(super) end: usize,
}

impl KernelLayout {
    pub(super) fn new(model: &Model) -> Self {
        let (n, m, ma) = (model.n(), model.m(), model.active.len());
        let big = n + ma;
        let sol = big * big;
        let tmp = sol + big;
        let mat = tmp + 2 * n * big;
        let kq = mat + m * n;
        let kv = kq + n * n;
        let cols = kv + n * n;
        let c = cols + 2 * n * big;
        let measure = c + m;
        let end = measure + MeasureLayout::new(model).end;
        KernelLayout {
            n,
            ma,
            sol,
            tmp,
            mat,
            kq,
            kv,
            cols,
            c,
            measure,
            end,
        }
    }
}

impl DynamicsKernel {
    /// Scratch needed: (reals, indices).
    pub fn scratch(model: &Model) -> (usize, usize) {
        let l = KernelLayout::new(model);
        (l.end, l.n + l.ma)
    }

    /// Computes q̈ into `ddq`; with `jac`, ∂q̈/∂q and ∂q̈/∂q̇ into the row-major n × n
    /// blocks. `force`, when given, is added to the scene's Q (the unknown actuator
    /// forces of inverse dynamics). The LU factors of the augmented system stay in
    /// the scratch for [`DynamicsKernel::force_jacobian`].
    #[allow(clippy::too_many_arguments)]
    pub fn evaluate(
        model: &Model,
        q: &[f64],
        dq: &[f64],
        t: f64,
        force: Option<&[f64]>,
        ddq: &mut [f64],
        jac: Option<(&mut [f64], &mut [f64])>,
        reals: &mut [f64],
        indices: &mut [usize],
    ) -> Result<()> {
        let l = KernelLayout::new(model);
        let (n, ma) = (l.n, l.ma);
        let big = n + ma;
        let m = model.m();
        let perm = &mut indices[..big];
        let (main, scratch) = reals[..l.end].split_at_mut(l.measure);
        let (kkt, rest) = main.split_at_mut(l.sol);
        let (sol, rest) = rest.split_at_mut(l.tmp - l.sol);
        let (tmp, rest) = rest.split_at_mut(l.mat - l.tmp);
        let (mat, rest) = rest.split_at_mut(l.kq - l.mat);
        let (kq, rest) = rest.split_at_mut(l.kv - l.kq);
        let (kv, rest) = rest.split_at_mut(l.cols - l.kv);
        let (cols, rest) = rest.split_at_mut(l.c - l.cols);
        let c = &mut rest[..m];

        // K = [M Aᵀ; A −E] and the right-hand side [Q; c].
        model.jacobian_into(q, mat);
        let reg = Self::measure(model, mat, scratch, false);
        kkt.fill(0.0);
        for i in 0..n {
            for j in 0..n {
                kkt[i * big + j] = model.mass[(i, j)];
            }
        }
        for (r, &k) in model.active.iter().enumerate() {
            for j in 0..n {
                let a = mat[k * n + j];
                kkt[(n + r) * big + j] = a;
                kkt[j * big + n + r] = a;
            }
        }
        if reg.w > 0.0 {
            let ml = MeasureLayout::new(model);
            let scale = Self::REGULARIZATION * reg.w / mass_scale(model);
            for r in 0..ma {
                let norm = scratch[ml.norms + r];
                let e = scale * norm * norm;
                scratch[ml.eps + r] = e;
                kkt[(n + r) * big + n + r] = -e;
            }
        }
        sol.fill(0.0);
        for f in &model.forces {
            f.add_to(model, q, dq, t, &mut sol[..n])?;
        }
        if let Some(f) = force {
            for (s, v) in sol[..n].iter_mut().zip(f) {
                *s += v;
            }
        }
        model.acceleration_rhs_into(q, dq, c);
        for (r, &k) in model.active.iter().enumerate() {
            sol[n + r] = c[k];
        }
        dense::lu(kkt, big, perm).map_err(|_| {
            Error::singular("the augmented (KKT) system is singular: a singular configuration or dependent constraints")
        })?;
        dense::lu_solve(kkt, big, perm, sol, tmp);
        ddq.copy_from_slice(&sol[..n]);
        let Some((jq, jv)) = jac else {
            return Ok(());
        };

        // Right-hand sides, column-major: n columns for q, then n for q̇.
        kq.fill(0.0);
        kv.fill(0.0);
        for f in &model.forces {
            f.add_jacobians(model, (q, dq, t), kq, kv)?;
        }
        // kq −= ∂(Φ_qᵀλ)/∂q, accumulated with −λ.
        for (t, l) in tmp.iter_mut().zip(&sol[n..big]) {
            *t = -l;
        }
        model.add_weighted_hessians(q, &tmp[..ma], kq);
        // The right-hand sides, row-major big × 2n: n columns for q, then n for q̇.
        let w = 2 * n;
        for i in 0..n {
            cols[i * w..i * w + n].copy_from_slice(&kq[i * n..(i + 1) * n]);
            cols[i * w + n..(i + 1) * w].copy_from_slice(&kv[i * n..(i + 1) * n]);
        }
        // Bottom rows for q: −∂(Φ̇_q q̇)/∂q − Φ_qq q̈.
        model.third_order_into(q, dq, mat);
        for (r, &k) in model.active.iter().enumerate() {
            let row = &mut cols[(n + r) * w..(n + r) * w + n];
            for (o, v) in row.iter_mut().zip(&mat[k * n..(k + 1) * n]) {
                *o = -v;
            }
        }
        let ddq_now: &[f64] = ddq;
        model.jacobian_derivative_into(q, ddq_now, mat);
        for (r, &k) in model.active.iter().enumerate() {
            let row = &mut cols[(n + r) * w..(n + r) * w + n];
            for (o, v) in row.iter_mut().zip(&mat[k * n..(k + 1) * n]) {
                *o -= v;
            }
        }
        if reg.w > 0.0 {
            Self::add_regularization_terms(model, q, reg, &sol[n..big], cols, w, scratch);
        }
        // Bottom rows for q̇: −2 Φ̇_q.
        model.jacobian_derivative_into(q, dq, mat);
        for (r, &k) in model.active.iter().enumerate() {
            let row = &mut cols[(n + r) * w + n..(n + r + 1) * w];
            for (o, v) in row.iter_mut().zip(&mat[k * n..(k + 1) * n]) {
                *o = -2.0 * v;
            }
        }
        dense::lu_solve_many(kkt, big, perm, &mut cols[..big * w], w, tmp);
        for i in 0..n {
            jq[i * n..(i + 1) * n].copy_from_slice(&cols[i * w..i * w + n]);
            jv[i * n..(i + 1) * n].copy_from_slice(&cols[i * w + n..(i + 1) * w]);
        }
        Ok(())
    }

    /// ∂q̈/∂Q_c for forces Q_c on the coordinates `columns` (row-major n × columns.len())
    /// with the factors a preceding [`DynamicsKernel::evaluate`] left in the scratch:
    /// the first n rows of K⁻¹[E; 0], E the columns of I they act on.
    pub fn force_jacobian(
        model: &Model,
        columns: &[usize],
        jf: &mut [f64],
        reals: &mut [f64],
        indices: &[usize],
    ) {
        let l = KernelLayout::new(model);
        let (n, ma) = (l.n, l.ma);
        let big = n + ma;
        let perm = &indices[..big];
        let (kkt, rest) = reals[..l.end].split_at_mut(l.sol);
        let (_, rest) = rest.split_at_mut(l.tmp - l.sol);
        let (tmp, rest) = rest.split_at_mut(l.mat - l.tmp);
        let (_, rest) = rest.split_at_mut(l.cols - l.mat);
        let (cols, _) = rest.split_at_mut(l.c - l.cols);
        let p = columns.len();
        let rhs = &mut cols[..big * p];
        rhs.fill(0.0);
        for (c, &j) in columns.iter().enumerate() {
            rhs[j * p + c] = 1.0;
        }
        dense::lu_solve_many(kkt, big, perm, rhs, p, tmp);
        jf[..n * p].copy_from_slice(&rhs[..n * p]);
    }
}
