//! One segment of a forward run: its steps solved as the plan's schedule says,
//! with one set of coordinates, each judged as it is solved ([`Judge`]).

use super::failure::StepFailure;
use super::graph::ForwardGraph;
use super::judge::Judge;
use super::options::{DcIntegrators, ForwardOptions};
use super::plan::{Plan, Rescue, Schedule};
use super::start::Start;
use super::substeps::Substeps;
use super::summary::{Iterations, Reselection};
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
    /// Steps taken by the paper's integrator factors where the run's own failed.
    pub(super) paper_steps: usize,
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
            paper: self.paper_plan(),
        }
    }

    /// The plan of one step under the paper's integrator factors, through the
    /// general smoother at N_w = 1: a failed step's last rescue.
    fn paper_plan(&self) -> Option<Plan> {
        if !self.plan.tries(Rescue::PaperIntegrators) || !self.plan.tangent_dc() {
            return None;
        }
        let mut options = self.options.clone();
        options.dc_integrators = DcIntegrators::Full;
        options.mode = crate::smoother::Mode::FixedLag(1);
        Plan::new(&self.model, &options).ok()
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
