//! The substep rescue of a failed step: a guess for it from the step before,
//! integrated over the step in [`SUBSTEPS`] substeps by the same graph at the
//! finer step, one step at a time. Where a step's own solve fails from the Taylor
//! guess (a coarse step through a fast or stiff stretch, whose implicit equations
//! Newton's method does not reach from so far), this guess lies within the step's
//! error of its solution.

use super::graph::ForwardGraph;
use super::options::NoiseModels;
use super::plan::{Plan, Schedule};
use super::square_step::SquareStep;
use super::start::Start;
use super::stepwise::{self, Rescued, StepHooks, Stepwise, Taker};
use crate::convergence::{SolveReport, Termination};
use crate::model::{Model, State};
use crate::smoother::{self, FixedLag, Hooks, Next};
use nalgebra::DVector;
use std::sync::Arc;

/// The substep counts tried, in turn: a few, then finer (at most 74 substep solves
/// per failed step).
const SUBSTEPS: [usize; 3] = [2, 8, 64];

/// Iterations a substep's solve gets: a step 8–64 times finer than one that failed
/// converges in a few, or that count of substeps is given up.
const SUBSTEP_ITERATIONS: usize = 10;

/// What a failed step's rescue needs of its run.
pub(super) struct Substeps<'a> {
    pub(super) model: &'a Arc<Model>,
    pub(super) plan: &'a Plan,
    pub(super) noise: &'a NoiseModels,
    /// The segment's independent coordinates (IC).
    pub(super) independent: &'a [usize],
    /// The graph's step layout: unknowns a step, and n.
    pub(super) s: usize,
    /// In DC with tangent integrator factors, the plan of a step under the
    /// paper's: tried where the substeps fail.
    pub(super) paper: Option<Plan>,
}

/// The substep counts of a step under the paper's integrator factors.
const PAPER_SUBSTEPS: [usize; 3] = [1, 2, 8];

impl Substeps<'_> {
    /// Writes a guess for step k of `values` (run step `step`) from step k − 1:
    /// the end of substeps of the run's own equations, or else the step's solution
    /// under the paper's integrator factors (in 1, 2 or 8 substeps); `None` where
    /// none converged. `square`: the run's square step, whose analysis the
    /// substeps reuse.
    pub(super) fn guess(
        &self,
        square: Option<&SquareStep>,
        step: usize,
        values: &mut [f64],
        k: usize,
    ) -> Option<Rescued> {
        if self.fine_guess(self.plan, &SUBSTEPS, square, step, values, k) {
            return Some(Rescued::Guess);
        }
        let paper = self.paper.as_ref()?;
        self.fine_guess(paper, &PAPER_SUBSTEPS, None, step, values, k)
            .then_some(Rescued::Paper)
    }

    /// Whether one of the substep counts of `plan` converged (its end then in
    /// step k of `values`).
    fn fine_guess(
        &self,
        plan: &Plan,
        counts: &[usize],
        square: Option<&SquareStep>,
        step: usize,
        values: &mut [f64],
        k: usize,
    ) -> bool {
        let (n, s) = (self.model.n(), self.s);
        let before = &values[(k - 1) * s..k * s];
        let start = Start {
            state: State {
                q: DVector::from_column_slice(&before[..n]),
                dq: DVector::from_column_slice(&before[n..2 * n]),
            },
            independent: self.independent.to_vec(),
        };
        for &substeps in counts {
            let mut fine = plan.clone();
            fine.dt = plan.dt / substeps as f64;
            fine.steps = substeps + 1;
            fine.settings.max_iterations = fine.settings.max_iterations.min(SUBSTEP_ITERATIONS);
            let graph = ForwardGraph::planned(self.model.clone(), &fine, self.noise, start.clone());
            let Ok(mut graph) = graph else {
                return false;
            };
            graph.graph.set_t0((step - 1) as f64 * plan.dt);
            let Ok(first) = graph.initial_block(self.model) else {
                return false;
            };
            let mut fine_values = vec![0.0; (substeps + 1) * s];
            fine_values[..s].copy_from_slice(&first);
            let converged = if fine.schedule == Schedule::Stepwise {
                let square = square.and_then(|q| q.at_dt(fine.dt));
                run_stepwise(&graph, square, &fine, &mut fine_values)
            } else {
                run_window(&graph, &fine, &mut fine_values)
            };
            if converged {
                values[k * s..(k + 1) * s].copy_from_slice(&fine_values[substeps * s..]);
                return true;
            }
        }
        false
    }
}

/// Whether every substep converged, one at a time.
fn run_stepwise(
    graph: &ForwardGraph,
    square: Option<SquareStep>,
    fine: &Plan,
    values: &mut [f64],
) -> bool {
    let Ok(mut solver) = Stepwise::new(&graph.graph, square, fine.settings) else {
        return false;
    };
    struct Converged(bool);
    impl StepHooks for Converged {
        fn after(
            &mut self,
            _: (usize, usize),
            report: &SolveReport,
            _: Taker,
            _: &[f64],
        ) -> Option<usize> {
            self.0 &= report.termination == Termination::Converged;
            (!self.0).then_some(0)
        }
    }
    let mut converged = Converged(true);
    let solved = stepwise::run(graph, &mut solver, values, fine.steps, &mut converged);
    let converged = converged.0;
    solved.is_ok() && converged
}

/// Whether every substep converged, in the one-step window of the general smoother.
fn run_window(graph: &ForwardGraph, fine: &Plan, values: &mut [f64]) -> bool {
    struct Fine<'a> {
        graph: &'a ForwardGraph,
        converged: bool,
    }
    impl Hooks for Fine<'_> {
        fn predict(&mut self, values: &mut [f64], k: usize) {
            self.graph.predict(values, k);
        }
        fn on_step(&mut self, _: usize, _: usize, report: &SolveReport, _: &[f64]) -> Next {
            self.converged &= report.termination == Termination::Converged;
            if self.converged {
                Next::Continue
            } else {
                Next::Stop
            }
        }
    }
    let mut hooks = Fine {
        graph,
        converged: true,
    };
    let run = FixedLag {
        steps: fine.steps,
        window: 1,
        settings: fine.settings,
        capacity: None,
    };
    let solved = smoother::fixed_lag(&graph.graph, values, &run, &mut hooks);
    solved.is_ok() && hooks.converged
}
