//! What a step leaves as it leaves a fixed-lag window: the marginal (Schur) or
//! conditional prior on the next step, and its projection on the tangent space.

use super::linearize::HardPass;
use super::prior::{Information, TangentInformation};
use super::prior::{LinearPrior, Projection};
use super::structure::{Instance, Scope, Source, Span};
use super::{structure, WindowSolver};
use crate::error::{Error, Result};
use crate::graph::ChainGraph;
use crate::linalg::dense;

/// What a window solve that converged on a small step leaves for marginalizing its
/// first block: valid while the solver has linearized nothing since
/// (`generation`) and the first block's values are those it converged at (kept in
/// [`Marginalization::last_x`]).
#[derive(Clone, Copy)]
pub(super) struct LastSolve {
    pub(super) k0: usize,
    pub(super) k1: usize,
    pub(super) generation: u64,
}

/// What marginalization works in: the rows joining a leaving step to the next, and
/// the first block's values where the last solve converged.
pub(super) struct Marginalization {
    /// The nonzeros of a row joining a marginalized step to the next.
    pub(super) nonzero: Vec<(usize, f64)>,
    /// The rows of the factors joining a marginalized step to the next, on the
    /// next step's unknowns (`marginalize_last`): their nonzeros one row after
    /// another, each row's end, and each row's whitened residual.
    pub(super) joint: JointRows,
    /// The first block's values where the last solve converged (see [`LastSolve`]).
    pub(super) last_x: Vec<f64>,
}

impl Marginalization {
    /// For steps of `s` unknowns.
    pub(super) fn new(s: usize) -> Self {
        Marginalization {
            nonzero: Vec::with_capacity(s),
            joint: JointRows::default(),
            last_x: vec![0.0; s],
        }
    }
}

/// Sparse rows on one step's unknowns with their residuals.
#[derive(Default)]
pub(super) struct JointRows {
    nonzeros: Vec<(usize, f64)>,
    end: Vec<usize>,
    residual: Vec<f64>,
}

impl JointRows {
    fn clear(&mut self) {
        self.nonzeros.clear();
        self.end.clear();
        self.residual.clear();
    }

    fn push(&mut self, nonzeros: &[(usize, f64)], residual: f64) {
        self.nonzeros.extend_from_slice(nonzeros);
        self.end.push(self.nonzeros.len());
        self.residual.push(residual);
    }

    /// Each row's nonzeros and residual, in order.
    fn rows(&self) -> impl Iterator<Item = (&[(usize, f64)], f64)> {
        let starts = std::iter::once(0).chain(self.end.iter().copied());
        starts
            .zip(&self.end)
            .zip(&self.residual)
            .map(|((a, &b), &r)| (&self.nonzeros[a..b], r))
    }
}

/// Sparse row entries (column, value) sorted by column, the values of one column
/// summed in their order (as a dense row accumulates them), the sums that vanish
/// dropped.
fn merge_columns(entries: &mut Vec<(usize, f64)>) {
    entries.sort_by_key(|e| e.0);
    let mut kept = 0;
    for i in 0..entries.len() {
        let (c, v) = entries[i];
        if kept > 0 && entries[kept - 1].0 == c {
            entries[kept - 1].1 += v;
        } else {
            entries[kept] = (c, v);
            kept += 1;
        }
    }
    entries.truncate(kept);
    entries.retain(|e| e.1 != 0.0);
}

/// Copies a rows × cols matrix stored with row stride cols into `dst` with row
/// The prior on block k0 + 1 with block k0 held at its estimate: H₁₁ and g₁ of the
/// 2-block system in the scratch (see [`WindowSolver::schur`]), and the factors' cost.
pub(super) fn conditional_prior(
    scratch: &[f64],
    s: usize,
    cost: f64,
    values: &[f64],
    k0: usize,
) -> Result<LinearPrior> {
    let ss = s * s;
    let h11 = &scratch[2 * ss..3 * ss];
    let g1 = &scratch[3 * ss + s..3 * ss + 2 * s];
    let mut information = vec![0.0; ss];
    for i in 0..s {
        for j in 0..=i {
            let v = 0.5 * (h11[i * s + j] + h11[j * s + i]);
            information[i * s + j] = v;
            information[j * s + i] = v;
        }
    }
    if !information.iter().chain(g1).all(|v| v.is_finite()) {
        return Err(Error::singular(format!(
            "conditioning on step {k0}: non-finite values"
        )));
    }
    Ok(LinearPrior {
        information: Information::Dense(information),
        eta: g1.to_vec(),
        constant: cost,
        xbar: values[(k0 + 1) * s..(k0 + 2) * s].to_vec(),
        projection: None,
    })
}

/// The s × s matrix `a` made exactly symmetric: each pair of entries replaced by
/// their mean (the two triangles of a product are summed in different orders).
fn symmetrize(a: &mut [f64], s: usize) {
    for i in 0..s {
        for j in 0..i {
            let v = 0.5 * (a[i * s + j] + a[j * s + i]);
            a[i * s + j] = v;
            a[j * s + i] = v;
        }
    }
}

/// stride `ld`.
pub(super) fn restride(src: &[f64], rows: usize, cols: usize, dst: &mut [f64], ld: usize) {
    for r in 0..rows {
        dst[r * ld..r * ld + cols].copy_from_slice(&src[r * cols..(r + 1) * cols]);
    }
}

impl WindowSolver {
    /// Restricts a prior on step k to the tangent space of k's hard equations: with
    /// x̃ = x_k + p̄ on their linearization and P = N̄N̄ᵀ the projector onto its null
    /// space, the prior becomes Q(x̃) + (P∇Q(x̃))ᵀ(x − x̃) + ½(x − x̃)ᵀPΛP(x − x̃).
    ///
    /// On the constraint manifold the two agree to second order but for one term:
    /// the prior's pull across the manifold (the conflict between the integrated
    /// motion and the constraints) times the manifold's curvature. Where the prior
    /// knows little along the motion (its information there decays over a run) that
    /// term dominates and has the wrong sign on the concave side: the window's cost
    /// gets two minima on either side of the motion, a phase jump between them, and
    /// Gauss-Newton stalls between them (docs/dc-stall.md). A Gaussian on the
    /// manifold is a Gaussian in its tangent coordinates; this is that Gaussian.
    pub fn project_prior(
        &mut self,
        graph: &ChainGraph,
        values: &[f64],
        k: usize,
        prior: &mut LinearPrior,
    ) -> Result<()> {
        let s = self.s;
        self.collect_instances(graph, k, k + 1, Scope::Window { held: false });
        self.lin
            .hard_block(graph, &self.structure, values, 0, HardPass::Linearize)?;
        // A one-step window solve of step k that follows finds it reduced.
        prior.projection = Some(Projection {
            step: k,
            generation: self.lin.generation,
        });
        let block = &mut self.lin.hard[0];
        if block.rows == 0 {
            return Ok(());
        }
        if let Information::Tangent(_) = prior.information {
            prior.information = Information::Dense(prior.dense_information());
        }
        let Information::Dense(lambda) = &mut prior.information else {
            unreachable!("made dense above")
        };
        let red = &block.reduction;
        let d = red.dim;
        let x = &values[k * s..(k + 1) * s];
        let (delta, rest) = self.scratch.split_at_mut(s);
        let (grad, rest) = rest.split_at_mut(s);
        let (gt, rest) = rest.split_at_mut(s);
        let (ln, rest) = rest.split_at_mut(s * s);
        let (reduced, rest) = rest.split_at_mut(s * s);
        let (nr, rest) = rest.split_at_mut(s * s);
        // δ = x̃ − x̄, ∇Q(x̃) = η + Λδ and Q(x̃).
        let (mut lin, mut quad) = (0.0, 0.0);
        for i in 0..s {
            delta[i] = x[i] + red.particular[i] - prior.xbar[i];
        }
        for i in 0..s {
            let row = &lambda[i * s..(i + 1) * s];
            let ld: f64 = row.iter().zip(delta.iter()).map(|(a, b)| a * b).sum();
            grad[i] = prior.eta[i] + ld;
            quad += delta[i] * ld;
            lin += prior.eta[i] * delta[i];
        }
        let constant = prior.constant + lin + 0.5 * quad;
        // N̄'s structure: columns 0..q dense on the rows `free`, column q + u the unit
        // vector of `untouched[u]`, rows of fixed unknowns 0.
        let (free, untouched) = red.structure();
        let q = d - untouched.len();
        let blocked = dense::blocked_products(s, q);
        let nb = &mut rest[..s * d];
        if blocked {
            // The same products, dense, by faer's blocked kernels.
            red.basis_into(nb);
            for (i, out) in gt[..d].iter_mut().enumerate() {
                *out = (0..s).map(|k| nb[k * d + i] * grad[k]).sum();
            }
            let (nv, lv) = (dense::rows(nb, s, d, d), dense::rows(lambda, s, s, s));
            dense::multiply(dense::rows_mut(ln, s, d, d), false, lv, nv);
            let lnv = dense::rows(ln, s, d, d);
            dense::multiply(
                dense::rows_mut(reduced, d, d, d),
                false,
                nv.transpose(),
                lnv,
            );
        } else {
            // ΛN̄ (s × d).
            for i in 0..s {
                let row = &lambda[i * s..(i + 1) * s];
                let out = &mut ln[i * d..(i + 1) * d];
                out[..q].fill(0.0);
                for &j in free {
                    let lij = row[j];
                    for (o, b) in out[..q].iter_mut().zip(red.free_row(j)) {
                        *o += lij * b;
                    }
                }
                for (o, &j) in out[q..].iter_mut().zip(untouched) {
                    *o = row[j];
                }
            }
            // N̄ᵀΛN̄ (d × d) and N̄ᵀ∇Q.
            reduced[..q * d].fill(0.0);
            gt[..q].fill(0.0);
            for &i in free {
                let li = &ln[i * d..(i + 1) * d];
                for (a, &b) in red.free_row(i).iter().enumerate() {
                    gt[a] += b * grad[i];
                    for (o, l) in reduced[a * d..(a + 1) * d].iter_mut().zip(li) {
                        *o += b * l;
                    }
                }
            }
            for (u, &i) in untouched.iter().enumerate() {
                let a = q + u;
                gt[a] = grad[i];
                reduced[a * d..(a + 1) * d].copy_from_slice(&ln[i * d..(i + 1) * d]);
            }
        }
        for i in 0..s {
            prior.xbar[i] = x[i] + red.particular[i];
        }
        prior.constant = constant;
        if s >= self.tangent_form_from {
            // Kept as N̄CN̄ᵀ with C = N̄ᵀΛN̄, η = N̄(N̄ᵀ∇Q).
            symmetrize(&mut reduced[..d * d], d);
            let tangent = TangentInformation::new(red, reduced[..d * d].to_vec(), gt[..d].to_vec());
            for (i, e) in prior.eta.iter_mut().enumerate() {
                let (start, row) = red.row(i);
                *e = row.iter().zip(&gt[start..d]).map(|(a, b)| a * b).sum();
            }
            prior.information = Information::Tangent(tangent);
            return Ok(());
        }
        // Back to full coordinates: R = N̄(N̄ᵀΛN̄) (s × d), PΛP = R N̄ᵀ, P∇Q = N̄(N̄ᵀ∇Q).
        if blocked {
            let nv = dense::rows(nb, s, d, d);
            let rv = dense::rows(reduced, d, d, d);
            dense::multiply(dense::rows_mut(nr, s, d, d), false, nv, rv);
            let nrv = dense::rows(nr, s, d, d);
            dense::multiply(dense::rows_mut(lambda, s, s, s), false, nrv, nv.transpose());
            for (i, e) in prior.eta.iter_mut().enumerate() {
                *e = (0..d).map(|a| nb[i * d + a] * gt[a]).sum();
            }
            symmetrize(lambda, s);
            return Ok(());
        }
        nr[..s * d].fill(0.0);
        prior.eta.fill(0.0);
        for &i in free {
            let out = &mut nr[i * d..(i + 1) * d];
            for (a, &b) in red.free_row(i).iter().enumerate() {
                prior.eta[i] += b * gt[a];
                for (o, r) in out.iter_mut().zip(&reduced[a * d..(a + 1) * d]) {
                    *o += b * r;
                }
            }
        }
        for (u, &i) in untouched.iter().enumerate() {
            let a = q + u;
            prior.eta[i] = gt[a];
            nr[i * d..(i + 1) * d].copy_from_slice(&reduced[a * d..(a + 1) * d]);
        }
        lambda.fill(0.0);
        for i in 0..s {
            let row = &nr[i * d..(i + 1) * d];
            let out = &mut lambda[i * s..(i + 1) * s];
            for &j in free {
                out[j] = row[..q]
                    .iter()
                    .zip(red.free_row(j))
                    .map(|(a, b)| a * b)
                    .sum::<f64>();
            }
            for (u, &j) in untouched.iter().enumerate() {
                out[j] = row[q + u];
            }
        }
        symmetrize(lambda, s);
        Ok(())
    }

    /// Marginalizes step k0 (with `prior` on it, if any) into a prior on step k0+1:
    /// the factors touching k0 are linearized at `values`, k0's hard equations fix
    /// δ₀ = p₀ + N₀y₀, and y₀ is eliminated from the reduced normal equations by the
    /// Schur complement Λ = H₁₁ − H₁₀H₀₀⁻¹H₀₁, η = g₁ − H₁₀H₀₀⁻¹g₀. Block k0+1 carries
    /// no hard equation in this linearization, so its coordinates are the full ones.
    pub fn marginalize(
        &mut self,
        graph: &ChainGraph,
        values: &[f64],
        k0: usize,
        prior: Option<&LinearPrior>,
    ) -> Result<LinearPrior> {
        self.marginalize_with(graph, values, k0, prior, false)
    }

    /// [`WindowSolver::marginalize`], then [`WindowSolver::project_prior`] on step
    /// k0 + 1. A large mechanism's marginal from the last solve's linearization is
    /// projected as it is made, C = N̄ᵀH₁₁N̄ − (YN̄)ᵀ(YN̄) from the rows joining the
    /// two steps and Y's products with N̄, so that its s × s form is never written.
    pub fn marginalize_projected(
        &mut self,
        graph: &ChainGraph,
        values: &[f64],
        k0: usize,
        prior: Option<&LinearPrior>,
    ) -> Result<LinearPrior> {
        let mut p = self.marginalize_with(graph, values, k0, prior, true)?;
        if p.projection.is_none() {
            self.project_prior(graph, values, k0 + 1, &mut p)?;
        }
        Ok(p)
    }

    fn marginalize_with(
        &mut self,
        graph: &ChainGraph,
        values: &[f64],
        k0: usize,
        prior: Option<&LinearPrior>,
        project: bool,
    ) -> Result<LinearPrior> {
        let s = self.s;
        if let Some(last) = self.last.take() {
            let x = &values[k0 * s..(k0 + 1) * s];
            if last.k0 == k0
                && last.generation == self.lin.generation
                && x.iter()
                    .zip(&self.marginal.last_x)
                    .all(|(a, b)| a.to_bits() == b.to_bits())
            {
                let project = project && s >= self.tangent_form_from && !self.past_conditioned();
                return self.marginalize_last(graph, values, k0, last.k1, project);
            }
        }
        let oldest = Span {
            k0,
            k1: k0 + 2,
            prior,
            scope: Scope::Oldest,
        };
        let cost = self.evaluate(graph, values, oldest, true)?;
        let d0 = self.normal.h.dim(0);
        debug_assert_eq!(self.normal.h.dim(1), s);
        // H₀₀, H₁₀ (block 1 rows × block 0 columns), H₁₁, g₀, g₁ into the scratch.
        let ss = s * s;
        let (h00, rest) = self.scratch.split_at_mut(ss);
        let (h10, rest) = rest.split_at_mut(ss);
        let (h11, rest) = rest.split_at_mut(ss);
        let (g01, _) = rest.split_at_mut(2 * s);
        restride(self.normal.h.diag(0), d0, d0, h00, s);
        restride(self.normal.h.lower(1), s, d0, h10, s);
        restride(self.normal.h.diag(1), s, s, h11, s);
        g01[..s].copy_from_slice(&self.normal.g[..s]);
        g01[s..].copy_from_slice(&self.normal.g[s..2 * s]);
        self.schur(k0, d0, cost, values)
    }

    /// The Schur complement of block 0 in the 2-block system held in the scratch
    /// (H₀₀ d0 × d0, H₁₀ s × d0, H₁₁ s × s, all with stride s; g₀, g₁): the prior on
    /// block k0 + 1, whose values are x̄.
    pub(super) fn schur(
        &mut self,
        k0: usize,
        d0: usize,
        cost: f64,
        values: &[f64],
    ) -> Result<LinearPrior> {
        let s = self.s;
        let ss = s * s;
        if self.past_conditioned() {
            return conditional_prior(&self.scratch, s, cost, values, k0);
        }
        let (h00, rest) = self.scratch.split_at_mut(ss);
        let (h10, rest) = rest.split_at_mut(ss);
        let (h11, rest) = rest.split_at_mut(ss);
        let (g01, rest) = rest.split_at_mut(2 * s);
        let (w, rest) = rest.split_at_mut(s);
        let (y, rest) = rest.split_at_mut(ss);
        let acc = &mut rest[..s];
        // L₀ = chol(H₀₀) in place; Y = L₀⁻¹H₀₁ (d0 × s, row-major; row j of h10 is
        // column j of H₀₁); w = L₀⁻¹g₀.
        dense::cholesky_strided(h00, d0, s).map_err(|_| {
            Error::singular(format!(
                "marginalizing step {k0}: its soft factors leave a direction undetermined"
            ))
        })?;
        let blocked = s >= dense::FAER_PRODUCTS_FROM;
        if blocked {
            for (a, row) in y.chunks_exact_mut(s).take(d0).enumerate() {
                for (j, out) in row.iter_mut().enumerate() {
                    *out = h10[j * s + a];
                }
            }
            dense::solve_lower_rows(dense::rows(h00, d0, d0, s), dense::rows_mut(y, d0, s, s));
        } else {
            // Forward substitution a whole row of Y at a time (the same sums, in the
            // same order, as one column at a time, but along contiguous rows).
            for a in 0..d0 {
                acc.fill(0.0);
                let (done, row) = y.split_at_mut(a * s);
                for (l, yk) in h00[a * s..a * s + a].iter().zip(done.chunks_exact(s)) {
                    for (c, v) in acc.iter_mut().zip(yk) {
                        *c += l * v;
                    }
                }
                let lii = h00[a * s + a];
                for (j, out) in row[..s].iter_mut().enumerate() {
                    *out = (h10[j * s + a] - acc[j]) / lii;
                }
            }
        }
        w[..d0].copy_from_slice(&g01[..d0]);
        dense::solve_lower_strided(h00, d0, s, &mut w[..d0]);
        // Λ = H₁₁ − YᵀY, η = g₁ − Yᵀw. YᵀY is summed over the rows of Y in order, one
        // triangle (Λ is symmetric, H₁₁ and YᵀY to the bit), then mirrored.
        let mut information = vec![0.0; ss];
        let mut eta = vec![0.0; s];
        dense::gram_lower(y, d0, s, &mut information);
        for a in 0..d0 {
            for (e, yi) in eta.iter_mut().zip(&y[a * s..(a + 1) * s]) {
                *e += yi * w[a];
            }
        }
        for i in 0..s {
            for j in 0..=i {
                let v = h11[i * s + j] - information[i * s + j];
                information[i * s + j] = v;
                information[j * s + i] = v;
            }
            eta[i] = g01[s + i] - eta[i];
        }
        if self.prior_floor > 0.0 {
            let largest = (0..s).map(|i| information[i * s + i]).fold(0.0, f64::max);
            for i in 0..s {
                information[i * s + i] += self.prior_floor * largest;
            }
        }
        // ≥ 0 in exact arithmetic (the least value of a sum of squares); round-off
        // near singular configurations can push it below.
        let constant = (cost - 0.5 * w[..d0].iter().map(|v| v * v).sum::<f64>()).max(0.0);
        if !information.iter().chain(&eta).all(|v| v.is_finite()) {
            return Err(Error::singular(format!(
                "marginalizing step {k0}: non-finite values"
            )));
        }
        Ok(LinearPrior {
            information: Information::Dense(information),
            eta,
            constant,
            xbar: values[(k0 + 1) * s..(k0 + 2) * s].to_vec(),
            projection: None,
        })
    }

    /// Keeps the converged window's linearization of its first block for
    /// marginalizing it ([`LastSolve`]), with the values it holds at.
    pub(super) fn keep_for_marginal(&mut self, values: &[f64], k0: usize, k1: usize) {
        if self.reuse.in_last {
            // Kept rows in H: the fresh rows of the joining factors would not fit
            // them (`marginalize_last`); the marginal linearizes its two steps.
            return;
        }
        let s = self.s;
        self.last = Some(LastSolve {
            k0,
            k1,
            generation: self.lin.generation,
        });
        self.marginal
            .last_x
            .copy_from_slice(&values[k0 * s..(k0 + 1) * s]);
    }

    /// Marginalization from the last window solve's linearization of its first block
    /// (it converged on a step below the tolerance, so that linearization is the one
    /// at the optimum up to O(tolerance)); only the factors joining k0 to k0 + 1 are
    /// evaluated again, for their columns on k0 + 1 in full coordinates.
    /// With `project`, the prior comes projected on step k0 + 1's tangent space
    /// (see [`WindowSolver::marginalize_projected`]).
    pub(super) fn marginalize_last(
        &mut self,
        graph: &ChainGraph,
        values: &[f64],
        k0: usize,
        k1: usize,
        project: bool,
    ) -> Result<LinearPrior> {
        let s = self.s;
        let ss = s * s;
        let d0 = self.normal.h.dim(0);
        let window_holds_next = k1 > k0 + 1;
        // H₀₀ and g₀ at the optimum: the gradient moves by H δ with the last step.
        {
            let (h00, rest) = self.scratch.split_at_mut(ss);
            let (h10, rest) = rest.split_at_mut(ss);
            let (_, rest) = rest.split_at_mut(ss);
            let g01 = &mut rest[..2 * s];
            restride(self.normal.h.diag(0), d0, d0, h00, s);
            // H₁₀ is read only in its first d0 columns.
            for row in h10.chunks_exact_mut(s) {
                row[..d0].fill(0.0);
            }
            g01.fill(0.0);
            for a in 0..d0 {
                g01[a] = self.normal.g[a] + self.normal.hd[a];
            }
        }
        let mut cost = self.cost_first;
        let blocked = s >= dense::FAER_PRODUCTS_FROM;
        self.marginal.joint.clear();
        // The factors joining k0 and k0 + 1: the step factors, then those of run
        // step k0 + 1 alone.
        let steps = graph.step_terms().len();
        let at = graph.sparse_range(
            self.structure.run_step(k0 + 1),
            self.structure.run_step(k0 + 2),
        );
        for i in 0..steps + at.len() {
            let inst = Instance {
                source: if i < steps { Source::Step } else { Source::At },
                index: if i < steps { i } else { at.start + i - steps },
                step: k0 + 1,
            };
            let term = structure::term_of(graph, inst);
            let factor = term.factor();
            let keys = factor.keys();
            if term.is_constraint() || !keys.iter().any(|k| k.lag == 1) {
                continue;
            }
            self.lin
                .evaluate_instance(graph, self.structure.base, values, inst, true)?;
            let buf = self.lin.buffers.of(inst);
            let dim = factor.dim();
            buf.whiten(factor, true);
            if !window_holds_next {
                for r in &buf.r {
                    cost += 0.5 * r * r;
                }
            }
            // Rows: J₀N₀ (dim × d0, row stride s) into reduced[1]; J₁ row by row below.
            let red = &self.lin.hard[0].reduction;
            for row in self.lin.reduced.jacobian[1].chunks_exact_mut(s).take(dim) {
                row[..d0].fill(0.0);
            }
            for (a, k) in keys.iter().enumerate() {
                if k.lag == 0 {
                    continue;
                }
                let (off, d) = buf.slots[a];
                let diagonal = factor.diagonal_jacobian(a);
                for r in 0..dim {
                    let columns = if diagonal { r..r + 1 } else { 0..d };
                    for j in columns {
                        let v = buf.jac[a][r * d + j];
                        if v == 0.0 {
                            continue;
                        }
                        let (start, nrow) = red.row(off + j);
                        let out = &mut self.lin.reduced.jacobian[1][r * s + start..r * s + d0];
                        for (o, nv) in out.iter_mut().zip(nrow) {
                            *o += v * nv;
                        }
                    }
                }
            }
            let (h00, rest) = self.scratch.split_at_mut(ss);
            let (h10, rest) = rest.split_at_mut(ss);
            let (_, rest) = rest.split_at_mut(ss);
            let g01 = &mut rest[..2 * s];
            for r in 0..dim {
                let j0 = &self.lin.reduced.jacobian[1][r * s..r * s + d0];
                let rr = buf.r[r];
                // J₁'s row: its nonzeros (integrators: two) by ascending column, the
                // keys' entries on one column summed in key order.
                self.marginal.nonzero.clear();
                for (a, k) in keys.iter().enumerate() {
                    if k.lag != 0 {
                        continue;
                    }
                    let (off, d) = buf.slots[a];
                    let columns = if factor.diagonal_jacobian(a) {
                        r..r + 1
                    } else {
                        0..d
                    };
                    for j in columns {
                        let v = buf.jac[a][r * d + j];
                        if v != 0.0 {
                            self.marginal.nonzero.push((off + j, v));
                        }
                    }
                }
                merge_columns(&mut self.marginal.nonzero);
                for &(i, vi) in &self.marginal.nonzero {
                    for (o, v) in h10[i * s..i * s + d0].iter_mut().zip(j0) {
                        *o += vi * v;
                    }
                }
                self.marginal.joint.push(&self.marginal.nonzero, rr);
                if !window_holds_next {
                    for (a, &va) in j0.iter().enumerate() {
                        if !blocked {
                            for (o, vb) in h00[a * s..a * s + d0].iter_mut().zip(j0) {
                                *o += va * vb;
                            }
                        }
                        g01[a] += va * rr;
                    }
                }
            }
            if blocked && !window_holds_next {
                // H₀₀ += (J₀N₀)ᵀ(J₀N₀) over the factor's rows at once.
                let j0 = dense::rows(&self.lin.reduced.jacobian[1], dim, d0, s);
                dense::multiply(dense::rows_mut(h00, d0, d0, s), true, j0.transpose(), j0);
            }
        }
        if project {
            return self.schur_projected(graph, values, k0, d0, cost);
        }
        self.joint_into_scratch();
        self.schur(k0, d0, cost, values)
    }

    /// H₁₁ and g₁ of the 2-block system in the scratch from the joining rows
    /// (`joint`), row after row.
    fn joint_into_scratch(&mut self) {
        let s = self.s;
        let ss = s * s;
        let (h11, rest) = self.scratch[2 * ss..].split_at_mut(ss);
        let g1 = &mut rest[s..2 * s];
        h11.fill(0.0);
        for (row, r) in self.marginal.joint.rows() {
            for &(i, vi) in row {
                let out = &mut h11[i * s..(i + 1) * s];
                for &(j, vj) in row {
                    out[j] += vi * vj;
                }
                g1[i] += vi * r;
            }
        }
    }

    /// The Schur complement of block 0 in the 2-block system (H₀₀ and H₁₀ in the
    /// scratch, H₁₁ and g₁ as the joining rows), projected on the tangent space of
    /// step k0 + 1's hard equations as it is formed: with N̄ and p̄ their reduction,
    /// Y = L₀⁻¹H₀₁ and w = L₀⁻¹g₀,
    ///   C = N̄ᵀH₁₁N̄ − (YN̄)ᵀ(YN̄),  γ = N̄ᵀ(g₁ + H₁₁p̄) − (YN̄)ᵀ(w + Yp̄),
    /// the value at x̄ + p̄ from the same products; nothing s × s is formed.
    fn schur_projected(
        &mut self,
        graph: &ChainGraph,
        values: &[f64],
        k0: usize,
        d0: usize,
        cost: f64,
    ) -> Result<LinearPrior> {
        let s = self.s;
        let ss = s * s;
        let k = k0 + 1;
        self.collect_instances(graph, k, k + 1, Scope::Window { held: false });
        self.lin
            .hard_block(graph, &self.structure, values, 0, HardPass::Linearize)?;
        let projection = Some(Projection {
            step: k,
            generation: self.lin.generation,
        });
        if self.lin.hard[0].rows == 0 {
            // No tangent space to project on: the prior as it is.
            self.joint_into_scratch();
            let mut p = self.schur(k0, d0, cost, values)?;
            p.projection = projection;
            return Ok(p);
        }
        let red = &self.lin.hard[0].reduction;
        let d = red.dim;
        let (h00, rest) = self.scratch.split_at_mut(ss);
        let (h10, rest) = rest.split_at_mut(ss);
        let (_, rest) = rest.split_at_mut(ss);
        let (g01, rest) = rest.split_at_mut(2 * s);
        let yn = &mut rest[..d0 * d];
        dense::cholesky_strided(h00, d0, s).map_err(|_| {
            Error::singular(format!(
                "marginalizing step {k0}: its soft factors leave a direction undetermined"
            ))
        })?;
        // H₀₁N̄ (d0 × d) and H₀₁p̄ over N̄'s nonzeros (row i of H₁₀ is column i of
        // H₀₁), then YN̄ and Yp̄ by L₀⁻¹; w = L₀⁻¹g₀.
        yn.fill(0.0);
        let mut yp = vec![0.0; d0];
        // H₁₀'s rows are 0 but on the columns the joining rows touch.
        let mut touched: Vec<usize> = self.marginal.joint.nonzeros.iter().map(|e| e.0).collect();
        touched.sort_unstable();
        touched.dedup();
        for &i in &touched {
            let (first, row) = red.row(i);
            let pi = red.particular[i];
            for (a, &v) in h10[i * s..i * s + d0].iter().enumerate() {
                if v == 0.0 {
                    continue;
                }
                yp[a] += v * pi;
                let out = &mut yn[a * d + first..a * d + first + row.len()];
                for (o, n) in out.iter_mut().zip(row) {
                    *o += v * n;
                }
            }
        }
        let l0 = dense::rows(h00, d0, d0, s);
        dense::solve_lower_rows(l0, dense::rows_mut(yn, d0, d, d));
        dense::solve_lower_strided(h00, d0, s, &mut yp);
        let mut w = g01[..d0].to_vec();
        dense::solve_lower_strided(h00, d0, s, &mut w);
        // N̄ᵀH₁₁N̄, N̄ᵀ(g₁ + H₁₁p̄), g₁ᵀp̄ and p̄ᵀH₁₁p̄ row by row: each joining row j
        // (two nonzeros for an integrator) meets few of N̄'s columns.
        let mut core = vec![0.0; d * d];
        let mut gamma = vec![0.0; d];
        let (mut nj, mut seen, mut touched) = (vec![0.0; d], vec![false; d], Vec::new());
        let (mut g1p, mut php) = (0.0, 0.0);
        for (row, r) in self.marginal.joint.rows() {
            let mut jp = 0.0;
            for &(i, v) in row {
                jp += v * red.particular[i];
                let (first, nrow) = red.row(i);
                for (a, &n) in nrow.iter().enumerate() {
                    let a = first + a;
                    if !seen[a] {
                        seen[a] = true;
                        touched.push(a);
                    }
                    nj[a] += v * n;
                }
            }
            for &a in &touched {
                let va = nj[a];
                for &b in &touched {
                    core[a * d + b] += va * nj[b];
                }
                gamma[a] += va * (r + jp);
            }
            g1p += r * jp;
            php += jp * jp;
            for &a in &touched {
                nj[a] = 0.0;
                seen[a] = false;
            }
            touched.clear();
        }
        // − (YN̄)ᵀ(YN̄) and − (YN̄)ᵀ(w + Yp̄).
        let mut gram = vec![0.0; d * d];
        dense::gram_lower(yn, d0, d, &mut gram);
        for i in 0..d {
            for j in 0..=i {
                let v = core[i * d + j] - gram[i * d + j];
                core[i * d + j] = v;
                core[j * d + i] = v;
            }
        }
        for a in 0..d0 {
            let wa = w[a] + yp[a];
            for (g, y) in gamma.iter_mut().zip(&yn[a * d..(a + 1) * d]) {
                *g -= y * wa;
            }
        }
        let dot = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(x, y)| x * y).sum::<f64>();
        // The marginal's value at x̄ (≥ 0 but for round-off, as in `schur`), then at
        // x̄ + p̄: + ηᵀp̄ + ½p̄ᵀΛp̄.
        let at_mean = (cost - 0.5 * dot(&w, &w)).max(0.0);
        let constant = at_mean + (g1p - dot(&w, &yp)) + 0.5 * (php - dot(&yp, &yp));
        if !(core.iter().chain(&gamma).all(|v| v.is_finite()) && constant.is_finite()) {
            return Err(Error::singular(format!(
                "marginalizing step {k0}: non-finite values"
            )));
        }
        let x = &values[k * s..(k + 1) * s];
        let xbar = x.iter().zip(&red.particular).map(|(a, b)| a + b).collect();
        let tangent = TangentInformation::new(red, core, gamma);
        let mut eta = vec![0.0; s];
        tangent.lift(tangent.gamma(), &mut eta);
        Ok(LinearPrior {
            information: Information::Tangent(tangent),
            eta,
            constant,
            xbar,
            projection,
        })
    }
}
