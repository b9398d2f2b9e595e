//! One segment of a forward run: its steps solved as the plan's schedule says,
//! with one set of coordinates, each judged as it is solved ([`Judge`]).

use super::failure::StepFailure;
use super::graph::ForwardGraph;
use super::judge::{Judge, Verdict};
use super::options::ForwardOptions;
use super::plan::{Plan, Schedule, STEPWISE_BUFFER};
use super::square_step::SquareStep;
use super::start::Start;
use super::stepwise::{self, StepHooks, Stepwise, Taker};
use super::substeps::Substeps;
use super::summary::{Iterations, Reselection};
use crate::convergence::SolveReport;
use crate::error::Result;
use crate::model::Model;
use std::ops::ControlFlow;
use std::sync::Arc;

/// What the segments of a run add up.
#[derive(Default)]
pub(super) struct Run {
    pub(super) iterations: Iterations,
    pub(super) failures: Vec<StepFailure>,
    pub(super) conditioned_from: Option<(usize, f64)>,
    pub(super) reselections: Vec<Reselection>,
    pub(super) interrupted: Option<usize>,
    /// Steps the square step took, and steps of a stepwise run the general solver took.
    pub(super) square_steps: usize,
    pub(super) general_steps: usize,
}

/// Where a segment hands its steps as they become final: `emit(step, t, block)` with
/// the run's step, its time and the step's variables (q, q̇, q̈ first, in model
/// order).
pub(super) type Emit<'a> = dyn FnMut(usize, f64, &[f64]) -> Result<()> + 'a;

/// A segment's part of the run: where it starts, and what it reports to.
pub(super) struct Segment<'a> {
    pub(super) model: Arc<Model>,
    /// The state step `first` starts from, and the independent coordinates (IC).
    pub(super) start: Start,
    pub(super) options: &'a ForwardOptions,
    pub(super) plan: &'a Plan,
    /// Run steps first..total.
    pub(super) first: usize,
    pub(super) total: usize,
}

impl Segment<'_> {
    /// Steps first..total of the run (the segment's start state is step `first`'s),
    /// handed to `emit` in order as they become final. Returns where (run step) and
    /// to which independent coordinates the next segment switches.
    pub(super) fn run(
        &self,
        progress: &mut dyn FnMut(usize, usize) -> ControlFlow<()>,
        run: &mut Run,
        emit: &mut Emit<'_>,
    ) -> Result<Option<(usize, Vec<usize>)>> {
        let mut fg = ForwardGraph::planned(
            self.model.clone(),
            self.plan,
            &self.options.noise,
            self.start.clone(),
        )?;
        fg.graph.set_t0(self.first as f64 * self.plan.dt);
        match self.plan.schedule {
            Schedule::Stepwise => self.stepwise(&fg, progress, run, emit),
            Schedule::FixedLag(window) => self.windows(&fg, window, progress, run, emit),
            Schedule::Batch => self.batch(&fg, progress, run, emit),
        }
    }

    pub(super) fn steps(&self) -> usize {
        self.total - self.first
    }

    pub(super) fn substeps<'b>(&'b self, fg: &ForwardGraph) -> Substeps<'b> {
        Substeps {
            model: &self.model,
            plan: self.plan,
            noise: &self.options.noise,
            independent: &self.start.independent,
            s: fg.graph.layout().size(),
        }
    }

    pub(super) fn judge<'b>(
        &'b self,
        progress: &'b mut dyn FnMut(usize, usize) -> ControlFlow<()>,
    ) -> Judge<'b> {
        Judge::new(
            &self.model,
            &self.start,
            self.options,
            (self.first, self.total),
            progress,
        )
    }

    /// One step at a time; each step is final once judged.
    fn stepwise(
        &self,
        fg: &ForwardGraph,
        progress: &mut dyn FnMut(usize, usize) -> ControlFlow<()>,
        run: &mut Run,
        emit: &mut Emit<'_>,
    ) -> Result<Option<(usize, Vec<usize>)>> {
        let s = fg.graph.layout().size();
        let square = super::square_step::for_plan(&self.model, self.plan, &self.start.independent);
        let mut solver = Stepwise::new(&fg.graph, square, self.plan.settings)?;
        if let Some(observers) = &self.options.observer {
            solver.observe(observers.make());
        }
        let mut values = vec![0.0; STEPWISE_BUFFER.min(self.steps()).max(3) * s];
        values[..s].copy_from_slice(&fg.initial_block(&self.model)?);
        let mut hooks = Steps {
            segment: self,
            fg,
            substeps: self.substeps(fg),
            judge: self.judge(progress),
            emit,
            reselect: None,
            taken: (0, 0),
        };
        stepwise::run(fg, &mut solver, &mut values, self.steps(), &mut hooks)?;
        let Steps {
            judge,
            reselect,
            taken: (square_steps, general_steps),
            ..
        } = hooks;
        run.square_steps += square_steps;
        run.general_steps += general_steps;
        finish(run, judge, None);
        Ok(reselect)
    }
}

/// What a segment's judge adds to the run.
pub(super) fn finish(run: &mut Run, judge: Judge<'_>, conditioned_from: Option<(usize, f64)>) {
    run.iterations.extend(judge.iterations);
    run.failures.extend(judge.failures);
    run.interrupted = run.interrupted.or(judge.interrupted);
    if run.conditioned_from.is_none() {
        run.conditioned_from = conditioned_from;
    }
}

/// The hooks of a segment's stepwise run.
struct Steps<'a, 'e> {
    segment: &'a Segment<'a>,
    fg: &'a ForwardGraph,
    substeps: Substeps<'a>,
    judge: Judge<'a>,
    emit: &'a mut Emit<'e>,
    reselect: Option<(usize, Vec<usize>)>,
    /// Steps the square step and the general solver took.
    taken: (usize, usize),
}

impl StepHooks for Steps<'_, '_> {
    fn rescue(
        &mut self,
        values: &mut [f64],
        (k, j): (usize, usize),
        square: Option<&SquareStep>,
    ) -> bool {
        self.substeps
            .guess(square, self.segment.first + j, values, k)
    }

    fn after(
        &mut self,
        (k, j): (usize, usize),
        report: &SolveReport,
        taker: Taker,
        values: &[f64],
    ) -> Option<usize> {
        match taker {
            Taker::Square => self.taken.0 += 1,
            Taker::General => self.taken.1 += 1,
        }
        let s = self.fg.graph.layout().size();
        let t = self.fg.graph.run_time(j);
        match self.judge.after((k, j, t), report, values, s) {
            Verdict::Continue => None,
            Verdict::Stop { keep } => Some(keep),
            Verdict::Reselect(set) => {
                self.reselect = Some((self.segment.first + j, set));
                Some(j + 1)
            }
        }
    }

    fn on_final(&mut self, j: usize, block: &[f64]) -> Result<()> {
        (self.emit)(self.segment.first + j, self.fg.graph.run_time(j), block)
    }
}
