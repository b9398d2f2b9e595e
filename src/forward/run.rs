//! A forward run ([`simulate`]): the run in segments over the horizon, made again
//! with tangent integrator factors where the paper's fail, and at a finer step where
//! a step is too coarse for the motion.

use super::failure::first_non_finite;
use super::failure::StepFailure;
use super::options::{DcIntegrators, ForwardOptions};
use super::segment::{segment, Run};
use super::summary::summarize;
use super::summary::{Refinement, Reselection, RunSummary};
use crate::error::Result;
use crate::model::Model;
use crate::solver::{SolveReport, Termination};
use crate::trajectory::{round_time, Trajectory};
use std::ops::ControlFlow;
use std::sync::Arc;
use std::time::Instant;

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
/// [`RunSummary::interrupted`] names the last one. A batch solve is interrupted only
/// during its one-step start, and then returns no step.
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
    let (mut trajectory, mut summary) = simulate_integrators(model.clone(), options, progress)?;
    if !options.refine {
        return Ok((trajectory, summary));
    }
    // A step too coarse for the motion: the implicit equations of a step over which a
    // body turns a radian or more have no nearby solution, at any window. The run is
    // made again at a step that keeps the turn near TARGET_TURN, as many times as the
    // finer run still fails that way, and the output stays on the grid asked for.
    let mut factor: usize = 1;
    // The unsampled motion of the last refined run, for the check of its turns.
    let mut fine: Option<(Trajectory, f64)> = None;
    while summary.interrupted.is_none() {
        let failure = match summary.failures.first() {
            Some(f) if f.singular.is_none() => f.clone(),
            Some(_) => break,
            // A run that converged while a body turned more than LARGE_TURN a step
            // converged to a poor answer (Andrews' squeezer at 1 ms, 0.9-1.3 rad a
            // step, ended 7e-4 m off where its failed 5 ms run, refined, ended 5e-5
            // m off); so does a finer run whose motion sped up after the step the
            // first failure measured: both are refined from that step.
            None => {
                let (tr, dt) = fine
                    .as_ref()
                    .map_or((&trajectory, options.dt), |(tr, dt)| (tr, *dt));
                match coarse_turn(&model, tr, dt) {
                    Some(f) => f,
                    None => break,
                }
            }
        };
        let turn = match &failure.fast_body {
            Some((_, turn)) if *turn >= Refinement::MIN_TURN => *turn,
            _ => break,
        };
        let more = ((turn / Refinement::TARGET_TURN).ceil() as usize).max(2);
        let next = factor.saturating_mul(more);
        if next > Refinement::MAX_FACTOR {
            break;
        }
        factor = next;
        let mut finer = options.clone();
        finer.dt = options.dt / factor as f64;
        finer.t_end = (options.steps().saturating_sub(1) * factor) as f64 * finer.dt;
        let (fine_trajectory, mut fine_summary) =
            simulate_integrators(model.clone(), &finer, progress)?;
        fine_summary.wall_time += summary.wall_time;
        fine_summary.refinement = Some(Refinement {
            factor,
            dt: finer.dt,
            after: failure,
        });
        trajectory = fine_trajectory.every(factor, options.dt);
        fine_summary.steps = trajectory.len();
        summary = fine_summary;
        fine = Some((fine_trajectory, finer.dt));
    }
    Ok((trajectory, summary))
}

/// The first step of a converged run over which a body turned more than
/// [`StepFailure::LARGE_TURN`], as a failure to refine from (its solve converged).
fn coarse_turn(model: &Model, trajectory: &Trajectory, dt: f64) -> Option<StepFailure> {
    (0..trajectory.len()).find_map(|k| {
        let (body, omega) = model.fastest_body(trajectory.q_at(k), trajectory.dq_at(k))?;
        let turn = omega * dt;
        (turn > StepFailure::LARGE_TURN).then(|| StepFailure {
            step: k + 1,
            t: trajectory.t[k] + dt,
            report: SolveReport::new(Termination::Converged, 0, 0.0),
            constraint_conditioning: 1.0,
            singular: None,
            warm_start: false,
            batch: false,
            cause: None,
            fast_body: Some((body, turn)),
        })
    })
}

/// One run at `options.dt`; with [`DcIntegrators::Auto`], made again with tangent
/// integrators where the paper's do not converge.
fn simulate_integrators(
    model: Arc<Model>,
    options: &ForwardOptions,
    progress: &mut dyn FnMut(usize, usize) -> ControlFlow<()>,
) -> Result<(Trajectory, RunSummary)> {
    let (trajectory, summary) = simulate_with(model.clone(), options, progress)?;
    let retry = options.retries_tangent()
        && summary.interrupted.is_none()
        && summary.failures.iter().all(|f| f.singular.is_none());
    let Some(failure) = summary.failures.first().filter(|_| retry) else {
        return Ok((trajectory, summary));
    };
    // The paper's factors ask more equations than a step has unknowns; where their
    // least-squares compromise does not converge, the tangent ones (one equation per
    // unknown) usually do.
    let failure = failure.clone();
    let mut tangent = options.clone();
    tangent.dc_integrators = DcIntegrators::Tangent;
    let first_attempt = summary.wall_time;
    let (trajectory, mut summary) = simulate_with(model, &tangent, progress)?;
    summary.tangent_after = Some(failure);
    summary.wall_time += first_attempt;
    Ok((trajectory, summary))
}

fn simulate_with(
    model: Arc<Model>,
    options: &ForwardOptions,
    progress: &mut dyn FnMut(usize, usize) -> ControlFlow<()>,
) -> Result<(Trajectory, RunSummary)> {
    options.validate(&model)?;
    let total = options.steps();
    let start = Instant::now();
    let mut run = Run::default();
    let mut trajectory: Option<Trajectory> = None;
    let mut segment_model = model.clone();
    let mut first = 0;
    loop {
        let seg = segment(
            segment_model.clone(),
            options,
            first,
            total,
            progress,
            &mut run,
        )?;
        let next = seg.reselect.filter(|_| run.interrupted.is_none());
        match trajectory.as_mut() {
            None => trajectory = Some(seg.trajectory),
            Some(tr) => tr.append_after_first(&seg.trajectory),
        }
        let Some((k, independent)) = next else { break };
        let tr = trajectory.as_ref().expect("a segment was run");
        run.reselections.push(Reselection {
            step: k,
            t: round_time(tr.t[k]),
            from: names_of(&model, &segment_model.independent),
            to: names_of(&model, &independent),
        });
        let mut next_model = (*segment_model).clone();
        next_model.independent = independent;
        next_model.initial.q = nalgebra::DVector::from_column_slice(tr.q_at(k));
        next_model.initial.dq = nalgebra::DVector::from_column_slice(tr.dq_at(k));
        // The rest of the run continues from step k (its row is kept from this
        // segment; the next segment's first row is the same state).
        trajectory.as_mut().unwrap().truncate(k + 1);
        segment_model = Arc::new(next_model);
        first = k;
    }
    let mut trajectory = trajectory.expect("a segment was run");
    if let Some(f) = first_non_finite(&model, &trajectory)? {
        // Keep the steps before it; the step itself is a failure, named.
        trajectory.truncate(f.step);
        run.failures.retain(|g| g.step < f.step);
        run.failures.push(f);
    }
    let wall_time = start.elapsed();
    let mut summary = summarize(
        &model,
        &trajectory,
        wall_time,
        &run.iterations,
        run.failures,
    )?;
    summary.conditioned_from = run.conditioned_from;
    summary.reselections = run.reselections;
    summary.interrupted = run.interrupted;
    Ok((trajectory, summary))
}

fn names_of(model: &Model, idx: &[usize]) -> Vec<String> {
    idx.iter().map(|&i| model.names[i].clone()).collect()
}
