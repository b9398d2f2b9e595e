//! What a run decides after each step's solve ([`Judge`]): go on, stop (and
//! which steps are kept), or go on with other independent coordinates; with the
//! failures it names and the work it counts.

use super::failure::StepFailure;
use super::start::Start;
use super::summary::Iterations;
use crate::convergence::{SolveReport, Termination};
use crate::kinematics::{constraint_conditioning, Watch, Watched};
use crate::model::Model;
use std::ops::ControlFlow;

/// The decision after a step j of a segment (its first step is 0).
#[derive(Debug, Clone, PartialEq)]
pub(super) enum Verdict {
    Continue,
    /// The segment ends with its steps before `keep` (j, or j + 1 to keep step j).
    Stop {
        keep: usize,
    },
    /// The segment ends at step j, kept; the next starts there with these
    /// independent coordinates.
    Reselect(Vec<usize>),
}

/// The judge of a segment's steps.
pub(super) struct Judge<'a> {
    model: &'a Model,
    /// The segment's start configuration: the coordinates' scales of the
    /// conditioning a failure quotes.
    q0: &'a [f64],
    dt: f64,
    /// The run step of the segment's first step, and the run's steps.
    first: usize,
    total: usize,
    continue_on_failure: bool,
    progress: &'a mut dyn FnMut(usize, usize) -> ControlFlow<()>,
    /// In independent coordinates, how well they determine the others.
    watch: Option<Watch>,
    pub(super) iterations: Iterations,
    pub(super) failures: Vec<StepFailure>,
    pub(super) interrupted: Option<usize>,
}

impl<'a> Judge<'a> {
    pub(super) fn new(
        model: &'a Model,
        start: &'a Start,
        options: &super::ForwardOptions,
        (first, total): (usize, usize),
        progress: &'a mut dyn FnMut(usize, usize) -> ControlFlow<()>,
    ) -> Self {
        let independent = options.coordinates == crate::coordinates::Coordinates::Independent;
        let q0 = start.state.q.as_slice();
        Judge {
            model,
            q0,
            dt: options.dt,
            first,
            total,
            continue_on_failure: options.continue_on_failure,
            progress,
            watch: independent.then(|| Watch::new(model, &start.independent, q0)),
            iterations: Iterations::default(),
            failures: Vec::new(),
            interrupted: None,
        }
    }

    /// After step k of `values` (segment step j, time t; `s` unknowns a step)
    /// was solved with `report`.
    pub(super) fn after(
        &mut self,
        (k, j, t): (usize, usize, f64),
        report: &SolveReport,
        values: &[f64],
        s: usize,
    ) -> Verdict {
        self.iterations.push(report);
        // Asked to stop: after this step's own outcome is recorded.
        let stop = (self.progress)(self.first + j + 1, self.total).is_break();
        let n = self.model.n();
        let q_at = |i: usize| &values[i * s..i * s + n];
        if report.termination != Termination::Converged {
            let mut f = self.failure((k, j, t), report, values, s);
            if let Some(watch) = self.watch.as_mut() {
                // A solve that fails while z and every other set of coordinates
                // approach a rank loss fails because of it. A step too coarse for the
                // motion fails for that reason: in a violent transient s moves fast too.
                let too_coarse = f
                    .fast_body
                    .as_ref()
                    .is_some_and(|(_, turn)| *turn > StepFailure::LARGE_TURN);
                let last_two = (q_at(k.max(2) - 2), q_at(k.max(1) - 1));
                if let Some(singular) =
                    watch.attribute(self.model, j, self.dt, last_two, too_coarse)
                {
                    f.singular = Some(singular);
                    self.failures.push(f);
                    return Verdict::Stop { keep: j };
                }
            }
            self.failures.push(f);
            if !self.continue_on_failure || report.termination == Termination::Diverged {
                // The failed step is left out of the trajectory.
                return Verdict::Stop { keep: j };
            }
        }
        if let Some(watch) = self.watch.as_mut() {
            match watch.observe(self.model, j, t, q_at(k.max(1) - 1), q_at(k)) {
                Watched::Continue => {}
                Watched::Reselect(set) => return Verdict::Reselect(set),
                Watched::Stop(singular) => {
                    let mut f = self.failure((k, j, t), report, values, s);
                    f.singular = Some(singular);
                    self.failures.push(f);
                    return Verdict::Stop { keep: j };
                }
            }
        }
        if stop {
            // Interrupted: this step is kept as the last one.
            self.interrupted = Some(self.first + j);
            return Verdict::Stop { keep: j + 1 };
        }
        Verdict::Continue
    }

    /// The failure of step k of `values` (segment step j, time t).
    pub(super) fn failure(
        &self,
        (k, j, t): (usize, usize, f64),
        report: &SolveReport,
        values: &[f64],
        s: usize,
    ) -> StepFailure {
        let model = self.model;
        let n = model.n();
        let at = |i: usize| (&values[i * s..i * s + n], &values[i * s + n..i * s + 2 * n]);
        // A non-finite cost: look for the effect that cannot be evaluated, at the
        // step's state or, where that is not finite, at the step before's.
        let cause = (!report.cost.is_finite()).then(|| {
            let (mut q, mut dq) = at(k);
            if !q.iter().chain(dq).all(|x| x.is_finite()) {
                (q, dq) = at(k.saturating_sub(1));
            }
            model.effect_fault(q, dq, t)
        });
        StepFailure {
            step: self.first + j,
            t,
            report: report.clone(),
            constraint_conditioning: constraint_conditioning(model, self.q0, at(k).0),
            singular: None,
            warm_start: false,
            batch: false,
            // The effect at fault where one is; else why the solve's evaluation failed.
            cause: cause.flatten().or_else(|| report.cause.clone()),
            fast_body: self.fast_body(k, values, s),
        }
    }

    /// The body turning fastest over step k: its turn estimated from the step
    /// before's velocities and accelerations (the rate at mid-step), so that a run
    /// from rest is measured too.
    fn fast_body(&self, k: usize, values: &[f64], s: usize) -> Option<(String, f64)> {
        let n = self.model.n();
        let before = &values[k.checked_sub(1)? * s..k * s];
        let mid: Vec<f64> = (0..n)
            .map(|i| before[n + i] + 0.5 * self.dt * before[2 * n + i])
            .collect();
        let (body, omega) = self.model.fastest_body(&before[..n], &mid)?;
        Some((body, omega * self.dt))
    }
}
