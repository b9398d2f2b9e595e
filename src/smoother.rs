//! Running a [`ChainGraph`] over a horizon: the fixed-lag smoother (a window of the
//! N_w newest steps is optimized; the step leaving it is marginalized into a Gaussian
//! prior on the ones that remain) and the batch solve of the whole horizon.

use crate::error::{Error, Result};
use crate::graph::ChainGraph;
use crate::solver::{
    LinearPrior, Observer, Past, Settings, SolveReport, Termination, WindowSolver,
};

/// How a horizon is solved.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Mode {
    /// Fixed-lag smoother over the N_w newest steps (N_w ≥ 1).
    FixedLag(usize),
    /// All steps at once.
    Batch,
}

/// What the caller wants after a step's window was solved.
pub enum Next {
    Continue,
    Stop,
}

/// What a fixed-lag run tells its caller after each event, and asks of it. Steps are
/// named twice: `k`, the step of the values buffer, and `run_k`, the run's step (they
/// differ once a streamed run has compacted its buffer).
pub trait Hooks {
    /// Fills the guess of step k from the steps before, before it enters the window.
    fn predict(&mut self, _values: &mut [f64], _k: usize) {}

    /// Where the window ending at step k failed from its guess: a better guess of
    /// step k (the window is then solved again from the guesses it had, but for step
    /// k's); whether one was written.
    fn rescue(&mut self, _values: &mut [f64], _k: usize, _run_k: usize) -> bool {
        false
    }

    /// The window ending at step k was solved; the caller may stop the run.
    fn on_step(&mut self, k: usize, run_k: usize, report: &SolveReport, values: &[f64]) -> Next;

    /// An observer of every iteration of the run's solves, asked once.
    fn observer(&mut self) -> Option<Box<dyn Observer>> {
        None
    }

    /// With [`Past::Adaptive`], priors are conditioned from step k on.
    fn on_switch(&mut self, _k: usize, _run_k: usize) {}

    /// Run step j's values (one step), final: no later solve changes them. Called in
    /// step order, each step once, for every step that left a streamed buffer; an
    /// error ends the run with it.
    fn on_final(&mut self, _j: usize, _block: &[f64]) -> Result<()> {
        Ok(())
    }
}

/// A fixed-lag run: its length, window, solver settings and buffer.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FixedLag {
    /// Steps of the run (step 0 included).
    pub steps: usize,
    /// N_w ≥ 1 (a window longer than the run is the whole run).
    pub window: usize,
    pub settings: Settings,
    /// Steps the values buffer holds (at least the window + 4), `None` for every step:
    /// when the next step would not fit, the steps still needed (the window and the
    /// two steps before it) move to the buffer's start and the others leave through
    /// [`Hooks::on_final`]. The results are those of the run in place, to the bit.
    pub capacity: Option<usize>,
}

/// Where a fixed-lag run ended in its buffer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Finished {
    /// The run step of the values' step 0.
    pub base: usize,
    /// The first run step not handed to [`Hooks::on_final`]: the steps from there on
    /// are still in the values.
    pub handed: usize,
}

/// The steps a streamed buffer holds for a window of `window` steps by default:
/// a copy of the window every few thousand steps costs nothing next to the solves.
pub fn stream_capacity(window: usize) -> usize {
    (window + 4).max(4096.min(2 * window + 4096))
}

/// Runs the fixed-lag smoother over `run.steps` steps of `values` (step-major; step 0
/// holds the initial guess). Each step's final estimate is the one it has when it
/// leaves the window (or at the end of the run).
///
/// With [`Past::Adaptive`], a window solve that does not converge after a marginal
/// prior is solved again from the same guess after a conditioned one, and every
/// later prior is conditioned ([`Hooks::on_switch`]). With a conditioned past and a
/// window of one step, each step is solved as the exact conditional on the one before.
pub fn fixed_lag(
    graph: &ChainGraph,
    values: &mut [f64],
    run: &FixedLag,
    hooks: &mut dyn Hooks,
) -> Result<Finished> {
    let FixedLag {
        steps, settings, ..
    } = *run;
    // A window longer than the run is the whole run.
    let window = run.window.max(1).min(steps.max(1));
    let s = graph.layout().size();
    let mut solver = WindowSolver::new(graph, window + 1, settings)?;
    if let Some(observer) = hooks.observer() {
        solver.observe(observer);
    }
    let mut adaptive = settings.past == Past::Adaptive;
    let mut prior: Option<LinearPrior> = None;
    // The prior on the step before the window's first, kept to solve the window again
    // after a conditioned prior.
    let mut earlier: Option<LinearPrior> = None;
    let mut start = Start {
        values: Vec::with_capacity((window + 1) * s),
        first: 0,
        s,
    };
    let mut k0 = 0;
    // The first run step not handed out.
    let mut handed = 0;
    let capacity = run.capacity.map(|c| c.max(window + 4));
    if let Some(capacity) = capacity {
        if values.len() < capacity.min(steps) * s {
            return Err(Error::InvalidArgument(format!(
                "a streaming buffer of {} values holds fewer than {} steps",
                values.len(),
                capacity.min(steps)
            )));
        }
    }
    for run_k in 0..steps {
        let mut k = run_k - solver.base();
        if capacity.is_some_and(|c| k >= c) {
            // Keep the window and the two steps before it (the predictions and the
            // conditioned solves read them); the steps before are final.
            let base = solver.base();
            let lo = k0.min(k).saturating_sub(2);
            for j in handed..base + lo {
                hooks.on_final(j, &values[(j - base) * s..(j - base + 1) * s])?;
            }
            handed = handed.max(base + lo);
            values.copy_within(lo * s..k * s, 0);
            k0 -= lo;
            k -= lo;
            solver.shift_steps(lo);
            for p in [prior.as_mut(), earlier.as_mut()].into_iter().flatten() {
                p.shift_steps(lo);
            }
        }
        if k > 0 {
            hooks.predict(values, k);
        }
        if k > 0 && window == 1 && solver.settings().past == Past::Conditioned {
            // One step held on the one before, fixed: the exact conditional, every
            // factor joining them evaluated as it is (a linearized prior would hold
            // the factors nonlinear in the new step only to first order about its
            // prediction).
            k0 = k;
            start.keep(values, k - 1, k);
            let mut report = solver.solve_conditional(graph, values, k, k + 1)?;
            if report.termination != Termination::Converged {
                report = start.rescue(values, (k0, k, run_k), report, hooks, |v| {
                    solver.solve_conditional(graph, v, k, k + 1)
                })?;
            }
            if let Next::Stop = hooks.on_step(k, run_k, &report, values) {
                break;
            }
            continue;
        }
        if k + 1 - k0 > window {
            // The prior on k0 moves to `earlier` (no copy): it is what a re-solve of
            // this window after a conditioned prior starts from.
            earlier = prior.take();
            let left = leave(&mut solver, graph, values, k0, earlier.as_ref(), settings);
            prior = Some(match left {
                // The marginal leaves a direction without information (its Schur
                // complement cannot be formed): condition from here on instead.
                Err(Error::Singular { .. }) if adaptive => {
                    adaptive = false;
                    solver.condition_on_past();
                    hooks.on_switch(k, run_k);
                    leave(&mut solver, graph, values, k0, None, settings)?
                }
                other => other?,
            });
            k0 += 1;
        }
        let first = k0.max(1) - 1;
        start.keep(values, first, k);
        let mut report = solve_window(&mut solver, graph, values, k0, k, prior.as_ref())?;
        if adaptive && k0 > 0 && report.termination != Termination::Converged {
            // The marginal information along the motion no longer carries the solve:
            // condition from here on, starting with this window's prior.
            adaptive = false;
            solver.condition_on_past();
            hooks.on_switch(k, run_k);
            values[first * s..(k + 1) * s].copy_from_slice(&start.values);
            prior = Some(leave(
                &mut solver,
                graph,
                values,
                k0 - 1,
                earlier.as_ref(),
                settings,
            )?);
            let again = solve_window(&mut solver, graph, values, k0, k, prior.as_ref())?;
            report = SolveReport {
                iterations: report.iterations + again.iterations,
                factorizations: report.factorizations + again.factorizations,
                ..again
            };
        }
        if k > 0 && report.termination != Termination::Converged {
            // The newest step's guess may be too far from its solution (a coarse
            // step through a fast or stiff stretch): ask for a better one.
            let prior = prior.as_ref();
            report = start.rescue(values, (k0, k, run_k), report, hooks, |v| {
                solve_window(&mut solver, graph, v, k0, k, prior)
            })?;
        }
        if let Next::Stop = hooks.on_step(k, run_k, &report, values) {
            break;
        }
    }
    Ok(Finished {
        base: solver.base(),
        handed,
    })
}

/// A window's guess, from the step before it: what a window solved again (after a
/// conditioned prior, or from a rescue) starts from.
struct Start {
    /// Steps `first`..=k of the values.
    values: Vec<f64>,
    first: usize,
    /// Unknowns a step.
    s: usize,
}

impl Start {
    /// Keeps steps first..=k of `values`.
    fn keep(&mut self, values: &[f64], first: usize, k: usize) {
        self.first = first;
        self.values.clear();
        self.values
            .extend_from_slice(&values[first * self.s..(k + 1) * self.s]);
    }

    /// After the window k0..=k (run step `run_k`) failed to converge (`failed`): the
    /// window back at its guess, [`Hooks::rescue`] asked for a new guess of step k,
    /// and `solve` run again from there; without a new guess the failed solve's
    /// values stay.
    fn rescue(
        &self,
        values: &mut [f64],
        (k0, k, run_k): (usize, usize, usize),
        failed: SolveReport,
        hooks: &mut dyn Hooks,
        mut solve: impl FnMut(&mut [f64]) -> Result<SolveReport>,
    ) -> Result<SolveReport> {
        let s = self.s;
        let window = k0 * s..(k + 1) * s;
        let failed_values = values[window.clone()].to_vec();
        values[window.clone()].copy_from_slice(&self.values[(k0 - self.first) * s..]);
        if !hooks.rescue(values, k, run_k) {
            values[window].copy_from_slice(&failed_values);
            return Ok(failed);
        }
        let again = solve(values)?;
        Ok(SolveReport {
            iterations: failed.iterations + again.iterations,
            factorizations: failed.factorizations + again.factorizations,
            ..again
        })
    }
}

/// The prior that step k0 leaves on k0 + 1 as it leaves the window.
fn leave(
    solver: &mut WindowSolver,
    graph: &ChainGraph,
    values: &mut [f64],
    k0: usize,
    prior: Option<&LinearPrior>,
    settings: Settings,
) -> Result<LinearPrior> {
    let marginal = if settings.tangent_priors {
        solver.marginalize_projected(graph, values, k0, prior)
    } else {
        solver.marginalize(graph, values, k0, prior)
    };
    marginal.map_err(|e| match e {
        crate::Error::Singular { what, .. } => crate::Error::Singular {
            what: format!(
                "{what}; --past conditioned holds the past at its estimate instead of \
                     marginalizing it"
            ),
            step: Some(solver.base() + k0),
            t: Some(crate::trajectory::round_time(solver.time(graph, k0))),
        },
        other => other,
    })
}

/// One window solve [k0, k]: the newest step first brought to its optimum given the
/// one before, then the window from there (usually one iteration that confirms it).
fn solve_window(
    solver: &mut WindowSolver,
    graph: &ChainGraph,
    values: &mut [f64],
    k0: usize,
    k: usize,
    prior: Option<&LinearPrior>,
) -> Result<SolveReport> {
    let mut warm = 0;
    if k > k0 {
        warm = solver
            .solve_conditional(graph, values, k, k + 1)?
            .iterations;
    }
    let mut report = solver.solve(graph, values, k0, k + 1, prior)?;
    report.iterations += warm;
    Ok(report)
}

/// Solves all steps 0..steps of `values` at once, from the guess they hold.
pub fn batch(
    graph: &ChainGraph,
    values: &mut [f64],
    steps: usize,
    settings: Settings,
) -> Result<SolveReport> {
    let mut solver = WindowSolver::new(graph, steps, settings)?;
    solver.solve(graph, values, 0, steps, None)
}
