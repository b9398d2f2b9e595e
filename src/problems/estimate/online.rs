//! The fixed-lag smoother as an online estimator ([`Estimator`]): each call adds a
//! step with its readings, solves the window of the newest steps, and hands out the
//! newest step's filtered estimate and the oldest's final one, each with its
//! marginal covariance. Its cost per step does not grow with the record: the
//! values are kept in a buffer that moves, and the readings that left the window
//! leave the graph.

use super::consistency::Nis;
use super::determination::watched_coordinates;
use super::graph::EstimationGraph;
use crate::error::{Error, Result};
use crate::graph::{Factor, Noise, Workspace};
use crate::model::{Model, State};
use crate::solver::{LinearPrior, Marginals, Settings, SolveReport, Termination, WindowSolver};
use crate::trajectory::round_time;
use nalgebra::DVector;
use std::sync::Arc;

/// One step's estimate: its variables (the graph's block: q, q̇, q̈, inputs) and
/// their marginal covariance.
#[derive(Debug, Clone, PartialEq)]
pub struct StepEstimate {
    /// The run step.
    pub step: usize,
    pub t: f64,
    pub x: Vec<f64>,
    /// Row-major s × s.
    pub covariance: Vec<f64>,
}

impl StepEstimate {
    /// The standard deviation of every variable.
    pub fn sd(&self) -> Vec<f64> {
        let s = self.x.len();
        (0..s)
            .map(|i| self.covariance[i * s + i].max(0.0).sqrt())
            .collect()
    }
}

/// What one step of the estimator gives.
#[derive(Debug, Clone)]
pub struct Update {
    /// The newest step, given the readings up to it (filtered).
    pub newest: StepEstimate,
    /// The step that leaves the window with this update, final (a window of one
    /// step: the newest itself).
    pub finals: Vec<StepEstimate>,
    /// The normalized innovation squared of this step's readings, if it had any.
    pub nis: Option<f64>,
    pub report: SolveReport,
}

/// A window solve that reaches the iteration limit is kept when its cost is below
/// this many times its residual count: a fit still improving (a rough start whose
/// error the window's readings only slowly reveal), not one no estimate explains (a
/// corrupted reading), which stops the run. An online estimator has a budget of
/// solves per step; the next step's solve goes on from where this one stopped.
pub const PLAUSIBLE_COST: f64 = 10.0;

/// A window holding the start whose cost exceeds this many times its residual
/// count (χ² at twice its expected value) is solved again from the filter's path
/// ([`Estimator::refit_from_filter`]).
const MISFIT_COST: f64 = 1.0;

/// The most steps a window holding the start grows to while its cost stays a
/// misfit (`MISFIT_COST`), where its own longest is shorter: a few hundred
/// milliseconds of readings at common rates, which tell the two motions apart.
const MISFIT_LONGEST: usize = 100;

/// At the start of a record, a window grows up to this many times its length while
/// its oldest step is less certain (a larger σ of a watched coordinate) than its
/// newest: where the readings determine the start only slowly (a gyroscope that
/// cannot yet tell the start angle from an unknown torque), a step leaves the window
/// once the readings have caught up with it, not while its estimate is still mostly
/// the prior's.
pub const LONGEST_FACTOR: usize = 4;

/// Steps the buffer holds before it moves, past the window.
const BUFFER: usize = 1024;

/// Steps without readings from which the estimate is in a gap: its marginal priors
/// keep a floor of information ([`PRIOR_FLOOR`]), and the readings that end it
/// move the window's guess to them where they lie far from its prediction.
pub const GAP_STEPS: usize = 20;

/// The floor of a marginal prior's information in a gap, as a share of its largest
/// diagonal entry ([`WindowSolver::set_prior_floor`]).
const PRIOR_FLOOR: f64 = 1e-9;

/// The σ (rad or m) given the prediction where readings end a gap: far wider than
/// any sensor's, so the guess moves to the readings.
const GAP_SIGMA: f64 = 1e3;

/// The fixed-lag estimator over a growing record.
pub struct Estimator {
    model: Arc<Model>,
    eg: EstimationGraph,
    solver: WindowSolver,
    window: usize,
    /// The window once the readings have caught up with the start, where it differs.
    settled: Option<usize>,
    /// The most steps the window grows to while its oldest step is unsettled.
    longest: usize,
    /// The oldest steps the next update marginalizes (handed out final by this one).
    leaving: usize,
    /// The coordinates whose σ decide when the oldest step leaves: the scene's
    /// independent ones, else every q.
    watched: Vec<usize>,
    /// The readings have caught up with the start: a full window's oldest step was
    /// as certain as its newest once (the window no longer grows).
    caught_up: bool,
    /// Steps the windows held, summed over the updates.
    held_sum: usize,
    /// The most steps a window held.
    pub held_most: usize,
    /// Values of the buffer's steps (step-major); its step 0 is run step `solver.base()`.
    values: Vec<f64>,
    /// Steps the buffer holds (`None`: every step, for a batch solve after).
    capacity: Option<usize>,
    prior: Option<LinearPrior>,
    /// The buffer step of the window's oldest step.
    k0: usize,
    /// The run step the next update makes.
    next: usize,
    /// The first run step not yet handed out as final.
    finalized: usize,
    covariances: Vec<Vec<f64>>,
    /// The newest step's prediction, kept while its conditional solve runs.
    guess: Vec<f64>,
    /// The run step of the latest update with readings.
    last_read: Option<usize>,
    /// The readings of the update under way where they end a gap
    /// ([`Estimator::near_after_gap`]).
    gap_readings: Vec<super::record::StepReading>,
    ws: Workspace,
    pub nis: Nis,
    pub iterations: usize,
    /// Window solves that reached the iteration limit and were kept (see
    /// [`PLAUSIBLE_COST`]).
    pub unsettled: usize,
    /// Windows holding the start that were solved again from the filter's path and
    /// kept that solution.
    pub refits: usize,
    /// Updates whose window kept the start for its cost alone (far from a fit's).
    pub misfit_holds: usize,
}

impl Estimator {
    /// An estimator of the model in `eg` over windows of `window` steps; with
    /// `keep_all`, every step stays in the buffer (and every reading in the graph).
    pub fn new(
        model: Arc<Model>,
        eg: EstimationGraph,
        window: usize,
        settings: Settings,
        keep_all: bool,
    ) -> Result<Self> {
        let window = window.max(1);
        let longest = LONGEST_FACTOR * window;
        let watched = watched_coordinates(&model);
        let solver = WindowSolver::new(&eg.graph, longest.max(MISFIT_LONGEST) + 1, settings)?;
        let s = eg.size();
        let capacity = (!keep_all).then_some(window + BUFFER);
        let ws = eg.graph.workspace();
        Ok(Estimator {
            model,
            solver,
            window,
            settled: None,
            longest,
            leaving: 0,
            watched,
            held_sum: 0,
            caught_up: false,
            held_most: 0,
            values: Vec::with_capacity(capacity.unwrap_or(window + BUFFER) * s),
            capacity,
            prior: None,
            k0: 0,
            next: 0,
            finalized: 0,
            covariances: Vec::new(),
            guess: Vec::new(),
            last_read: None,
            gap_readings: Vec::new(),
            ws,
            eg,
            nis: Nis::default(),
            iterations: 0,
            unsettled: 0,
            refits: 0,
            misfit_holds: 0,
        })
    }

    /// The estimator whose window becomes `window` steps once the readings have caught
    /// up with the start (and no misfit holds it): a batch's start pass, whose windows
    /// only guess the batch's solution after the start. A narrower window shrinks to
    /// it two steps an update.
    pub fn settling_to(mut self, window: usize) -> Self {
        self.settled = Some(window.max(1));
        self
    }

    /// The mean number of steps the windows held, over the updates so far.
    pub fn mean_window(&self) -> f64 {
        self.held_sum as f64 / self.next.max(1) as f64
    }

    pub fn graph(&self) -> &EstimationGraph {
        &self.eg
    }

    /// Before the first update: its solve begins at `readings` (the first step's)
    /// where they lie far from the start ([`super::start`]); σ's of the start prior
    /// `initial_q`.
    pub fn begin_near(&mut self, readings: &[super::record::StepReading], initial_q: &[f64]) {
        if self.next == 0 {
            self.eg.guess =
                super::start::toward_readings(&self.model, &self.eg.start, readings, initial_q);
        }
    }

    /// Before an update: where its readings end a gap of [`GAP_STEPS`] steps or more
    /// without any and an encoder reads a coordinate far from the prediction, the
    /// window's guess moves to them ([`super::start`]), every step of it by the same
    /// shift of the read coordinates. Over a long gap the prediction drifts from the
    /// motion (a four-bar left 100 s without readings came back 1.4 rad off its crank
    /// reading), and a solve from there does not converge.
    pub fn near_after_gap(&mut self, readings: &[super::record::StepReading]) {
        let gap = self.last_read.map_or(0, |k| self.next.saturating_sub(k));
        if !readings.is_empty() && gap >= GAP_STEPS && self.eg.independent.is_empty() {
            self.gap_readings = readings.to_vec();
        }
    }

    /// The window's guess moved toward `self.gap_readings` (see
    /// [`Estimator::near_after_gap`]), buffer steps k0..=k.
    fn guess_near_gap_readings(&mut self, k: usize) {
        let readings = std::mem::take(&mut self.gap_readings);
        let (n, s) = (self.eg.n, self.eg.size());
        let state = |values: &[f64], j: usize| State {
            q: DVector::from_column_slice(&values[j * s..j * s + n]),
            dq: DVector::from_column_slice(&values[j * s + n..j * s + 2 * n]),
        };
        let loose = vec![GAP_SIGMA; n];
        let newest = state(&self.values, k);
        let Some(moves) = super::start::moves_toward(&self.model, &newest, &readings, &loose)
        else {
            return;
        };
        for j in self.k0..=k {
            if let Some(m) = super::start::moved(&self.model, &state(&self.values, j), &moves) {
                self.values[j * s..j * s + n].copy_from_slice(m.q.as_slice());
                self.values[j * s + n..j * s + 2 * n].copy_from_slice(m.dq.as_slice());
            }
        }
    }

    /// The run step the next update makes.
    pub fn next_step(&self) -> usize {
        self.next
    }

    /// The time of run step `step`.
    pub fn time(&self, step: usize) -> f64 {
        round_time(self.eg.graph.run_time(step))
    }

    /// The buffer's values from run step `solver.base()` on (every step with `keep_all`).
    pub fn values(&self) -> &[f64] {
        &self.values
    }

    /// Adds the next step with its readings (factors whose datum is the reading, each
    /// with its noise) and solves the window ending there.
    pub fn update(&mut self, readings: Vec<(Box<dyn Factor>, Noise)>) -> Result<Update> {
        let run_k = self.next;
        let s = self.eg.size();
        let mut k = run_k - self.solver.base();
        if self.capacity.is_some_and(|c| k >= c) {
            // Keep the window and the two steps before it (the prediction reads them).
            let lo = self.k0.min(k).saturating_sub(2);
            self.values.copy_within(lo * s..k * s, 0);
            self.values.truncate((k - lo) * s);
            self.k0 -= lo;
            k -= lo;
            self.solver.shift_steps(lo);
            if let Some(p) = self.prior.as_mut() {
                p.shift_steps(lo);
            }
            // The readings of the steps that left the window no solve reads again.
            self.eg.graph.drop_at_before(self.solver.base() + self.k0);
        }
        let has_readings = !readings.is_empty();
        for (factor, noise) in readings {
            self.eg.graph.add_soft_at(run_k, factor, noise)?;
        }
        let gap = self.last_read.map_or(0, |r| run_k - r);
        self.solver
            .set_prior_floor(if gap >= GAP_STEPS { PRIOR_FLOOR } else { 0.0 });
        if k == 0 {
            let block = self.eg.initial_block(&self.model)?;
            self.values.extend_from_slice(&block);
        } else {
            self.values.resize((k + 1) * s, 0.0);
            self.eg.predict(&mut self.values, k);
        }
        for _ in 0..self.leaving {
            let earlier = self.prior.take();
            let prior = self
                .solver
                .marginalize(&self.eg.graph, &self.values, self.k0, earlier.as_ref())
                .map_err(|e| self.located(e, run_k - (k - self.k0)))?;
            self.prior = Some(prior);
            self.k0 += 1;
        }
        if !self.gap_readings.is_empty() {
            self.guess_near_gap_readings(k);
        }
        self.held_most = self.held_most.max(k + 1 - self.k0);
        self.held_sum += k + 1 - self.k0;
        // Until the window has caught up with the start, it grows on a comparison of
        // its ends' σ's: every factor differentiated, so that kept Jacobians do not
        // tip it.
        self.solver.pause_kept_jacobians(!self.caught_up);
        // The newest step first brought to its optimum given the one before, then
        // the window from there.
        let mut warm = 0;
        if k > self.k0 {
            self.guess.clear();
            self.guess.extend_from_slice(&self.values[k * s..]);
            let first =
                self.solver
                    .solve_conditional(&self.eg.graph, &mut self.values, k, k + 1)?;
            warm = first.iterations;
            if first.termination != Termination::Converged {
                self.values[k * s..].copy_from_slice(&self.guess);
            }
        }
        let mut report = self.solver.solve(
            &self.eg.graph,
            &mut self.values,
            self.k0,
            k + 1,
            self.prior.as_ref(),
        )?;
        // While the window holds the start, a cost far from a fit's is solved again
        // from the filter's path (`refit_from_filter`), and the start stays in the
        // window for as long as the cost stays so (see `leaving` below).
        let mut misfit = false;
        if self.prior.is_none() && k > self.k0 {
            let bound = MISFIT_COST * self.residuals(k + 1 - self.k0) as f64;
            if report.cost > bound {
                report = self.refit_from_filter(k, report)?;
            }
            misfit = report.cost > bound;
        }
        report.iterations += warm;
        self.iterations += report.iterations;
        let plausible = report.termination == Termination::IterationLimit
            && report.cost <= PLAUSIBLE_COST * self.residuals(k + 1 - self.k0) as f64;
        if plausible {
            // Still improving at the limit, its cost that of a fit: kept, and the
            // next step's solve goes on from it.
            self.unsettled += 1;
        } else if report.termination != Termination::Converged {
            return Err(Error::NotConverged {
                what: format!("the estimate at step {run_k} (t = {} s)", self.time(run_k)),
                report,
            });
        }
        // The last solve's normal equations, unless they hold the exact Hessian of
        // a solve that switched to Newton's method (not positive definite away from
        // the optimum): then the Gauss–Newton matrix at the estimate.
        let reused = !plausible
            && self
                .solver
                .covariances_after_solve(
                    &self.eg.graph,
                    self.k0,
                    k + 1,
                    Marginals::Ends,
                    &mut self.covariances,
                )
                .is_ok();
        if !reused {
            self.solver
                .covariances(
                    &self.eg.graph,
                    &self.values,
                    self.k0..k + 1,
                    self.prior.as_ref(),
                    Marginals::Ends,
                    &mut self.covariances,
                )
                .map_err(|e| self.located(e, run_k))?;
        }
        let newest = self.estimate_of(k);
        let nis = {
            let t = self.eg.graph.run_time(run_k);
            self.nis.add(
                self.eg.graph.layout(),
                self.eg.graph.terms_at(run_k),
                &newest.x,
                &newest.covariance,
                t,
                &mut self.ws,
            )
        };
        // How many of the oldest steps leave with the next update: none while the
        // window fills, or, at the start of the record, while the oldest knows less
        // than the newest (the readings have not yet caught up with the start, which
        // the sensors determine only slowly) and the window may grow; two while a
        // grown window shrinks back; else one. Past the start, a σ that only follows
        // the configuration (how well a sensor sees the motion there) grows nothing.
        let held = k + 1 - self.k0;
        let less_certain = self.oldest_less_certain(k);
        self.caught_up |= held >= self.window && !less_certain;
        let unsettled = !self.caught_up && less_certain;
        if let (true, false, Some(w)) = (self.caught_up, misfit, self.settled) {
            self.window = w;
        }
        let for_start = unsettled && held < self.longest;
        let for_misfit = misfit && held < MISFIT_LONGEST;
        if for_misfit && !for_start && held >= self.window {
            self.misfit_holds += 1;
        }
        self.leaving = if held < self.window || for_start || for_misfit {
            0
        } else if held > self.window && !unsettled {
            2
        } else {
            1
        };
        if self.leaving == 2 {
            self.solver.covariances_after_solve(
                &self.eg.graph,
                self.k0,
                k + 1,
                Marginals::Every,
                &mut self.covariances,
            )?;
        }
        // The steps that leave with the next update: these are their final estimates.
        let finals: Vec<StepEstimate> = (self.k0..self.k0 + self.leaving)
            .map(|b| self.estimate_of(b))
            .collect();
        self.finalized = self.solver.base() + self.k0 + self.leaving;
        if has_readings {
            self.last_read = Some(run_k);
        }
        self.next += 1;
        Ok(Update {
            newest,
            finals,
            nis,
            report,
        })
    }

    /// Whether the oldest step's σ of a watched coordinate is above the newest's:
    /// its smoothed estimate knows less than the filtered one at the window's end.
    fn oldest_less_certain(&self, k: usize) -> bool {
        let s = self.eg.size();
        let (old, new) = (&self.covariances[0], &self.covariances[k - self.k0]);
        self.watched
            .iter()
            .any(|&i| old[i * s + i] > new[i * s + i])
    }

    /// The steps still in the window, final: the record has ended. Their
    /// covariances, left out step by step, come from the last update's
    /// linearization.
    pub fn finish(&mut self) -> Result<Vec<StepEstimate>> {
        let base = self.solver.base();
        if self.next > base + self.k0 {
            self.solver.covariances_after_solve(
                &self.eg.graph,
                self.k0,
                self.next - base,
                Marginals::Every,
                &mut self.covariances,
            )?;
        }
        Ok((self.finalized.max(base + self.k0)..self.next)
            .map(|run| self.estimate_of(run - base))
            .collect())
    }

    /// The soft residuals of a window of `steps` steps ending at the newest: every
    /// step's factors and the readings in it.
    fn residuals(&self, steps: usize) -> usize {
        let graph = &self.eg.graph;
        let per_step: usize = graph
            .step_terms()
            .iter()
            .filter(|t| !t.is_constraint())
            .map(|t| t.factor().dim())
            .sum();
        let last = self.next;
        let first = (last + 1).saturating_sub(steps);
        let readings: usize = graph.sparse_terms()[graph.sparse_range(first, last + 1)]
            .iter()
            .map(|(_, t)| t.factor().dim())
            .sum();
        per_step * steps + readings
    }

    /// The estimate of buffer step k of the last solve.
    fn estimate_of(&self, k: usize) -> StepEstimate {
        let s = self.eg.size();
        let run = self.solver.base() + k;
        StepEstimate {
            step: run,
            t: self.time(run),
            x: self.values[k * s..(k + 1) * s].to_vec(),
            covariance: self.covariances[k - self.k0].clone(),
        }
    }

    /// At the start of a record the readings may fit two motions for a few steps
    /// (the start's velocity, which a gyroscope and an encoder of a five-bar barely
    /// tell apart at rest: the crank rising or falling). A window that holds the
    /// start re-solves it at every update, and once it has settled on the wrong one,
    /// its solves stay there however strongly the later readings disagree: a local
    /// minimum, its cost growing step after step, while a filter that only moves
    /// its newest step follows the readings. Where such a window's cost is far from
    /// a fit's, it is solved once more from the filter's path (each step solved
    /// given the one before, from the start), and the lower of the two costs is
    /// kept. `report` is the window solve's; returns the kept one's.
    fn refit_from_filter(&mut self, k: usize, report: SolveReport) -> Result<SolveReport> {
        let s = self.eg.size();
        let (k0, graph) = (self.k0, &self.eg.graph);
        let mut path = self.values.clone();
        path[k0 * s..(k0 + 1) * s].copy_from_slice(&self.eg.initial_block(&self.model)?);
        let start = self.solver.solve(graph, &mut path, k0, k0 + 1, None)?;
        let mut fitted = start.termination == Termination::Converged;
        for j in k0 + 1..=k {
            self.eg.predict(&mut path, j);
            let step = self.solver.solve_conditional(graph, &mut path, j, j + 1)?;
            fitted &= step.termination == Termination::Converged;
        }
        let refit = match fitted {
            true => Some(self.solver.solve(graph, &mut path, k0, k + 1, None)?),
            false => None,
        };
        match refit {
            Some(r) if r.termination == Termination::Converged && r.cost < report.cost => {
                self.values = path;
                self.refits += 1;
                Ok(SolveReport {
                    iterations: r.iterations + report.iterations,
                    ..r
                })
            }
            // The window's own solve stands; solved again from its estimate (at
            // once) so that the solver's last linearization is the window's.
            _ => {
                let again = self
                    .solver
                    .solve(graph, &mut self.values, k0, k + 1, None)?;
                Ok(SolveReport {
                    iterations: report.iterations + again.iterations,
                    ..again
                })
            }
        }
    }

    fn located(&self, e: Error, run_step: usize) -> Error {
        match e {
            Error::Singular { what, .. } => Error::Singular {
                what,
                step: Some(run_step),
                t: Some(self.time(run_step)),
            },
            other => other,
        }
    }
}
