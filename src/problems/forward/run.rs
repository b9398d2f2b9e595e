//! A forward run ([`simulate`]): the run in segments over the horizon, made again
//! with tangent integrator factors where the paper's fail, and at a finer step where
//! a step is too coarse for the motion.

use super::failure::non_finite_at;
use super::failure::StepFailure;
use super::options::ForwardOptions;
use super::plan::Plan;
use super::segment::{Run, Segment};
use super::start::Start;
use super::summary::{Refinement, Reselection, RunSummary, Stats};
use crate::error::Result;
use crate::model::{Model, State};
use crate::solver::{SolveReport, Termination};
use crate::trajectory::{round_time, Trajectory};
use nalgebra::DVector;
use std::ops::ControlFlow;
use std::sync::Arc;
use std::time::Instant;

/// Receives a forward run's states, in order, as they become final (a step that left
/// the fixed-lag smoother's window, or every step once a batch solve ended), so
/// that a caller can write them out instead of holding the run
/// ([`simulate_streaming`]). A [`Trajectory`] holds them all.
pub trait StepSink {
    /// The state of the next step at time `t` (the first call: the initial state).
    fn step(&mut self, t: f64, q: &[f64], dq: &[f64], ddq: &[f64]) -> Result<()>;
    /// The run starts again from its initial state (made again at a finer step):
    /// the steps received so far are void.
    fn restart(&mut self) -> Result<()>;
    /// A step of a refined run between two of the rows it hands to `step` (at the
    /// step's own time): ignored, but by a sink that integrates over every step taken
    /// ([`crate::derived::Steps`]).
    fn between(&mut self, _t: f64, _q: &[f64], _dq: &[f64], _ddq: &[f64]) -> Result<()> {
        Ok(())
    }
}

impl StepSink for Trajectory {
    fn step(&mut self, t: f64, q: &[f64], dq: &[f64], ddq: &[f64]) -> Result<()> {
        self.t.push(t);
        self.q.extend_from_slice(q);
        self.dq.extend_from_slice(dq);
        self.ddq.extend_from_slice(ddq);
        Ok(())
    }

    fn restart(&mut self) -> Result<()> {
        self.truncate(0);
        Ok(())
    }
}

/// Simulates the model's motion. `progress(done, total)` is called after each step.
pub fn simulate(
    model: Arc<Model>,
    options: &ForwardOptions,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<(Trajectory, RunSummary)> {
    simulate_interruptible(model, options, &mut |done, total| {
        progress(done, total);
        ControlFlow::Continue(())
    })
}

/// [`simulate`], where `progress` returning `Break` after a step ends the run there
/// (a user's Ctrl-C): the steps solved so far are returned, and
/// [`RunSummary::interrupted`] names the last one. A batch through the general solver
/// ([`Schedule::Batch`](super::Schedule::Batch)) is interrupted only during its
/// one-step start, and then returns no step.
///
/// In independent coordinates the run goes in segments: where the coordinates in use
/// approach a configuration where they stop determining the others while Φ_q keeps
/// its rank, the segment ends at the current step and the next one starts there with
/// a well-conditioned set chosen from q ([`Determinacy::reselect`]), conditioned on
/// that step's state (its graph's initial priors), as generalized coordinate
/// partitioning does. Where Φ_q itself loses rank no set helps: the run stops.
pub fn simulate_interruptible(
    model: Arc<Model>,
    options: &ForwardOptions,
    progress: &mut dyn FnMut(usize, usize) -> ControlFlow<()>,
) -> Result<(Trajectory, RunSummary)> {
    // The trajectory of every step is held too.
    options.check_memory(&model, true)?;
    let mut trajectory = Trajectory {
        names: model.names.clone(),
        t: Vec::new(),
        q: Vec::new(),
        dq: Vec::new(),
        ddq: Vec::new(),
    };
    let summary = simulate_streaming(model, options, progress, &mut trajectory)?;
    Ok((trajectory, summary))
}

/// [`simulate_interruptible`], handing the steps to `sink` as they become final
/// instead of returning them: what `sink` receives, up to its last
/// [`StepSink::restart`], is the trajectory [`simulate_interruptible`] returns, to
/// the bit. With the fixed-lag smoother the run holds a few thousand steps whatever
/// its length; a batch solve holds every step (its linear system spans them all),
/// and hands them out when it ends.
///
/// A run made again at a finer step ([`ForwardOptions::refine`]) restarts the sink: a writer that
/// cannot take back what it wrote should hold its output until the run ends.
pub fn simulate_streaming(
    model: Arc<Model>,
    options: &ForwardOptions,
    progress: &mut dyn FnMut(usize, usize) -> ControlFlow<()>,
    sink: &mut dyn StepSink,
) -> Result<RunSummary> {
    if let Some(tolerance) = options.tolerance {
        // Its steps are sized by the error they make: no refinement; a run whose rows
        // miss the tolerance is made again at a tighter one (the sink restarted).
        return match options.tolerance_scope {
            super::ToleranceScope::Run => {
                super::run_check::simulate(model, options, tolerance, progress, sink)
            }
            super::ToleranceScope::Steps => {
                super::adaptive::simulate(model, options, tolerance, 1.0, progress, sink)
            }
        };
    }
    let (mut summary, mut coarse) = simulate_with(model.clone(), options, progress, sink, None)?;
    if !options.refine {
        // Refinement off: a run that converged over a step too coarse for the
        // motion fails there (its answer is a poor one, see below), named as such.
        if summary.failures.is_empty() && summary.interrupted.is_none() {
            summary.failures.extend(coarse);
        }
        return Ok(summary);
    }
    // A step too coarse for the motion: the implicit equations of a step over which a
    // body turns a radian or more have no nearby solution, at any window. The run is
    // made again at a step that keeps the turn near TARGET_TURN, as many times as the
    // finer run still fails that way, and the output stays on the grid asked for.
    let mut factor: usize = 1;
    while summary.interrupted.is_none() {
        let failure = match summary.failures.first() {
            Some(f) if f.singular.is_none() => f.clone(),
            Some(_) => break,
            // A run that converged while a body turned more than LARGE_TURN a step
            // converged to a poor answer, and so did a finer run whose motion sped up
            // after the step the first failure measured: both are refined from that
            // step (docs/robustness.md, "Refinement of a step too coarse").
            None => match coarse.take() {
                Some(f) => f,
                None => break,
            },
        };
        let Some(next) = refinement_factor(&failure, factor) else {
            break;
        };
        factor = next;
        let mut finer = options.clone();
        finer.dt = options.dt / factor as f64;
        finer.t_end = (options.steps().saturating_sub(1) * factor) as f64 * finer.dt;
        sink.restart()?;
        let (mut fine_summary, fine_coarse) = simulate_with(
            model.clone(),
            &finer,
            progress,
            sink,
            Some((factor, options.dt)),
        )?;
        fine_summary.wall_time += summary.wall_time;
        fine_summary.refinement = Some(Refinement {
            factor,
            dt: finer.dt,
            after: failure,
        });
        summary = fine_summary;
        coarse = fine_coarse;
    }
    Ok(summary)
}

/// What one attempt of a run does with each step as it becomes final: the checks
/// the whole trajectory was checked for (a non-finite state ends it there, the first
/// step too coarse for the motion is noted), the summary's measures, and the rows
/// passed on to the sink (every `factor`-th of a refined run, on the grid asked for).
struct Rows<'a> {
    model: &'a Model,
    sink: &'a mut dyn StepSink,
    /// The attempt's time step.
    dt: f64,
    /// A refined attempt: internal steps per row, and the row spacing asked for.
    every: Option<(usize, f64)>,
    /// Steps taken (the attempt's trajectory so far), rows passed on.
    len: usize,
    written: usize,
    stats: Stats,
    /// The last step taken: its time and state (q, q̇, q̈).
    last_t: f64,
    last: Vec<f64>,
    /// The first step whose state is not finite: it and the steps after are dropped.
    non_finite: Option<StepFailure>,
    /// The first step over which a body turned more than [`StepFailure::LARGE_TURN`].
    coarse: Option<StepFailure>,
}

impl<'a> Rows<'a> {
    fn new(
        model: &'a Model,
        options: &ForwardOptions,
        sink: &'a mut dyn StepSink,
        every: Option<(usize, f64)>,
    ) -> Self {
        Rows {
            model,
            sink,
            dt: options.dt,
            every,
            len: 0,
            written: 0,
            stats: Stats::new(model, options.integrator),
            last_t: 0.0,
            last: Vec::with_capacity(3 * model.n()),
            non_finite: None,
            coarse: None,
        }
    }

    /// Takes the next step (its state q, q̇, q̈ at `block`'s start, at time t).
    fn take(&mut self, t: f64, block: &[f64]) -> Result<()> {
        if self.non_finite.is_some() {
            return Ok(());
        }
        let n = self.model.n();
        let (q, dq, ddq) = (&block[..n], &block[n..2 * n], &block[2 * n..3 * n]);
        let k = self.len;
        let before = if k > 0 {
            (&self.last[..n], &self.last[n..2 * n])
        } else {
            (q, dq)
        };
        if let Some(f) = non_finite_at(self.model, k, t, (q, dq, ddq), before)? {
            self.non_finite = Some(f);
            return Ok(());
        }
        self.stats.add(self.model, t, q, dq)?;
        if k > 0 {
            let before = (self.last_t, &self.last[..n], &self.last[n..2 * n]);
            self.stats.watch(self.model, before, t, q, dq);
            let before = (self.last_t, &self.last[..3 * n]);
            self.stats.balance(self.model, before, t, &block[..3 * n]);
        }
        if self.coarse.is_none() {
            self.coarse = coarse_turn(self.model, q, dq, t, self.dt, k);
        }
        match self.every {
            None => {
                self.sink.step(t, q, dq, ddq)?;
                self.written += 1;
            }
            Some((factor, dt)) if k % factor == 0 => {
                self.sink.step(self.written as f64 * dt, q, dq, ddq)?;
                self.written += 1;
            }
            Some(_) => self.sink.between(t, q, dq, ddq)?,
        }
        self.len += 1;
        self.last_t = t;
        self.last.clear();
        self.last.extend_from_slice(&block[..3 * n]);
        Ok(())
    }
}

/// Whether a body turned more than [`StepFailure::LARGE_TURN`] over the step after
/// step k (state q, q̇ at time t) of a converged run: a failure to refine from, or
/// with refinement off to report ([`StepFailure::is_too_coarse`]: its solve
/// converged).
fn coarse_turn(
    model: &Model,
    q: &[f64],
    dq: &[f64],
    t: f64,
    dt: f64,
    k: usize,
) -> Option<StepFailure> {
    let (body, omega) = model.fastest_body_index(q, dq)?;
    let turn = omega * dt;
    (turn > StepFailure::LARGE_TURN).then(|| StepFailure {
        step: k + 1,
        t: t + dt,
        report: SolveReport::new(Termination::Converged, 0, 0.0),
        constraint_conditioning: 1.0,
        singular: None,
        warm_start: false,
        batch: false,
        cause: None,
        fast_body: Some((model.scene.bodies[body].name.clone(), turn)),
    })
}

/// The refinement factor a run at `factor` times finer than asked goes to after
/// `failure`: one that keeps the turn of its fastest body near
/// [`Refinement::TARGET_TURN`] a step; `None` where the body turned less than
/// [`Refinement::MIN_TURN`] (the step's size is not the cause) or that would pass
/// [`Refinement::MAX_FACTOR`].
fn refinement_factor(failure: &StepFailure, factor: usize) -> Option<usize> {
    let turn = match &failure.fast_body {
        Some((_, turn)) if *turn >= Refinement::MIN_TURN => *turn,
        _ => return None,
    };
    let more = ((turn / Refinement::TARGET_TURN).ceil() as usize).max(2);
    let next = factor.saturating_mul(more);
    (next <= Refinement::MAX_FACTOR).then_some(next)
}

fn simulate_with(
    model: Arc<Model>,
    options: &ForwardOptions,
    progress: &mut dyn FnMut(usize, usize) -> ControlFlow<()>,
    sink: &mut dyn StepSink,
    every: Option<(usize, f64)>,
) -> Result<(RunSummary, Option<StepFailure>)> {
    let plan = Plan::new(&model, options)?;
    let total = plan.steps;
    let start = Instant::now();
    let mut run = Run::default();
    let mut rows = Rows::new(&model, options, sink, every);
    // The first segment starts from the scene's start; a later one from the state
    // the one before ended with, in the coordinates it re-selected.
    let mut segment_start = Start::of(&model);
    let mut first = 0;
    loop {
        let segment = Segment {
            model: model.clone(),
            start: segment_start,
            options,
            plan: &plan,
            first,
            total,
        };
        let next = segment
            .run(progress, &mut run, &mut |j, t, block| {
                if j == first && first > 0 {
                    return Ok(());
                }
                rows.take(t, block)
            })?
            .filter(|_| run.interrupted.is_none());
        let Some((k, independent)) = next else { break };
        let n = model.n();
        run.reselections.push(Reselection {
            step: k,
            t: round_time(rows.last_t),
            from: names_of(&model, &segment.start.independent),
            to: names_of(&model, &independent),
        });
        debug_assert_eq!(
            rows.len,
            k + 1,
            "a segment ends at the step it re-selects at"
        );
        // The rest of the run continues from step k (its row is kept from this
        // segment; the next segment's first row is the same state).
        segment_start = Start {
            state: State {
                q: DVector::from_column_slice(&rows.last[..n]),
                dq: DVector::from_column_slice(&rows.last[n..2 * n]),
            },
            independent,
        };
        first = k;
    }
    if let Some(f) = rows.non_finite.take() {
        // The steps before it were kept; the step itself is a failure, named.
        run.failures.retain(|g| g.step < f.step);
        run.failures.push(f);
    }
    let wall_time = start.elapsed();
    let mut summary = rows
        .stats
        .finish(wall_time, run.iterations, run.failures, plan);
    summary.square_steps = run.square_steps;
    summary.general_steps = run.general_steps;
    summary.paper_steps = run.paper_steps;
    summary.steps = rows.written;
    summary.conditioned_from = run.conditioned_from;
    summary.reselections = run.reselections;
    summary.interrupted = run.interrupted;
    Ok((summary, rows.coarse))
}

pub(super) fn names_of(model: &Model, idx: &[usize]) -> Vec<String> {
    idx.iter().map(|&i| model.names[i].clone()).collect()
}
