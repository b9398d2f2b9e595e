//! The iteration: Gauss-Newton / Levenberg-Marquardt steps with backtracking,
//! second-order correction and the switch to the exact Hessian.

use super::chord::ChordOutcome;
use super::*;

impl WindowSolver {
    /// After a full step from `saved` along `direction` failed to lower the cost:
    /// the first of its halves, quarters, … (down to 1/256) that does, linearized for
    /// the next iteration, or `None` with the window back at `saved`.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn backtrack(
        &mut self,
        graph: &ChainGraph,
        values: &mut [f64],
        k0: usize,
        k1: usize,
        prior: Option<&LinearPrior>,
        scope: Scope,
        cost: f64,
    ) -> Result<Option<f64>> {
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
                Ok(()) => self.evaluate(graph, values, k0, k1, prior, scope, false),
                Err(e) => Err(e),
            };
            if let Ok(c) = trial {
                if c < cost {
                    return match self.evaluate(graph, values, k0, k1, prior, scope, true) {
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
        let scope = Scope::Window { held };
        let th = self.settings.thresholds;
        self.prior_roots = None;
        if k1 <= k0 || k1 - k0 > self.h.capacity() {
            return Err(Error::InvalidArgument(format!(
                "window {k0}..{k1} is empty or larger than the solver's capacity {}",
                self.h.capacity()
            )));
        }
        let s = self.s;
        let n = (k1 - k0) * s;
        let lm = self.settings.method == Method::LevenbergMarquardt;
        // Start undamped: with a good guess the Gauss-Newton step is accepted; damping
        // (relative to diag H) is switched on only when a step fails to lower the cost.
        let mut mu: f64 = 0.0;
        let mut nu = 2.0;
        let diverged =
            |cost: f64, iterations| SolveReport::new(Termination::Diverged, iterations, cost);
        // An evaluation that fails ends the solve as diverged, its reason kept.
        let failed = |e: Error, cost: f64, iterations| SolveReport {
            cause: Some(e.to_string()),
            ..diverged(cost, iterations)
        };
        let mut cost = match self.evaluate(graph, values, k0, k1, prior, scope, true) {
            Ok(c) => c,
            Err(e) => return Ok(failed(e, f64::INFINITY, 0)),
        };
        let mut iterations = 0;
        // Gauss-Newton until it shows the slow linear convergence or the failed step
        // of a poor model; then the exact reduced Hessian (`exact_hessian`) for the
        // rest of the solve. `gauss_newton` says H holds a fresh Gauss-Newton matrix.
        let mut newton = false;
        let mut gauss_newton = true;
        let mut previous = f64::INFINITY;
        let mut slow = false;
        // The last accepted step was below the tolerance and kept the hard equations:
        // the point is an optimum as far as a damped model can tell.
        let mut settled = false;
        while iterations < self.settings.max_iterations {
            iterations += 1;
            if newton && gauss_newton {
                if let Err(e) = self.exact_hessian(graph, values, k0, k1, prior, scope) {
                    return Ok(failed(e, cost, iterations));
                }
                gauss_newton = false;
            }
            let floor = th.damping_floor;
            for (b, damping) in self.damping[..n].chunks_exact_mut(s).enumerate() {
                let (diag, d) = (self.h.diag(b), self.h.dim(b));
                let scale = &self.newton.scale[b * s..(b + 1) * s];
                for (r, v) in damping[..d].iter_mut().enumerate() {
                    let x = if newton { scale[r] } else { diag[r * d + r] };
                    *v = mu * x.max(floor);
                }
            }
            let factored = self
                .chol
                .factor(&self.h, if lm { &self.damping[..n] } else { &[] })
                .is_ok();
            // Gauss-Newton from J itself where H = JᵀJ is too ill-conditioned for its
            // Cholesky factor to give the step to more than a few digits.
            let ill_conditioned = mu == 0.0
                && !newton
                && (!factored || self.chol.pivot_ratio() < self.settings.normal_equations_limit);
            if ill_conditioned && self.rows_width.is_none() && k1 == k0 + 1 {
                // The rows were not kept (a window a marginal prior is made from keeps
                // none, see `evaluate`): the same linearization again, keeping them, as
                // every one-step linearization will from now on (ill-conditioning
                // persists along a run: the 128-link pendulum's every window).
                self.keep_rows = true;
                if let Err(e) = self.evaluate(graph, values, k0, k1, prior, scope, true) {
                    return Ok(failed(e, cost, iterations));
                }
            }
            let from_rows =
                ill_conditioned && self.least_squares_step(&values[k0 * s..(k0 + 1) * s], prior);
            if factored && !from_rows {
                for i in 0..n {
                    self.delta[i] = -self.g[i];
                }
                self.chol.solve(&mut self.delta[..n]);
            } else if !from_rows {
                if mu == 0.0 && settled {
                    // H is singular to working precision where the damped steps have
                    // already come to rest: no undamped step can say more (the six-bar
                    // press's windows in IC, cycling from 1e-4 down to 1e-12 and back).
                    return Ok(SolveReport::new(Termination::Converged, iterations, cost));
                }
                if !lm || mu > th.max_damping {
                    return Ok(diverged(cost, iterations));
                }
                mu = (mu * 10.0).max(self.settings.initial_damping);
                continue;
            }
            // The decrease the linear model predicts for the soft factors in y:
            // −gᵀy − ½yᵀHy.
            self.h.multiply(&self.delta[..n], &mut self.hd[..n]);
            let predicted: f64 = (0..n)
                .map(|i| -self.g[i] * self.delta[i] - 0.5 * self.delta[i] * self.hd[i])
                .sum();
            let window = &mut values[k0 * s..k1 * s];
            self.saved[..n].copy_from_slice(window);
            // δ = p + N y per block; `largest` is max |δᵢ| / (1 + |xᵢ|).
            let (mut largest, mut restored) = (0.0f64, true);
            for b in 0..k1 - k0 {
                let red = &self.hard[b].reduction;
                let at_round_off = self.hard[b].at_round_off;
                let y = &self.delta[b * s..(b + 1) * s];
                let x = &mut window[b * s..(b + 1) * s];
                for i in 0..s {
                    let p = red.particular[i];
                    let (start, nrow) = red.row(i);
                    let step = p + nrow
                        .iter()
                        .zip(&y[start..])
                        .map(|(a, b)| a * b)
                        .sum::<f64>();
                    let scale = 1.0 + x[i].abs();
                    largest = largest.max(step.abs() / scale);
                    restored &= at_round_off || p.abs() <= self.settings.step_tolerance * scale;
                    x[i] += step;
                    self.direction[b * s + i] = step;
                }
            }
            let small = largest <= self.settings.step_tolerance;
            // This iteration as an observer sees it (the trial's cost once known).
            let record = Iteration {
                k0,
                k1,
                iteration: iterations,
                newton,
                cost,
                trial: None,
                damping: mu,
                predicted,
                largest_step: largest,
                small,
                restored,
                chord: false,
            };
            if small && mu == 0.0 {
                // Converged: the point moved by less than the tolerance, so the cost
                // the model predicts is the cost there, to far below its round-off,
                // and the hard equations, exact to first order along δ, are off by
                // O(|δ|²) ≤ 1e-16: no correction needed.
                if let Some(observer) = self.observer.as_mut() {
                    observer.iteration(&record);
                }
                if !held && !newton {
                    self.keep_for_marginal(values, k0, k1);
                }
                return Ok(SolveReport::new(
                    Termination::Converged,
                    iterations,
                    cost - predicted,
                ));
            }
            // The trial is linearized at once: accepted (the usual case), it is the
            // next iteration's system; rejected, the old point is linearized again.
            // After an undamped Gauss-Newton step of a one-block window, the chord
            // step from the trial may show convergence without that linearization.
            let chord = mu == 0.0
                && !newton
                && !from_rows
                && iterations < self.settings.max_iterations
                && self.chord_ready(k0, k1, held);
            let trial = match self.correct(graph, values, k0, k1) {
                Ok(()) if chord => match self.chord_test(graph, values, prior, held, record) {
                    ChordOutcome::Converged(report) => return Ok(report),
                    ChordOutcome::Failed(e, c) => return Ok(failed(e, c, iterations + 1)),
                    ChordOutcome::Trial(trial) => trial,
                },
                Ok(()) => self.evaluate(graph, values, k0, k1, prior, scope, true),
                Err(e) => Err(e),
            };
            gauss_newton = true;
            // Converged when an undamped step is small; or when it restores the hard
            // factors and either the model predicts a decrease below `flat_decrease`
            // of the cost, or the step fails to lower the cost while it is below
            // `stall` (relative) or predicts less than `stall` of it: then the cost
            // comparison only sees the
            // residuals' round-off (their evaluation goes through a factorization),
            // and what is left is a slow Gauss-Newton tail along a direction with
            // little information. A small damped step proves nothing: damping alone
            // can make it small.
            let no_progress = match &trial {
                Ok(c) => *c >= cost,
                Err(_) => true,
            };
            // A negative prediction is no "little left to gain": the model itself is
            // off (H's round-off), and the step may be anything.
            let little = |fraction: f64| (0.0..=fraction * cost.abs()).contains(&predicted);
            let flat = restored
                && (little(th.flat_decrease)
                    || (no_progress && (largest <= th.stall || little(th.stall))));
            let converged = (small || flat) && mu == 0.0;
            if let Some(observer) = self.observer.as_mut() {
                observer.iteration(&Iteration {
                    trial: trial.as_ref().ok().copied(),
                    ..record
                });
            }

            match trial {
                Ok(c) if converged || c <= cost || !lm => {
                    if converged && c > cost {
                        // Converged where the step could not lower the cost: the point
                        // before the step is the answer (within round-off of the trial
                        // where the comparison is round-off, far better where not).
                        values[k0 * s..k1 * s].copy_from_slice(&self.saved[..n]);
                        return Ok(SolveReport::new(Termination::Converged, iterations, cost));
                    }
                    if converged {
                        return Ok(SolveReport::new(Termination::Converged, iterations, c));
                    }
                    // Where the model predicted the decrease well (ratio > 3/4), go back
                    // to Gauss-Newton at once: damping relative to diag H all but
                    // freezes directions with little information, and easing it off
                    // by thirds costs a dozen iterations.
                    // Undamped steps shrinking by less than 4× twice in a row: the
                    // linear convergence of a model missing its second-order terms.
                    if mu == 0.0 {
                        let slower = largest > th.slow_rate * previous;
                        newton |= slow && slower && self.settings.second_order;
                        slow = slower;
                        previous = largest;
                    }
                    settled = small && restored;
                    let ratio = (cost - c) / predicted.max(f64::MIN_POSITIVE);
                    // A step below the tolerance leaves only round-off to compare, and
                    // says no more about the model than that the undamped step is due.
                    mu = if ratio > th.good_ratio || mu < th.negligible_damping || settled {
                        0.0
                    } else {
                        mu / 3.0
                    };
                    cost = c;
                    nu = 2.0;
                }
                _ => {
                    // A failed full step after the first (which starts from a
                    // prediction off the constraints): the model is wrong at its scale.
                    newton |= iterations >= 2 && self.settings.second_order;
                    if lm && mu == 0.0 && !small {
                        // The full step overshot: try fractions of it before damping,
                        // which would turn the step away from the directions with
                        // little information, where it is most needed.
                        if let Some(c) =
                            self.backtrack(graph, values, k0, k1, prior, scope, cost)?
                        {
                            previous = f64::INFINITY;
                            slow = false;
                            settled = false;
                            cost = c;
                            continue;
                        }
                    }
                    values[k0 * s..k1 * s].copy_from_slice(&self.saved[..n]);
                    if !lm {
                        return Ok(diverged(cost, iterations));
                    }
                    if let Err(e) = self.evaluate(graph, values, k0, k1, prior, scope, true) {
                        return Ok(failed(e, cost, iterations));
                    }
                    if small && restored {
                        // A damped step below the tolerance, along a descent direction,
                        // failed to lower the cost: the cost's changes are below its
                        // round-off (the residuals go through factorizations), so no
                        // step can be judged any more. This is the optimum.
                        return Ok(SolveReport::new(Termination::Converged, iterations, cost));
                    }
                    if small {
                        // The damped step vanished without lowering the cost: try the
                        // undamped one again.
                        mu = 0.0;
                        continue;
                    }
                    mu = (mu * nu).max(self.settings.initial_damping);
                    nu *= 2.0;
                    if mu > th.max_damping {
                        return Ok(diverged(cost, iterations));
                    }
                }
            }
        }
        Ok(SolveReport::new(
            Termination::IterationLimit,
            iterations,
            cost,
        ))
    }
}
