//! Jacobians kept across a fixed-lag window's solves. Each new reading moves the
//! window's older steps by little, yet a plain Gauss–Newton solve differentiates
//! every factor of every step again. With [`Settings::relinearize_beyond`] a step
//! whose values moved less than that since its factors were differentiated keeps
//! their Jacobians: its hard equations' reduction and its soft factors' reduced
//! rows stay as they were, and only their residuals are evaluated again, at the
//! current values. The cost, and so every convergence and acceptance test, stays
//! exact; a Jacobian off by a relative ε moves the optimum by about ε of the
//! estimate's σ. Only the newest steps, the steps that moved and the factors
//! touching them are differentiated again (iSAM2's fluid relinearization, with
//! fresh residuals).
//!
//! [`Settings::relinearize_beyond`]: super::Settings::relinearize_beyond

use super::linearize::{CostSum, HardPass};
use super::structure::{factor_of, is_hard, Instance, Source, Span};
use super::WindowSolver;
use crate::error::Result;
use crate::graph::ChainGraph;
use crate::linalg::nullspace::NullSpace;
use std::collections::VecDeque;

/// One soft factor's reduced, whitened Jacobian rows, as a linearization left them.
struct KeptFactor {
    /// Which factor (see [`factor_key`]).
    key: (u8, usize),
    dim: usize,
    /// J N per block it touches (its step's, the step before's), dim × width.
    jacobian: [Vec<f64>; 2],
    width: [usize; 2],
    spans: [Vec<(usize, usize)>; 2],
}

/// A step's linearization: its hard equations reduced at `x`, and its soft
/// factors' rows, made with this reduction and the one before (`made_with`).
struct KeptStep {
    /// Tells this step's reductions apart (a new one for every linearization).
    id: u64,
    x: Vec<f64>,
    reduction: NullSpace,
    rows: usize,
    /// The ids of the reductions (of this step, of the step before; 0: none) the
    /// factors' rows were made with.
    made_with: (u64, u64),
    factors: Vec<KeptFactor>,
    /// The factors' share of H: Σ R₀ᵀR₀ (this step's block), Σ R₁ᵀR₁ (the step
    /// before's) and Σ R₀ᵀR₁ (the block between them), row-major.
    h: [Vec<f64>; 3],
    /// Whether `h` is the sum of the current `factors` (made when first used).
    summed: bool,
}

/// The kept linearizations, by run step.
#[derive(Default)]
pub(super) struct Reuse {
    steps: VecDeque<Option<KeptStep>>,
    /// The run step of `steps[0]`.
    first: usize,
    next_id: u64,
    /// Steps forgotten, whose buffers the next kept ones reuse.
    spare: Vec<KeptStep>,
    /// Steps whose factors entered through kept rows, and steps differentiated,
    /// over the solver's linearizations.
    pub(super) counts: (usize, usize),
    /// Whether the current solve may use kept Jacobians (its first iterations).
    pub(super) allowed: bool,
    /// Set by the caller while every factor is to be differentiated
    /// ([`WindowSolver::pause_kept_jacobians`]).
    pub(super) paused: bool,
    /// For each soft factor of the block at hand, its kept rows (`reusable`).
    map: Vec<usize>,
    /// The share of H of some of a step's kept factors (the first block's).
    subset: [Vec<f64>; 3],
    /// Whether the last linearization took some factors through kept rows.
    pub(super) in_last: bool,
    /// The run step of the window's first block at the last linearization here.
    hard_first: Option<usize>,
}

impl Reuse {
    /// Forgets every step before run step `from`.
    fn forget_before(&mut self, from: usize) {
        // A run that went back (a new run on this solver) keeps nothing.
        let drop = match from.checked_sub(self.first) {
            Some(ahead) => ahead.min(self.steps.len()),
            None => self.steps.len(),
        };
        self.spare.extend(self.steps.drain(..drop).flatten());
        self.first = from;
    }

    fn get(&self, run: usize) -> Option<&KeptStep> {
        run.checked_sub(self.first)
            .and_then(|i| self.steps.get(i))
            .and_then(Option::as_ref)
    }

    fn get_mut(&mut self, run: usize) -> Option<&mut KeptStep> {
        run.checked_sub(self.first)
            .and_then(|i| self.steps.get_mut(i))
            .and_then(Option::as_mut)
    }

    /// The id of the step's kept reduction (0 if none).
    fn id(&self, run: usize) -> u64 {
        self.get(run).map_or(0, |k| k.id)
    }

    /// Keeps `reduction` (of `rows` hard equations, made at `x`) as run step `run`'s;
    /// the factor rows made with the one before go with it.
    fn keep_step(&mut self, run: usize, x: &[f64], reduction: &NullSpace, rows: usize) -> u64 {
        if run < self.first {
            self.forget_before(run);
        }
        let i = run - self.first;
        if self.steps.len() <= i {
            self.steps.resize_with(i + 1, || None);
        }
        self.next_id += 1;
        let id = self.next_id;
        let slot = &mut self.steps[i];
        if slot.is_none() {
            *slot = self.spare.pop();
        }
        match slot {
            Some(k) => {
                k.id = id;
                k.x.clear();
                k.x.extend_from_slice(x);
                k.reduction.copy_from(reduction);
                k.rows = rows;
                k.made_with = (0, 0);
            }
            None => {
                *slot = Some(KeptStep {
                    id,
                    x: x.to_vec(),
                    reduction: reduction.clone(),
                    rows,
                    made_with: (0, 0),
                    factors: Vec::new(),
                    h: [Vec::new(), Vec::new(), Vec::new()],
                    summed: false,
                })
            }
        }
        id
    }

    /// Whether `x` is within `beyond` of where the step's reduction was made, each
    /// unknown relative to 1 + its size there.
    fn near(kept: &KeptStep, x: &[f64], beyond: f64) -> bool {
        kept.x
            .iter()
            .zip(x)
            .all(|(a, b)| (b - a).abs() <= beyond * (1.0 + a.abs()))
    }
}

impl WindowSolver {
    /// While `paused`, every linearization differentiates every factor (a caller
    /// that decides on small differences of the σ's, as an estimate's start does).
    pub fn pause_kept_jacobians(&mut self, paused: bool) {
        self.reuse.paused = paused;
    }

    /// Linearizes window `span` (every step held free: not a conditional solve, nor
    /// a marginalization) into H and g, differentiating again only the steps that
    /// moved beyond `beyond` since their kept linearization, and the newest one; the
    /// soft factors' cost goes to `soft`.
    pub(super) fn linearize_reusing(
        &mut self,
        graph: &ChainGraph,
        values: &[f64],
        span: Span,
        beyond: f64,
        soft: &mut CostSum,
    ) -> Result<()> {
        let Span { k0, k1, .. } = span;
        let s = self.s;
        let blocks = k1 - k0;
        let first_run = self.structure.run_step(k0);
        self.reuse.forget_before(first_run.saturating_sub(1));
        // The blocks follow their steps as the window moves on: a kept reduction
        // still in its step's block is not copied again.
        if let Some(last) = self.reuse.hard_first.filter(|&l| l < first_run) {
            let by = (first_run - last).min(self.lin.hard.len());
            self.lin.hard.rotate_left(by);
        }
        self.reuse.hard_first = Some(first_run);
        for b in 0..blocks {
            let x = &values[(k0 + b) * s..(k0 + b + 1) * s];
            // The newest step is always differentiated: it was only predicted before.
            let kept = self
                .reuse
                .get(first_run + b)
                .filter(|k| b + 1 < blocks && Reuse::near(k, x, beyond));
            if let Some(k) = kept {
                // The last solve corrected the step onto its hard equations (to
                // 10⁻¹⁰, `correct`), and it has not moved since: no particular step,
                // and their cost is left out.
                let hb = &mut self.lin.hard[b];
                if hb.kept != k.id {
                    hb.reduction.copy_from(&k.reduction);
                    hb.kept = k.id;
                }
                hb.reduction.particular.fill(0.0);
                hb.rows = k.rows;
                hb.at_round_off = true;
                continue;
            }
            self.lin
                .hard_block(graph, &self.structure, values, b, HardPass::Linearize)?;
            let hb = &mut self.lin.hard[b];
            hb.kept = self
                .reuse
                .keep_step(first_run + b, x, &hb.reduction, hb.rows);
        }
        let hard = &self.lin.hard;
        self.normal
            .h
            .reset_active(blocks, |b| hard[b].reduction.dim);
        self.normal.g[..blocks * s].fill(0.0);
        for b in 0..blocks {
            let run = first_run + b;
            let usable = self.reusable(graph, (k0, b));
            if usable {
                self.reuse.counts.0 += 1;
                self.reuse.in_last = true;
            } else {
                self.reuse.counts.1 += 1;
            }
            let (from, to) = (
                self.structure.block_start[b],
                self.structure.block_start[b + 1],
            );
            let mut ordinal = 0;
            for at in from..to {
                let i = self.structure.by_step[at];
                let inst = self.structure.instances[i];
                if is_hard(graph, inst) {
                    continue;
                }
                if usable {
                    self.reuse_factor(graph, values, (k0, b, i), ordinal, soft)?;
                } else {
                    self.soft_instance(graph, values, (k0, i), true, soft)?;
                    self.keep_factor(graph, (k0, b, i), ordinal);
                }
                ordinal += 1;
            }
            if usable {
                self.add_kept_information(k0, b);
            } else {
                let made_with = (self.reuse.id(run), self.reuse.id(run.wrapping_sub(1)));
                if let Some(k) = self.reuse.get_mut(run) {
                    k.factors.truncate(ordinal);
                    k.made_with = made_with;
                    k.summed = false;
                }
            }
        }
        Ok(())
    }

    /// Whether block `b`'s soft factors can enter through their kept rows: they were
    /// made with the reductions its step and the one before hold now, and they are
    /// the same factors.
    fn reusable(&mut self, graph: &ChainGraph, (k0, b): (usize, usize)) -> bool {
        let mut map = std::mem::take(&mut self.reuse.map);
        map.clear();
        let found = self.kept_factors_of(graph, (k0, b), &mut map);
        self.reuse.map = map;
        found
    }

    /// Into `map`, for each soft factor of block `b`, the index of its kept rows:
    /// false where the block has no usable kept rows (see [`Self::reusable`]). The
    /// same factors, in the same order; the first block of a window leaves out
    /// those reaching back before it.
    fn kept_factors_of(
        &self,
        graph: &ChainGraph,
        (k0, b): (usize, usize),
        map: &mut Vec<usize>,
    ) -> bool {
        let run = self.structure.run_step(k0 + b);
        let Some(k) = self.reuse.get(run) else {
            return false;
        };
        let before = run.checked_sub(1).map_or(0, |r| self.reuse.id(r));
        if k.made_with != (k.id, before) {
            return false;
        }
        let mut next = 0;
        (self.structure.block_start[b]..self.structure.block_start[b + 1]).all(|at| {
            let inst = self.structure.instances[self.structure.by_step[at]];
            if is_hard(graph, inst) {
                return true;
            }
            let key = factor_key(graph, inst);
            let Some(i) = k.factors[next..].iter().position(|f| f.key == key) else {
                return false;
            };
            map.push(next + i);
            next += i + 1;
            true
        })
    }

    /// Keeps the reduced rows soft factor instance `i` (at block `b`) has just left
    /// in `lin.reduced` as its step's `ordinal`-th factor.
    fn keep_factor(
        &mut self,
        graph: &ChainGraph,
        (k0, b, i): (usize, usize, usize),
        ordinal: usize,
    ) {
        let s = self.s;
        let inst = self.structure.instances[i];
        let factor = factor_of(graph, inst);
        let dim = factor.dim();
        let lagged = b >= 1 && factor.keys().iter().any(|k| k.lag == 1);
        let width = [
            self.lin.hard[b].reduction.dim,
            if lagged {
                self.lin.hard[b - 1].reduction.dim
            } else {
                0
            },
        ];
        let key = factor_key(graph, inst);
        let run = self.structure.run_step(k0 + b);
        let Some(k) = self.reuse.get_mut(run) else {
            return;
        };
        if k.factors.len() <= ordinal {
            k.factors.resize_with(ordinal + 1, || KeptFactor {
                key,
                dim: 0,
                jacobian: [Vec::new(), Vec::new()],
                width: [0, 0],
                spans: [Vec::new(), Vec::new()],
            });
        }
        let f = &mut k.factors[ordinal];
        let reduced = &self.lin.reduced;
        f.key = key;
        f.dim = dim;
        f.width = width;
        for (part, &w) in width.iter().enumerate() {
            f.jacobian[part].clear();
            f.spans[part].clear();
            for row in 0..dim {
                let (lo, hi) = reduced.spans[part][row];
                let (lo, hi) = (lo.min(w), hi.min(w));
                f.spans[part].push((lo, hi));
                let jr = &reduced.jacobian[part][row * s..row * s + w];
                f.jacobian[part].extend(jr.iter().enumerate().map(|(c, &v)| {
                    if (lo..hi).contains(&c) {
                        v
                    } else {
                        0.0
                    }
                }));
            }
        }
    }

    /// Soft factor instance `i` (block `b`'s `ordinal`-th) with its kept rows: its
    /// residual at the current values, its cost into `soft`, Rᵀr into g.
    fn reuse_factor(
        &mut self,
        graph: &ChainGraph,
        values: &[f64],
        (k0, b, i): (usize, usize, usize),
        ordinal: usize,
        soft: &mut CostSum,
    ) -> Result<()> {
        let s = self.s;
        let inst = self.structure.instances[i];
        let factor = factor_of(graph, inst);
        self.lin
            .evaluate_instance(graph, self.structure.base, values, inst, false)?;
        let buf = self.lin.buffers.of(inst);
        buf.whiten(factor, false);
        let run = self.structure.run_step(k0 + b);
        let k = self.reuse.get(run).expect("a reusable step is kept");
        let f = &k.factors[self.reuse.map[ordinal]];
        // The particular step p is the round-off the last correction left: J p is
        // dropped. H's share is the step's sum (`add_kept_information`); g += Rᵀr.
        let touches_first = factor.keys().iter().any(|key| inst.step - key.lag == k0);
        soft.add(&buf.r[..f.dim], touches_first);
        let lagged = b >= 1 && factor.keys().iter().any(|key| key.lag == 1);
        for (part, block) in [(0, b), (1, b.wrapping_sub(1))] {
            let w = f.width[part];
            if w == 0 || (part == 1 && !lagged) {
                continue;
            }
            let g = &mut self.normal.g[block * s..block * s + w];
            for (row, &r) in buf.r[..f.dim].iter().enumerate() {
                let (lo, hi) = f.spans[part][row];
                for c in lo..hi {
                    g[c] += f.jacobian[part][row * w + c] * r;
                }
            }
        }
        Ok(())
    }
}

impl WindowSolver {
    /// Adds block `b`'s kept share of H: its diagonal block, and where the window
    /// holds the step before, that step's block and the one between them.
    fn add_kept_information(&mut self, k0: usize, b: usize) {
        let run = self.structure.run_step(k0 + b);
        let Reuse {
            steps,
            first,
            map,
            subset,
            ..
        } = &mut self.reuse;
        let k = steps
            .get_mut(run - *first)
            .and_then(Option::as_mut)
            .expect("a reusable step is kept");
        let sums = if map.len() < k.factors.len() {
            // Some kept factors are not in this window (they reach back before it):
            // the share of those that are.
            sum_information(map.iter().map(|&i| &k.factors[i]), k.reduction.dim, subset);
            &*subset
        } else {
            if !k.summed {
                sum_information(k.factors.iter(), k.reduction.dim, &mut k.h);
                k.summed = true;
            }
            &k.h
        };
        let h = &mut self.normal.h;
        for (o, v) in h.diag_mut(b).iter_mut().zip(&sums[0]) {
            *o += v;
        }
        if b >= 1 && !sums[1].is_empty() {
            for (o, v) in h.diag_mut(b - 1).iter_mut().zip(&sums[1]) {
                *o += v;
            }
            for (o, v) in h.lower_mut(b).iter_mut().zip(&sums[2]) {
                *o += v;
            }
        }
    }
}

/// Into `h`, the share of H of `factors` (kept at a block of `d0` reduced
/// unknowns): Σ R₀ᵀR₀, Σ R₁ᵀR₁ and Σ R₀ᵀR₁, row-major ([`KeptStep::h`]).
fn sum_information<'a>(
    factors: impl Iterator<Item = &'a KeptFactor> + Clone,
    d0: usize,
    h: &mut [Vec<f64>; 3],
) {
    let d1 = factors.clone().map(|f| f.width[1]).max().unwrap_or(0);
    let [h00, h11, h01] = h;
    h00.clear();
    h00.resize(d0 * d0, 0.0);
    h11.clear();
    h11.resize(d1 * d1, 0.0);
    h01.clear();
    h01.resize(d0 * d1, 0.0);
    for f in factors {
        let (w0, w1) = (f.width[0], f.width[1]);
        for row in 0..f.dim {
            let r0 = &f.jacobian[0][row * w0..(row + 1) * w0];
            let r1 = &f.jacobian[1][row * w1..(row + 1) * w1];
            for (a, &va) in r0.iter().enumerate().filter(|(_, v)| **v != 0.0) {
                for (c, &vc) in r0.iter().enumerate() {
                    h00[a * d0 + c] += va * vc;
                }
                for (c, &vc) in r1.iter().enumerate() {
                    h01[a * d1 + c] += va * vc;
                }
            }
            for (a, &va) in r1.iter().enumerate().filter(|(_, v)| **v != 0.0) {
                for (c, &vc) in r1.iter().enumerate() {
                    h11[a * d1 + c] += va * vc;
                }
            }
        }
    }
}

/// Which factor an instance is, the same at every position of the window: its
/// list and its index there (factors of chosen steps counted from the first the
/// graph ever held).
fn factor_key(graph: &ChainGraph, inst: Instance) -> (u8, usize) {
    match inst.source {
        Source::Step => (0, inst.index),
        Source::Initial => (1, inst.index),
        Source::At => (2, inst.index + graph.dropped_at()),
    }
}
