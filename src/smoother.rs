//! Running a [`ChainGraph`] over a horizon: the fixed-lag smoother (a window of the
//! N_w newest steps is optimized; the step leaving it is marginalized into a Gaussian
//! prior on the ones that remain) and the batch solve of the whole horizon.

use crate::error::{Error, Result};
use crate::graph::{ChainGraph, StepIteration, StepLimits};
use crate::solver::{
    Iteration, LinearPrior, Observer, Past, Settings, SolveReport, Termination, WindowSolver,
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

/// Step k of `values` solved by the graph's [`ExactStep`] given step k − 1, if it
/// has one and it converges; else step k is given back its `guess` (what it held)
/// and `None` is returned. Its iterations go to `observer` as the window k..k+1's.
fn exact_step(
    graph: &ChainGraph,
    values: &mut [f64],
    k: usize,
    guess: &[f64],
    limits: StepLimits,
    observer: Option<&mut dyn Observer>,
) -> Option<SolveReport> {
    let exact = graph.exact_step()?;
    let s = graph.layout().size();
    let (before, block) = values[(k - 1) * s..(k + 1) * s].split_at_mut(s);
    let mut watch = observer.map(|observer| {
        move |step: &StepIteration| {
            observer.iteration(&Iteration {
                k0: k,
                k1: k + 1,
                iteration: step.iteration,
                newton: true,
                cost: step.cost,
                trial: None,
                damping: 0.0,
                // Newton's model of a square system predicts its residual gone.
                predicted: step.cost,
                largest_step: step.update,
                small: step.settled,
                restored: false,
                chord: !step.fresh,
            })
        }
    });
    let watch = watch.as_mut().map(|w| w as &mut dyn FnMut(&StepIteration));
    match exact.solve(graph.time(k), before, block, limits, watch) {
        // Its equations hold to round-off: a cost of zero.
        Some(work) => Some(SolveReport {
            factorizations: work.factorizations,
            ..SolveReport::new(Termination::Converged, work.iterations, 0.0)
        }),
        None => {
            block.copy_from_slice(guess);
            None
        }
    }
}

/// Runs the fixed-lag smoother over steps 0..steps of `values` (step-major; step 0
/// holds the initial guess). Before a step enters, `predict(values, k)` fills its
/// initial guess from the steps before. After each window solve, `on_step(k, report,
/// values)` sees the newest step k; it may stop the run. Each step's final estimate
/// is the one it has when it leaves the window (or at the end of the run).
///
/// With [`Past::Adaptive`], a window solve that does not converge after a marginal
/// prior is solved again from the same guess after a conditioned one, and every
/// later prior is conditioned; `on_switch(k)` is told the step.
#[allow(clippy::too_many_arguments)] // the run's callbacks, one per event
pub fn fixed_lag(
    graph: &ChainGraph,
    values: &mut [f64],
    steps: usize,
    window: usize,
    settings: Settings,
    predict: impl FnMut(&mut [f64], usize),
    on_step: impl FnMut(usize, &SolveReport, &[f64]) -> Next,
    on_switch: impl FnMut(usize),
) -> Result<()> {
    fixed_lag_with_rescue(
        graph,
        values,
        steps,
        window,
        settings,
        predict,
        |_, _| false,
        on_step,
        on_switch,
    )
}

/// [`fixed_lag`], and where a window solve fails, `rescue(values, k)` may replace the
/// guess of the newest step k by a better one (the forward problem integrates from
/// step k − 1 in substeps); the window is then solved again from the guesses it had,
/// but for step k's. `rescue` returns whether it wrote a guess.
#[allow(clippy::too_many_arguments)] // the run's callbacks, one per event
pub fn fixed_lag_with_rescue(
    graph: &ChainGraph,
    values: &mut [f64],
    steps: usize,
    window: usize,
    settings: Settings,
    predict: impl FnMut(&mut [f64], usize),
    rescue: impl FnMut(&mut [f64], usize) -> bool,
    on_step: impl FnMut(usize, &SolveReport, &[f64]) -> Next,
    on_switch: impl FnMut(usize),
) -> Result<()> {
    run_fixed_lag(
        graph, values, None, steps, window, settings, predict, rescue, on_step, on_switch,
    )
    .map(drop)
}

/// Where a [`fixed_lag_streaming`] run hands its final steps, and how many steps its
/// buffer holds.
pub struct Stream<'a> {
    /// Steps the values buffer holds (at least the window + 4): when the next step
    /// would not fit, the steps still needed (the window and the two steps before
    /// it) move to the start of the buffer and the others are handed out first.
    pub capacity: usize,
    /// `on_final(j, block)`: run step j's values (one step, `layout().size()`),
    /// final: no later solve changes them. Called in step order, each step once,
    /// for every step that left the window; an error ends the run with it.
    pub on_final: &'a mut dyn FnMut(usize, &[f64]) -> Result<()>,
}

/// The steps a [`Stream`] buffer holds for a window of `window` steps by default:
/// a copy of the window every few thousand steps costs nothing next to the solves.
pub fn stream_capacity(window: usize) -> usize {
    (window + 4).max(4096.min(2 * window + 4096))
}

/// [`fixed_lag_with_rescue`] in a buffer of `stream.capacity` steps whatever the
/// run's length: step 0 of `values` stands for run step `graph.step_offset()`
/// while it runs (so [`ChainGraph::time`] of a step of `values` is its run time), and
/// the callbacks get and index steps of `values`. Steps leave through
/// `stream.on_final` as they become final; the ones still in the buffer when the run
/// ends do not: the run step of `values`' step 0 is returned (the graph's offset is
/// back to 0 then), and the steps from the last one handed out on are in `values`.
/// The results are those of [`fixed_lag_with_rescue`] to the bit.
#[allow(clippy::too_many_arguments)] // the run's callbacks, one per event
pub fn fixed_lag_streaming(
    graph: &ChainGraph,
    values: &mut [f64],
    stream: Stream<'_>,
    steps: usize,
    window: usize,
    settings: Settings,
    predict: impl FnMut(&mut [f64], usize),
    rescue: impl FnMut(&mut [f64], usize) -> bool,
    on_step: impl FnMut(usize, &SolveReport, &[f64]) -> Next,
    on_switch: impl FnMut(usize),
) -> Result<(usize, usize)> {
    run_fixed_lag(
        graph,
        values,
        Some(stream),
        steps,
        window,
        settings,
        predict,
        rescue,
        on_step,
        on_switch,
    )
}

/// Puts the graph's step offset back to 0 however the run ends.
struct OffsetGuard<'a>(&'a ChainGraph);

impl Drop for OffsetGuard<'_> {
    fn drop(&mut self) {
        self.0.set_step_offset(0);
    }
}

/// The fixed-lag run, in place (`stream` None: `values` holds every step) or in a
/// compacted buffer. Returns the run step of `values`' step 0 and the first step not
/// handed to `on_final`.
#[allow(clippy::too_many_arguments)] // the run's callbacks, one per event
fn run_fixed_lag(
    graph: &ChainGraph,
    values: &mut [f64],
    mut stream: Option<Stream<'_>>,
    steps: usize,
    window: usize,
    settings: Settings,
    mut predict: impl FnMut(&mut [f64], usize),
    mut rescue: impl FnMut(&mut [f64], usize) -> bool,
    mut on_step: impl FnMut(usize, &SolveReport, &[f64]) -> Next,
    mut on_switch: impl FnMut(usize),
) -> Result<(usize, usize)> {
    // A window longer than the run is the whole run. Steps a graph takes exactly are
    // the solution of every window length (each holds all its equations): one at a
    // time.
    let window = if graph.exact_step().is_some() {
        1
    } else {
        window.max(1).min(steps.max(1))
    };
    let s = graph.layout().size();
    let mut solver = WindowSolver::new(graph, window + 1, settings)?;
    let mut adaptive = settings.past == Past::Adaptive;
    let mut prior: Option<LinearPrior> = None;
    // The prior on the step before the window's first, kept to solve the window again
    // after a conditioned prior.
    let mut earlier: Option<LinearPrior> = None;
    // The window's guess, from the step before it (steps `first`..=k): what a window
    // solved again (after a conditioned prior, or from substeps) starts from.
    let mut start = Vec::with_capacity((window + 1) * s);
    let mut k0 = 0;
    // The run step of `values`' step 0, and the first run step not handed out.
    let mut base = 0;
    let mut handed = 0;
    let _guard = OffsetGuard(graph);
    if let Some(st) = &stream {
        let capacity = st.capacity.max(window + 4);
        if values.len() < capacity.min(steps) * s {
            return Err(Error::InvalidArgument(format!(
                "a streaming buffer of {} values holds fewer than {} steps",
                values.len(),
                capacity.min(steps)
            )));
        }
    }
    for run_k in 0..steps {
        let mut k = run_k - base;
        if let Some(st) = stream.as_mut() {
            let capacity = st.capacity.max(window + 4);
            if k >= capacity {
                // Keep the window and the two steps before it (the predictions and
                // the conditioned solves read them); the steps before are final.
                let lo = k0.min(k).saturating_sub(2);
                for j in handed..base + lo {
                    (st.on_final)(j, &values[(j - base) * s..(j - base + 1) * s])?;
                }
                handed = handed.max(base + lo);
                values.copy_within(lo * s..k * s, 0);
                base += lo;
                k0 -= lo;
                k -= lo;
                graph.set_step_offset(base);
                solver.shift_steps(lo);
                for p in [prior.as_mut(), earlier.as_mut()].into_iter().flatten() {
                    p.shift_steps(lo);
                }
            }
        }
        if k > 0 {
            predict(values, k);
        }
        if k > 0 && window == 1 && solver.settings().past == Past::Conditioned {
            // One step held on the one before, fixed: the exact conditional, every
            // factor joining them evaluated as it is (a linearized prior would hold
            // the factors nonlinear in the new step only to first order about its
            // prediction).
            k0 = k;
            start.clear();
            start.extend_from_slice(&values[(k - 1) * s..(k + 1) * s]);
            let limits = StepLimits {
                max_iterations: solver.settings().max_iterations,
                step_tolerance: solver.settings().step_tolerance,
            };
            let exact = exact_step(graph, values, k, &start[s..], limits, solver.observer());
            let mut report = match exact {
                Some(report) => report,
                None => solver.solve_conditional(graph, values, k, k + 1)?,
            };
            if report.termination != Termination::Converged {
                report =
                    solve_from_rescue(values, s, &start, k - 1, k0, k, report, &mut rescue, |v| {
                        solver.solve_conditional(graph, v, k, k + 1)
                    })?;
            }
            if let Next::Stop = on_step(k, &report, values) {
                break;
            }
            continue;
        }
        if run_k == 0 && window == 1 && solver.settings().past == Past::Conditioned {
            // The first step, where the graph can solve it alone: the later steps
            // are held on it, and need no prior from it.
            if let Some(work) = graph
                .exact_step()
                .and_then(|e| e.solve_first(graph.time(0), &mut values[..s]))
            {
                let report = SolveReport {
                    factorizations: work.factorizations,
                    ..SolveReport::new(Termination::Converged, work.iterations, 0.0)
                };
                if let Next::Stop = on_step(k, &report, values) {
                    break;
                }
                continue;
            }
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
                    on_switch(k);
                    leave(&mut solver, graph, values, k0, None, settings)?
                }
                other => other?,
            });
            k0 += 1;
        }
        let first = k0.max(1) - 1;
        start.clear();
        start.extend_from_slice(&values[first * s..(k + 1) * s]);
        let mut report = solve_window(&mut solver, graph, values, k0, k, prior.as_ref())?;
        if adaptive && k0 > 0 && report.termination != Termination::Converged {
            // The marginal information along the motion no longer carries the solve:
            // condition from here on, starting with this window's prior.
            adaptive = false;
            solver.condition_on_past();
            on_switch(k);
            values[first * s..(k + 1) * s].copy_from_slice(&start);
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
            report =
                solve_from_rescue(values, s, &start, first, k0, k, report, &mut rescue, |v| {
                    solve_window(&mut solver, graph, v, k0, k, prior)
                })?;
        }
        if let Next::Stop = on_step(k, &report, values) {
            break;
        }
    }
    Ok((base, handed))
}

/// After the window k0..=k failed to converge (`failed`): the window back at its guess
/// (`start` holds steps `first`..=k), `rescue` asked for a new guess of step k, and
/// `solve` run again from there; without a new guess the failed solve's values stay.
#[allow(clippy::too_many_arguments)] // the window's bounds, its guess and two callbacks
fn solve_from_rescue(
    values: &mut [f64],
    s: usize,
    start: &[f64],
    first: usize,
    k0: usize,
    k: usize,
    failed: SolveReport,
    rescue: &mut impl FnMut(&mut [f64], usize) -> bool,
    mut solve: impl FnMut(&mut [f64]) -> Result<SolveReport>,
) -> Result<SolveReport> {
    let window = k0 * s..(k + 1) * s;
    let failed_values = values[window.clone()].to_vec();
    values[window.clone()].copy_from_slice(&start[(k0 - first) * s..]);
    if !rescue(values, k) {
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
            step: Some(k0),
            t: Some(crate::trajectory::round_time(graph.time(k0))),
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
