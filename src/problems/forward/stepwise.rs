//! A square graph's steps taken one at a time ([`Schedule::Stepwise`]), each given
//! the step before, held fixed: the square step where it can, else the general
//! solver's conditional solve, else that solve again from substeps. Every window
//! and the batch of such a graph have this solution, so this is how the plan runs
//! them all.
//!
//! [`Schedule::Stepwise`]: super::plan::Schedule::Stepwise

use super::graph::ForwardGraph;
use super::square_step::{SquareStep, StepIteration, StepLimits};
use crate::convergence::{SolveReport, Termination};
use crate::error::Result;
use crate::graph::ChainGraph;
use crate::solver::{Iteration, Settings, WindowSolver};

/// A better guess of a failed step k of the values, from the step before (given the
/// run's square step, whose analysis it may reuse); what was written, if anything.
pub(super) type Rescue<'a> =
    dyn FnMut(&mut [f64], usize, Option<&SquareStep>) -> Option<Rescued> + 'a;

/// What a rescue wrote into a failed step.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Rescued {
    /// A guess, from substeps of the run's own equations.
    Guess,
    /// The step's solution under the paper's integrator factors: kept where the
    /// run's own equations do not converge from it either.
    Paper,
}

/// Which solver took a step.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Taker {
    Square,
    General,
    /// The paper's integrator factors, for this step only (the run's own failed).
    Paper,
}

/// The solvers of one step given the one before.
pub(super) struct Stepwise {
    square: Option<SquareStep>,
    general: WindowSolver,
    /// The guess of the step being solved, kept to start again from.
    guess: Vec<f64>,
}

impl Stepwise {
    pub(super) fn new(
        graph: &ChainGraph,
        square: Option<SquareStep>,
        settings: Settings,
    ) -> Result<Stepwise> {
        Ok(Stepwise {
            square,
            general: WindowSolver::new(graph, 2, settings)?,
            guess: vec![0.0; graph.layout().size()],
        })
    }

    /// Installs an observer of every iteration, the square step's too.
    pub(super) fn observe(&mut self, observer: Box<dyn crate::solver::Observer>) {
        self.general.observe(observer);
    }

    /// The values moved `by` steps toward the start of their buffer.
    pub(super) fn shift_steps(&mut self, by: usize) {
        self.general.shift_steps(by);
    }

    /// The time of step k of the values.
    pub(super) fn time(&self, graph: &ChainGraph, k: usize) -> f64 {
        self.general.time(graph, k)
    }

    /// Step 0 under the graph's initial factors.
    pub(super) fn first(
        &mut self,
        graph: &ChainGraph,
        values: &mut [f64],
    ) -> Result<(SolveReport, Taker)> {
        let s = graph.layout().size();
        let t = self.time(graph, 0);
        if let Some(work) = self
            .square
            .as_mut()
            .and_then(|square| square.solve_first(t, &mut values[..s]))
        {
            let report = SolveReport {
                factorizations: work.factorizations,
                ..SolveReport::new(Termination::Converged, work.iterations, 0.0)
            };
            return Ok((report, Taker::Square));
        }
        Ok((
            self.general.solve(graph, values, 0, 1, None)?,
            Taker::General,
        ))
    }

    /// Step k (its guess in `values`) given step k − 1; where neither solver
    /// converges from the guess, `rescue(values, k)` may write a better one, from
    /// which the general solver tries again.
    pub(super) fn step(
        &mut self,
        graph: &ChainGraph,
        values: &mut [f64],
        k: usize,
        rescue: &mut Rescue<'_>,
    ) -> Result<(SolveReport, Taker)> {
        let s = graph.layout().size();
        self.guess.copy_from_slice(&values[k * s..(k + 1) * s]);
        if let Some(report) = self.square_step(graph, values, k) {
            return Ok((report, Taker::Square));
        }
        let failed = self.general.solve_conditional(graph, values, k, k + 1)?;
        if failed.termination == Termination::Converged {
            return Ok((failed, Taker::General));
        }
        // The guess may be too far from the solution (a coarse step through a fast
        // or stiff stretch): from a better one, if there is one.
        let failed_values = values[k * s..(k + 1) * s].to_vec();
        values[k * s..(k + 1) * s].copy_from_slice(&self.guess);
        let Some(rescued) = rescue(values, k, self.square.as_ref()) else {
            values[k * s..(k + 1) * s].copy_from_slice(&failed_values);
            return Ok((failed, Taker::General));
        };
        let rescue_values = values[k * s..(k + 1) * s].to_vec();
        let again = self.general.solve_conditional(graph, values, k, k + 1)?;
        let mut report = SolveReport {
            iterations: failed.iterations + again.iterations,
            factorizations: failed.factorizations + again.factorizations,
            ..again
        };
        if rescued == Rescued::Paper && report.termination != Termination::Converged {
            values[k * s..(k + 1) * s].copy_from_slice(&rescue_values);
            report.termination = Termination::Converged;
            return Ok((report, Taker::Paper));
        }
        Ok((report, Taker::General))
    }

    /// Step k by the square step, its iterations reported to the general solver's
    /// observer as the window k..k+1's; `None`, with step k back at its guess, where
    /// there is none or it declines.
    fn square_step(
        &mut self,
        graph: &ChainGraph,
        values: &mut [f64],
        k: usize,
    ) -> Option<SolveReport> {
        let square = self.square.as_mut()?;
        let s = graph.layout().size();
        let settings = self.general.settings();
        let limits = StepLimits {
            max_iterations: settings.max_iterations,
            step_tolerance: settings.step_tolerance,
        };
        let t = self.general.time(graph, k);
        let (before, block) = values[(k - 1) * s..(k + 1) * s].split_at_mut(s);
        let mut watch = self
            .general
            .observer()
            .map(|observer| move |step: &StepIteration| observer.iteration(&as_iteration(k, step)));
        let watch = watch.as_mut().map(|w| w as &mut dyn FnMut(&StepIteration));
        match square.solve(t, before, block, limits, watch) {
            // Its equations hold to round-off: a cost of zero.
            Some(work) => Some(SolveReport {
                factorizations: work.factorizations,
                ..SolveReport::new(Termination::Converged, work.iterations, 0.0)
            }),
            None => {
                block.copy_from_slice(&self.guess);
                None
            }
        }
    }
}

/// A square step's iteration as a solve's observer sees the general solver's.
fn as_iteration(k: usize, step: &StepIteration) -> Iteration {
    Iteration {
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
    }
}

/// What a stepwise run asks of its caller.
pub(super) trait StepHooks {
    /// A better guess of the failed step k of the buffer (run step j) from the step
    /// before, given the run's square step (whose analysis it may reuse); whether
    /// one was written.
    fn rescue(
        &mut self,
        _values: &mut [f64],
        _at: (usize, usize),
        _square: Option<&SquareStep>,
    ) -> Option<Rescued> {
        None
    }

    /// Step k of the buffer (run step j) was solved: `None` to go on, `Some(keep)` to
    /// end the run with its steps before `keep`.
    fn after(
        &mut self,
        at: (usize, usize),
        report: &SolveReport,
        taker: Taker,
        values: &[f64],
    ) -> Option<usize>;

    /// Run step j's values, final; in step order, each kept step once.
    fn on_final(&mut self, _j: usize, _block: &[f64]) -> Result<()> {
        Ok(())
    }
}

/// A run of `steps` steps of `fg` one at a time from the state in `values`' step 0,
/// in a buffer of `values.len()` / s steps (at least 3): when it is full, the two
/// steps the predictions read move to its start and the steps before leave through
/// [`StepHooks::on_final`] (handed out together, not one by one between solves).
pub(super) fn run(
    fg: &ForwardGraph,
    stepwise: &mut Stepwise,
    values: &mut [f64],
    steps: usize,
    hooks: &mut dyn StepHooks,
) -> Result<()> {
    let graph = &fg.graph;
    let s = graph.layout().size();
    let capacity = (values.len() / s).max(3);
    let (mut base, mut completed) = (0, steps);
    for j in 0..steps {
        let mut k = j - base;
        if k >= capacity {
            for i in base..j - 2 {
                hooks.on_final(i, &values[(i - base) * s..(i - base + 1) * s])?;
            }
            values.copy_within((k - 2) * s..k * s, 0);
            stepwise.shift_steps(k - 2);
            base += k - 2;
            k = 2;
        }
        let (report, taker) = if k == 0 {
            stepwise.first(graph, values)?
        } else {
            fg.predict(values, k);
            stepwise.step(graph, values, k, &mut |v, k, square| {
                hooks.rescue(v, (k, j), square)
            })?
        };
        if let Some(keep) = hooks.after((k, j), &report, taker, values) {
            completed = keep;
            break;
        }
    }
    for i in base..completed {
        hooks.on_final(i, &values[(i - base) * s..(i - base + 1) * s])?;
    }
    Ok(())
}
