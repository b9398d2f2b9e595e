//! A segment's steps taken one at a time ([`Schedule::Stepwise`]): each judged as
//! it is solved, rescued from substeps where it fails, and handed out once final.
//!
//! [`Schedule::Stepwise`]: super::plan::Schedule::Stepwise

use super::graph::ForwardGraph;
use super::judge::{Judge, Verdict};
use super::plan::STEPWISE_BUFFER;
use super::segment::{finish, Emit, Run, Segment};
use super::square_step::SquareStep;
use super::stepwise::{self, Rescued, StepHooks, Stepwise, Taker};
use super::substeps::Substeps;
use crate::convergence::SolveReport;
use crate::error::Result;
use std::ops::ControlFlow;

impl Segment<'_> {
    /// One step at a time; each step is final once judged.
    pub(super) fn stepwise(
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
            taken: (0, 0, 0),
        };
        stepwise::run(fg, &mut solver, &mut values, self.steps(), &mut hooks)?;
        let Steps {
            judge,
            reselect,
            taken: (square_steps, general_steps, paper_steps),
            ..
        } = hooks;
        run.square_steps += square_steps;
        run.general_steps += general_steps;
        run.paper_steps += paper_steps;
        finish(run, judge, None);
        Ok(reselect)
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
    /// Steps the square step, the general solver and the paper's integrators took.
    taken: (usize, usize, usize),
}

impl StepHooks for Steps<'_, '_> {
    fn rescue(
        &mut self,
        values: &mut [f64],
        (k, j): (usize, usize),
        square: Option<&SquareStep>,
    ) -> Option<Rescued> {
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
            Taker::Paper => self.taken.2 += 1,
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
