//! A forward run whose steps are sized by the accuracy asked
//! ([`ForwardOptions::tolerance`]): each step solved at a size the controller chose
//! ([`error_control`](super::error_control)), kept or taken again smaller from its
//! estimated error, and the rows written on the grid of `dt` by interpolation
//! between the steps taken.
//!
//! The step sizes lie on a ladder of [`LEVELS_PER_OCTAVE`] sizes per factor of 2
//! around `dt`, each with its own solvers, made as it is first needed: the square
//! step (from the first one's sparse analysis) where the plan has one, so that its
//! simplified Newton iteration keeps reusing one Jacobian's factors while the size
//! stays, and the general solver's one-step solve of the graph at that size where
//! it declines a step or there is no square step (Hermite–Simpson). The size moves
//! up only by two rungs or more at once, so that it does not flicker between
//! neighbours. A step that no solver converges on is taken again smaller. A step
//! the square step takes within a longer step over a rank loss of Φ_q is followed
//! by the steps of that size to the longer step's end, the state the run goes on
//! from.

use super::error_control::{local_error, Controller, Decision, History, Tolerance};
use super::failure::StepFailure;
use super::graph::ForwardGraph;
use super::options::ForwardOptions;
use super::plan::Plan;
use super::run::names_of;
use super::square_step::{self, SquareStep, StepLimits};
use super::start::Start;
use super::stepwise::{Stepwise, Taker};
use super::summary::{ErrorControl, Iterations, Reselection, RunSummary, Stats};
use super::StepSink;
use crate::convergence::{SolveReport, Termination};
use crate::coordinates::Coordinates;
use crate::dynamics;
use crate::error::{Error, Result};
use crate::kinematics::{Watch, Watched};
use crate::model::Model;
use std::collections::HashMap;
use std::ops::ControlFlow;
use std::sync::Arc;
use std::time::Instant;

/// Step sizes per factor of 2: neighbouring sizes differ by 19 %.
pub(super) const LEVELS_PER_OCTAVE: f64 = 4.0;

/// The largest step, in steps of the row grid `dt`.
const MAX_STEP_IN_ROWS: f64 = 64.0;

/// The first step tried, in steps of the row grid (the controller grows it by up to
/// [`Controller::MAX_GROWTH`] a step).
const FIRST_STEP_IN_ROWS: f64 = 1.0 / 64.0;

/// The largest turn of a body over one step (rad): half the turn past which a
/// failed step is named too coarse for the motion.
const MAX_TURN: f64 = 0.5 * StepFailure::LARGE_TURN;

/// The smallest step, relative to the horizon: near a rank loss at a tight
/// tolerance the estimates are noise that no smaller step lowers, and the steps
/// there stop shrinking at this size.
const SMALLEST_STEP: f64 = 1e-9;

/// The solvers of one step size: the square step, and the general solver's
/// one-step solve of the graph at that size (made where first needed).
struct Rung {
    h: f64,
    square: Option<SquareStep>,
    general: Option<General>,
}

/// A step solved: its report, who took it, whether it is an interpolant of a
/// longer step over a rank loss that goes on past it (the square step's passage),
/// and whether it damped its projections near one.
struct Taken {
    report: SolveReport,
    taker: Taker,
    within_step_over: bool,
    damped: bool,
}

/// The graph of one step at a size, its solver, and the two steps it reads.
struct General {
    graph: ForwardGraph,
    solver: Stepwise,
    values: Vec<f64>,
}

/// The rungs of the ladder of sizes.
struct Ladder<'a> {
    model: &'a Arc<Model>,
    options: &'a ForwardOptions,
    plan: &'a Plan,
    /// The independent coordinates of the steps (in IC, the set the run is in).
    independent: Vec<usize>,
    /// The square step at the row grid's dt, whose analysis the others copy.
    first: Option<SquareStep>,
    /// The size of rung 0 (the row grid's dt).
    h0: f64,
    rungs: HashMap<i32, Rung>,
    /// The guess of the step being solved, kept to start again from.
    guess: Vec<f64>,
}

impl Ladder<'_> {
    fn size(&self, rung: i32) -> f64 {
        self.h0 * (f64::from(rung) / LEVELS_PER_OCTAVE).exp2()
    }

    /// The rung at or below `h`.
    fn rung_below(&self, h: f64) -> i32 {
        // (A size the controller computed from a rung's own is that rung, not the
        // one below, despite the rounding of the logarithm.)
        ((h / self.h0).log2() * LEVELS_PER_OCTAVE + 1e-9).floor() as i32
    }

    /// The ladder in another set of independent coordinates: its solvers made
    /// afresh as they are needed.
    fn reselect(&mut self, independent: Vec<usize>) {
        self.first = square_step::for_plan(self.model, self.plan, &independent)
            .map(SquareStep::error_controlled);
        self.independent = independent;
        self.rungs.clear();
    }

    fn at(&mut self, rung: i32) -> &mut Rung {
        let h = self.size(rung);
        let first = &self.first;
        self.rungs.entry(rung).or_insert_with(|| Rung {
            h,
            square: first.as_ref().and_then(|square| square.at_dt(h)),
            general: None,
        })
    }

    /// The step of the rung's size from `before` at t to `block` (its guess in,
    /// solution out): by the square step, else the general solver; `None` where
    /// neither converged.
    fn step(
        &mut self,
        rung: i32,
        t: f64,
        before: &[f64],
        block: &mut [f64],
        limits: StepLimits,
    ) -> Result<Option<Taken>> {
        let s = block.len();
        self.guess.clear();
        self.guess.extend_from_slice(block);
        self.at(rung);
        let Ladder {
            model,
            options,
            independent,
            rungs,
            guess,
            ..
        } = self;
        let rung = rungs.get_mut(&rung).expect("made above");
        let h = rung.h;
        if let Some(square) = rung.square.as_mut() {
            if let Some(work) = square.solve(t + h, before, block, limits, None) {
                if block.iter().all(|v| v.is_finite()) {
                    let report = SolveReport {
                        factorizations: work.factorizations,
                        ..SolveReport::new(Termination::Converged, work.iterations, 0.0)
                    };
                    return Ok(Some(Taken {
                        report,
                        taker: Taker::Square,
                        within_step_over: square.passed() && square.passing(),
                        damped: square.damped(),
                    }));
                }
            }
            block.copy_from_slice(guess);
        }
        if rung.general.is_none() {
            rung.general = Some(General::new(model, options, independent, h)?);
        }
        let general = rung.general.as_mut().expect("made above");
        general.graph.graph.set_t0(t);
        general.values[..s].copy_from_slice(before);
        general.values[s..].copy_from_slice(block);
        let (report, taker) = general.solver.step(
            &general.graph.graph,
            &mut general.values,
            1,
            &mut |_, _, _| None,
        )?;
        let solved = &general.values[s..];
        if report.termination != Termination::Converged || !solved.iter().all(|v| v.is_finite()) {
            return Ok(None);
        }
        block.copy_from_slice(solved);
        Ok(Some(Taken {
            report,
            taker,
            within_step_over: false,
            damped: false,
        }))
    }
}

impl General {
    /// The one-step graph of the run at size h, solved by the general solver.
    fn new(
        model: &Arc<Model>,
        options: &ForwardOptions,
        independent: &[usize],
        h: f64,
    ) -> Result<General> {
        let mut one = options.clone();
        one.dt = h;
        one.t_end = h;
        one.tolerance = None;
        one.square_steps = false;
        let plan = Plan::new(model, &one)?;
        let start = Start {
            state: model.initial.clone(),
            independent: independent.to_vec(),
        };
        let graph = ForwardGraph::planned(model.clone(), &plan, &options.noise, start)?;
        let solver = Stepwise::new(&graph.graph, None, plan.settings)?;
        let s = graph.graph.layout().size();
        Ok(General {
            graph,
            solver,
            values: vec![0.0; 2 * s],
        })
    }
}

/// The Taylor guess of the state h after `before` (q, q̇, q̈ of n coordinates, then in
/// IC z, ż, z̈ of f), into `out`.
fn taylor(before: &[f64], out: &mut [f64], n: usize, f: usize, h: f64) {
    for (offset, m) in [(0, n), (3 * n, f)] {
        for i in 0..m {
            let (x, v, a) = (
                before[offset + i],
                before[offset + m + i],
                before[offset + 2 * m + i],
            );
            out[offset + i] = x + h * v + 0.5 * h * h * a;
            out[offset + m + i] = v + h * a;
            out[offset + 2 * m + i] = a;
        }
    }
}

/// q, q̇, q̈ at τ into a step of `h` from `start` to `end` (n coordinates each), into
/// `out[..3n]`: q on the cubic Hermite interpolant of q and q̇ at both ends (fourth
/// order), q̇ on that of q̇ and q̈ and q̈ its derivative.
pub(super) fn interpolate(start: &[f64], end: &[f64], h: f64, tau: f64, n: usize, out: &mut [f64]) {
    let s = (tau / h).clamp(0.0, 1.0);
    let ([h00, h10, h01, h11], [d00, d10, d01, d11]) = crate::trajectory::cubic_hermite(s);
    for i in 0..n {
        let (q0, v0, a0) = (start[i], start[n + i], start[2 * n + i]);
        let (q1, v1, a1) = (end[i], end[n + i], end[2 * n + i]);
        out[i] = h00 * q0 + h10 * h * v0 + h01 * q1 + h11 * h * v1;
        out[n + i] = h00 * v0 + h10 * h * a0 + h01 * v1 + h11 * h * a1;
        out[2 * n + i] = (d00 * v0 + d01 * v1) / h + d10 * a0 + d11 * a1;
    }
}

/// The run of `options` (whose `tolerance` is set) with steps sized by the error
/// controller, its rows at t = k·dt handed to `sink`. `bounds` scales the step
/// sizes' bounds that are not the tolerance's (the largest step, the largest turn
/// of a body over one): a run checked against another at a coarser tolerance
/// ([`run_check`](super::run_check)) is coarser in them too, so that where they
/// set the steps the two runs still differ by their errors.
pub(super) fn simulate(
    model: Arc<Model>,
    options: &ForwardOptions,
    tolerance: Tolerance,
    bounds: f64,
    progress: &mut dyn FnMut(usize, usize) -> ControlFlow<()>,
    sink: &mut dyn StepSink,
) -> Result<RunSummary> {
    let plan = Plan::new(&model, options)?;
    let start_clock = Instant::now();
    let n = model.n();
    let mut independent = match options.coordinates {
        Coordinates::Independent => model.independent.clone(),
        Coordinates::Dependent => Vec::new(),
    };
    let f = independent.len();
    let s = 3 * (n + f);
    let rows = plan.steps;
    let dt = plan.dt;
    let t_last = (rows - 1) as f64 * dt;
    let mut ladder = Ladder {
        model: &model,
        options,
        plan: &plan,
        independent: model.independent.clone(),
        first: square_step::for_plan(&model, &plan, &model.independent)
            .map(SquareStep::error_controlled),
        h0: dt,
        rungs: HashMap::new(),
        guess: Vec::new(),
    };
    let controller = Controller {
        order: options.integrator.order(),
        h_min: SMALLEST_STEP * t_last.max(dt),
        h_max: (bounds * MAX_STEP_IN_ROWS * dt).min(t_last.max(dt)),
    };
    let limits = StepLimits {
        max_iterations: plan.settings.max_iterations,
        step_tolerance: plan.settings.step_tolerance.min(tolerance.rtol),
    };

    // The initial state, q̈ from the dynamics.
    let init = &model.initial;
    let ddq = dynamics::accelerations_guess(&model, &init.q, &init.dq, 0.0)?;
    let mut current = Vec::with_capacity(s);
    current.extend_from_slice(init.q.as_slice());
    current.extend_from_slice(init.dq.as_slice());
    current.extend_from_slice(ddq.as_slice());
    current.resize(s, 0.0);
    fill_independent(&mut current, n, &independent);
    let mut iterations = Iterations::default();
    if let Some(work) = ladder
        .first
        .as_mut()
        .and_then(|first| first.solve_first(0.0, &mut current))
    {
        iterations.push(&SolveReport {
            factorizations: work.factorizations,
            ..SolveReport::new(Termination::Converged, work.iterations, 0.0)
        });
    }
    if !current.iter().all(|v| v.is_finite()) {
        return Err(Error::singular(format!(
            "{}: the initial state cannot be used: its accelerations are not finite",
            model.scene.file
        )));
    }
    let mut stats = Stats::new(&model, options.integrator);
    stats.add(&model, 0.0, &current[..n], &current[n..2 * n])?;
    sink.step(
        0.0,
        &current[..n],
        &current[n..2 * n],
        &current[2 * n..3 * n],
    )?;
    let mut written = 1;
    let mut interrupted = None;
    if progress(written, rows).is_break() {
        interrupted = Some(0);
    }

    let mut control = ErrorControl {
        tolerance,
        accepted: 0,
        rejected: 0,
        failed_solves: 0,
        smallest: f64::INFINITY,
        largest: 0.0,
        at_floor: 0,
        damped: 0,
        check: None,
    };
    let (mut square_steps, mut general_steps) = (0, 0);
    let mut failures = Vec::new();
    let mut next = vec![0.0; s];
    let mut row = vec![0.0; 3 * n];
    let mut last_row = current[..3 * n].to_vec();
    let mut error = vec![0.0; 2 * n];
    let mut history = History::default();
    history.push(0.0, &current[2 * n..3 * n]);
    let mut t = 0.0;
    let mut h_try = (FIRST_STEP_IN_ROWS * dt).clamp(controller.h_min, controller.h_max);
    let mut rung = ladder.rung_below(h_try);
    let mut after_reject = false;
    // Whether the current state is an interpolant of a step over a rank loss that
    // goes on past it. Such a state is not stepped from: its q̈ is not the
    // dynamics' and its q, q̇ hold the constraints only as the interpolant does.
    // The steps at the same size follow the step over to its end, a state solved,
    // and are kept whatever their estimate, which reads the interpolant's q̈.
    let mut within_step_over = false;
    let mut watch = (options.coordinates == Coordinates::Independent)
        .then(|| Watch::new(&model, &independent, &current[..n]));
    // Accepted steps since the run's start or its last switch of coordinates.
    let mut segment_step = 0;
    let mut reselections = Vec::new();
    while written < rows && interrupted.is_none() {
        // The rung of the size asked, within what the integrators follow: down at
        // once, up only by two rungs or more.
        let wanted = ladder.rung_below(h_try.min(bounds * turn_limit(&model, &current)));
        if (wanted < rung || wanted >= rung + 2) && !within_step_over {
            rung = wanted;
        }
        let h = ladder.size(rung);
        taylor(&current, &mut next, n, f, h);
        let Some(Taken {
            report,
            taker,
            within_step_over: ends_within,
            damped,
        }) = ladder.step(rung, t, &current, &mut next, limits)?
        else {
            within_step_over = false;
            control.failed_solves += 1;
            match controller.after_failure(h) {
                Some(smaller) => {
                    h_try = smaller;
                    rung = ladder.rung_below(h_try);
                    after_reject = true;
                    continue;
                }
                None => {
                    let cause = no_step_cause(&model, &current, t, h);
                    failures.push(failure(&model, &current, written, dt, Some(cause)));
                    break;
                }
            }
        };
        iterations.push(&report);
        local_error(
            options.integrator,
            n,
            h,
            &current,
            &next,
            &history,
            &mut error,
        );
        let norm = tolerance.norm(&error, &current[..2 * n], &next[..2 * n]);
        let ratio = Controller::error_ratio(h, norm);
        let decision = match controller.decide(h, ratio, after_reject) {
            // No smaller size to take: the estimate at the smallest is the noise of
            // the solves' accelerations (rounding, or solves near a rank loss),
            // which grows as the step shrinks, not the step's error. The step is
            // kept and counted (not among a run's first steps, whose estimate
            // lacks the steps before).
            Decision::Reject { retry } if ladder.rung_below(retry) >= rung => {
                if !history.short_for(options.integrator) {
                    control.at_floor += 1;
                }
                Decision::Accept { next: h }
            }
            // A step interpolated from a step over, or damped near a rank loss,
            // whose estimate reads q̈'s lost component, is kept at the size that
            // reached the rank loss.
            _ if within_step_over => Decision::Accept { next: h },
            _ if damped => {
                control.damped += 1;
                Decision::Accept { next: h }
            }
            d => d,
        };
        match decision {
            Decision::Reject { retry } => {
                control.rejected += 1;
                h_try = retry;
                after_reject = true;
            }
            Decision::Accept { next: h_next } => {
                // In IC: whether the coordinates still determine the others at the
                // step's end, as the fixed steps' runs watch it.
                let mut reselect = None;
                if let Some(watch) = watch.as_mut() {
                    match watch.observe(&model, segment_step, t + h, &current[..n], &next[..n]) {
                        Watched::Continue => {}
                        Watched::Reselect(set) => reselect = Some(set),
                        Watched::Stop(singular) => {
                            let mut f = failure(&model, &current, written, dt, None);
                            f.singular = Some(singular);
                            failures.push(f);
                            break;
                        }
                    }
                }
                segment_step += 1;
                control.accepted += 1;
                control.smallest = control.smallest.min(h);
                control.largest = control.largest.max(h);
                match taker {
                    Taker::Square => square_steps += 1,
                    _ => general_steps += 1,
                }
                let t1 = t + h;
                // The rows this step reaches (the last one's time may lie a rounding
                // past the last step's end).
                while written < rows {
                    let t_row = written as f64 * dt;
                    let last = written + 1 == rows && t1 >= t_last - 1e-9 * dt;
                    if t_row > t1 + 1e-9 * h && !last {
                        break;
                    }
                    interpolate(&current, &next, h, t_row - t, n, &mut row);
                    // The summary's measures are of the rows written: between the
                    // steps they hold the constraints only as well as the interpolant.
                    stats.add(&model, t_row, &row[..n], &row[n..2 * n])?;
                    stats.watch(
                        &model,
                        (t_row - dt, &last_row[..n], &last_row[n..2 * n]),
                        t_row,
                        &row[..n],
                        &row[n..2 * n],
                    );
                    last_row.copy_from_slice(&row);
                    sink.step(
                        crate::trajectory::round_time(t_row),
                        &row[..n],
                        &row[n..2 * n],
                        &row[2 * n..],
                    )?;
                    written += 1;
                }
                history.push(t1, &next[2 * n..3 * n]);
                std::mem::swap(&mut current, &mut next);
                t = t1;
                h_try = h_next;
                within_step_over = ends_within;
                after_reject = false;
                if let Some(set) = reselect {
                    reselections.push(Reselection {
                        step: written - 1,
                        t: crate::trajectory::round_time(t),
                        from: names_of(&model, &independent),
                        to: names_of(&model, &set),
                    });
                    // The run goes on from this step's end in the new coordinates.
                    fill_independent(&mut current, n, &set);
                    watch = Some(Watch::new(&model, &set, &current[..n]));
                    ladder.reselect(set.clone());
                    independent = set;
                    segment_step = 0;
                    within_step_over = false;
                }
                if progress(written, rows).is_break() {
                    interrupted = Some(written - 1);
                }
            }
        }
    }
    let has_square_step = ladder.first.is_some();
    drop(ladder);
    let mut summary = stats.finish(start_clock.elapsed(), iterations, failures, plan);
    summary.steps = written;
    summary.square_steps = square_steps;
    // (Counted where there is a square step to decline them.)
    if has_square_step {
        summary.general_steps = general_steps;
    }
    summary.interrupted = interrupted;
    summary.reselections = reselections;
    summary.error_control = Some(control);
    Ok(summary)
}

/// The IC part of `state` (z, ż, z̈ of the coordinates `independent`, after q, q̇,
/// q̈ of n), from its q, q̇, q̈.
fn fill_independent(state: &mut [f64], n: usize, independent: &[usize]) {
    let f = independent.len();
    for part in 0..3 {
        for (j, &i) in independent.iter().enumerate() {
            state[3 * n + part * f + j] = state[part * n + i];
        }
    }
}

/// The longest step over which no body turns more than [`MAX_TURN`] at the speeds
/// of `state` (q, q̇, …): past about half a radian a step the integrators' chords
/// stop following the motion, and their error estimates with them.
fn turn_limit(model: &Model, state: &[f64]) -> f64 {
    let n = model.n();
    match model.fastest_body_index(&state[..n], &state[n..2 * n]) {
        Some((_, omega)) if omega > 0.0 => MAX_TURN / omega,
        _ => f64::INFINITY,
    }
}

/// How the cause of a failed error-controlled run begins where no step size
/// converged (not an effect that cannot be evaluated).
pub const NO_STEP_CONVERGED: &str = "no step from t =";

/// The failure at row `row`, the first the run could not write, from `state`:
/// `cause`, or where there is none the caller names it (a singular configuration).
fn failure(
    model: &Model,
    state: &[f64],
    row: usize,
    dt: f64,
    cause: Option<String>,
) -> StepFailure {
    let q = &state[..model.n()];
    StepFailure::outside_solve(
        row,
        row as f64 * dt,
        SolveReport::new(Termination::IterationLimit, 0, f64::NAN),
        crate::kinematics::constraint_conditioning(model, model.initial.q.as_slice(), q),
        cause,
    )
}

/// Why no step from `state` at t converged, down to the smallest size `h`: an
/// effect that cannot be evaluated there, or the steps' failure itself.
fn no_step_cause(model: &Model, state: &[f64], t: f64, h: f64) -> String {
    let n = model.n();
    model
        .effect_fault(&state[..n], &state[n..2 * n], t)
        .unwrap_or_else(|| {
            format!(
                "{NO_STEP_CONVERGED} {} s converged, down to {h:.1e} s (error-controlled steps)",
                crate::trajectory::round_time(t)
            )
        })
}

#[cfg(test)]
mod tests {
    use super::interpolate;

    /// The interpolant reproduces q of a cubic and q̇ of a cubic at every τ.
    #[test]
    fn interpolation_is_exact_on_cubics() {
        let q = |t: f64| 0.3 - 1.1 * t + 0.7 * t * t + 2.0 * t.powi(3);
        let v = |t: f64| -1.1 + 1.4 * t + 6.0 * t * t;
        let w = |t: f64| 0.5 - 2.0 * t + 3.0 * t * t - 0.7 * t.powi(3);
        let dw = |t: f64| -2.0 + 6.0 * t - 2.1 * t * t;
        let (t0, h) = (0.4, 0.8);
        // One coordinate: q on the first cubic; its velocity on the second (each
        // checked on its own interpolant).
        let start = [q(t0), v(t0), 0.0];
        let end = [q(t0 + h), v(t0 + h), 0.0];
        let vstart = [0.0, w(t0), dw(t0)];
        let vend = [0.0, w(t0 + h), dw(t0 + h)];
        for tau in [0.0, 0.1, 0.35, 0.8] {
            let mut out = [0.0; 3];
            interpolate(&start, &end, h, tau, 1, &mut out);
            assert!((out[0] - q(t0 + tau)).abs() < 1e-13, "q at {tau}");
            interpolate(&vstart, &vend, h, tau, 1, &mut out);
            assert!((out[1] - w(t0 + tau)).abs() < 1e-13, "q̇ at {tau}");
            assert!((out[2] - dw(t0 + tau)).abs() < 1e-12, "q̈ at {tau}");
        }
    }
}
