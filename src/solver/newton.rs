//! The exact (Newton) model: the Lagrangian's gradient, its reduced Hessian by
//! central differences, and the least-squares step of a one-block window.

use super::prior::{Information, LinearPrior};
use super::structure::{factor_of, is_hard, Span};
use super::WindowSolver;
use crate::error::Result;
use crate::graph::ChainGraph;
use crate::linalg::nullspace::NullSpace;

/// Buffers of the exact (Newton) model: the Lagrangian's gradient in full
/// coordinates at the point and at its perturbations, each block's multipliers, and
/// the Gauss-Newton diagonal that scales LM's damping in its place.
pub(super) struct NewtonBuffers {
    pub(super) lambda: Vec<f64>,
    pub(super) grad: Vec<f64>,
    pub(super) plus: Vec<f64>,
    pub(super) minus: Vec<f64>,
    pub(super) scale: Vec<f64>,
    /// Per block, the hard rows seen so far; one reduced column.
    pub(super) rows: Vec<usize>,
    pub(super) column: Vec<f64>,
    pub(super) max_hard: usize,
}

/// A prior's information as rows, Λ = Σᵢ (√λᵢ vᵢ)(√λᵢ vᵢ)ᵀ over the directions it
/// informs above round-off (λᵢ > s ε λ_max), with vᵢᵀη / √λᵢ per row: its cost
/// ½δᵀΛδ + ηᵀδ is ½|R δ + c|² up to a constant.
pub(super) struct PriorRoots {
    /// Row-major, s columns.
    pub(super) rows: Vec<f64>,
    pub(super) eta: Vec<f64>,
}

impl PriorRoots {
    pub(super) fn of(prior: &LinearPrior, s: usize) -> Self {
        let (mut rows, mut eta) = (Vec::new(), Vec::new());
        // Λ = V diag(λ) Vᵀ; on a tangent space Λ = N̄CN̄ᵀ and C's eigenvectors u
        // give Λ's as N̄u, with vᵀη = uᵀγ.
        let (matrix, size) = match &prior.information {
            Information::Dense(lambda) => (lambda.as_slice(), s),
            Information::Tangent(t) => (t.core(), t.dim()),
        };
        let lambda = faer::MatRef::from_row_major_slice(matrix, size, size);
        // An eigendecomposition that fails (a NaN in Λ) informs no direction: the
        // step then rests on the window's rows, and a NaN in them ends the solve.
        let Ok(eigen) = lambda.self_adjoint_eigen(faer::Side::Lower) else {
            return PriorRoots { rows, eta };
        };
        let values = eigen.S().column_vector();
        let vectors = eigen.U();
        let top = values.iter().cloned().fold(0.0, f64::max);
        let floor = s as f64 * f64::EPSILON * top;
        let mut u = vec![0.0; size];
        let mut v = vec![0.0; s];
        for (i, &l) in values.iter().enumerate() {
            if !(l > floor && l.is_finite()) {
                continue;
            }
            u.iter_mut()
                .zip(vectors.col(i).iter())
                .for_each(|(o, x)| *o = *x);
            let root = l.sqrt();
            let along = match &prior.information {
                Information::Dense(_) => {
                    v.copy_from_slice(&u);
                    u.iter().zip(&prior.eta).map(|(a, b)| a * b).sum::<f64>()
                }
                Information::Tangent(t) => {
                    t.lift(&u, &mut v);
                    u.iter().zip(t.gamma()).map(|(a, b)| a * b).sum::<f64>()
                }
            };
            rows.extend(v.iter().map(|vk| root * vk));
            eta.push(along / root);
        }
        PriorRoots { rows, eta }
    }
}

impl WindowSolver {
    /// The gradient of the Lagrangian of the window's problem in full coordinates,
    /// Σ Jᵢᵀrᵢ over the soft factors (whitened), the prior's Λ(x − x̄) + η, and
    /// Σ C_bᵀλ_b over each block's hard equations (rows in `hard_block` order) with the
    /// multipliers in `self.newton.lambda`; into `out` (blocks × s).
    pub(super) fn lagrangian_gradient(
        &mut self,
        graph: &ChainGraph,
        values: &[f64],
        span: Span,
        out: &mut [f64],
    ) -> Result<()> {
        let Span { k0, k1, prior, .. } = span;
        let s = self.s;
        let blocks = k1 - k0;
        out[..blocks * s].fill(0.0);
        self.newton.rows[..blocks].fill(0);
        for i in 0..self.structure.instances.len() {
            let inst = self.structure.instances[i];
            let factor = factor_of(graph, inst);
            self.lin
                .evaluate_instance(graph, self.structure.base, values, inst, true)?;
            let buf = self.lin.buffers.of(inst);
            let hard = is_hard(graph, inst);
            let dim = factor.dim();
            // What multiplies each row: its whitened residual, or its multiplier.
            let weights: &[f64] = if hard {
                let b = inst.step - k0;
                let row0 = self.newton.rows[b];
                self.newton.rows[b] += dim;
                let base = b * self.newton.max_hard + row0;
                &self.newton.lambda[base..base + dim]
            } else {
                buf.whiten(factor, true);
                &buf.r
            };
            for (a, k) in factor.keys().iter().enumerate() {
                if inst.step < k0 + k.lag {
                    continue; // a variable held fixed before the window
                }
                let (off, d) = buf.slots[a];
                let base = (inst.step - k.lag - k0) * s + off;
                let jac = &buf.jac[a];
                let diagonal = factor.diagonal_jacobian(a);
                for (r, &w) in weights.iter().enumerate() {
                    let columns = if diagonal { r..r + 1 } else { 0..d };
                    for j in columns {
                        out[base + j] += jac[r * d + j] * w;
                    }
                }
            }
        }
        if let Some(p) = prior {
            let x = &values[k0 * s..(k0 + 1) * s];
            let (delta, rest) = self.scratch.split_at_mut(s);
            let (grad, work) = rest.split_at_mut(s);
            p.gradient(x, delta, grad, work);
            for (o, g) in out.iter_mut().zip(grad.iter()) {
                *o += g;
            }
        }
        Ok(())
    }

    /// Replaces the Gauss-Newton matrix in H by the reduced Hessian of the Lagrangian,
    /// Nᵀ(JᵀJ + Σ rᵢ∇²rᵢ + Σ λⱼ∇²cⱼ)N per block pair, by central differences of the
    /// Lagrangian's exact gradient along the null-space columns. Blocks three apart
    /// share no factor, so one perturbation serves every third block (3·d gradients
    /// per difference side, whatever the window's length). The gradient g is kept.
    ///
    /// Gauss-Newton leaves the second-order terms out, which is right when they are
    /// small against JᵀJ. Along the motion of a dependent-coordinate graph they are
    /// not: that direction is informed only by the marginal prior, whose information
    /// decays over a run, while the conflict between the integrated motion and the
    /// constraints keeps the residuals finite; Gauss-Newton then converges linearly
    /// with a rate near 1, or alternates (docs/dc-stall.md).
    pub(super) fn exact_hessian(
        &mut self,
        graph: &ChainGraph,
        values: &mut [f64],
        span: Span,
    ) -> Result<()> {
        let Span { k0, k1, scope, .. } = span;
        let s = self.s;
        let blocks = k1 - k0;
        let n = blocks * s;
        self.collect_instances(graph, k0, k1, scope);
        // Multipliers from the soft gradient at the point.
        let mut grad = std::mem::take(&mut self.newton.grad);
        self.newton.lambda.fill(0.0);
        let result = self.lagrangian_gradient(graph, values, span, &mut grad);
        if let Err(e) = result {
            self.newton.grad = grad;
            return Err(e);
        }
        let mh = self.newton.max_hard;
        for b in 0..blocks {
            let red = &mut self.lin.hard[b].reduction;
            red.multipliers(
                &grad[b * s..(b + 1) * s],
                &mut self.newton.lambda[b * mh..(b + 1) * mh],
            );
        }
        self.newton.grad = grad;
        for b in 0..blocks {
            let (diag, d) = (self.normal.h.diag(b), self.normal.h.dim(b));
            for r in 0..d {
                self.newton.scale[b * s + r] = diag[r * d + r];
            }
        }
        let colors = blocks.min(3);
        let dmax = (0..blocks)
            .map(|b| self.lin.hard[b].reduction.dim)
            .max()
            .unwrap_or(0);
        self.saved[..n].copy_from_slice(&values[k0 * s..k1 * s]);
        let (mut plus, mut minus) = (
            std::mem::take(&mut self.newton.plus),
            std::mem::take(&mut self.newton.minus),
        );
        // ε per block, relative to its largest entry.
        // ε per direction, relative to the size of the values it moves: a block holds
        // q, q̇ and q̈ of very different sizes (a 7 mm crank at 6e5 rad/s²), and an ε
        // taken from the block's largest entry moved the positions by 0.1 m.
        let eps = self.settings.thresholds.difference_step;
        let step = |red: &NullSpace, j: usize, x: &[f64]| {
            let along: f64 = (0..x.len())
                .map(|i| {
                    let (start, row) = red.row(i);
                    if j >= start && j < start + row.len() {
                        row[j - start].abs() * x[i].abs()
                    } else {
                        0.0
                    }
                })
                .sum();
            eps * (1.0 + along)
        };
        let mut column = std::mem::take(&mut self.newton.column);
        let mut result: Result<()> = Ok(());
        'columns: for color in 0..colors {
            for j in 0..dmax {
                for (out, sign) in [(&mut plus, 1.0), (&mut minus, -1.0)] {
                    let window = &mut values[k0 * s..k1 * s];
                    window.copy_from_slice(&self.saved[..n]);
                    for b in (color..blocks).step_by(3) {
                        let red = &self.lin.hard[b].reduction;
                        if j >= red.dim {
                            continue;
                        }
                        let x = &mut window[b * s..(b + 1) * s];
                        let eps = sign * step(red, j, x);
                        for (i, xi) in x.iter_mut().enumerate() {
                            let (start, row) = red.row(i);
                            if j >= start && j < start + row.len() {
                                *xi += eps * row[j - start];
                            }
                        }
                    }
                    result = self.lagrangian_gradient(graph, values, span, out);
                    if result.is_err() {
                        break 'columns;
                    }
                }
                // Column j of H_bb and H_{b+1,b} in reduced coordinates for every
                // perturbed block b.
                for b in (color..blocks).step_by(3) {
                    if j >= self.lin.hard[b].reduction.dim {
                        continue;
                    }
                    let h = 2.0
                        * step(
                            &self.lin.hard[b].reduction,
                            j,
                            &self.saved[b * s..(b + 1) * s],
                        );
                    // H_bb and H_{b+1,b} both have d_b columns (packed, stride d_b).
                    let db = self.lin.hard[b].reduction.dim;
                    for target in [b, b + 1] {
                        if target >= blocks {
                            continue;
                        }
                        let red = &self.lin.hard[target].reduction;
                        let col = &mut column[..red.dim];
                        col.fill(0.0);
                        for i in 0..s {
                            let hv = (plus[target * s + i] - minus[target * s + i]) / h;
                            let (start, row) = red.row(i);
                            for (c, nv) in col[start..].iter_mut().zip(row) {
                                *c += nv * hv;
                            }
                        }
                        let block = if target == b {
                            self.normal.h.diag_mut(target)
                        } else {
                            self.normal.h.lower_mut(target)
                        };
                        for (a, v) in col.iter().enumerate() {
                            block[a * db + j] = *v;
                        }
                    }
                }
            }
        }
        self.newton.column = column;
        values[k0 * s..k1 * s].copy_from_slice(&self.saved[..n]);
        self.newton.plus = plus;
        self.newton.minus = minus;
        result?;
        // The differences are symmetric only to their error: symmetrize.
        for b in 0..blocks {
            let d = self.lin.hard[b].reduction.dim;
            let diag = self.normal.h.diag_mut(b);
            for i in 0..d {
                for j in 0..i {
                    let v = 0.5 * (diag[i * d + j] + diag[j * d + i]);
                    diag[i * d + j] = v;
                    diag[j * d + i] = v;
                }
            }
        }
        Ok(())
    }

    /// The Gauss-Newton step of a one-block window from its rows (`rows`) and those
    /// of its prior, by an SVD of the reduced Jacobian itself, into `delta`; false
    /// when the rows are not at hand or the step is not finite. H = JᵀJ squares J's
    /// condition number: a stiff force's row next to the integrators' (a light crank
    /// against a stiff spring, in independent coordinates) makes J's 1e8 into H's
    /// 1e16, where the Cholesky factor fails although J still determines the step to
    /// 8 digits; a 2 mm crank's f_dyn rows (∂q̈/∂q ~ 1e9 whitened) swamp the
    /// integrators' information in a dependent-coordinate window's H altogether.
    ///
    /// The prior's rows come from its information Λ = V diag(λ) Vᵀ: the row
    /// √λᵢ vᵢᵀ N with the residual √λᵢ vᵢᵀ(x + p − x̄) + vᵢᵀη / √λᵢ per direction
    /// it informs above round-off (λᵢ > s ε λ_max), for ½(δᵀΛδ) + ηᵀδ with
    /// δ = x + p + N y − x̄. Λ's own condition is that of its factors' rows squared
    /// only, not that of the window's.
    pub(super) fn least_squares_step(&mut self, x: &[f64], prior: Option<&LinearPrior>) -> bool {
        let Some(d) = self.kept.width else {
            return false;
        };
        let s = self.s;
        let window_rows = self.kept.rows.len() / (d + 1);
        if let Some(p) = prior {
            // The prior is the same for the whole solve: its roots are made once.
            self.prior_roots.get_or_insert_with(|| PriorRoots::of(p, s));
        }
        let prior_rows = self.prior_roots.as_ref().map_or(0, |r| r.eta.len());
        let m = window_rows + if prior.is_some() { prior_rows } else { 0 };
        if d == 0 || m < d || (prior.is_none() && window_rows < d) {
            return false;
        }
        // [J N; R N] y ≈ b: the window's rows, then the prior's (R N, with the residual
        // R (x + p − x̄) + c), b their residuals negated.
        let mut a = faer::Mat::<f64>::zeros(m, d);
        let mut b = vec![0.0; m];
        for (i, row) in self.kept.rows.chunks_exact(d + 1).enumerate() {
            a.row_mut(i).iter_mut().zip(row).for_each(|(o, v)| *o = *v);
            b[i] = -row[d];
        }
        if let (Some(p), Some(roots)) = (prior, self.prior_roots.as_ref()) {
            let red = &self.lin.hard[0].reduction;
            let basis = &mut self.scratch[..s * d];
            red.basis_into(basis);
            faer::linalg::matmul::matmul(
                a.as_mut().subrows_mut(window_rows, prior_rows),
                faer::Accum::Replace,
                faer::MatRef::from_row_major_slice(&roots.rows, prior_rows, s),
                faer::MatRef::from_row_major_slice(basis, s, d),
                1.0,
                faer::Par::Seq,
            );
            for (i, (root, c)) in roots.rows.chunks_exact(s).zip(&roots.eta).enumerate() {
                let offset: f64 = (0..s)
                    .map(|k| root[k] * (x[k] + red.particular[k] - p.xbar[k]))
                    .sum();
                b[window_rows + i] = -(offset + c);
            }
        }
        let Ok(svd) = a.thin_svd() else {
            return false;
        };
        // y = V Σ⁺ Uᵀ b over the singular values above the cutoff (sorted, the
        // largest first).
        let (u, sigma, v) = (svd.U(), svd.S().column_vector(), svd.V());
        let Some(&largest) = sigma.iter().next().filter(|l| l.is_finite()) else {
            return false;
        };
        // Below max(m, d)·ε of the largest a singular value is its own round-off
        // (the usual numerical-rank tolerance), whatever the threshold says.
        let relative =
            (m.max(d) as f64 * f64::EPSILON).max(self.settings.thresholds.least_squares_cutoff);
        let cutoff = largest * relative;
        let mut y = vec![0.0; d];
        for (i, &sv) in sigma.iter().enumerate() {
            if !(sv > cutoff) {
                break;
            }
            let ub: f64 = (0..m).map(|r| u[(r, i)] * b[r]).sum::<f64>() / sv;
            for (yk, vk) in y.iter_mut().zip(v.col(i).iter()) {
                *yk += vk * ub;
            }
        }
        if !y.iter().all(|v| v.is_finite()) {
            return false;
        }
        self.normal.delta[..self.s].fill(0.0);
        self.normal.delta[..d].copy_from_slice(&y);
        true
    }
}
