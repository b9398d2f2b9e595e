//! The dynamics kernel of the factors: q̈(q, q̇, t) from the augmented system
//! without allocating, its exact Jacobians and ∂q̈/∂Q, regularized near a singular
//! configuration (the measure is in `regularization`, the directional products in
//! `along`).

use super::regularization::{mass_scale, MeasureLayout};
use crate::error::{Error, Result};
use crate::linalg::dense;
use crate::model::Model;

/// Forward dynamics q̈(q, q̇, t) by the augmented system, and optionally its exact
/// Jacobians, without allocating.
///
/// With K = [M Aᵀ; A −E] (A: the active rows of Φ_q, E = diag(εₖ), see below) and
/// [q̈; λ] = K⁻¹[Q; c]:
///   K [∂q̈/∂q; ∂λ/∂q] = [∂Q/∂q − ∂(Φ_qᵀλ)/∂q; −∂(Φ̇_q q̇)/∂q − Φ_qq q̈ + E_q λ]
///   K [∂q̈/∂q̇; ∂λ/∂q̇] = [∂Q/∂q̇; −2 Φ̇_q]
/// (rows of the right-hand sides restricted to the active constraints; row k of
/// E_q λ is λₖ ∂εₖ/∂q).
///
/// **Singular configurations.** Where Φ_q is regular, E = 0: the KKT system of the
/// paper (eq. "qDynSys"), computed exactly as before. Where Φ_q loses a rank (the
/// parallelogram's flat configurations) K is singular, and near it the KKT q̈
/// answers a velocity off the constraint manifold by round-off with an acceleration
/// 1/σ larger (σ the smallest singular value of Φ_q); the hard constraints cannot
/// remove that round-off there (they fix the velocity along the lost rank only to
/// ε_mach/σ²), ∂q̈/∂q grows like 1/σ, and K no longer factors below σ ≈ 1e-8. So
/// near rank loss the bottom block is −E with εₖ = w(s) ε_rel ‖aₖ‖²/m̄ (aₖ row k of
/// A, m̄ the largest diagonal entry of M): the Tikhonov-regularized (penalty) form
/// (M + AᵀE⁻¹A) q̈ = Q + AᵀE⁻¹c, regular at every configuration, with a bounded
/// response to such velocities, and within O(ε/σ²) of the KKT q̈ where σ² ≫ ε.
/// s = (tr G⁻¹)^(−1/2), G = ÂÂᵀ with Â the rows of A normalized, measures the
/// distance to rank loss (√λ_min(G/m) ≤ s ≤ √λ_min(G)); w = 0 above
/// [`DynamicsKernel::REGULAR_ABOVE`], 1 below [`DynamicsKernel::SINGULAR_BELOW`] and
/// the cubic 1 − x²(3 − 2x) of x = log(s/below)/log(above/below) between, so q̈ is C¹
/// and the Jacobians above exact everywhere.
pub struct DynamicsKernel;

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
    /// ε_rel: εₖ = w ε_rel ‖aₖ‖²/m̄. With the ramp below, ε_rel from 5e-8 to 5e-5
    /// lets DC pass the parallelogram's five flat points at Δt = 1e-3 to 1e-5 s and
    /// seven phases of the motion; 5e-9 does not. 1e-6 sits in the middle.
    pub const REGULARIZATION: f64 = 1e-6;
    /// Below this s the regularization is full (w = 1).
    pub const SINGULAR_BELOW: f64 = 1e-4;
    /// At or above this s the system is the plain KKT system (w = 0). With the
    /// damped corrections of [`crate::linalg::nullspace::NullSpace`] the KKT system
    /// serves down to s ≈ 1e-4: ramps from (1e-5, 1e-4) to (1e-3, 1e-2) all pass the
    /// parallelogram, (1e-7, 1e-6) does not. The top stays below the regular motion
    /// of every scene: pick-and-place comes closest (s = 4.5e-3 at t = 0.39 s; a
    /// ramp up to 1e-2 changed its run), the four-bar stays above 0.37.
    pub const REGULAR_ABOVE: f64 = 1e-3;

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
            Error::Singular("the augmented (KKT) system is singular: a singular configuration or dependent constraints".into())
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
