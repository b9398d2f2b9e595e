//! The iteration: Gauss-Newton / Levenberg-Marquardt steps with backtracking,
//! second-order correction and the switch to the exact Hessian.

use super::chord::ChordOutcome;
use super::observer::Iteration;
use super::prior::LinearPrior;
use super::settings::{Method, Thresholds};
use super::structure::{Scope, Span};
use super::WindowSolver;
use crate::convergence::{SolveReport, Termination};
use crate::error::{Error, Result};
use crate::graph::ChainGraph;
use std::ops::ControlFlow;

impl WindowSolver {
    /// After a full step from `saved` along `direction` failed to lower the cost:
    /// the first of its halves, quarters, … (down to 1/256) that does, linearized for
    /// the next iteration, or `None` with the window back at `saved`.
    pub(super) fn backtrack(
        &mut self,
        graph: &ChainGraph,
        values: &mut [f64],
        span: Span,
        cost: f64,
    ) -> Result<Option<f64>> {
        let Span { k0, k1, .. } = span;
        let s = self.s;
        let n = (k1 - k0) * s;
        let mut t = 1.0;
        for _ in 0..self.settings.thresholds.backtrack_halvings {
            t *= 0.5;
            for ((x, x0), d) in values[k0 * s..k1 * s]
                .iter_mut()
                .zip(&self.saved[..n])
                .zip(&self.direction[..n])
            {
                *x = x0 + t * d;
            }
            let trial = match self.correct(graph, values, k0, k1) {
                Ok(()) => self.evaluate(graph, values, span, false),
                Err(e) => Err(e),
            };
            if let Ok(c) = trial {
                if c < cost {
                    return match self.evaluate(graph, values, span, true) {
                        Ok(c) => Ok(Some(c)),
                        Err(_) => break,
                    };
                }
            }
        }
        values[k0 * s..k1 * s].copy_from_slice(&self.saved[..n]);
        Ok(None)
    }

    /// Optimizes steps k0..k1 (k0 ≥ 1) with step k0 − 1 held at its value: the factors
    /// joining them stay, as constraints on the window rather than unknowns. The
    /// fixed-lag smoother uses it to bring a new step close to its optimum before the
    /// whole window is solved, which then mostly converges in one iteration.
    pub fn solve_conditional(
        &mut self,
        graph: &ChainGraph,
        values: &mut [f64],
        k0: usize,
        k1: usize,
    ) -> Result<SolveReport> {
        if k0 == 0 {
            return Err(Error::InvalidArgument(
                "a conditional solve needs a step before the window".into(),
            ));
        }
        self.solve_span(graph, values, k0, k1, None, true)
    }

    /// Optimizes steps k0..k1 of `values` (step-major, the whole trajectory) with an
    /// optional prior on step k0; the rest of `values` is read, not changed.
    pub fn solve(
        &mut self,
        graph: &ChainGraph,
        values: &mut [f64],
        k0: usize,
        k1: usize,
        prior: Option<&LinearPrior>,
    ) -> Result<SolveReport> {
        self.solve_span(graph, values, k0, k1, prior, false)
    }

    /// A window solve; with `held`, step k0 − 1 is held at its value.
    fn solve_span(
        &mut self,
        graph: &ChainGraph,
        values: &mut [f64],
        k0: usize,
        k1: usize,
        prior: Option<&LinearPrior>,
        held: bool,
    ) -> Result<SolveReport> {
        let span = Span {
            k0,
            k1,
            prior,
            scope: Scope::Window { held },
        };
        self.prior_roots = None;
        if k1 <= k0 || k1 - k0 > self.normal.h.capacity() {
            return Err(Error::InvalidArgument(format!(
                "window {k0}..{k1} is empty or larger than the solver's capacity {}",
                self.normal.h.capacity()
            )));
        }
        self.reuse.allowed = true;
        let cost = match self.evaluate(graph, values, span, true) {
            Ok(c) => c,
            Err(e) => return Ok(failed(e, f64::INFINITY, 0)),
        };
        let mut state = SolveState::new(cost);
        while state.iterations < self.settings.max_iterations {
            // Kept Jacobians speed up the solves that end in an iteration or two; one
            // that needs more differentiates everything from its third linearization
            // on, and converges as a plain Gauss–Newton solve does.
            self.reuse.allowed = state.iterations < 2;
            state.iterations += 1;
            if let Outcome::Done(report) = self.iteration(graph, values, span, &mut state)? {
                return Ok(report);
            }
        }
        Ok(SolveReport::new(
            Termination::IterationLimit,
            state.iterations,
            state.cost,
        ))
    }

    /// One iteration from a point linearized in H and g: the step, its trial point
    /// (corrected onto the hard equations), the convergence tests, and the step's
    /// acceptance or rejection.
    fn iteration(
        &mut self,
        graph: &ChainGraph,
        values: &mut [f64],
        span: Span,
        state: &mut SolveState,
    ) -> Result<Outcome> {
        let Span { k0, k1, .. } = span;
        if state.newton && state.gauss_newton {
            if let Err(e) = self.exact_hessian(graph, values, span) {
                return Ok(Outcome::Done(failed(e, state.cost, state.iterations)));
            }
            state.gauss_newton = false;
        }
        let from_rows = match self.step(graph, values, span, state) {
            ControlFlow::Continue(from_rows) => from_rows,
            ControlFlow::Break(outcome) => return Ok(outcome),
        };
        let predicted = self.normal.predicted_decrease((k1 - k0) * self.s);
        let (largest, restored) = self.take_step(values, k0, k1);
        let small = largest <= self.settings.step_tolerance;
        // This iteration as an observer sees it (the trial's cost once known).
        let record = Iteration {
            k0,
            k1,
            iteration: state.iterations,
            newton: state.newton,
            cost: state.cost,
            trial: None,
            damping: state.mu,
            predicted,
            largest_step: largest,
            small,
            restored,
            chord: false,
        };
        if small && state.mu == 0.0 {
            // Converged: the point moved by less than the tolerance, so the cost
            // the model predicts is the cost there, to far below its round-off,
            // and the hard equations, exact to first order along δ, are off by
            // O(|δ|²) ≤ 1e-16: no correction needed.
            self.report(&record);
            if !span.held() && !state.newton {
                self.keep_for_marginal(values, k0, k1);
            }
            return Ok(Outcome::Done(SolveReport::new(
                Termination::Converged,
                state.iterations,
                state.cost - predicted,
            )));
        }
        let th = &self.settings.thresholds;
        let flat = (0.0..=th.flat_decrease * state.cost.abs()).contains(&predicted);
        if self.settings.end_on_flat_step
            && flat
            && restored
            && state.mu == 0.0
            && !state.newton
            && !from_rows
        {
            // `converges` would pass on any trial cost: only the hard equations are
            // restored, and the cost is the model's.
            self.report(&record);
            if let Err(e) = self.correct(graph, values, k0, k1) {
                return Ok(Outcome::Done(failed(e, state.cost, state.iterations)));
            }
            return Ok(Outcome::Done(SolveReport::new(
                Termination::Converged,
                state.iterations,
                state.cost - predicted,
            )));
        }
        // After an undamped Gauss-Newton step of a one-block window, the chord
        // step from the trial may show convergence without a linearization there.
        let chord = state.mu == 0.0
            && !state.newton
            && !from_rows
            && state.iterations < self.settings.max_iterations
            && self.chord_ready(k0, k1, span.held());
        let trial = match self.trial(graph, values, span, chord, record) {
            ControlFlow::Continue(trial) => trial,
            ControlFlow::Break(report) => return Ok(Outcome::Done(report)),
        };
        state.gauss_newton = true;
        let converged = converges(&self.settings.thresholds, &record, &trial);
        self.report(&Iteration {
            trial: trial.as_ref().ok().copied(),
            ..record
        });
        let lm = self.settings.method == Method::LevenbergMarquardt;
        match trial {
            Ok(c) if converged || c <= state.cost || !lm => {
                Ok(self.accept(values, span, state, &record, (c, converged)))
            }
            _ => self.reject(graph, values, span, state, &record),
        }
    }

    /// The reduced step y into `delta`: from the Cholesky factor of the normal
    /// equations (damped by `mu` relative to diag H, or to the Gauss-Newton diagonal
    /// once H is Newton's), or from the rows where H is too ill-conditioned. Continues
    /// with whether it came from the rows; breaks where no step can be had at this
    /// damping (the damping raised for the next iteration, or the solve ended).
    fn step(
        &mut self,
        graph: &ChainGraph,
        values: &[f64],
        span: Span,
        state: &mut SolveState,
    ) -> ControlFlow<Outcome, bool> {
        let Span { k0, k1, prior, .. } = span;
        let (s, th) = (self.s, self.settings.thresholds);
        let n = (k1 - k0) * s;
        let lm = self.settings.method == Method::LevenbergMarquardt;
        let mu = state.mu;
        for (b, damping) in self.normal.damping[..n].chunks_exact_mut(s).enumerate() {
            let (diag, d) = (self.normal.h.diag(b), self.normal.h.dim(b));
            let scale = &self.newton.scale[b * s..(b + 1) * s];
            for (r, v) in damping[..d].iter_mut().enumerate() {
                let x = if state.newton {
                    scale[r]
                } else {
                    diag[r * d + r]
                };
                *v = mu * x.max(th.damping_floor);
            }
        }
        let factored = self
            .normal
            .chol
            .factor(
                &self.normal.h,
                if lm { &self.normal.damping[..n] } else { &[] },
            )
            .is_ok();
        self.normal.undamped_factor =
            (factored && mu == 0.0 && !state.newton).then_some(self.lin.generation);
        // Gauss-Newton from J itself where H = JᵀJ is too ill-conditioned for its
        // Cholesky factor to give the step to more than a few digits.
        let ill_conditioned = mu == 0.0
            && !state.newton
            && (!factored || self.normal.chol.pivot_ratio() < self.settings.normal_equations_limit);
        if ill_conditioned && self.kept.width.is_none() && k1 == k0 + 1 {
            // The rows were not kept (a window a marginal prior is made from keeps
            // none, see `evaluate`): the same linearization again, keeping them, as
            // every one-step linearization will from now on (ill-conditioning
            // persists along a run: the 128-link pendulum's every window).
            self.kept.keep = true;
            if let Err(e) = self.evaluate(graph, values, span, true) {
                let report = failed(e, state.cost, state.iterations);
                return ControlFlow::Break(Outcome::Done(report));
            }
        }
        let from_rows =
            ill_conditioned && self.least_squares_step(&values[k0 * s..(k0 + 1) * s], prior);
        if factored && !from_rows {
            self.normal.solve(n);
            return ControlFlow::Continue(false);
        }
        if from_rows {
            return ControlFlow::Continue(true);
        }
        if mu == 0.0 && state.settled {
            // H is singular to working precision where the damped steps have
            // already come to rest: no undamped step can say more.
            let report = SolveReport::new(Termination::Converged, state.iterations, state.cost);
            return ControlFlow::Break(Outcome::Done(report));
        }
        if !lm || mu > th.max_damping {
            return ControlFlow::Break(Outcome::Done(diverged(state.cost, state.iterations)));
        }
        state.mu = (mu * 10.0).max(self.settings.initial_damping);
        ControlFlow::Break(Outcome::Next)
    }

    /// Moves steps k0..k1 by δ = p + N y per block (the point before into `saved`,
    /// δ into `direction`); returns max |δᵢ| / (1 + |xᵢ|) and whether every block's
    /// particular part p was within the tolerance (or its equations at round-off):
    /// the step kept the hard equations rather than restoring them.
    fn take_step(&mut self, values: &mut [f64], k0: usize, k1: usize) -> (f64, bool) {
        let s = self.s;
        let n = (k1 - k0) * s;
        let window = &mut values[k0 * s..k1 * s];
        self.saved[..n].copy_from_slice(window);
        let (mut largest, mut restored) = (0.0f64, true);
        for b in 0..k1 - k0 {
            let red = &self.lin.hard[b].reduction;
            let at_round_off = self.lin.hard[b].at_round_off;
            let y = &self.normal.delta[b * s..(b + 1) * s];
            let x = &mut window[b * s..(b + 1) * s];
            step_scales(
                x,
                self.settings
                    .step_per_variable
                    .then_some(&self.variables[..]),
                &mut self.step_scale,
            );
            let scales = &self.step_scale;
            for i in 0..s {
                let p = red.particular[i];
                let (start, nrow) = red.row(i);
                let step = p + nrow
                    .iter()
                    .zip(&y[start..])
                    .map(|(a, b)| a * b)
                    .sum::<f64>();
                let scale = scales[i];
                largest = largest.max(step.abs() / scale);
                restored &= at_round_off || p.abs() <= self.settings.step_tolerance * scale;
                x[i] += step;
                self.direction[b * s + i] = step;
            }
        }
        (largest, restored)
    }

    /// The cost at the trial point the step led to, once corrected onto the hard
    /// equations and linearized there: accepted (the usual case), that is the next
    /// iteration's system; rejected, the old point is linearized again. With `chord`,
    /// the chord test first, which may end the solve.
    fn trial(
        &mut self,
        graph: &ChainGraph,
        values: &mut [f64],
        span: Span,
        chord: bool,
        record: Iteration,
    ) -> ControlFlow<SolveReport, Result<f64>> {
        let Span { k0, k1, .. } = span;
        ControlFlow::Continue(match self.correct(graph, values, k0, k1) {
            Ok(()) if chord => match self.chord_test(graph, values, span, record) {
                ChordOutcome::Converged(report) => return ControlFlow::Break(report),
                ChordOutcome::Failed(e, c) => {
                    return ControlFlow::Break(failed(e, c, record.iteration + 1))
                }
                ChordOutcome::Trial(trial) => trial,
            },
            Ok(()) => self.evaluate(graph, values, span, true),
            Err(e) => Err(e),
        })
    }

    /// Hands an iteration's record to the observer, if any.
    fn report(&mut self, record: &Iteration) {
        if let Some(observer) = self.observer.as_mut() {
            observer.iteration(record);
        }
    }

    /// After a step to a trial of cost `c` that lowered the cost, `converged`, or
    /// that Gauss-Newton takes regardless: the trial is the new point, with the
    /// damping eased and the switch to Newton decided by how fast the steps shrink.
    fn accept(
        &mut self,
        values: &mut [f64],
        span: Span,
        state: &mut SolveState,
        step: &Iteration,
        (c, converged): (f64, bool),
    ) -> Outcome {
        let Span { k0, k1, .. } = span;
        let th = self.settings.thresholds;
        if converged && c > state.cost {
            // Converged where the step could not lower the cost: the point before
            // the step is the answer (within round-off of the trial where the
            // comparison is round-off, far better where not).
            let (s, n) = (self.s, (k1 - k0) * self.s);
            values[k0 * s..k1 * s].copy_from_slice(&self.saved[..n]);
            let report = SolveReport::new(Termination::Converged, state.iterations, state.cost);
            return Outcome::Done(report);
        }
        if converged {
            return Outcome::Done(SolveReport::new(
                Termination::Converged,
                state.iterations,
                c,
            ));
        }
        // Undamped steps shrinking by less than 4× twice in a row: the linear
        // convergence of a model missing its second-order terms.
        if state.mu == 0.0 {
            let slower = step.largest_step > th.slow_rate * state.previous;
            state.newton |= state.slow && slower && self.settings.second_order;
            state.slow = slower;
            state.previous = step.largest_step;
        }
        state.settled = step.small && step.restored;
        // Where the model predicted the decrease well (ratio > 3/4), back to
        // Gauss-Newton at once: damping relative to diag H all but freezes the
        // directions with little information. A step below the tolerance leaves only
        // round-off to compare, and says only that the undamped step is due.
        let ratio = (state.cost - c) / step.predicted.max(f64::MIN_POSITIVE);
        state.mu = if ratio > th.good_ratio || state.mu < th.negligible_damping || state.settled {
            0.0
        } else {
            state.mu / 3.0
        };
        state.cost = c;
        state.nu = 2.0;
        Outcome::Next
    }

    /// After a step that failed to lower the cost (or whose trial failed): fractions
    /// of a full undamped step, else the point before the step, linearized again, with
    /// more damping; a failed step of a Gauss-Newton solve ends it.
    fn reject(
        &mut self,
        graph: &ChainGraph,
        values: &mut [f64],
        span: Span,
        state: &mut SolveState,
        step: &Iteration,
    ) -> Result<Outcome> {
        let Span { k0, k1, .. } = span;
        let th = self.settings.thresholds;
        let lm = self.settings.method == Method::LevenbergMarquardt;
        let (s, n) = (self.s, (k1 - k0) * self.s);
        let (small, iterations) = (step.small, state.iterations);
        // A failed full step after the first (which starts from a prediction off
        // the constraints): the model is wrong at its scale.
        state.newton |= iterations >= 2 && self.settings.second_order;
        if lm && state.mu == 0.0 && !small {
            // The full step overshot: try fractions of it before damping, which
            // would turn the step away from the directions with little information,
            // where it is most needed.
            if let Some(c) = self.backtrack(graph, values, span, state.cost)? {
                state.previous = f64::INFINITY;
                state.slow = false;
                state.settled = false;
                state.cost = c;
                return Ok(Outcome::Next);
            }
        }
        values[k0 * s..k1 * s].copy_from_slice(&self.saved[..n]);
        if !lm {
            return Ok(Outcome::Done(diverged(state.cost, iterations)));
        }
        if let Err(e) = self.evaluate(graph, values, span, true) {
            return Ok(Outcome::Done(failed(e, state.cost, iterations)));
        }
        if small && step.restored {
            // A damped step below the tolerance, along a descent direction, failed
            // to lower the cost: the cost's changes are below its round-off (the
            // residuals go through factorizations), so no step can be judged any
            // more. This is the optimum.
            let report = SolveReport::new(Termination::Converged, iterations, state.cost);
            return Ok(Outcome::Done(report));
        }
        if small {
            // The damped step vanished without lowering the cost: the undamped one
            // again.
            state.mu = 0.0;
            return Ok(Outcome::Next);
        }
        state.mu = (state.mu * state.nu).max(self.settings.initial_damping);
        state.nu *= 2.0;
        if state.mu > th.max_damping {
            return Ok(Outcome::Done(diverged(state.cost, iterations)));
        }
        Ok(Outcome::Next)
    }
}

/// Where a window solve stands between iterations.
struct SolveState {
    /// The cost at the current point, whose linearization H and g hold.
    cost: f64,
    iterations: usize,
    /// Levenberg-Marquardt's damping, relative to diag H, and its growth factor on
    /// a failed step. It starts at 0: with a good guess the Gauss-Newton step is
    /// accepted, and damping is switched on only when a step fails.
    mu: f64,
    nu: f64,
    /// Gauss-Newton until it shows the slow linear convergence or the failed step
    /// of a poor model; then the exact reduced Hessian (`exact_hessian`) for the
    /// rest of the solve.
    newton: bool,
    /// H holds a fresh Gauss-Newton matrix.
    gauss_newton: bool,
    /// The last undamped step's size, and whether it shrank slowly from the one
    /// before.
    previous: f64,
    slow: bool,
    /// The last accepted step was below the tolerance and kept the hard equations:
    /// the point is an optimum as far as a damped model can tell.
    settled: bool,
}

impl SolveState {
    fn new(cost: f64) -> Self {
        SolveState {
            cost,
            iterations: 0,
            mu: 0.0,
            nu: 2.0,
            newton: false,
            gauss_newton: true,
            previous: f64::INFINITY,
            slow: false,
            settled: false,
        }
    }
}

/// How an iteration ends.
enum Outcome {
    /// On to the next iteration.
    Next,
    /// The solve ends with this report.
    Done(SolveReport),
}

/// Whether the step of `step` (its trial's cost `trial`) ends the solve: it was
/// undamped and either small, or restored the hard factors while the model predicts
/// a decrease below `flat_decrease` of the cost, or failed to lower the cost while
/// below `stall` (relative) or predicting less than `stall` of it. Then the cost
/// comparison only sees the residuals' round-off (their evaluation goes through a
/// factorization), and what is left is a slow Gauss-Newton tail along a direction
/// with little information. A small damped step proves nothing: damping alone can
/// make it small.
fn converges(th: &Thresholds, step: &Iteration, trial: &Result<f64>) -> bool {
    let cost = step.cost;
    let predicted = step.predicted;
    let no_progress = match trial {
        Ok(c) => *c >= cost,
        Err(_) => true,
    };
    // A negative prediction is no "little left to gain": the model itself is off
    // (H's round-off), and the step may be anything.
    let little = |fraction: f64| (0.0..=fraction * cost.abs()).contains(&predicted);
    let flat = step.restored
        && (little(th.flat_decrease)
            || (no_progress && (step.largest_step <= th.stall || little(th.stall))));
    (step.small || flat) && step.damping == 0.0
}

/// What each entry's step of a step's values `x` is measured against: 1 + |xᵢ|, or
/// with `variables` (offset, length per variable) 1 + the largest |x| of its
/// variable.
pub(super) fn step_scales(x: &[f64], variables: Option<&[(usize, usize)]>, out: &mut [f64]) {
    for (o, v) in out.iter_mut().zip(x) {
        *o = 1.0 + v.abs();
    }
    for &(off, len) in variables.unwrap_or(&[]) {
        let top = x[off..off + len].iter().fold(0.0f64, |m, v| m.max(v.abs()));
        out[off..off + len].fill(1.0 + top);
    }
}

/// A solve that ends diverged.
fn diverged(cost: f64, iterations: usize) -> SolveReport {
    SolveReport::new(Termination::Diverged, iterations, cost)
}

/// A solve whose evaluation failed: diverged, its reason kept.
fn failed(e: Error, cost: f64, iterations: usize) -> SolveReport {
    // The failure names its step and time: a located error says them only once.
    let cause = match e {
        Error::Singular { what, .. } => format!("singular system: {what}"),
        other => other.to_string(),
    };
    SolveReport {
        cause: Some(cause),
        ..diverged(cost, iterations)
    }
}
