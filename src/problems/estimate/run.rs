//! An estimate of a whole record: the fixed-lag smoother over it, or the batch
//! solve of every step started from a fixed-lag pass, each step handed out final
//! with its covariance.

use super::consistency::Nis;
use super::determination::{watched_coordinates, Determination, Undetermined};
use super::graph::EstimationGraph;
use super::identification::Identification;
use super::online::{Estimator, StepEstimate};
use super::options::{
    EstimateOptions, Smoothing, Uncertainty, BATCH_PASS_WINDOW, BATCH_START_WINDOW,
};
use super::process_noise::{self, DynamicsUse, ProcessSource};
use super::record::{Record, StepReading};
use crate::coordinates::Coordinates;
use crate::error::{Error, Result};
use crate::factors::Integrator;
use crate::factors::{InputReading, Reading};
use crate::graph::{Factor, Noise};
use crate::model::Model;
use crate::sensors::SensorKind;
use crate::solver::Marginals;
use crate::solver::{Termination, WindowSolver};
use std::sync::Arc;

/// What a run did, for its summary.
#[derive(Debug, Clone, PartialEq)]
pub struct EstimateSummary {
    pub coordinates: Coordinates,
    /// The integrator the graph was written with.
    pub integrator: Integrator,
    pub steps: usize,
    pub dt: f64,
    pub smoothing: Smoothing,
    pub readings: usize,
    /// The readings taken between steps, and the largest |δ| from their steps
    /// ([`Record::between_steps`]).
    pub between_steps: (usize, f64),
    /// Linear solves of the fixed-lag pass (and the batch solve).
    pub iterations: usize,
    /// The normalized innovations of the fixed-lag pass (filtered estimates).
    pub nis: Nis,
    /// Window solves of the fixed-lag pass kept at the iteration limit.
    pub unsettled: usize,
    /// Windows holding the start that were solved again from the filter's path,
    /// that solution kept (their cost far from a fit's); and the updates whose window
    /// kept the start for that cost alone.
    pub refits: usize,
    pub misfit_holds: usize,
    pub process_sigma: f64,
    /// Whether the process σ is the scene's (else the default, or the readings').
    pub scene_process_sigma: bool,
    /// Where the process σ came from.
    pub process_source: ProcessSource,
    /// The most steps a window held (the window asked, or more where its oldest
    /// step was less certain than its newest), and the mean over the updates.
    pub longest_window: usize,
    pub mean_window: f64,
    /// The watched coordinates (the scene's independent ones, else every q) whose
    /// σ stayed of the order of their start prior's: no reading determines them.
    pub undetermined: Vec<Undetermined>,
    /// The identified parameters at the end of the record (empty: none identified).
    pub identification: Identification,
}

/// The factors of one step's readings, each with its noise: an `input` sensor's on
/// the unknown input of its coordinate (at the step, where it was read between
/// steps), any other's on the motion (at its own time).
pub fn reading_factors(
    model: &Arc<Model>,
    readings: &[StepReading],
) -> Result<Vec<(Box<dyn Factor>, Noise)>> {
    readings
        .iter()
        .map(|reading| {
            let (s, v) = (reading.sensor, &reading.values);
            let sensor = &model.sensors[s];
            let noise = Noise::Isotropic(sensor.effective_sigma());
            let factor: Box<dyn Factor> = match sensor.kind {
                SensorKind::Input { .. } => Box::new(InputReading::new(model, s, v[0])?),
                _ => {
                    Box::new(Reading::new(model.clone(), s, v.clone()).taken_before(reading.before))
                }
            };
            Ok((factor, noise))
        })
        .collect()
}

/// The graph an estimate of `record` starts from: the scene's model and its start,
/// with `uncertainty`.
pub fn graph_with(
    model: &Arc<Model>,
    (coordinates, integrator): (Coordinates, Integrator),
    record: &Record,
    uncertainty: &Uncertainty,
) -> Result<EstimationGraph> {
    let mut eg = EstimationGraph::new(
        model.clone(),
        coordinates,
        integrator,
        uncertainty,
        record.dt,
        model.initial.clone(),
    )?;
    eg.graph.set_t0(record.t0);
    if let Some(first) = record.steps.first() {
        eg.guess = super::start::toward_readings(model, &eg.start, first, &uncertainty.initial_q);
    }
    Ok(eg)
}

/// Estimates the motion over `record`, handing every step to `sink` once final, in
/// step order. A failure ends the run with its error; the steps handed out before
/// stay final.
pub fn estimate(
    model: Arc<Model>,
    record: &Record,
    options: &EstimateOptions,
    sink: &mut dyn FnMut(&StepEstimate) -> Result<()>,
) -> Result<EstimateSummary> {
    estimate_with_progress(model, record, options, sink, &mut |_, _| {})
}

/// [`estimate`], telling `progress` (steps done, steps in all) after each step of
/// the fixed-lag pass.
pub fn estimate_with_progress(
    model: Arc<Model>,
    record: &Record,
    options: &EstimateOptions,
    sink: &mut dyn FnMut(&StepEstimate) -> Result<()>,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<EstimateSummary> {
    options.validate()?;
    if model.sensors.is_empty() {
        return Err(Error::InvalidArgument(
            "the scene has no sensors: an estimate needs a `sensors:` section".into(),
        ));
    }
    if record.readings() == 0 {
        return Err(Error::InvalidArgument(super::record::NO_READINGS.into()));
    }
    let mut uncertainty = Uncertainty::of(&model, record.dt);
    let (mut process_sigma, mut process_source) =
        process_noise::choose(&model, options, record, &uncertainty)?;
    uncertainty.process = process_sigma;
    let eg = graph_with(&model, options.motion(&model), record, &uncertainty)?;
    let (window, keep_all) = match options.smoothing {
        Smoothing::Window(w) => (w, false),
        Smoothing::Batch => (BATCH_START_WINDOW, true),
    };
    let settings = options.settings;
    let size = eg.size();
    if matches!(options.smoothing, Smoothing::Batch) {
        let steps = record.steps.len();
        crate::limits::ensure_fits(
            &format!("a batch estimate of {steps} steps of {size} unknowns"),
            batch_memory(steps, size),
        )
        .map_err(|e| match e {
            Error::InvalidArgument(m) => Error::InvalidArgument(format!(
                "{m}: a fixed-lag estimate (--window N, or window=N in Python) holds a \
                 memory that does not grow with the record"
            )),
            e => e,
        })?;
    }
    let mut determination =
        Determination::new(&watched_coordinates(&model), &uncertainty.initial_q);
    // The parameters' estimate and covariance at the last step handed out: the
    // estimate from the whole record.
    let params_at = eg.parameters_at();
    let mut last_parameters: Option<(Vec<f64>, Vec<f64>)> = None;
    let sink = &mut |e: &StepEstimate| {
        determination.add(&e.covariance, size);
        if let Some((at, np)) = params_at {
            let c = (0..np * np)
                .map(|k| e.covariance[(at + k / np) * size + at + k % np])
                .collect();
            last_parameters = Some((e.x[at..at + np].to_vec(), c));
        }
        sink(e)
    };
    let mut est = Estimator::new(model.clone(), eg, window, settings, keep_all)?;
    if keep_all {
        est = est.settling_to(BATCH_PASS_WINDOW);
    }
    let total = record.steps.len();
    let mut divergence = Divergence::default();
    for (k, readings) in record.steps.iter().enumerate() {
        let before = (est.nis.sum, est.nis.dof);
        est.near_after_gap(readings);
        let update = est.update(reading_factors(&model, readings)?)?;
        divergence
            .add(est.nis.sum - before.0, est.nis.dof - before.1)
            .map_err(|why| Error::Diverged {
                step: k,
                t: est.time(k),
                why: format!("{why}{}", divergence_advice(options.smoothing)),
            })?;
        progress(k + 1, total);
        if !keep_all {
            for f in &update.finals {
                sink(f)?;
            }
        }
    }
    let rest = est.finish()?;
    let identification_of = |last: &Option<(Vec<f64>, Vec<f64>)>| match (last, &model.parameters) {
        (Some((p, c)), Some(params)) => {
            Identification::new(&params.names, p, c, &params.values, &uncertainty.parameters)
        }
        _ => Identification::default(),
    };
    let steps = record.steps.len();
    let mut iterations = est.iterations;
    let mut lowered_parameters = Vec::new();
    match options.smoothing {
        Smoothing::Window(_) => {
            for f in &rest {
                sink(f)?;
            }
        }
        Smoothing::Batch => {
            // Parameters carry the model's bias: the default σ may be lowered to
            // what the identified model's residuals show.
            let lower = process_source == ProcessSource::Default && model.parameters.is_some();
            let batch = Batch {
                model: &model,
                record,
                options,
                uncertainty: &uncertainty,
                lower,
            };
            let (its, lowered) = batch.smooth_all(&est, steps, sink)?;
            iterations += its;
            if let Some(l) = lowered {
                process_source = ProcessSource::Identified {
                    from: process_sigma,
                    used: l.first_use,
                };
                process_sigma = l.sigma;
                lowered_parameters = l.parameters;
            }
        }
    }
    let mut identification = identification_of(&last_parameters);
    if !lowered_parameters.is_empty() && !identification.is_empty() {
        identification = identification.with_lowered(&lowered_parameters);
    }
    Ok(EstimateSummary {
        coordinates: options.coordinates,
        integrator: options.motion(&model).1,
        steps,
        dt: record.dt,
        smoothing: options.smoothing,
        readings: record.readings(),
        between_steps: record.between_steps(),
        iterations,
        nis: est.nis.clone(),
        unsettled: est.unsettled,
        refits: est.refits,
        misfit_holds: est.misfit_holds,
        process_sigma,
        scene_process_sigma: model.estimation.process_sigma.is_some(),
        process_source,
        undetermined: determination.undetermined(),
        longest_window: est.held_most,
        mean_window: est.mean_window(),
        identification,
    })
}

/// Bytes a batch estimate of `steps` steps of `size` unknowns holds at its peak,
/// roughly: a lowering stage's graph and solver (normal equations, their factor,
/// the reduced rows of each step) beside the last stage's estimate and every
/// step's covariance, and the pass's estimator.
pub fn batch_memory(steps: usize, size: usize) -> f64 {
    let s = size as f64;
    steps as f64 * (BATCH_BYTES_PER_SQUARE * s * s + BATCH_BYTES_PER_UNKNOWN * s)
}

/// [`batch_memory`]'s terms, a little above a fit to the growth of the peak resident
/// size from 2001 to 20,001 steps of batch identifications with 11 to 24 unknowns a
/// step (13.6 to 39.7 kB a step).
const BATCH_BYTES_PER_SQUARE: f64 = 34.0;
const BATCH_BYTES_PER_UNKNOWN: f64 = 950.0;

/// How many of the latest steps with readings the divergence test reads.
const DIVERGENCE_STEPS: usize = 100;
/// The mean NIS over [`DIVERGENCE_STEPS`], as a multiple of its expected value, past
/// which the estimate has left the motion: far beyond any process or sensor σ set a
/// few times too small (σ's 30 times too small give 1000), as where a window settled
/// on the wrong one of two motions that fit the start.
const DIVERGED: f64 = 1000.0;

/// Where a step's solve failed (not converged, or diverged) with the step left at the
/// readings' period (no `dt` chosen): the advice to step finer, the readings then falling on or between steps.
/// A motion fast for the readings' period (a 1 cm link whipped by a stiff spring,
/// read at 200 Hz) fails there and holds at a fifth of it.
pub fn finer_step_advice(error: &Error, options: &EstimateOptions, dt: f64) -> Option<String> {
    // Not a singular system: that is a direction no reading determines (a long gap
    // without readings), which a finer step does not mend.
    let failed_step = matches!(error, Error::NotConverged { .. } | Error::Diverged { .. });
    (failed_step && options.dt.is_none()).then(|| {
        format!(
            "the motion may be too fast for steps of the readings' period ({} s): a smaller \
             dt (--dt {}, or dt= in Python) puts steps between the readings",
            crate::io::three_digits(dt),
            crate::io::three_digits(dt / 5.0)
        )
    })
}

/// What a diverged run may change: the sensors' σ's (far below the readings' noise,
/// they give such a NIS from the first steps), else a longer window; a batch's
/// fixed-lag pass is the one that left the motion.
fn divergence_advice(smoothing: Smoothing) -> &'static str {
    match smoothing {
        Smoothing::Window(_) => {
            "; check the sensors' `sigma` against the readings' noise (30 times too small \
             gives 1000), else a longer --window, or --batch, may hold to the motion"
        }
        Smoothing::Batch => {
            "; check the sensors' `sigma` against the readings' noise (30 times too small \
             gives 1000), and the model (the batch starts from a fixed-lag pass, which left \
             the motion)"
        }
    }
}

/// The NIS of the latest steps with readings, for the divergence test.
#[derive(Default)]
struct Divergence {
    recent: std::collections::VecDeque<(f64, usize)>,
    sum: f64,
    dof: usize,
}

impl Divergence {
    /// Adds a step's NIS and its degrees of freedom (none: a step without readings);
    /// the reason, once the latest steps' mean NIS is [`DIVERGED`] times its expected.
    fn add(&mut self, nis: f64, dof: usize) -> std::result::Result<(), String> {
        if dof == 0 {
            return Ok(());
        }
        self.recent.push_back((nis, dof));
        self.sum += nis;
        self.dof += dof;
        if self.recent.len() > DIVERGENCE_STEPS {
            let (n, d) = self.recent.pop_front().expect("a step to drop");
            self.sum -= n;
            self.dof -= d;
        }
        let steps = self.recent.len();
        let (mean, expected) = (self.sum / steps as f64, self.dof as f64 / steps as f64);
        if steps < DIVERGENCE_STEPS || mean <= DIVERGED * expected {
            return Ok(());
        }
        Err(format!(
            "the last {steps} steps' readings give a mean NIS of {mean:.2e} against {expected} \
             expected"
        ))
    }
}

/// The most stages of the lowering of the process σ after identification, each
/// to at most [`MAX_CUT`] times smaller: a homotopy, every stage's solve started
/// from the last one's estimate, which a σ far smaller would leave in a narrow
/// curved valley (Gauss–Newton steps that overshoot, damped ones that crawl).
const MAX_STAGES: usize = 8;
/// The largest factor a stage lowers σ by.
const MAX_CUT: f64 = 10.0;
/// The lowest σ, as a fraction of the default: below it the dynamics' weight
/// swamps the readings' in double precision long before the estimate could gain.
const LOWEST: f64 = 1e-3;
/// Matched: the residuals use at least this share of their expected χ², and at
/// most its inverse.
const MATCHED: f64 = 0.8;
/// The degrees of freedom of the dynamics residuals below which their χ² says
/// nothing of the process σ.
const SEEN_DOF: f64 = 1.0;

/// The choice of each stage's σ: covariance matching's fixed point σ² = σ²·χ²/dof,
/// approached from above.
///
/// The first stage takes matching's step, σ·√(χ²/dof). The next ones take the
/// secant's root of ln ratio in ln σ through the last two stages, which reaches the
/// fixed point in a few stages where matching's steps shrink (the estimate
/// absorbing its residuals as σ falls, the ratio barely rising); where the ratio
/// does not rise as σ falls, the fixed point lies far below, and the stage cuts by
/// [`MAX_CUT`], as it does at most. A stage past the fixed point (too much of the
/// χ² used) is followed by the root between it and the last stage short of it.
///
/// Where the estimate absorbs all but a fraction of one degree of freedom of the
/// residuals, the readings do not see the process noise at that σ, and their ratio
/// says little: the stage cuts by MAX_CUT², the estimate hardly moving from one
/// such σ to the next, unless the ratio is already matched.
#[derive(Debug, Default)]
struct Lowering {
    /// (ln σ, ln ratio) of the last stage whose residuals the readings saw.
    last: Option<(f64, f64)>,
    /// The last such stage short of the fixed point, and the last one past it.
    under: Option<(f64, f64)>,
    over: Option<(f64, f64)>,
}

impl Lowering {
    /// The next stage's σ from this stage's (σ and what its residuals used), or
    /// `None` where σ is matched (or was too small at the start: never raised).
    fn next(&mut self, sigma: f64, used: DynamicsUse) -> Option<f64> {
        let ratio = used.ratio().max(f64::MIN_POSITIVE);
        let seen = used.dof >= SEEN_DOF;
        if (seen && (MATCHED..=1.0 / MATCHED).contains(&ratio)) || (!seen && ratio >= MATCHED) {
            return None;
        }
        if !seen {
            self.last = None;
            return Some(sigma / (MAX_CUT * MAX_CUT));
        }
        let here = (sigma.ln(), ratio.ln());
        if ratio > 1.0 {
            self.over = Some(here);
        } else {
            self.under = Some(here);
        }
        let next = match (self.under, self.over) {
            (Some(a), Some(b)) => (a.0 + (b.0 - a.0) * a.1 / (a.1 - b.1)).exp(),
            (None, _) => return None,
            (Some(_), None) => {
                let cut = match self.last {
                    None => ratio.sqrt(),
                    Some((u0, v0)) => {
                        let slope = (here.1 - v0) / (here.0 - u0);
                        if slope < -RISING {
                            (-here.1 / slope).exp()
                        } else {
                            0.0
                        }
                    }
                };
                sigma * cut.clamp(1.0 / MAX_CUT, 1.0)
            }
        };
        self.last = Some(here);
        Some(next)
    }
}

/// The least rise of ln ratio per unit fall of ln σ that the secant follows.
const RISING: f64 = 0.05;

/// Where a batch lowered the process σ: the σ it ended at, the share of their
/// expected χ² the dynamics residuals used at the first σ, and the identified
/// parameters' covariance at the σ it ended at (row-major P × P, empty without).
struct Lowered {
    sigma: f64,
    first_use: f64,
    parameters: Vec<f64>,
}

/// A batch estimate of a record from a fixed-lag pass over it.
struct Batch<'a> {
    model: &'a Arc<Model>,
    record: &'a Record,
    options: &'a EstimateOptions,
    uncertainty: &'a Uncertainty,
    /// Whether the process σ may be lowered to what the residuals show.
    lower: bool,
}

impl Batch<'_> {
    /// The batch solve of every step from the fixed-lag pass's estimate, and each
    /// step's marginal covariance from it; with `lower`, the process σ lowered in
    /// stages to what the dynamics residuals show ([`DynamicsUse`]). Returns the
    /// linear solves, and where it lowered σ, the σ it ended at with the share of
    /// its expected χ² the residuals used at the first σ.
    ///
    /// The readings barely tell the process σ's below the first one apart (the
    /// residuals' χ² has a few degrees of freedom), and each narrows the parameters'
    /// covariance further: their reported covariance stays the first σ's, the
    /// widest of those the readings do not reject.
    fn smooth_all(
        &self,
        est: &Estimator,
        steps: usize,
        sink: &mut dyn FnMut(&StepEstimate) -> Result<()>,
    ) -> Result<(usize, Option<Lowered>)> {
        let settings = self.options.settings;
        let mut values = est.values().to_vec();
        let s = est.graph().size();
        let (mut first, mut iterations) = solve(&est.graph().graph, &mut values, steps, settings)?;
        let mut covariances = Vec::new();
        first.covariances_after_solve(
            &est.graph().graph,
            0,
            steps,
            Marginals::Every,
            &mut covariances,
        )?;
        // The solver holds the whole record's normal equations: freed before a
        // stage builds its own.
        drop(first);
        let params = est.graph().parameters_at();
        // The covariance at the first σ (its parameters' block).
        let at_first = params.map(|_| covariances[steps - 1].clone());
        let mut own: Option<EstimationGraph> = None;
        let mut sigma = self.uncertainty.process;
        let mut first_use = None;
        let mut ws = est.graph().graph.workspace();
        let lowest = LOWEST * sigma;
        let mut lowering = Lowering::default();
        for _ in 0..if self.lower { MAX_STAGES } else { 0 } {
            let eg = own.as_ref().unwrap_or(est.graph());
            let Some(used) = DynamicsUse::of(eg, &values, &covariances, &mut ws) else {
                break;
            };
            first_use.get_or_insert(used.ratio());
            let Some(next) = lowering.next(sigma, used) else {
                break;
            };
            let next = next.max(lowest);
            if (next - sigma).abs() <= 1e-3 * sigma {
                break;
            }
            let eg = self.graph_at(next)?;
            let mut trial = values.clone();
            // A stage that does not converge, or whose covariances fail, keeps the
            // last one's estimate.
            let Ok((mut stage, its)) = solve(&eg.graph, &mut trial, steps, settings) else {
                break;
            };
            iterations += its;
            let mut c = Vec::new();
            if stage
                .covariances_after_solve(&eg.graph, 0, steps, Marginals::Every, &mut c)
                .is_err()
            {
                break;
            }
            (values, covariances, sigma) = (trial, c, next);
            own = Some(eg);
        }
        let mut lowered_block = Vec::new();
        if let (Some((at, np)), Some(c0), true) = (params, &at_first, own.is_some()) {
            let last = &covariances[steps - 1];
            lowered_block = (0..np * np)
                .map(|k| last[(at + k / np) * s + at + k % np])
                .collect();
            for c in &mut covariances {
                for r in at..at + np {
                    c[r * s + at..r * s + at + np]
                        .copy_from_slice(&c0[r * s + at..r * s + at + np]);
                }
            }
        }
        for (k, covariance) in covariances.into_iter().enumerate() {
            sink(&StepEstimate {
                step: k,
                t: est.time(k),
                x: values[k * s..(k + 1) * s].to_vec(),
                covariance,
            })?;
        }
        let lowered = own.map(|_| Lowered {
            sigma,
            first_use: first_use.unwrap_or(f64::NAN),
            parameters: lowered_block,
        });
        Ok((iterations, lowered))
    }

    /// The estimation graph with process σ `sigma`, holding every reading of the
    /// record.
    fn graph_at(&self, sigma: f64) -> Result<EstimationGraph> {
        let mut u = self.uncertainty.clone();
        u.process = sigma;
        let mut eg = graph_with(self.model, self.options.motion(self.model), self.record, &u)?;
        for (k, readings) in self.record.steps.iter().enumerate() {
            for (factor, noise) in reading_factors(self.model, readings)? {
                eg.graph.add_soft_at(k, factor, noise)?;
            }
        }
        Ok(eg)
    }
}

/// The batch solve of every step of `graph` from `values`: the solver (its
/// linearization kept for the covariances) and its linear solves.
fn solve(
    graph: &crate::graph::ChainGraph,
    values: &mut [f64],
    steps: usize,
    settings: crate::solver::Settings,
) -> Result<(WindowSolver, usize)> {
    let mut solver = WindowSolver::new(graph, steps, settings)?;
    solver.optimize_for_batch();
    let report = solver.solve(graph, values, 0, steps, None)?;
    if report.termination != Termination::Converged {
        return Err(Error::NotConverged {
            what: "the batch estimate".into(),
            report,
        });
    }
    Ok((solver, report.iterations))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The stages `Lowering` takes from σ = 0.3 where the residuals use `ratio(σ)`
    /// of their χ² (dof 5), and the σ it stops at.
    fn stages(ratio: impl Fn(f64) -> f64) -> (Vec<f64>, f64) {
        let (mut lowering, mut sigma, mut taken) = (Lowering::default(), 0.3, Vec::new());
        for _ in 0..MAX_STAGES {
            let used = DynamicsUse {
                chi2: 5.0 * ratio(sigma),
                dof: 5.0,
            };
            let Some(next) = lowering.next(sigma, used) else {
                break;
            };
            sigma = next;
            taken.push(next);
        }
        (taken, sigma)
    }

    #[test]
    fn the_lowering_reaches_the_fixed_point_in_few_stages_and_never_ends_past_it() {
        // A power law (the estimate absorbing half its residuals' growth): matching
        // takes one step, the secant lands on the fixed point 0.05.
        let (taken, end) = stages(|s| (0.05f64 / s).powf(0.5));
        assert_eq!(taken.len(), 2, "{taken:?}");
        assert!((end / 0.05 - 1.0).abs() < 1e-9, "{taken:?}");
        // Matching's own steps would take many: σ·√ratio from 0.3 is still 40 %
        // above the fixed point after 3 steps.
        let mut s = 0.3f64;
        for _ in 0..3 {
            s *= (0.05 / s).powf(0.25);
        }
        assert!(s > 1.4 * 0.05, "{s}");
        // A ratio that does not rise as σ falls: 10× a stage after the first.
        let (taken, _) = stages(|_| 0.3);
        assert!(
            (taken[0] / (0.3 * 0.3f64.sqrt()) - 1.0).abs() < 1e-12,
            "{taken:?}"
        );
        assert!((taken[1] / taken[0] - 0.1).abs() < 1e-12, "{taken:?}");
        // A ratio that shoots past its fixed point (0.05) from a secant step: the
        // next stage raises σ back between the two, and the end is matched.
        let steep = |s: f64| {
            if s > 0.06 {
                (0.05f64 / s).powf(0.3)
            } else {
                (0.05f64 / s).powi(4)
            }
        };
        let (taken, end) = stages(steep);
        assert!(taken.iter().any(|&s| s < 0.05), "{taken:?}");
        assert!(
            (MATCHED..=1.0 / MATCHED).contains(&steep(end)),
            "{taken:?} {end}"
        );
        // Too much used at the first σ: no stage.
        assert!(stages(|_| 2.0).0.is_empty());
        // Residuals the readings do not see (dof < 1): 100× cuts.
        let mut lowering = Lowering::default();
        let unseen = DynamicsUse {
            chi2: 0.1,
            dof: 0.5,
        };
        assert_eq!(lowering.next(0.3, unseen), Some(0.3 / 100.0));
    }

    #[test]
    fn a_finer_step_is_advised_for_a_failed_step_at_the_readings_period_only() {
        let options = EstimateOptions::default();
        let diverged = Error::Diverged {
            step: 3,
            t: 0.015,
            why: "a mean NIS of 1e4".into(),
        };
        let advice = finer_step_advice(&diverged, &options, 0.005).unwrap();
        assert!(
            advice.contains("(0.005 s)") && advice.contains("--dt 0.001"),
            "{advice}"
        );
        // A step chosen by the user is theirs to change.
        let chosen = EstimateOptions {
            dt: Some(0.005),
            ..EstimateOptions::default()
        };
        assert_eq!(finer_step_advice(&diverged, &chosen, 0.005), None);
        // A singular system is a direction no reading determines (a long gap), which a
        // finer step does not mend.
        let singular = Error::Singular {
            what: "the information matrix".into(),
            step: Some(13126),
            t: Some(65.63),
        };
        assert_eq!(finer_step_advice(&singular, &options, 0.005), None);
    }
}
