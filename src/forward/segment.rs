//! One segment of a forward run: the steps solved by the fixed-lag smoother or in
//! batch with one set of coordinates, watching, in independent coordinates, how well
//! they determine the others; and the substep guess that rescues a failed step.

use super::failure::StepFailure;
use super::graph::ForwardGraph;
use super::options::ForwardOptions;
use super::summary::{Iterations, Reselection};
use crate::coordinates::Coordinates;
use crate::error::Result;
use crate::kinematics::{constraint_conditioning, Determinacy};
use crate::model::{Model, State};
use crate::smoother::{self, Mode, Next};
use crate::solver::{Past, Settings, SolveReport, Termination};
use crate::trajectory::round_time;
use nalgebra::DVector;
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
}

/// Where a segment hands its steps as they become final: `emit(step, t, block)` with
/// the run's step, its time and the step's variables (q, q̇, q̈ first, in model
/// order).
pub(super) type Emit<'a> = dyn FnMut(usize, f64, &[f64]) -> Result<()> + 'a;

/// Steps first..total of a run with `model` (its initial state is step `first`'s),
/// handed to `emit` in order as they become final. Returns where (global step) and
/// to which independent coordinates the next segment switches.
///
/// The fixed-lag smoother keeps a buffer of a few thousand steps whatever the
/// segment's length ([`smoother::fixed_lag_streaming`]); a batch holds every step.
pub(super) fn segment(
    model: Arc<Model>,
    options: &ForwardOptions,
    first: usize,
    total: usize,
    progress: &mut dyn FnMut(usize, usize) -> ControlFlow<()>,
    run: &mut Run,
    emit: &mut Emit<'_>,
) -> Result<Option<(usize, Vec<usize>)>> {
    let mut fg = ForwardGraph::new(model.clone(), options)?;
    fg.graph.set_t0(first as f64 * options.dt);
    let steps = total - first;
    let s = fg.graph.layout().size();
    let held = match options.mode {
        Mode::FixedLag(window) => smoother::stream_capacity(window).min(steps),
        Mode::Batch => steps,
    };
    let mut values = vec![0.0; held * s];
    values[..s].copy_from_slice(&fg.initial_block(&model)?);
    let mut completed = steps;
    let mut reselect = None;
    let n = model.n();
    // The body turning fastest over step k: its turn estimated from the step
    // before's velocities and accelerations (the rate at mid-step), so that a run
    // from rest is measured too.
    let fast_body = |k: usize, v: &[f64]| {
        let before = &v[k.checked_sub(1)? * s..k * s];
        let mid: Vec<f64> = (0..n)
            .map(|i| before[n + i] + 0.5 * options.dt * before[2 * n + i])
            .collect();
        let (body, omega) = model.fastest_body(&before[..n], &mid)?;
        Some((body, omega * options.dt))
    };
    let failure = |k: usize, report: &SolveReport, v: &[f64]| {
        let q = &v[k * s..k * s + n];
        // A non-finite cost: look for the effect that cannot be evaluated, at the
        // step's state or, where that is not finite, at the step before's.
        let cause = (!report.cost.is_finite()).then(|| {
            let at = |j: usize| (&v[j * s..j * s + n], &v[j * s + n..j * s + 2 * n]);
            let (mut qk, mut dqk) = at(k);
            if !qk.iter().chain(dqk).all(|x| x.is_finite()) {
                (qk, dqk) = at(k.saturating_sub(1));
            }
            model.effect_fault(qk, dqk, fg.graph.time(k))
        });
        StepFailure {
            // k is a step of `v`, which starts at the graph's step offset.
            step: first + fg.graph.step_offset() + k,
            t: fg.graph.time(k),
            report: report.clone(),
            constraint_conditioning: constraint_conditioning(&model, q),
            singular: None,
            warm_start: false,
            batch: false,
            // The effect at fault where one is; else why the solve's evaluation failed.
            cause: cause.flatten().or_else(|| report.cause.clone()),
            fast_body: fast_body(k, v),
        }
    };
    match options.mode {
        Mode::FixedLag(window) => {
            // In independent coordinates, how well z determines the rest, step by step.
            let mut determinacy = (options.coordinates == Coordinates::Independent).then(|| {
                let far = (0.0, f64::INFINITY);
                // The last two steps' (t, s), and s at the segment's first step.
                (Determinacy::new(&model), far, far, f64::INFINITY)
            });
            let mut failures = Vec::new();
            let mut iterations = Iterations::default();
            let mut conditioned_from = None;
            let mut interrupted = None;
            let settings = Settings {
                // The DC graph's integrators conflict with its constraints.
                tangent_priors: options.coordinates == Coordinates::Dependent,
                // Independent coordinates and tangent integrators leave every step with
                // as many equations as unknowns: a marginal prior adds nothing to the
                // next step's solution (each window has N_w = 1's) but its
                // linearization about the step's prediction; the exact conditional is
                // the step's own solution, and the batch's. In a stiff transient that
                // linearization's error is no longer small: Andrews' squeezer in IC
                // ended 0.1 rad off at dt = 50 µs with marginal priors, 7.8e-4 rad
                // with conditioned ones (and a batch of the mm slider-crank at 1 ms
                // had a cost of 6.3 to remove from the marginal run's start).
                past: if options.is_square(model.n()) && options.settings.past == Past::Adaptive {
                    Past::Conditioned
                } else {
                    options.settings.past
                },
                second_order: options.settings.second_order && !options.is_square(model.n()),
                ..options.settings
            };
            // The steps of `values` are from the graph's step offset on (the segment's
            // step of values' step k is `at(k)`).
            let at = |k: usize| fg.graph.step_offset() + k;
            let graph = &fg.graph;
            let mut on_final = |j: usize, block: &[f64]| emit(first + j, graph.run_time(j), block);
            let (base, handed) = smoother::fixed_lag_streaming(
                &fg.graph,
                &mut values,
                smoother::Stream {
                    capacity: held,
                    on_final: &mut on_final,
                },
                steps,
                window,
                settings,
                |v, k| fg.predict(v, k),
                |v, k| fg.substep_guess(&model, options, settings, first + at(k), v, k),
                |k, report, v| {
                    iterations.push(report);
                    // Asked to stop: after this step's own outcome is recorded.
                    let stop = progress(first + at(k) + 1, total).is_break();
                    // The positions of step j of the window's values.
                    let q_at = |j: usize| &v[j * s..j * s + model.n()];
                    let q = q_at(k);
                    if report.termination != Termination::Converged {
                        let mut f = failure(k, report, v);
                        if let Some((det, before, older, _)) = determinacy.as_mut() {
                            // A solve that fails while z and every other set of
                            // coordinates approach a rank loss fails because of it:
                            // name the singular configuration, located from the last
                            // two converged steps.
                            let (prev, older_q) = (q_at(k.max(1) - 1), q_at(k.max(2) - 2));
                            let rate = (older.1 - before.1) / (before.0 - older.0);
                            let steps_to_rank_loss = before.1 / (rate * fg.graph.dt());
                            // A step too coarse for the motion fails for that reason: in
                            // a violent transient s moves fast too (Andrews' squeezer at
                            // 1.7 ms, a body turning 1.8 rad a step, s = 0.026 falling),
                            // and the extrapolation alone would name a singular point.
                            let too_coarse = f
                                .fast_body
                                .as_ref()
                                .is_some_and(|(_, turn)| *turn > StepFailure::LARGE_TURN);
                            if k >= 2
                                && rate > 0.0
                                && ((steps_to_rank_loss <= Determinacy::ATTRIBUTE_WITHIN
                                    && before.1 < Determinacy::ATTRIBUTE_BELOW
                                    && !too_coarse)
                                    || before.1 < Determinacy::SEARCH_BELOW)
                            {
                                let (best, _) = det.best(&model, prev);
                                if best < Determinacy::SWITCH_GAIN * before.1 {
                                    f.singular = Some(det.singular_configuration(
                                        &model, older_q, prev, *older, *before,
                                    ));
                                    failures.push(f);
                                    completed = at(k);
                                    return Next::Stop;
                                }
                            }
                        }
                        failures.push(f);
                        if !options.continue_on_failure
                            || report.termination == Termination::Diverged
                        {
                            // The failed step is left out of the trajectory.
                            completed = at(k);
                            return Next::Stop;
                        }
                    }
                    if let Some((det, before, older, origin)) = determinacy.as_mut() {
                        // Approaching a configuration where z stops determining the
                        // other coordinates: switch to coordinates that do, or, where
                        // Φ_q itself loses rank (the problem is ill-posed), stop while
                        // the solves are still sound, and say where.
                        let now = (fg.graph.time(k), det.distance(&model, q));
                        // At coarse steps s can fall from well above the thresholds
                        // to beyond the singular point in one step: judge by the
                        // lower of s and its linear extrapolation to the next step.
                        let ahead = if before.1.is_finite() {
                            now.1.min(2.0 * now.1 - before.1).max(0.0)
                        } else {
                            now.1
                        };
                        let falling = now.1 < before.1;
                        // A long chain reads s below the threshold from its start (about
                        // 0.6/k for k links) with no better set to switch to: as for the
                        // stop below, it searches only where s has fallen to half its
                        // start (for a start above twice the threshold, every s below it).
                        // Not at a segment's first step, where no switch is made (its
                        // start is unknown there: a 128-link pendulum's IC run searched
                        // for 90 ms at step 0 and dropped the result).
                        if k > 0
                            && falling
                            && ahead < Determinacy::SEARCH_BELOW
                            && ahead <= 0.5 * *origin
                        {
                            let (best, set) = det.best(&model, q);
                            if best >= Determinacy::SWITCH_GAIN * now.1 {
                                reselect = Some((first + at(k), set));
                                completed = at(k) + 1;
                                return Next::Stop;
                            }
                        }
                        // The stop on the extrapolation only where it crosses 0 within
                        // the step: a regular dip (the robot's s bottoms out at 3e-3)
                        // seen at coarse steps must not stop the run.
                        let crossing = before.1.is_finite() && 2.0 * now.1 <= before.1;
                        // s shrinks with a mechanism's size (a chain of k links reads
                        // about 0.6/k: a 256-link pendulum starts at 2.4e-3): below
                        // the threshold from the start, the run stops only where s has
                        // fallen to half its value there.
                        if !before.1.is_finite() {
                            *origin = now.1;
                        }
                        // (Where it started at 2 STOP_BELOW or above, that is every
                        // s below the threshold, as before.)
                        let low = now.1 < Determinacy::STOP_BELOW && now.1 <= 0.5 * *origin;
                        if falling && (low || crossing) {
                            let mut f = failure(k, report, v);
                            f.singular = Some(det.singular_configuration(
                                &model,
                                q_at(k.max(1) - 1),
                                q,
                                *before,
                                now,
                            ));
                            failures.push(f);
                            completed = at(k);
                            return Next::Stop;
                        }
                        *older = *before;
                        *before = now;
                    }
                    if stop {
                        // Interrupted: this step is kept as the last one.
                        interrupted = Some(first + at(k));
                        completed = at(k) + 1;
                        return Next::Stop;
                    }
                    Next::Continue
                },
                |k| conditioned_from = Some((first + at(k), round_time(fg.graph.time(k)))),
            )?;
            // The steps still in the buffer: final now.
            for j in handed..completed {
                let b = (j - base) * s;
                emit(first + j, fg.graph.run_time(j), &values[b..b + s])?;
            }
            run.iterations.extend(iterations);
            run.failures.extend(failures);
            run.interrupted = run.interrupted.or(interrupted);
            if run.conditioned_from.is_none() {
                run.conditioned_from = conditioned_from;
            }
        }
        Mode::Batch => {
            // Start from the one-step smoother's solution over this segment (which
            // may end it where the independent coordinates are re-selected), then
            // solve all of it at once.
            let mut warm_options = options.clone();
            warm_options.mode = Mode::FixedLag(1);
            let mut warm = Run::default();
            // Its steps go straight into the batch's variables.
            let mut rows = 0;
            let warm_reselect = segment(
                model.clone(),
                &warm_options,
                first,
                total,
                progress,
                &mut warm,
                &mut |j, _, block| {
                    let n = model.n();
                    let (q, rest) = block.split_at(n);
                    let (dq, rest) = rest.split_at(n);
                    fg.fill_step(&model, q, dq, &rest[..n], j - first, &mut values);
                    rows = j - first + 1;
                    Ok(())
                },
            )?;
            if warm.interrupted.is_some() {
                // The one-step start is not the batch solution: nothing to return.
                run.interrupted = warm.interrupted;
                completed = 0;
            } else if let Some(f) = warm.failures.iter().find(|f| f.singular.is_some()) {
                // Ill-posed ahead: no batch solve of the whole horizon exists.
                run.failures.push(f.clone());
                completed = 0;
            } else if let Some(f) = warm.failures.first() {
                // No batch solve without its start: the step that failed there ends
                // the run, named as such.
                run.failures.push(StepFailure {
                    warm_start: true,
                    ..f.clone()
                });
                completed = 0;
            } else {
                reselect = warm_reselect;
                completed = rows;
                let mut settings = options.settings;
                // One equation per unknown: Gauss-Newton is Newton's method.
                settings.second_order &= !options.is_square(model.n());
                if options.retries_other() && !options.tangent_dc(model.n()) {
                    // The paper's factors get the iterations a window needs; past them
                    // their compromise crawls (the double pendulum at 1 ms: 30
                    // iterations, 35 s) where tangent ones converge in one.
                    settings.max_iterations = settings.max_iterations.min(AUTO_BATCH_ITERATIONS);
                }
                // Steps that hold all their equations (tangent integrators) make the
                // N_w = 1 start the batch's solution: a large mechanism's is not
                // solved again at the dense cost of the whole horizon's
                // linearization only to confirm it.
                let report = if fg.graph.exact_step().is_some() {
                    run.iterations.extend(std::mem::take(&mut warm.iterations));
                    SolveReport::new(Termination::Converged, 0, 0.0)
                } else {
                    let report = smoother::batch(&fg.graph, &mut values, completed, settings)?;
                    run.iterations.push(&report);
                    report
                };
                if report.termination != Termination::Converged {
                    let k = completed - 1;
                    run.failures.push(StepFailure {
                        batch: true,
                        ..failure(k, &report, &values)
                    });
                }
            }
            for k in 0..completed {
                emit(first + k, fg.graph.run_time(k), &values[k * s..(k + 1) * s])?;
            }
        }
    }
    Ok(reselect)
}

/// The iterations a batch solve with the paper's integrator factors gets under
/// [`DcIntegrators::Auto`](super::options::DcIntegrators::Auto) before the run is made again with tangent ones.
pub const AUTO_BATCH_ITERATIONS: usize = 10;

/// The substep counts tried, in turn, for a step whose solve failed from its guess:
/// a few, then finer (at most 74 substep solves per failed step).
const SUBSTEPS: [usize; 3] = [2, 8, 64];
/// Iterations a substep's solve gets: a step 8–64 times finer than one that failed
/// converges in a few, or that count of substeps is given up.
const SUBSTEP_ITERATIONS: usize = 10;

impl ForwardGraph {
    /// A guess for step k (run step `step`) from the state of step k − 1 in `values`,
    /// integrated over the step in [`SUBSTEPS`] substeps by the same graph at the
    /// finer step (N_w = 1), until all of them converge. Where the
    /// step's own solve fails from the Taylor guess (a coarse step through a fast or
    /// stiff stretch, whose implicit equations Newton's method does not reach from
    /// so far), this guess lies within the step's error of its solution. Writes the
    /// guess and returns true, or false when no substep count converged.
    fn substep_guess(
        &self,
        model: &Arc<Model>,
        options: &ForwardOptions,
        settings: Settings,
        step: usize,
        values: &mut [f64],
        k: usize,
    ) -> bool {
        let (n, s) = (self.n, self.graph.layout().size());
        let before = &values[(k - 1) * s..k * s];
        let mut start = (**model).clone();
        start.initial = State {
            q: DVector::from_column_slice(&before[..n]),
            dq: DVector::from_column_slice(&before[n..2 * n]),
        };
        let start = Arc::new(start);
        let settings = Settings {
            max_iterations: settings.max_iterations.min(SUBSTEP_ITERATIONS),
            ..settings
        };
        for substeps in SUBSTEPS {
            let mut fine = options.clone();
            fine.dt = options.dt / substeps as f64;
            fine.mode = Mode::FixedLag(1);
            let Ok(mut graph) = ForwardGraph::new(start.clone(), &fine) else {
                return false;
            };
            graph.graph.set_t0((step - 1) as f64 * options.dt);
            let Ok(first) = graph.initial_block(&start) else {
                return false;
            };
            let mut fine_values = vec![0.0; (substeps + 1) * s];
            fine_values[..s].copy_from_slice(&first);
            let mut converged = true;
            let solved = smoother::fixed_lag(
                &graph.graph,
                &mut fine_values,
                substeps + 1,
                1,
                settings,
                |v, j| graph.predict(v, j),
                |_, report, _| {
                    converged &= report.termination == Termination::Converged;
                    if converged {
                        Next::Continue
                    } else {
                        Next::Stop
                    }
                },
                |_| {},
            );
            if solved.is_ok() && converged {
                values[k * s..(k + 1) * s].copy_from_slice(&fine_values[substeps * s..]);
                return true;
            }
        }
        false
    }
}
