//! The evaluation of the [`DynamicsKernel`]: q̈(q, q̇, t) from the augmented system
//! without allocating, its exact Jacobians ∂q̈/∂q and ∂q̈/∂q̇, and ∂q̈/∂Q, with the
//! scratch they share.

use super::kernel::DynamicsKernel;
use super::regularization::{mass_scale, MeasureScratch};
use super::sparse_kkt::{KktStructure, SparseLu};
use crate::error::{Error, Result};
use crate::graph::{carve, PodStack, StackReq};
use crate::linalg::dense;
use crate::model::Model;

/// The kernel's scratch, carved from a [`PodStack`]: the augmented system (its LU
/// factors after an evaluation) and their pivots, [q̈; λ], room for the solves,
/// Φ_q and its like (m × n), ∂Q/∂q and ∂Q/∂q̇ (n × n), the Jacobians' right-hand
/// sides (big × 2n), c (m) and the singularity measure's ([`MeasureScratch`]).
/// [`DynamicsKernel::evaluate`] leaves the factors and [q̈; λ] in it for
/// [`DynamicsKernel::force_jacobian`] and [`DynamicsKernel::along`].
pub struct KernelScratch<'a> {
    pub(super) kkt: &'a mut [f64],
    pub(super) perm: &'a mut [usize],
    pub(super) sol: &'a mut [f64],
    tmp: &'a mut [f64],
    mat: &'a mut [f64],
    kq: &'a mut [f64],
    kv: &'a mut [f64],
    cols: &'a mut [f64],
    c: &'a mut [f64],
    measure: MeasureScratch<'a>,
    /// A large mechanism's K: its structure, and its factors once evaluated (then
    /// `kkt` and `perm` are not used).
    sparse: Option<&'a KktStructure>,
    factors: Option<SparseLu<'a>>,
    /// μ of the dense K factored as [M/μ Aᵀ; A −μE] (unknowns q̈ and λ/μ): 1 but
    /// where the plain K failed its pivot test for a heavy mechanism
    /// ([`DynamicsKernel::evaluate`]).
    scale: f64,
    /// Rows of K for λ (the active constraints).
    active: usize,
    /// Whether the last evaluation regularized K near a singular configuration
    /// (w > 0): its Jacobians then carry the regularization's derivative, which
    /// [`DynamicsKernel::along`] does not form.
    pub(super) regularized: bool,
    /// A mass matrix in place of the model's (row-major n × n; dense K only): the
    /// model's at other values of the parameters an estimate identifies.
    mass: Option<&'a [f64]>,
}

impl<'a> KernelScratch<'a> {
    fn lens(model: &Model) -> [usize; 8] {
        let (n, m) = (model.n(), model.m());
        let big = n + model.active.len();
        [
            big * big,
            big,
            2 * n * big,
            m * n,
            n * n,
            n * n,
            2 * n * big,
            m,
        ]
    }

    /// The scratch carved (zeroed) from `stack`, which must hold
    /// [`DynamicsKernel::scratch`], and the rest of `stack`; with `sparse`, K is
    /// factored sparse.
    pub fn new(
        model: &Model,
        sparse: Option<&'a KktStructure>,
        stack: &'a mut PodStack,
    ) -> (Self, &'a mut PodStack) {
        let big = model.n() + model.active.len();
        let [kkt, sol, tmp, mat, kq, kv, cols, c] = Self::lens(model);
        // Every array is written before it is read (K by `fill_kkt`, the others as
        // `evaluate` and the solves fill them): carved as they were left, not zeroed
        // (zeroing is most of a large mechanism's evaluation). A sparse K has no
        // dense copy.
        let (kkt, stack) = carve(stack, if sparse.is_some() { 0 } else { kkt });
        let (perm, stack) = stack.make_with(big, |_| 0usize);
        let (sol, stack) = carve(stack, sol);
        let (tmp, stack) = carve(stack, tmp);
        let (mat, stack) = carve(stack, mat);
        let (kq, stack) = carve(stack, kq);
        let (kv, stack) = carve(stack, kv);
        let (cols, stack) = carve(stack, cols);
        let (c, stack) = carve(stack, c);
        let (measure, stack) = MeasureScratch::new(model, stack);
        let scratch = KernelScratch {
            kkt,
            perm,
            sol,
            tmp,
            mat,
            kq,
            kv,
            cols,
            c,
            measure,
            sparse,
            factors: None,
            scale: 1.0,
            active: model.active.len(),
            regularized: false,
            mass: None,
        };
        (scratch, stack)
    }

    /// The scratch of a dense K whose mass matrix is `mass` (row-major n × n), not
    /// the model's ([`crate::model::parameters::Parameters::mass_at`]).
    pub fn with_mass(mut self, mass: &'a [f64]) -> Self {
        assert!(
            self.sparse.is_none(),
            "a mass matrix of its own needs a dense K"
        );
        self.mass = Some(mass);
        self
    }
}

impl KernelScratch<'_> {
    /// B ← K⁻¹B (row-major big × `cols`) with the factors [`DynamicsKernel::evaluate`]
    /// left here; `tmp` holds big × `cols` for the dense ones.
    pub(super) fn solve_many(&self, b: &mut [f64], cols: usize, tmp: &mut [f64]) -> Result<()> {
        let big = self.perm.len();
        match &self.factors {
            Some(lu) => lu.solve_many(b, cols),
            None => {
                solve_dense(
                    self.kkt,
                    self.perm,
                    (big - self.active, self.scale),
                    b,
                    cols,
                    tmp,
                );
                Ok(())
            }
        }
    }
}

/// K = [M/μ Aᵀ; A −μE] into `kkt` (row-major big × big), A the active rows of
/// Φ_q (`jacobian`, all m rows × n), E the regularization's diagonal where there is
/// one; M the model's, or `mass` (row-major n × n) where given.
fn fill_kkt(
    model: &Model,
    mass: Option<&[f64]>,
    jacobian: &[f64],
    eps: Option<&[f64]>,
    mu: f64,
    kkt: &mut [f64],
) {
    let (n, ma) = (model.n(), model.active.len());
    let big = n + ma;
    kkt[..big * big].fill(0.0);
    for i in 0..n {
        for j in 0..n {
            let m = mass.map_or(model.mass[(i, j)], |m| m[i * n + j]);
            kkt[i * big + j] = if mu == 1.0 { m } else { m / mu };
        }
    }
    for (r, &k) in model.active.iter().enumerate() {
        for j in 0..n {
            let a = jacobian[k * n + j];
            kkt[(n + r) * big + j] = a;
            kkt[j * big + n + r] = a;
        }
    }
    if let Some(eps) = eps {
        for (r, e) in eps.iter().enumerate() {
            kkt[(n + r) * big + n + r] = -mu * e;
        }
    }
}

/// B ← K⁻¹B (row-major big × `cols`, its first `n` rows for q̈) with the dense
/// factors of K scaled by `scale` (see [`KernelScratch::scale`]): those rows go in
/// over μ, the others (λ) come out times μ.
fn solve_dense(
    lu: &[f64],
    perm: &[usize],
    (n, scale): (usize, f64),
    b: &mut [f64],
    cols: usize,
    tmp: &mut [f64],
) {
    let big = perm.len();
    if scale != 1.0 {
        b[..n * cols].iter_mut().for_each(|v| *v /= scale);
    }
    dense::lu_solve_many(lu, big, perm, &mut b[..big * cols], cols, tmp);
    if scale != 1.0 {
        b[n * cols..big * cols].iter_mut().for_each(|v| *v *= scale);
    }
}

impl DynamicsKernel {
    /// The scratch of a [`KernelScratch`] (the sparse factors of a large K are on
    /// the heap).
    pub fn scratch(model: &Model) -> StackReq {
        let big = model.n() + model.active.len();
        let reals = KernelScratch::lens(model).map(StackReq::new::<f64>);
        StackReq::all_of(&reals)
            .and(StackReq::new::<usize>(big))
            .and(MeasureScratch::req(model))
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
        scratch: &mut KernelScratch,
    ) -> Result<()> {
        let (n, ma) = (model.n(), model.active.len());
        let big = n + ma;
        let KernelScratch {
            kkt,
            perm,
            sol,
            tmp,
            mat,
            kq,
            kv,
            cols,
            c,
            measure: scratch,
            sparse,
            factors,
            scale,
            regularized,
            mass,
            ..
        } = scratch;
        let mass = *mass;

        // K = [M Aᵀ; A −E] and the right-hand side [Q; c].
        *scale = 1.0;
        model.jacobian_into(q, mat);
        let reg = Self::measure(model, mat, scratch, false);
        *regularized = reg.w > 0.0;
        if let Some(structure) = sparse {
            // Sparse: K's values from M, Φ_q and E; factored below.
            if reg.w > 0.0 {
                let scale = Self::REGULARIZATION * reg.w / mass_scale(model);
                for r in 0..ma {
                    let norm = scratch.norms[r];
                    scratch.eps[r] = scale * norm * norm;
                }
            }
            *factors =
                Some(structure.factor(model, mat, (reg.w > 0.0).then_some(&scratch.eps[..ma]))?);
        } else {
            if reg.w > 0.0 {
                let scale = Self::REGULARIZATION * reg.w / mass_scale(model);
                for r in 0..ma {
                    let norm = scratch.norms[r];
                    scratch.eps[r] = scale * norm * norm;
                }
            }
            let eps = (reg.w > 0.0).then_some(&scratch.eps[..ma]);
            fill_kkt(model, mass, mat, eps, 1.0, kkt);
            // The pivot test is relative to K's largest entry: a heavy mechanism
            // (1e8 kg on 1 m links) makes the constraint block's pivots, |Φ_q|²/m,
            // look singular. Then K is factored again with M in units of its scale.
            if dense::lu(kkt, big, perm).is_err() {
                *scale = mass_scale(model);
                fill_kkt(model, mass, mat, eps, *scale, kkt);
                dense::lu(kkt, big, perm).map_err(|_| {
                    Error::singular("the augmented (KKT) system is singular: a singular configuration or dependent constraints")
                })?;
            }
        }
        sol.fill(0.0);
        for (i, f) in model.forces.iter().enumerate() {
            f.add_to(model, q, dq, t, &mut sol[..n])
                .map_err(|e| model.effect_error(i, e))?;
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
        match factors {
            Some(lu) => lu.solve_many(&mut sol[..big], 1)?,
            None if *scale == 1.0 => dense::lu_solve(kkt, big, perm, &mut sol[..big], tmp),
            None => solve_dense(kkt, perm, (n, *scale), &mut sol[..big], 1, tmp),
        }
        ddq.copy_from_slice(&sol[..n]);
        let Some((jq, jv)) = jac else {
            return Ok(());
        };

        // Right-hand sides, column-major: n columns for q, then n for q̇.
        kq.fill(0.0);
        kv.fill(0.0);
        for (i, f) in model.forces.iter().enumerate() {
            f.add_jacobians(model, (q, dq, t), kq, kv)
                .map_err(|e| model.effect_error(i, e))?;
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
        match factors {
            Some(lu) => lu.solve_many(&mut cols[..big * w], w)?,
            None => solve_dense(kkt, perm, (n, *scale), &mut cols[..big * w], w, tmp),
        }
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
        scratch: &mut KernelScratch,
    ) -> Result<()> {
        let (n, ma) = (model.n(), model.active.len());
        let big = n + ma;
        let KernelScratch {
            kkt,
            perm,
            tmp,
            cols,
            factors,
            scale,
            ..
        } = scratch;
        let p = columns.len();
        let rhs = &mut cols[..big * p];
        rhs.fill(0.0);
        for (c, &j) in columns.iter().enumerate() {
            rhs[j * p + c] = 1.0;
        }
        match factors {
            Some(lu) => lu.solve_many(rhs, p)?,
            None => solve_dense(kkt, perm, (n, *scale), rhs, p, tmp),
        }
        jf[..n * p].copy_from_slice(&rhs[..n * p]);
        Ok(())
    }
}
