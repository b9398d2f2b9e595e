//! Running a [`ChainGraph`] over a horizon: the fixed-lag smoother (a window of the
//! N_w newest steps is optimized; the step leaving it is marginalized into a Gaussian
//! prior on the ones that remain) and the batch solve of the whole horizon.

use crate::error::Result;
use crate::graph::ChainGraph;
use crate::solver::{LinearPrior, Settings, SolveReport, WindowSolver};

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

/// Runs the fixed-lag smoother over steps 0..steps of `values` (step-major; step 0
/// holds the initial guess). Before a step enters, `predict(values, k)` fills its
/// initial guess from the steps before. After each window solve, `on_step(k, report,
/// values)` sees the newest step k; it may stop the run. Each step's final estimate
/// is the one it has when it leaves the window (or at the end of the run).
pub fn fixed_lag(
    graph: &ChainGraph,
    values: &mut [f64],
    steps: usize,
    window: usize,
    settings: Settings,
    mut predict: impl FnMut(&mut [f64], usize),
    mut on_step: impl FnMut(usize, &SolveReport, &[f64]) -> Next,
) -> Result<()> {
    let window = window.max(1);
    let mut solver = WindowSolver::new(graph, window + 1, settings)?;
    let mut prior: Option<LinearPrior> = None;
    let mut k0 = 0;
    for k in 0..steps {
        if k > 0 {
            predict(values, k);
        }
        if k + 1 - k0 > window {
            let mut p = solver.marginalize(graph, values, k0, prior.as_ref())?;
            k0 += 1;
            if settings.tangent_priors {
                solver.project_prior(graph, values, k0, &mut p)?;
            }
            prior = Some(p);
        }
        let mut warm = 0;
        if k > k0 {
            // Bring the new step to its optimum given the one before, then solve the
            // window from there: usually a single iteration that confirms it.
            warm = solver
                .solve_conditional(graph, values, k, k + 1)?
                .iterations;
        }
        let mut report = solver.solve(graph, values, k0, k + 1, prior.as_ref())?;
        report.iterations += warm;
        if let Next::Stop = on_step(k, &report, values) {
            break;
        }
    }
    Ok(())
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
