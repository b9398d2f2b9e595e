//! A segment's steps through the general solver: the fixed-lag smoother over N_w
//! steps, or the batch of the whole segment from a one-step start.

use super::failure::StepFailure;
use super::graph::ForwardGraph;
use super::judge::{Judge, Verdict};
use super::options::Observers;
use super::plan::Schedule;
use super::segment::{finish, Emit, Run, Segment};
use super::substeps::Substeps;
use crate::convergence::{SolveReport, Termination};
use crate::error::Result;
use crate::smoother::{self, FixedLag, Hooks, Next};
use crate::solver::{Observer, WindowSolver};
use crate::trajectory::round_time;
use std::ops::ControlFlow;

/// The hooks of a segment's fixed-lag run.
struct Windows<'a, 'e> {
    fg: &'a ForwardGraph,
    first: usize,
    judge: Judge<'a>,
    substeps: Substeps<'a>,
    emit: &'a mut Emit<'e>,
    /// The segment's steps before this one are kept.
    completed: usize,
    reselect: Option<(usize, Vec<usize>)>,
    conditioned_from: Option<(usize, f64)>,
    observers: Option<Observers>,
}

impl Hooks for Windows<'_, '_> {
    fn predict(&mut self, values: &mut [f64], k: usize) {
        self.fg.predict(values, k);
    }

    fn rescue(&mut self, values: &mut [f64], k: usize, run_k: usize) -> bool {
        self.substeps
            .guess(None, self.first + run_k, values, k)
            .is_some()
    }

    fn on_step(&mut self, k: usize, j: usize, report: &SolveReport, values: &[f64]) -> Next {
        let s = self.fg.graph.layout().size();
        let t = self.fg.graph.run_time(j);
        match self.judge.after((k, j, t), report, values, s) {
            Verdict::Continue => return Next::Continue,
            Verdict::Stop { keep } => self.completed = keep,
            Verdict::Reselect(set) => {
                self.reselect = Some((self.first + j, set));
                self.completed = j + 1;
            }
        }
        Next::Stop
    }

    fn on_switch(&mut self, _: usize, j: usize) {
        let t = round_time(self.fg.graph.run_time(j));
        self.conditioned_from = Some((self.first + j, t));
    }

    fn observer(&mut self) -> Option<Box<dyn Observer>> {
        self.observers.as_ref().map(Observers::make)
    }

    fn on_final(&mut self, j: usize, block: &[f64]) -> Result<()> {
        (self.emit)(self.first + j, self.fg.graph.run_time(j), block)
    }
}

impl Segment<'_> {
    /// The fixed-lag smoother over `window` steps, in a buffer of a few thousand
    /// steps whatever the segment's length.
    pub(super) fn windows(
        &self,
        fg: &ForwardGraph,
        window: usize,
        progress: &mut dyn FnMut(usize, usize) -> ControlFlow<()>,
        run: &mut Run,
        emit: &mut Emit<'_>,
    ) -> Result<Option<(usize, Vec<usize>)>> {
        let s = fg.graph.layout().size();
        let steps = self.steps();
        let capacity = smoother::stream_capacity(window).min(steps);
        let mut values = vec![0.0; capacity * s];
        values[..s].copy_from_slice(&fg.initial_block(&self.model)?);
        let mut hooks = Windows {
            fg,
            first: self.first,
            judge: self.judge(progress),
            substeps: self.substeps(fg),
            emit,
            completed: steps,
            reselect: None,
            conditioned_from: None,
            observers: self.options.observer.clone(),
        };
        let horizon = FixedLag {
            steps,
            window,
            settings: self.plan.settings,
            capacity: Some(capacity),
        };
        let end = smoother::fixed_lag(&fg.graph, &mut values, &horizon, &mut hooks)?;
        // The steps still in the buffer: final now.
        for j in end.handed..hooks.completed {
            let b = (j - end.base) * s;
            (hooks.emit)(self.first + j, fg.graph.run_time(j), &values[b..b + s])?;
        }
        let Windows {
            judge,
            reselect,
            conditioned_from,
            ..
        } = hooks;
        finish(run, judge, conditioned_from);
        Ok(reselect)
    }

    /// The batch: the one-step run of this segment (which may end it where the
    /// independent coordinates are re-selected) as its start, then all of it at once.
    pub(super) fn batch(
        &self,
        fg: &ForwardGraph,
        progress: &mut dyn FnMut(usize, usize) -> ControlFlow<()>,
        run: &mut Run,
        emit: &mut Emit<'_>,
    ) -> Result<Option<(usize, Vec<usize>)>> {
        let s = fg.graph.layout().size();
        let mut values = vec![0.0; self.steps() * s];
        let mut warm_plan = self.plan.clone();
        warm_plan.schedule = Schedule::FixedLag(1);
        let warm_segment = Segment {
            plan: &warm_plan,
            model: self.model.clone(),
            start: self.start.clone(),
            ..*self
        };
        let mut warm = Run::default();
        // Its steps go straight into the batch's variables.
        let mut rows = 0;
        let n = self.model.n();
        let reselect = warm_segment.run(progress, &mut warm, &mut |j, _, block| {
            let (q, rest) = block.split_at(n);
            let (dq, rest) = rest.split_at(n);
            fg.fill_step(q, dq, &rest[..n], j - self.first, &mut values);
            rows = j - self.first + 1;
            Ok(())
        })?;
        let completed = if warm.interrupted.is_some() {
            // The one-step start is not the batch solution: nothing to return.
            run.interrupted = warm.interrupted;
            0
        } else if let Some(f) = warm.failures.iter().find(|f| f.singular.is_some()) {
            // Ill-posed ahead: no batch solve of the whole horizon exists.
            run.failures.push(f.clone());
            0
        } else if let Some(f) = warm.failures.first() {
            // No batch solve without its start: the step that failed there ends
            // the run, named as such.
            run.failures.push(StepFailure {
                warm_start: true,
                ..f.clone()
            });
            0
        } else {
            let mut solver = WindowSolver::new(&fg.graph, rows, self.plan.settings)?;
            if let Some(observers) = &self.options.observer {
                solver.observe(observers.make());
            }
            let report = solver.solve(&fg.graph, &mut values, 0, rows, None)?;
            run.iterations.push(&report);
            if report.termination != Termination::Converged {
                let mut go_on = |_, _| ControlFlow::Continue(());
                let judge = self.judge(&mut go_on);
                let k = rows - 1;
                let t = fg.graph.run_time(k);
                run.failures.push(StepFailure {
                    batch: true,
                    ..judge.failure((k, k, t), &report, &values, s)
                });
            }
            rows
        };
        for k in 0..completed {
            emit(
                self.first + k,
                fg.graph.run_time(k),
                &values[k * s..(k + 1) * s],
            )?;
        }
        Ok(reselect.filter(|_| completed > 0))
    }
}
