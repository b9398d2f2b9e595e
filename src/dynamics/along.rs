//! Directional derivatives of the dynamics kernel: Σ_a ∂q̈/∂x_a V_a for a few
//! directions at once, from the factors a preceding evaluation left, at a pair of
//! triangular solves per direction instead of one per coordinate.

use super::augmented::KernelScratch;
use super::kernel::DynamicsKernel;
use crate::error::Result;
use crate::graph::{carve, PodStack, StackReq};
use crate::model::Model;

/// [`DynamicsKernel::along`]'s scratch beyond the kernel's, for up to `max_cols`
/// directions: ∂Q/∂q and ∂Q/∂q̇ (n × n), Φ_q and its like (m × n), the bottom rows
/// of the right-hand sides (ma × n twice), B and room for its solves
/// (big × max_cols each), and the columns solved for (max_cols).
fn lens(model: &Model, max_cols: usize) -> [usize; 6] {
    let (n, m, ma) = (model.n(), model.m(), model.active.len());
    let big = n + ma;
    let cols = big * max_cols.max(1);
    [n * n, n * n, m * n, ma * n, ma * n, cols]
}

impl DynamicsKernel {
    /// Scratch [`DynamicsKernel::along`] needs beyond the kernel's, for up to
    /// `max_cols` directions.
    pub fn along_scratch(model: &Model, max_cols: usize) -> StackReq {
        let [kq, kv, mat, bq, bv, b] = lens(model, max_cols);
        StackReq::all_of(&[kq, kv, mat, bq, bv, b, b].map(StackReq::new::<f64>))
            .and(StackReq::new::<usize>(max_cols))
    }

    /// Rows `rows` (all n without) of Σ_a ∂q̈/∂x_a V_a over x = q, q̇ and the forces, for directions
    /// V_q, V_v (row-major n × c) and V_f (row-major columns.len() × c, the forces on
    /// the coordinates `columns`), into the row-major rows.len() × c `out`, at the
    /// point of a preceding [`DynamicsKernel::evaluate`] without Jacobians (its LU
    /// factors and [q̈; λ] are in `kernel`), with the scratch of
    /// [`DynamicsKernel::along_scratch`] carved from `stack`: the first n rows of
    /// K⁻¹ (R_q V_q + R_v V_v + [E V_f; 0]), R_q and R_v the right-hand sides from
    /// which `evaluate` solves for ∂q̈/∂q and ∂q̈/∂q̇. Only the columns where some
    /// direction is nonzero are solved for (one pair of triangular solves each, where
    /// the Jacobians take one per coordinate and force); returns false when more
    /// than `max_cols` are, or where the evaluation regularized K (`out` then holds
    /// nothing of use).
    #[allow(clippy::too_many_arguments)]
    pub fn along(
        model: &Model,
        (q, dq, t): (&[f64], &[f64], f64),
        directions: [&[f64]; 3],
        columns: &[usize],
        rows: Option<&[usize]>,
        c: usize,
        out: &mut [f64],
        kernel: &KernelScratch,
        stack: &mut PodStack,
        max_cols: usize,
    ) -> Result<bool> {
        let [vq, vv, vf] = directions;
        let (n, ma) = (model.n(), model.active.len());
        let big = n + ma;
        if kernel.regularized {
            // Near a singular configuration the Jacobians carry the regularization's
            // derivative (λₖ ∂εₖ/∂q), which the directions here leave out.
            return Ok(false);
        }
        // The columns where a direction is nonzero (flags in `out`'s first row).
        let flags = &mut out[..c];
        flags.fill(0.0);
        for v in [vq, vv, vf] {
            for row in v.chunks_exact(c) {
                for (f, x) in flags.iter_mut().zip(row) {
                    if *x != 0.0 {
                        *f = 1.0;
                    }
                }
            }
        }
        let na = flags.iter().filter(|f| **f != 0.0).count();
        if na > max_cols {
            return Ok(false);
        }
        let count = rows.map_or(n, <[usize]>::len);
        if na == 0 {
            // No direction moves q, q̇ or the forces.
            out[..count * c].fill(0.0);
            return Ok(true);
        }
        let (act, stack) = stack.make_with(na, |_| 0usize);
        for (a, (j, _)) in act
            .iter_mut()
            .zip(flags.iter().enumerate().filter(|(_, f)| **f != 0.0))
        {
            *a = j;
        }
        let act = &act[..];
        // Every array below is written before it is read.
        let [kq, kv, mat, bq, bv, _] = lens(model, max_cols);
        let (kq, stack) = carve(stack, kq);
        let (kv, stack) = carve(stack, kv);
        let (mat, stack) = carve(stack, mat);
        let (bq, stack) = carve(stack, bq);
        let (bv, stack) = carve(stack, bv);
        let (b, stack) = carve(stack, big * na);
        let (tmp, _) = carve(stack, big * na);
        let sol = &kernel.sol[..];
        let (kq, kv, mat) = (&mut kq[..], &mut kv[..], &mut mat[..]);
        let (bq, bv, tmp) = (&mut bq[..], &mut bv[..], &mut tmp[..]);
        // The right-hand sides of `evaluate`'s Jacobians (the same terms in the same
        // order): top rows ∂Q/∂q − ∂(Φ_qᵀλ)/∂q and ∂Q/∂q̇; bottom rows
        // −∂(Φ̇_q q̇)/∂q − Φ_qq q̈ and −2 Φ̇_q.
        kq.fill(0.0);
        kv.fill(0.0);
        for (i, f) in model.forces.iter().enumerate() {
            f.add_jacobians(model, (q, dq, t), kq, kv)
                .map_err(|e| model.effect_error(i, e))?;
        }
        for (t, lam) in tmp.iter_mut().zip(&sol[n..big]) {
            *t = -lam;
        }
        model.add_weighted_hessians(q, &tmp[..ma], kq);
        model.third_order_into(q, dq, mat);
        for (r, &k) in model.active.iter().enumerate() {
            for (o, v) in bq[r * n..(r + 1) * n]
                .iter_mut()
                .zip(&mat[k * n..(k + 1) * n])
            {
                *o = -v;
            }
        }
        model.jacobian_derivative_into(q, &sol[..n], mat);
        for (r, &k) in model.active.iter().enumerate() {
            for (o, v) in bq[r * n..(r + 1) * n]
                .iter_mut()
                .zip(&mat[k * n..(k + 1) * n])
            {
                *o -= v;
            }
        }
        model.jacobian_derivative_into(q, dq, mat);
        for (r, &k) in model.active.iter().enumerate() {
            for (o, v) in bv[r * n..(r + 1) * n]
                .iter_mut()
                .zip(&mat[k * n..(k + 1) * n])
            {
                *o = -2.0 * v;
            }
        }
        // B = R_q V_q + R_v V_v + [E V_f; 0] on the active columns, big × na.
        let b = &mut b[..big * na];
        b.fill(0.0);
        let add = |out: &mut [f64], coef: &[f64], v: &[f64]| {
            for (i, row) in out.chunks_exact_mut(na).enumerate() {
                for (k, &cf) in coef[i * n..(i + 1) * n].iter().enumerate() {
                    if cf == 0.0 {
                        continue;
                    }
                    let vrow = &v[k * c..(k + 1) * c];
                    for (o, &j) in row.iter_mut().zip(act) {
                        *o += cf * vrow[j];
                    }
                }
            }
        };
        let (top, bottom) = b.split_at_mut(n * na);
        add(top, kq, vq);
        add(top, kv, vv);
        add(bottom, bq, vq);
        add(bottom, bv, vv);
        for (k, &i) in columns.iter().enumerate() {
            let vrow = &vf[k * c..(k + 1) * c];
            for (o, &j) in top[i * na..(i + 1) * na].iter_mut().zip(act) {
                *o += vrow[j];
            }
        }
        kernel.solve_many(b, na, tmp)?;
        out[..count * c].fill(0.0);
        for r in 0..count {
            let i = rows.map_or(r, |rows| rows[r]);
            for (t, &j) in act.iter().enumerate() {
                out[r * c + j] = b[i * na + t];
            }
        }
        Ok(true)
    }
}
