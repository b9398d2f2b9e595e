//! An estimate of a whole record: the fixed-lag smoother over it, or the batch
//! solve of every step started from a fixed-lag pass, each step handed out final
//! with its covariance.

use super::consistency::Nis;
use super::determination::{watched_coordinates, Determination, Undetermined};
use super::graph::EstimationGraph;
use super::identification::Identification;
use super::online::{Estimator, StepEstimate};
use super::options::{EstimateOptions, Smoothing, Uncertainty, BATCH_START_WINDOW};
use super::process_noise::{self, ProcessSource};
use super::record::Record;
use crate::coordinates::Coordinates;
use crate::error::{Error, Result};
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
    pub steps: usize,
    pub dt: f64,
    pub smoothing: Smoothing,
    pub readings: usize,
    /// Linear solves of the fixed-lag pass (and the batch solve).
    pub iterations: usize,
    /// The normalized innovations of the fixed-lag pass (filtered estimates).
    pub nis: Nis,
    /// Window solves of the fixed-lag pass kept at the iteration limit.
    pub unsettled: usize,
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
/// the unknown input of its coordinate, any other's on the motion.
pub fn reading_factors(
    model: &Arc<Model>,
    readings: &[(usize, Vec<f64>)],
) -> Result<Vec<(Box<dyn Factor>, Noise)>> {
    readings
        .iter()
        .map(|(s, v)| {
            let sensor = &model.sensors[*s];
            let noise = Noise::Isotropic(sensor.effective_sigma());
            let factor: Box<dyn Factor> = match sensor.kind {
                SensorKind::Input { .. } => Box::new(InputReading::new(model, *s, v[0])?),
                _ => Box::new(Reading::new(model.clone(), *s, v.clone())),
            };
            Ok((factor, noise))
        })
        .collect()
}

/// The graph an estimate of `record` starts from: the scene's model and its start,
/// with `uncertainty`.
pub fn graph_with(
    model: &Arc<Model>,
    coordinates: Coordinates,
    record: &Record,
    uncertainty: &Uncertainty,
) -> Result<EstimationGraph> {
    let mut eg = EstimationGraph::new(
        model.clone(),
        coordinates,
        uncertainty,
        record.dt,
        model.initial.clone(),
    )?;
    eg.graph.set_t0(record.t0);
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
    let mut uncertainty = Uncertainty::of(&model);
    let (process_sigma, process_source) =
        process_noise::choose(&model, options, record, &uncertainty)?;
    uncertainty.process = process_sigma;
    let eg = graph_with(&model, options.coordinates, record, &uncertainty)?;
    let (window, keep_all) = match options.smoothing {
        Smoothing::Window(w) => (w, false),
        Smoothing::Batch => (BATCH_START_WINDOW, true),
    };
    let settings = options.settings;
    let size = eg.size();
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
    let total = record.steps.len();
    for (k, readings) in record.steps.iter().enumerate() {
        let update = est.update(reading_factors(&model, readings)?)?;
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
    match options.smoothing {
        Smoothing::Window(_) => {
            for f in &rest {
                sink(f)?;
            }
        }
        Smoothing::Batch => {
            iterations += smooth_all(&model, &mut est, steps, settings, sink)?;
        }
    }
    let identification = identification_of(&last_parameters);
    Ok(EstimateSummary {
        coordinates: options.coordinates,
        steps,
        dt: record.dt,
        smoothing: options.smoothing,
        readings: record.readings(),
        iterations,
        nis: est.nis.clone(),
        unsettled: est.unsettled,
        process_sigma,
        scene_process_sigma: model.estimation.process_sigma.is_some(),
        process_source,
        undetermined: determination.undetermined(),
        longest_window: est.held_most,
        mean_window: est.mean_window(),
        identification,
    })
}

/// The batch solve of every step from the fixed-lag pass's estimate, and each
/// step's marginal covariance from it.
fn smooth_all(
    _model: &Arc<Model>,
    est: &mut Estimator,
    steps: usize,
    settings: crate::solver::Settings,
    sink: &mut dyn FnMut(&StepEstimate) -> Result<()>,
) -> Result<usize> {
    let graph = &est.graph().graph;
    let mut values = est.values().to_vec();
    let s = est.graph().size();
    let mut solver = WindowSolver::new(graph, steps, settings)?;
    solver.optimize_for_batch();
    let report = solver.solve(graph, &mut values, 0, steps, None)?;
    if report.termination != Termination::Converged {
        return Err(Error::NotConverged {
            what: "the batch estimate".into(),
            report,
        });
    }
    let mut covariances = Vec::new();
    solver.covariances_after_solve(graph, 0, steps, Marginals::Every, &mut covariances)?;
    for (k, covariance) in covariances.into_iter().enumerate() {
        sink(&StepEstimate {
            step: k,
            t: est.time(k),
            x: values[k * s..(k + 1) * s].to_vec(),
            covariance,
        })?;
    }
    Ok(report.iterations)
}
