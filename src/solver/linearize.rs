//! Linearization of a window: each step's hard equations reduced to their null
//! space, the soft factors whitened, reduced and accumulated into the
//! block-tridiagonal normal equations.

use super::structure::{factor_of, is_hard, Instance, Scope, Source, Span, Structure};
use super::{WindowSolver, HARD_SIGMA};
use crate::error::{Error, Result};
#[cfg(doc)]
use crate::graph::AlongDirections;
use crate::graph::{ChainGraph, Factor, Term, Workspace, MAX_KEYS};
use crate::linalg::banded::BlockTridiagonal;
use crate::linalg::nullspace::NullSpace;

/// The whitened, reduced rows [J N | r + J p] of a one-block window's soft factors
/// (a prior's are not among them), kept beside H: for the least-squares step where H
/// cannot be factored or is conditioned past `Settings::normal_equations_limit`
/// (`least_squares_step`), and for the chord step (`chord_step`).
#[derive(Default)]
pub(super) struct KeptRows {
    /// Row-major, `width` columns (d + 1), one factor after another as `instances`
    /// lists them.
    pub(super) rows: Vec<f64>,
    pub(super) width: Option<usize>,
    pub(super) instances: Vec<usize>,
    /// Every one-step linearization keeps its rows, whatever its window: set once a
    /// window's normal equations proved too ill-conditioned to factor (`evaluate`).
    pub(super) keep: bool,
}

/// Buffers of one factor: residual and Jacobian blocks, and its rows' 1/σ.
pub(super) struct FactorBuffers {
    pub(super) r: Vec<f64>,
    pub(super) jac: Vec<Vec<f64>>,
    /// 1/σ per row of a soft factor; empty for a constraint (never whitened).
    pub(super) weights: Vec<f64>,
    /// Whether the factor linearizes along directions ([`Factor::along`]).
    pub(super) along: bool,
    /// Per key, its variable's (offset in the step's block, size), resolved once.
    pub(super) slots: Vec<(usize, usize)>,
}

impl FactorBuffers {
    pub(super) fn new(graph: &ChainGraph, term: &Term) -> Self {
        let f = term.factor();
        FactorBuffers {
            weights: term
                .noise()
                .map_or(Vec::new(), |n| (0..f.dim()).map(|r| n.weight(r)).collect()),
            along: f.along().is_some(),
            slots: f
                .keys()
                .iter()
                .map(|k| graph.layout().slot(k.kind).unwrap_or((0, 0)))
                .collect(),
            r: vec![0.0; f.dim()],
            jac: f
                .keys()
                .iter()
                .map(|k| {
                    let (_, d) = graph.layout().slot(k.kind).unwrap_or((0, 0));
                    vec![0.0; f.dim() * d]
                })
                .collect(),
        }
    }

    /// Divides the residual's rows, and with `jacobians` the Jacobians' rows, by their
    /// σ (a diagonal Jacobian block only on its diagonal: the rest is 0).
    pub(super) fn whiten(&mut self, factor: &dyn Factor, jacobians: bool) {
        for (r, w) in self.r.iter_mut().zip(&self.weights) {
            *r *= w;
        }
        if !jacobians {
            return;
        }
        for (a, (jac, &(_, d))) in self.jac.iter_mut().zip(&self.slots).enumerate() {
            if d == 0 {
                continue;
            }
            if factor.diagonal_jacobian(a) {
                for (r, w) in self.weights.iter().enumerate() {
                    jac[r * d + r] *= w;
                }
                continue;
            }
            for (row, w) in jac.chunks_exact_mut(d).zip(&self.weights) {
                for v in row {
                    *v *= w;
                }
            }
        }
    }
}

/// The buffers of the factors of each of a graph's lists (see [`Source`]).
pub(super) struct AllBuffers {
    pub(super) step: Vec<FactorBuffers>,
    pub(super) initial: Vec<FactorBuffers>,
    pub(super) at: Vec<FactorBuffers>,
    /// `graph.dropped_at()` when `at` last followed the graph's list.
    pub(super) at_dropped: usize,
}

impl AllBuffers {
    pub(super) fn new(graph: &ChainGraph) -> Self {
        let of = |terms: &mut dyn Iterator<Item = &Term>| {
            terms.map(|t| FactorBuffers::new(graph, t)).collect()
        };
        AllBuffers {
            step: of(&mut graph.step_terms().iter()),
            initial: of(&mut graph.initial_terms().iter()),
            at: of(&mut graph.sparse_terms().iter().map(|(_, t)| t)),
            at_dropped: graph.dropped_at(),
        }
    }

    /// The buffers of the factors of chosen steps brought in line with a graph
    /// that has gained or dropped some since ([`ChainGraph::add_soft_at`]).
    pub(super) fn follow(&mut self, graph: &ChainGraph) {
        let terms = graph.sparse_terms();
        let dropped = graph.dropped_at() - self.at_dropped;
        if dropped == 0 && self.at.len() == terms.len() {
            return;
        }
        self.at.drain(..dropped.min(self.at.len()));
        self.at_dropped = graph.dropped_at();
        let have = self.at.len().min(terms.len());
        self.at.truncate(have);
        for (_, t) in &terms[have..] {
            self.at.push(FactorBuffers::new(graph, t));
        }
    }

    /// The buffers of one factor instance.
    pub(super) fn of(&mut self, inst: Instance) -> &mut FactorBuffers {
        match inst.source {
            Source::Step => &mut self.step[inst.index],
            Source::Initial => &mut self.initial[inst.index],
            Source::At => &mut self.at[inst.index],
        }
    }
}

/// Names the factor, step and time in a factor's `Singular` error.
pub(super) fn located(
    factor: &dyn Factor,
    step: usize,
    t: f64,
) -> impl FnOnce(Error) -> Error + '_ {
    move |e| match e {
        Error::Singular {
            what,
            step: None,
            t: None,
        } => Error::Singular {
            what: format!("{}: {what}", in_words(factor.name())),
            step: Some(step),
            t: Some(t),
        },
        other => other,
    }
}

/// What a factor stands for, in a user's words rather than the paper's symbols.
fn in_words(name: &str) -> &str {
    match name {
        "f^d_dyn" | "f^i_dyn" => "the equations of motion",
        "f^d_idyn" | "f^i_idyn" => "the inverse dynamics",
        "f^d_pc" | "f^i_pc" => "the position constraints",
        "f^d_vc" | "f^i_vc" => "the velocity constraints",
        "f^i_ac" => "the acceleration constraints",
        other => other,
    }
}

/// A cost summed factor by factor, and its part from the factors touching the
/// window's first block (which a marginalization of that block takes along).
#[derive(Clone, Copy, Default)]
pub(super) struct CostSum {
    pub(super) total: f64,
    pub(super) first: f64,
}

impl CostSum {
    /// Adds the cost ½|r|² of whitened residuals `r`, to the first block's share too
    /// where the factor touches the first block.
    pub(super) fn add(&mut self, r: &[f64], touches_first: bool) {
        for r in r {
            let c = 0.5 * r * r;
            self.total += c;
            if touches_first {
                self.first += c;
            }
        }
    }
}

/// What a pass over the hard factors computes.
#[derive(Clone, Copy, PartialEq, Eq)]
pub(super) enum HardPass {
    Linearize,
    Residuals,
}

/// The reduction of one step's hard equations C δ = −c (C and c themselves live in
/// the solver's scratch only while the step is reduced or corrected).
pub(super) struct HardBlock {
    pub(super) rows: usize,
    pub(super) reduction: NullSpace,
    /// Every residual of the last linearization within NOISE_MARGIN of its round-off:
    /// the block's equations hold, and its particular solution is round-off divided
    /// by its pivots, no correction to wait for.
    pub(super) at_round_off: bool,
    /// The id of the kept linearization whose reduction this is, 0 if none
    /// ([`super::reuse`]).
    pub(super) kept: u64,
}

/// A whitened soft factor in reduced coordinates, on its way into H and g.
pub(super) struct ReducedRows {
    /// Per block it touches (lag 0, lag 1), the rows J N (dim × s, padded with zeros
    /// past the block's null-space dimension).
    pub(super) jacobian: [Vec<f64>; 2],
    /// Per row of `jacobian`, the columns outside which it is 0.
    pub(super) spans: [Vec<(usize, usize)>; 2],
    /// The residual r + J p, linearized at the point the hard equations' particular
    /// step leads to.
    pub(super) shifted: Vec<f64>,
    /// The nonzeros of a row, per block it touches (for `accumulate`).
    nonzeros: [Vec<(usize, f64)>; 2],
}

impl ReducedRows {
    /// Room for factors of up to `dim` rows over steps of `s` unknowns.
    pub(super) fn new(dim: usize, s: usize) -> Self {
        Self {
            jacobian: [vec![0.0; dim * s], vec![0.0; dim * s]],
            spans: [vec![(0, 0); dim], vec![(0, 0); dim]],
            shifted: vec![0.0; dim],
            nonzeros: [Vec::with_capacity(s), Vec::with_capacity(s)],
        }
    }

    /// Reduces soft factor `factor`, evaluated and whitened in `buf`, at window block
    /// `step` on the blocks' reductions in `hard`.
    pub(super) fn reduce(
        &mut self,
        hard: &[Box<HardBlock>],
        factor: &dyn Factor,
        step: usize,
        buf: &FactorBuffers,
        s: usize,
    ) {
        let ReducedRows {
            jacobian: reduced,
            spans,
            shifted,
            ..
        } = self;
        let keys = factor.keys();
        let dim = buf.r.len();
        // Only the columns of the blocks' null spaces are filled and read.
        for (lag, part) in reduced.iter_mut().enumerate() {
            if lag <= step {
                let width = hard[step - lag].reduction.dim;
                for r in 0..dim {
                    part[r * s..r * s + width].fill(0.0);
                }
            }
            spans[lag][..dim].fill((usize::MAX, 0));
        }
        shifted[..dim].copy_from_slice(&buf.r);
        for (a, k) in keys.iter().enumerate() {
            let (off, d) = buf.slots[a];
            if k.lag > step {
                continue; // a variable held fixed before the window
            }
            let red = &hard[step - k.lag].reduction;
            let out = &mut reduced[k.lag];
            let span = &mut spans[k.lag];
            let jac = &buf.jac[a];
            // Column by column, each of N's rows looked up once: every entry still
            // sums its terms in the order of the columns.
            let mut add = |r: usize, j: usize, p: f64, (start, nrow): (usize, &[f64])| {
                let v = jac[r * d + j];
                if v == 0.0 {
                    return;
                }
                shifted[r] += v * p;
                if !nrow.is_empty() {
                    let (lo, hi) = &mut span[r];
                    *lo = (*lo).min(start);
                    *hi = (*hi).max(start + nrow.len());
                }
                let row = &mut out[r * s + start..r * s + red.dim];
                for (o, nv) in row.iter_mut().zip(nrow) {
                    *o += v * nv;
                }
            };
            if factor.diagonal_jacobian(a) {
                for r in 0..dim {
                    add(r, r, red.particular[off + r], red.row(off + r));
                }
            } else {
                for j in 0..d {
                    let (p, nrow) = (red.particular[off + j], red.row(off + j));
                    for r in 0..dim {
                        add(r, j, p, nrow);
                    }
                }
            }
        }
    }

    /// Adds the reduced factor's JᵀJ and Jᵀr (its first `dim` rows) into the
    /// block-tridiagonal system (the diagonal blocks' lower triangles, mirrored once
    /// every factor is in): block `step` from `jacobian[0]` and, when `lagged`,
    /// block `step − 1` from `jacobian[1]` (only their active columns, H's block
    /// sizes). Reduced rows are often sparse (a scaled identity times a null-space
    /// basis with unit rows), so each row's products run over its nonzeros, gathered
    /// into `nonzeros`; every entry still sums the rows in order.
    pub(super) fn accumulate(
        &mut self,
        h: &mut BlockTridiagonal,
        g: &mut [f64],
        dim: usize,
        step: usize,
        lagged: bool,
        s: usize,
    ) {
        let ReducedRows {
            jacobian: reduced,
            spans,
            shifted,
            nonzeros: nonzero,
        } = self;
        let r = &shifted[..dim];
        let parts: &[(usize, usize)] = if lagged {
            &[(0, step), (1, step - 1)]
        } else {
            &[(0, step)]
        };
        for (row, &rr) in r.iter().enumerate() {
            for &(part, block) in parts {
                let d = h.dim(block);
                let jr = &reduced[part][row * s..row * s + d];
                // Past the row's span it is 0.
                let (lo, hi) = spans[part][row];
                let nz = &mut nonzero[part];
                nz.clear();
                if lo < hi {
                    nz.extend(
                        jr[lo..hi]
                            .iter()
                            .enumerate()
                            .filter(|(_, v)| **v != 0.0)
                            .map(|(a, &v)| (lo + a, v)),
                    );
                }
                let gb = &mut g[block * s..block * s + d];
                for &(a, va) in nz.iter() {
                    gb[a] += va * rr;
                }
                // The lower triangle only: the upper one is its mirror
                // (`mirror_diagonal_blocks`), the same products in the same order.
                let hb = h.diag_mut(block);
                for (i, &(a, va)) in nz.iter().enumerate() {
                    let out = &mut hb[a * d..(a + 1) * d];
                    for &(b, vb) in &nz[..=i] {
                        out[b] += va * vb;
                    }
                }
            }
            if lagged {
                // H[step][step−1] += J₀ᵀ J₁.
                let dp = h.dim(step - 1);
                let hl = h.lower_mut(step);
                for &(a, va) in &nonzero[0] {
                    let out = &mut hl[a * dp..(a + 1) * dp];
                    for &(b, vb) in &nonzero[1] {
                        out[b] += va * vb;
                    }
                }
            }
        }
    }
}

/// The linearization stage's state: each step's hard equations and their
/// reduction, the factors' buffers and the room they are evaluated in.
pub(super) struct Linearization {
    /// Unknowns per step.
    pub(super) s: usize,
    /// Each factor's residual and Jacobian buffers.
    pub(super) buffers: AllBuffers,
    /// Per block of the window, its hard equations reduced.
    /// Boxed, so that the blocks follow their steps as a window moves on (`reuse`)
    /// by moving pointers, not reductions of a kilobyte each.
    #[allow(clippy::vec_box)]
    pub(super) hard: Vec<Box<HardBlock>>,
    /// A soft factor's rows in reduced coordinates.
    pub(super) reduced: ReducedRows,
    /// Per instance, the cost of a hard one (summed in `instances` order).
    pub(super) hard_cost: Vec<f64>,
    /// One step's hard equations: C row-major rows × s, and −c.
    pub(super) hard_jac: Vec<f64>,
    pub(super) hard_rhs: Vec<f64>,
    /// Round-off in each hard residual (see [`NullSpace::set_noise`]).
    pub(super) hard_noise: Vec<f64>,
    /// Evaluate step by step (see `optimize_for_batch`).
    pub(super) step_major: bool,
    /// Directions and products of [`AlongDirections::evaluate_along`]: per key
    /// size × c, and dim × c (c ≤ 1 + 2s); empty when no factor evaluates along
    /// directions.
    pub(super) along_dirs: Vec<f64>,
    pub(super) along_out: Vec<f64>,
    pub(super) ws: Workspace,
    /// Counts linearizations, so that what one stage hands to the next (a solve's
    /// linearization to marginalization, a projected prior's reduction to a solve)
    /// is used only while it is current.
    pub(super) generation: u64,
}

impl Linearization {
    /// Makes room for the costs of the hard instances of `structure`.
    pub(super) fn clear_costs(&mut self, structure: &Structure) {
        self.hard_cost.clear();
        self.hard_cost.resize(structure.instances.len(), 0.0);
    }

    /// Evaluates one factor instance into its buffers (residual not yet whitened).
    pub(super) fn evaluate_instance(
        &mut self,
        graph: &ChainGraph,
        base: usize,
        values: &[f64],
        inst: Instance,
        linearize: bool,
    ) -> Result<()> {
        let s = self.s;
        let factor = factor_of(graph, inst);
        let buf = self.buffers.of(inst);
        let keys = factor.keys();
        let mut xs: [&[f64]; MAX_KEYS] = [&[]; MAX_KEYS];
        for ((slot, k), &(off, d)) in xs.iter_mut().zip(keys).zip(&buf.slots) {
            let base = (inst.step - k.lag) * s + off;
            *slot = &values[base..base + d];
        }
        let t = graph.run_time(base + inst.step);
        factor
            .evaluate(
                t,
                &xs[..keys.len()],
                &mut buf.r,
                linearize.then_some(buf.jac.as_mut_slice()),
                &mut self.ws,
            )
            .map_err(located(factor, inst.step, t))
    }

    /// Evaluates the hard factors of block `b` (step k0 + b) of `structure`'s instances,
    /// records their costs in `hard_cost`, and with `Linearize` reduces the block's
    /// equations C δ = −c; with `Residuals` leaves −c (in the same row order) in
    /// `hard_rhs` for a correction (or a chord step) with the current C.
    pub(super) fn hard_block(
        &mut self,
        graph: &ChainGraph,
        structure: &Structure,
        values: &[f64],
        b: usize,
        mode: HardPass,
    ) -> Result<()> {
        let s = self.s;
        let linearize = mode == HardPass::Linearize;
        // Residuals alone (a correction's) change no reduction, H or g: what was
        // made from the last linearization (the undamped factor the covariances
        // reuse) stays current.
        if linearize {
            self.generation += 1;
        }
        let mut rows = 0;
        let mut at_round_off = true;
        for at in structure.block_start[b]..structure.block_start[b + 1] {
            let i = structure.by_step[at];
            let inst = structure.instances[i];
            if !is_hard(graph, inst) {
                continue;
            }
            let factor = factor_of(graph, inst);
            self.evaluate_instance(graph, structure.base, values, inst, linearize)?;
            let buf = &*self.buffers.of(inst);
            let w = 1.0 / HARD_SIGMA;
            self.hard_cost[i] = buf.r.iter().map(|r| 0.5 * (w * r) * (w * r)).sum();
            let dim = factor.dim();
            if linearize {
                self.hard_jac[rows * s..(rows + dim) * s].fill(0.0);
                for (a, &(off, d)) in buf.slots.iter().enumerate() {
                    for r in 0..dim {
                        let row =
                            &mut self.hard_jac[(rows + r) * s + off..(rows + r) * s + off + d];
                        row.copy_from_slice(&buf.jac[a][r * d..(r + 1) * d]);
                    }
                }
            }
            for r in 0..dim {
                self.hard_rhs[rows + r] = -buf.r[r];
            }
            if linearize {
                // Round-off in each residual: ε times the size of its terms, Σ|C||x|,
                // summed along the row over its keys' blocks (the rest of the row is 0).
                let x = &values[inst.step * s..(inst.step + 1) * s];
                let mut keys: [usize; MAX_KEYS] = std::array::from_fn(|a| a);
                let keys = &mut keys[..buf.slots.len()];
                keys.sort_by_key(|&a| buf.slots[a].0);
                for r in 0..dim {
                    let mut terms = 0.0;
                    for &a in keys.iter() {
                        let (off, d) = buf.slots[a];
                        let jr = &buf.jac[a][r * d..(r + 1) * d];
                        for (c, v) in jr.iter().zip(&x[off..off + d]) {
                            terms += (c * v).abs();
                        }
                    }
                    let noise = f64::EPSILON * (terms + buf.r[r].abs());
                    self.hard_noise[rows + r] = noise;
                    at_round_off &= buf.r[r].abs() <= NullSpace::NOISE_MARGIN * noise;
                }
            }
            rows += dim;
        }
        let block = &mut self.hard[b];
        block.rows = rows;
        if linearize {
            block.kept = 0;
            block.at_round_off = at_round_off;
            block.reduction.set_noise(&self.hard_noise[..rows]);
            block
                .reduction
                .reduce(&self.hard_jac, &self.hard_rhs[..rows], rows);
        }
        Ok(())
    }

    /// The hard factors' share of the cost, summed in `instances` order, and the part
    /// of it at the first block.
    pub(super) fn hard_cost_sum(
        &self,
        graph: &ChainGraph,
        structure: &Structure,
        k0: usize,
    ) -> (f64, f64) {
        let (mut cost, mut first) = (0.0, 0.0);
        for (inst, &c) in structure.instances.iter().zip(&self.hard_cost) {
            if !is_hard(graph, *inst) {
                continue;
            }
            cost += c;
            if inst.step == k0 {
                first += c;
            }
        }
        (cost, first)
    }
}

impl WindowSolver {
    /// Second-order correction after a step: moves each block of the window back onto
    /// its hard equations with the least-norm step of the current C. Without it a step
    /// along the linearized constraints leaves an O(|δ|²) violation that the cost's
    /// 1/σ_hard² weight makes look like a failure (the Maratos effect).
    pub(super) fn correct(
        &mut self,
        graph: &ChainGraph,
        values: &mut [f64],
        k0: usize,
        k1: usize,
    ) -> Result<()> {
        let s = self.s;
        for b in 0..k1 - k0 {
            // A block's hard factors read that block only.
            self.lin
                .hard_block(graph, &self.structure, values, b, HardPass::Residuals)?;
            for pass in 0..self.settings.corrections.max(1) {
                if pass > 0 {
                    self.lin
                        .hard_block(graph, &self.structure, values, b, HardPass::Residuals)?;
                    let rows = self.lin.hard[b].rows;
                    let left = self.lin.hard_rhs[..rows]
                        .iter()
                        .fold(0.0f64, |m, r| m.max(r.abs()));
                    if left <= 1e-10 {
                        break;
                    }
                }
                let block = &mut self.lin.hard[b];
                if block.rows == 0 {
                    break;
                }
                block
                    .reduction
                    .solve(&self.lin.hard_rhs[..block.rows], &mut self.correction);
                let x = &mut values[(k0 + b) * s..(k0 + b + 1) * s];
                for (xi, c) in x.iter_mut().zip(&self.correction) {
                    *xi += c;
                }
            }
        }
        Ok(())
    }

    /// Evaluates soft factor instance `i` at `values` and adds its cost to `cost`;
    /// with `linearize` also adds its reduced JᵀJ and Jᵀr to H and g.
    pub(super) fn soft_instance(
        &mut self,
        graph: &ChainGraph,
        values: &[f64],
        (k0, i): (usize, usize),
        linearize: bool,
        cost: &mut CostSum,
    ) -> Result<()> {
        let s = self.s;
        let inst = self.structure.instances[i];
        let factor = factor_of(graph, inst);
        let along = linearize
            && self.lin.buffers.of(inst).along
            && self.evaluate_along(graph, values, k0, inst)?;
        if !along {
            self.lin
                .evaluate_instance(graph, self.structure.base, values, inst, linearize)?;
        }
        let buf = self.lin.buffers.of(inst);
        let keys = factor.keys();
        let touches_first = keys.iter().any(|k| inst.step - k.lag == k0);
        buf.whiten(factor, linearize && !along);
        cost.add(&buf.r, touches_first);
        if linearize {
            let step = inst.step - k0;
            let lagged = step >= 1 && keys.iter().any(|k| k.lag == 1);
            if along {
                // The rows J [p N] came back unwhitened: [p | N(step) | N(step − 1)].
                let d0 = self.lin.hard[step].reduction.dim;
                let d1 = if lagged {
                    self.lin.hard[step - 1].reduction.dim
                } else {
                    0
                };
                let c = 1 + d0 + d1;
                self.lin.reduced.spans[0][..buf.r.len()].fill((0, d0));
                self.lin.reduced.spans[1][..buf.r.len()].fill((0, d1));
                for (row, (&w, &r)) in buf.weights.iter().zip(&buf.r).enumerate() {
                    let out = &self.lin.along_out[row * c..(row + 1) * c];
                    self.lin.reduced.shifted[row] = r + w * out[0];
                    for (o, v) in self.lin.reduced.jacobian[0][row * s..row * s + d0]
                        .iter_mut()
                        .zip(&out[1..1 + d0])
                    {
                        *o = w * v;
                    }
                    for (o, v) in self.lin.reduced.jacobian[1][row * s..row * s + d1]
                        .iter_mut()
                        .zip(&out[1 + d0..])
                    {
                        *o = w * v;
                    }
                }
            } else {
                self.lin
                    .reduced
                    .reduce(&self.lin.hard, factor, step, buf, s);
            }
            if let Some(d) = self.kept.width.filter(|_| step == 0 && !lagged) {
                for (row, &rr) in self.lin.reduced.shifted[..factor.dim()].iter().enumerate() {
                    let (lo, hi) = self.lin.reduced.spans[0][row];
                    let jr = &self.lin.reduced.jacobian[0][row * s..row * s + d];
                    self.kept
                        .rows
                        .extend((0..d).map(|a| if a >= lo && a < hi { jr[a] } else { 0.0 }));
                    self.kept.rows.push(rr);
                }
                self.kept.instances.push(i);
            }
            self.lin.reduced.accumulate(
                &mut self.normal.h,
                &mut self.normal.g,
                factor.dim(),
                step,
                lagged,
                s,
            );
        }
        Ok(())
    }

    /// Linearizes a soft factor instance along its blocks' reductions, J [p N] per key
    /// ([`AlongDirections::evaluate_along`]), into `along_out` (columns: p, then block
    /// step's reduced coordinates, then those of the block before), its residual into
    /// its buffer; returns false when the factor declines.
    pub(super) fn evaluate_along(
        &mut self,
        graph: &ChainGraph,
        values: &[f64],
        k0: usize,
        inst: Instance,
    ) -> Result<bool> {
        let s = self.s;
        let factor = factor_of(graph, inst);
        let Some(along) = factor.along() else {
            return Ok(false);
        };
        let keys = factor.keys();
        let step = inst.step - k0;
        let lagged = step >= 1 && keys.iter().any(|k| k.lag == 1);
        let d0 = self.lin.hard[step].reduction.dim;
        let d1 = if lagged {
            self.lin.hard[step - 1].reduction.dim
        } else {
            0
        };
        let c = 1 + d0 + d1;
        let mut xs: [&[f64]; MAX_KEYS] = [&[]; MAX_KEYS];
        let mut ranges = [(0, 0); MAX_KEYS];
        let mut at = 0;
        let mut slots = [(0, 0); MAX_KEYS];
        slots[..keys.len()].copy_from_slice(&self.lin.buffers.of(inst).slots);
        for (a, k) in keys.iter().enumerate() {
            let (off, d) = slots[a];
            let base = (inst.step - k.lag) * s + off;
            xs[a] = &values[base..base + d];
            let v = &mut self.lin.along_dirs[at..at + d * c];
            v.fill(0.0);
            // A variable held fixed before the window (k.lag > step) moves not.
            if k.lag <= step {
                let red = &self.lin.hard[step - k.lag].reduction;
                let col0 = if k.lag == 0 { 1 } else { 1 + d0 };
                for (i, row) in v.chunks_exact_mut(c).enumerate() {
                    row[0] = red.particular[off + i];
                    let (start, nrow) = red.row(off + i);
                    row[col0 + start..col0 + start + nrow.len()].copy_from_slice(nrow);
                }
            }
            ranges[a] = (at, at + d * c);
            at += d * c;
        }
        let mut dirs: [&[f64]; MAX_KEYS] = [&[]; MAX_KEYS];
        for (d, &(a, b)) in dirs.iter_mut().zip(&ranges[..keys.len()]) {
            *d = &self.lin.along_dirs[a..b];
        }
        let buf = self.lin.buffers.of(inst);
        let t = graph.run_time(self.structure.base + inst.step);
        along
            .evaluate_along(
                t,
                &xs[..keys.len()],
                &mut buf.r,
                &dirs[..keys.len()],
                c,
                &mut self.lin.along_out[..factor.dim() * c],
                &mut self.lin.ws,
            )
            .map_err(located(factor, inst.step, t))
    }

    /// Evaluates the factors of a scope at `values` (the whole trajectory, step-major)
    /// and returns the cost; with `linearize`, also reduces each block's hard
    /// equations and fills H and g of the soft factors in reduced coordinates.
    pub(super) fn evaluate(
        &mut self,
        graph: &ChainGraph,
        values: &[f64],
        span: Span,
        linearize: bool,
    ) -> Result<f64> {
        let Span {
            k0,
            k1,
            prior,
            scope,
        } = span;
        let s = self.s;
        let blocks = k1 - k0;
        self.last = None;
        if linearize {
            self.reuse.in_last = false;
        }
        // A prior projected on this one-step window's hard equations brings their
        // reduction (see `LinearPrior::projection`).
        let projected = blocks == 1
            && prior.is_some_and(|p| {
                let x = &values[k0 * s..(k0 + 1) * s];
                let red = &self.lin.hard[0].reduction;
                p.projection
                    .is_some_and(|pr| pr.step == k0 && pr.generation == self.lin.generation)
                    && (0..s).all(|i| (x[i] + red.particular[i]).to_bits() == p.xbar[i].to_bits())
            });
        self.lin.generation += 1;
        self.collect_instances(graph, k0, k1, scope);
        let mode = if linearize {
            HardPass::Linearize
        } else {
            HardPass::Residuals
        };
        let mut soft = CostSum::default();
        // The rows describe the last linearization (as H and g do): an evaluation
        // without one leaves them for a chord step from it.
        if linearize {
            self.kept.rows.clear();
            self.kept.instances.clear();
            self.kept.width = None;
        }
        // Rows for the chord test (whose solves make no marginal prior) and the
        // least-squares step; the other one-step windows keep them only on demand.
        let record = linearize
            && blocks == 1
            && (prior.is_none()
                || self.past_conditioned()
                || scope == (Scope::Window { held: true })
                || self.kept.keep);
        let reusing = self
            .settings
            .relinearize_beyond
            .filter(|_| scope == (Scope::Window { held: false }) && blocks >= 3)
            .filter(|_| {
                !self.lin.step_major && !record && self.reuse.allowed && !self.reuse.paused
            });
        if let Some(beyond) = reusing.filter(|_| linearize) {
            self.linearize_reusing(graph, values, span, beyond, &mut soft)?;
        } else if self.lin.step_major && linearize {
            // Step by step: each step's hard equations, then its factors into its
            // blocks of H (and the lagged ones into the previous step's) while they
            // are in cache.
            self.normal.h.set_blocks(blocks);
            let cached = projected;
            for b in 0..blocks {
                if !cached {
                    self.lin
                        .hard_block(graph, &self.structure, values, b, mode)?;
                }
                self.normal.h.reset_block(b, self.lin.hard[b].reduction.dim);
                self.normal.g[b * s..(b + 1) * s].fill(0.0);
                if record {
                    self.kept.width = Some(self.lin.hard[0].reduction.dim);
                }
                for at in self.structure.block_start[b]..self.structure.block_start[b + 1] {
                    let i = self.structure.by_step[at];
                    if !is_hard(graph, self.structure.instances[i]) {
                        self.soft_instance(graph, values, (k0, i), true, &mut soft)?;
                    }
                }
            }
        } else {
            // Hard factors first: their linearization defines each block's reduction
            // (unless `project_prior` has just made it for this one-step window).
            let cached = projected && linearize;
            for b in 0..blocks {
                if !cached {
                    self.lin
                        .hard_block(graph, &self.structure, values, b, mode)?;
                }
            }
            if linearize {
                // Directions the hard equations fix carry no unknown.
                let hard = &self.lin.hard;
                self.normal
                    .h
                    .reset_active(blocks, |b| hard[b].reduction.dim);
                self.normal.g[..blocks * s].fill(0.0);
                if record {
                    self.kept.width = Some(self.lin.hard[0].reduction.dim);
                }
            }
        }
        let (mut cost, mut cost_first) = self.lin.hard_cost_sum(graph, &self.structure, k0);
        if (reusing.is_some() || self.lin.step_major) && linearize {
            cost += soft.total;
            cost_first += soft.first;
        } else {
            let mut sum = CostSum {
                total: cost,
                first: cost_first,
            };
            for i in 0..self.structure.instances.len() {
                if !is_hard(graph, self.structure.instances[i]) {
                    self.soft_instance(graph, values, (k0, i), linearize, &mut sum)?;
                }
            }
            (cost, cost_first) = (sum.total, sum.first);
        }
        if linearize {
            mirror_diagonal_blocks(&mut self.normal.h);
        }
        if let Some(p) = prior {
            let x = &values[k0 * s..(k0 + 1) * s];
            let (d, rest) = self.scratch.split_at_mut(s);
            let (grad, rest) = rest.split_at_mut(s);
            // grad = Λδ + η; cost = c + ηᵀδ + ½δᵀΛδ.
            let value = p.gradient(x, d, grad, rest);
            cost += value;
            cost_first += value;
            if linearize {
                // In reduced coordinates δ₀ = p₀ + N₀y: H += N₀ᵀΛN₀, g += N₀ᵀ(grad + Λp₀).
                let red = &self.lin.hard[0].reduction;
                p.add_information_times(&red.particular, grad, rest);
                p.add_reduced(
                    red,
                    grad,
                    self.normal.h.diag_mut(0),
                    &mut self.normal.g,
                    rest,
                );
            }
        }

        if !cost.is_finite() {
            return Err(Error::singular("the cost is not finite"));
        }
        self.cost_first = cost_first;
        Ok(cost)
    }
}

/// Copies each diagonal block's lower triangle onto its upper one: the soft factors
/// accumulate the lower triangle only ([`ReducedRows::accumulate`]).
fn mirror_diagonal_blocks(h: &mut BlockTridiagonal) {
    for b in 0..h.blocks() {
        let d = h.dim(b);
        let block = h.diag_mut(b);
        for a in 1..d {
            for c in 0..a {
                block[c * d + a] = block[a * d + c];
            }
        }
    }
}
