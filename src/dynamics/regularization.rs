//! The singularity measure of the dynamics kernel: the distance s to rank loss of
//! the active rows of Φ_q, the weight w(s) of the regularization that keeps the
//! augmented system regular near a singular configuration, ∂s/∂q, and the terms the
//! regularization adds to the Jacobians (see [`DynamicsKernel`]).

use super::kernel::DynamicsKernel;
use crate::graph::{carve, PodStack, StackReq};
use crate::linalg::dense::{inverse_trace, sparse_gram};
use crate::model::Model;
use faer::dyn_stack::PodBuffer;

/// The singularity measure's scratch: Â (ma × n), G and its Cholesky factor, L⁻¹
/// (G⁻² in [`DynamicsKernel::measure_gradient`]), G⁻¹ (ma × ma each), per-row vectors
/// and their Hessian products (m × n each), εₖ and ‖aₖ‖ (ma each), ∂s/∂q (n), and per
/// active row the columns [start, end) outside which it is 0 and G's row starts.
pub(super) struct MeasureScratch<'a> {
    pub(super) abar: &'a mut [f64],
    pub(super) chol: &'a mut [f64],
    pub(super) linv: &'a mut [f64],
    pub(super) ginv: &'a mut [f64],
    pub(super) vrows: &'a mut [f64],
    pub(super) hrows: &'a mut [f64],
    pub(super) eps: &'a mut [f64],
    pub(super) norms: &'a mut [f64],
    pub(super) ds: &'a mut [f64],
    span: &'a mut [[usize; 2]],
    first: &'a mut [usize],
}

impl<'a> MeasureScratch<'a> {
    fn lens(model: &Model) -> [usize; 9] {
        let (n, m, ma) = (model.n(), model.m(), model.active.len());
        [ma * n, ma * ma, ma * ma, ma * ma, m * n, m * n, ma, ma, n]
    }

    pub(super) fn req(model: &Model) -> StackReq {
        let ma = model.active.len();
        StackReq::all_of(&[
            StackReq::all_of(&Self::lens(model).map(StackReq::new::<f64>)),
            StackReq::new::<(usize, usize)>(ma),
            StackReq::new::<usize>(ma),
        ])
    }

    /// The scratch carved from `stack` (not zeroed: the measure and its gradient
    /// write every entry they read, the triangles they use of the square ones), and
    /// the rest of `stack`.
    pub(super) fn new(model: &Model, stack: &'a mut PodStack) -> (Self, &'a mut PodStack) {
        let [abar, chol, linv, ginv, vrows, hrows, eps, norms, ds] = Self::lens(model);
        let (abar, stack) = carve(stack, abar);
        let (chol, stack) = carve(stack, chol);
        let (linv, stack) = carve(stack, linv);
        let (ginv, stack) = carve(stack, ginv);
        let (vrows, stack) = carve(stack, vrows);
        let (hrows, stack) = carve(stack, hrows);
        let (eps, stack) = carve(stack, eps);
        let (norms, stack) = carve(stack, norms);
        let (ds, stack) = carve(stack, ds);
        let ma = model.active.len();
        let (span, stack) = stack.make_with(ma, |_| [0, 0]);
        let (first, stack) = stack.make_with(ma, |_| 0);
        let scratch = MeasureScratch {
            abar,
            chol,
            linv,
            ginv,
            vrows,
            hrows,
            eps,
            norms,
            ds,
            span,
            first,
        };
        (scratch, stack)
    }
}

/// The regularization at one configuration: the weight w(s), dw/ds and s.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) struct Regularization {
    pub(super) w: f64,
    pub(super) dw: f64,
    pub(super) s: f64,
}

/// m̄: the largest diagonal entry of M (1 for a massless model).
pub(super) fn mass_scale(model: &Model) -> f64 {
    let m = (0..model.n()).fold(0.0f64, |m, i| m.max(model.mass[(i, i)]));
    if m > 0.0 {
        m
    } else {
        1.0
    }
}

impl DynamicsKernel {
    /// The distance to rank loss s(q) = (tr G⁻¹)^(−1/2) of the active rows of Φ_q
    /// (see [`DynamicsKernel`]), the weight w(s) of the regularization there (w = 0,
    /// the plain KKT system, for s ≥ [`DynamicsKernel::REGULAR_ABOVE`]) and, where
    /// w is in its ramp, ∂s/∂q (else `None`). Allocates; for diagnostics and tests.
    pub fn regularization_at(model: &Model, q: &[f64]) -> (f64, f64, Option<Vec<f64>>) {
        let (n, m) = (model.n(), model.m());
        let mut mat = vec![0.0; m * n];
        model.jacobian_into(q, &mut mat);
        let mut buffer = PodBuffer::new(MeasureScratch::req(model));
        let (mut scratch, _) = MeasureScratch::new(model, PodStack::new(&mut buffer));
        let reg = Self::measure(model, &mat, &mut scratch, true);
        let gradient = (reg.dw != 0.0).then(|| {
            Self::measure_gradient(model, q, reg.s, &mut scratch);
            scratch.ds[..n].to_vec()
        });
        (reg.s, reg.w, gradient)
    }

    /// The distance s to rank loss of the active rows of Φ_q (`mat`, row-major
    /// m × n) and the weight w(s); leaves ‖aₖ‖ and, below
    /// [`DynamicsKernel::REGULAR_ABOVE`], G⁻¹ in `scratch` for
    /// [`DynamicsKernel::measure_gradient`]. s = 0 where Φ_q has lost a rank or has
    /// a zero row. Unless `exact`, s may be reported as REGULAR_ABOVE where a bound
    /// shows it is at least that (w = 0 either way).
    pub(super) fn measure(
        model: &Model,
        mat: &[f64],
        scratch: &mut MeasureScratch,
        exact: bool,
    ) -> Regularization {
        let (n, ma) = (model.n(), model.active.len());
        let singular = Regularization {
            w: 1.0,
            dw: 0.0,
            s: 0.0,
        };
        if ma == 0 {
            return Regularization {
                w: 0.0,
                dw: 0.0,
                s: f64::INFINITY,
            };
        }
        let MeasureScratch {
            chol,
            linv,
            ginv,
            norms,
            span,
            first,
            ..
        } = scratch;
        // AAᵀ (lower triangle) over the rows' nonzeros, and the row norms from its
        // diagonal.
        sparse_gram(
            ma,
            |i| &mat[model.active[i] * n..(model.active[i] + 1) * n],
            span,
            first,
            chol,
        );
        for i in 0..ma {
            let n2 = chol[i * ma + i];
            if !(n2 > 0.0) {
                return singular;
            }
            norms[i] = n2.sqrt();
        }
        // In place, the Cholesky factor L of G = ÂÂᵀ, G_ij = (AAᵀ)_ij/(‖aᵢ‖‖aⱼ‖),
        // normalized as it goes. Its products are subtracted one at a time, where
        // `dense::cholesky` subtracts their sum: another rounding, so not that kernel.
        for i in 0..ma {
            chol[i * ma..i * ma + first[i]].fill(0.0);
            for j in first[i]..=i {
                let mut g = chol[i * ma + j] / (norms[i] * norms[j]);
                for k in first[i].max(first[j])..j {
                    g -= chol[i * ma + k] * chol[j * ma + k];
                }
                if i == j {
                    if !(g > 0.0) {
                        return singular;
                    }
                    chol[i * ma + i] = g.sqrt();
                } else {
                    chol[i * ma + j] = g / chol[j * ma + j];
                }
            }
        }
        // λ_min(G) ≥ det G / λ_max^(m−1) ≥ det G / m^(m−1) (tr G = m), and
        // s² ≥ λ_min/m: far from rank loss that settles w = 0 without G⁻¹.
        if !exact {
            let det: f64 = (0..ma)
                .map(|i| chol[i * ma + i] * chol[i * ma + i])
                .product();
            let hi = Self::REGULAR_ABOVE;
            if det >= hi * hi * (ma as f64).powi(ma as i32) {
                return Regularization {
                    w: 0.0,
                    dw: 0.0,
                    s: hi,
                };
            }
        }
        // L⁻¹ (lower triangular) column by column, each column passing through G⁻¹'s
        // place (filled below); tr G⁻¹ = ‖L⁻¹‖_F².
        let trace = inverse_trace(chol, ma, ginv, first, Some(&mut linv[..]));
        let s = trace.recip().sqrt();
        if !(s > 0.0) {
            return singular;
        }
        let (lo, hi) = (Self::SINGULAR_BELOW, Self::REGULAR_ABOVE);
        if s >= hi {
            return Regularization { w: 0.0, dw: 0.0, s };
        }
        // G⁻¹ = L⁻ᵀL⁻¹, for the gradient of s.
        for i in 0..ma {
            for j in 0..=i {
                let g: f64 = (i..ma).map(|k| linv[k * ma + i] * linv[k * ma + j]).sum();
                ginv[i * ma + j] = g;
                ginv[j * ma + i] = g;
            }
        }
        if s <= lo {
            return Regularization { w: 1.0, dw: 0.0, s };
        }
        let span = (hi / lo).ln();
        let x = (s / lo).ln() / span;
        Regularization {
            w: 1.0 - x * x * (3.0 - 2.0 * x),
            dw: -6.0 * x * (1.0 - x) / (s * span),
            s,
        }
    }

    /// ∂s/∂q into the scratch's `ds`, from what [`DynamicsKernel::measure`] left:
    /// s = T^(−1/2) with T = tr G⁻¹ and ∂T = −tr(G⁻²∂G), G = ÂÂᵀ, so
    /// ∂s/∂q = s³ Σₖ Φᵏ_qq yₖ with zₖ = Σₗ (G⁻²)ₖₗ âₗ and
    /// yₖ = (zₖ − (âₖ·zₖ) âₖ)/‖aₖ‖ (âₖ = aₖ/‖aₖ‖ moves by (I − âₖâₖᵀ) ∂aₖ/‖aₖ‖,
    /// ∂aₖ/∂q = Φᵏ_qq).
    fn measure_gradient(model: &Model, q: &[f64], s: f64, scratch: &mut MeasureScratch) {
        let (n, ma) = (model.n(), model.active.len());
        let MeasureScratch {
            abar,
            linv: g2,
            ginv,
            vrows,
            hrows,
            norms,
            ds,
            ..
        } = scratch;
        // Â from the active rows of Φ_q.
        model.jacobian_into(q, hrows);
        for (r, &k) in model.active.iter().enumerate() {
            for (a, v) in abar[r * n..(r + 1) * n]
                .iter_mut()
                .zip(&hrows[k * n..(k + 1) * n])
            {
                *a = v / norms[r];
            }
        }
        // G⁻² where L⁻¹ was.
        for i in 0..ma {
            for j in 0..ma {
                g2[i * ma + j] = (0..ma).map(|k| ginv[i * ma + k] * ginv[k * ma + j]).sum();
            }
        }
        vrows.fill(0.0);
        for (r, &k) in model.active.iter().enumerate() {
            let y = &mut vrows[k * n..(k + 1) * n];
            for (c, yc) in y.iter_mut().enumerate() {
                *yc = (0..ma).map(|j| g2[r * ma + j] * abar[j * n + c]).sum();
            }
            let a = &abar[r * n..(r + 1) * n];
            let dot: f64 = a.iter().zip(y.iter()).map(|(x, z)| x * z).sum();
            for (yc, ac) in y.iter_mut().zip(a) {
                *yc = (*yc - dot * ac) / norms[r];
            }
        }
        model.hessian_rows_into(q, vrows, hrows);
        let s3 = s * s * s;
        for (j, d) in ds[..n].iter_mut().enumerate() {
            *d = s3 * model.active.iter().map(|&k| hrows[k * n + j]).sum::<f64>();
        }
    }

    /// Adds λₖ ∂εₖ/∂q to the bottom rows' q columns of the right-hand sides `cols`
    /// (row-major, `width` columns): εₖ = w(s) ε_rel ‖aₖ‖²/m̄, ∂‖aₖ‖² = 2 Φᵏ_qq aₖ,
    /// ∂w = w'(s) ∂s/∂q.
    pub(super) fn add_regularization_terms(
        model: &Model,
        q: &[f64],
        reg: Regularization,
        lambda: &[f64],
        cols: &mut [f64],
        width: usize,
        scratch: &mut MeasureScratch,
    ) {
        let n = model.n();
        if reg.dw != 0.0 {
            Self::measure_gradient(model, q, reg.s, scratch);
        }
        let MeasureScratch {
            vrows,
            hrows,
            norms,
            ds,
            ..
        } = scratch;
        model.jacobian_into(q, vrows);
        model.hessian_rows_into(q, vrows, hrows);
        let scale = Self::REGULARIZATION / mass_scale(model);
        for (r, &k) in model.active.iter().enumerate() {
            let norm2 = norms[r] * norms[r];
            let row = &mut cols[(n + r) * width..(n + r) * width + n];
            for (j, o) in row.iter_mut().enumerate() {
                let mut de = 2.0 * reg.w * hrows[k * n + j];
                if reg.dw != 0.0 {
                    de += norm2 * reg.dw * ds[j];
                }
                *o += lambda[r] * scale * de;
            }
        }
    }
}
