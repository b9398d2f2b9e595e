//! State estimation from Python: `mbfg.estimate` over a record of readings, and the
//! online `Estimator`, one step at a time.

use super::args::{arg_count, arg_numbers, arg_path, arg_real, arg_str, describe};
use super::errors::{arg_error, guard, invalid, one_line, SolveError};
use super::model::study_model;
use crate::coordinates::Coordinates;
use crate::estimate::run::{graph_with, reading_factors};
use crate::estimate::ProcessSource;
use crate::estimate::{
    estimate, EstimateOptions, Estimates, Estimator, Record, Smoothing, Uncertainty,
};
use crate::factors::Integrator;
use crate::Model;
use numpy::{PyArray1, PyArrayMethods};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyString};
use std::sync::Arc;

/// The smoothing a window and batch flag ask for.
fn smoothing(window: Option<&Bound<'_, PyAny>>, batch: bool) -> PyResult<Smoothing> {
    match (window, batch) {
        (Some(w), true) if !w.is_none() => Err(invalid("give a window or batch=True, not both")),
        (_, true) => Ok(Smoothing::Batch),
        (Some(w), false) if !w.is_none() => Ok(Smoothing::Window(arg_count(w, "window", 1)?)),
        _ => Ok(EstimateOptions::default().smoothing),
    }
}

/// "dc" or "ic".
fn coordinates(coords: &Bound<'_, PyAny>) -> PyResult<Coordinates> {
    match arg_str(coords, "coords")?.as_str() {
        "dc" => Ok(Coordinates::Dependent),
        "ic" => Ok(Coordinates::Independent),
        other => Err(invalid(format!(
            "coords must be \"dc\" or \"ic\", got {other:?}"
        ))),
    }
}

/// An estimate's integrator by name: "trapezoidal" or "hermite-simpson".
fn estimate_integrator(name: &Bound<'_, PyAny>) -> PyResult<Integrator> {
    let name = arg_str(name, "integrator")?;
    match Integrator::from_name(&name) {
        Some(i) if i != Integrator::Euler => Ok(i),
        _ => Err(invalid(format!(
            "integrator must be \"trapezoidal\" or \"hermite-simpson\", got {name:?}"
        ))),
    }
}

/// `mbfg.estimate`: {"columns", "values" (rows × columns), "summary"}.
#[pyfunction]
#[pyo3(signature = (scene, measurements, columns, values, window, batch, dt, max_iterations, coords, integrator=None))]
#[pyo3(name = "estimate")]
#[allow(clippy::too_many_arguments)]
pub(super) fn estimate_run<'py>(
    py: Python<'py>,
    scene: &Bound<'py, PyAny>,
    measurements: Option<&Bound<'py, PyAny>>,
    columns: Option<&Bound<'py, PyAny>>,
    values: Option<&Bound<'py, PyAny>>,
    window: Option<&Bound<'py, PyAny>>,
    batch: bool,
    dt: Option<&Bound<'py, PyAny>>,
    max_iterations: &Bound<'py, PyAny>,
    coords: &Bound<'py, PyAny>,
    integrator: Option<&Bound<'py, PyAny>>,
) -> PyResult<Bound<'py, PyDict>> {
    guard(|| {
        let model = study_model(scene, &[], &[], &[])?;
        let dt = match dt {
            Some(d) if !d.is_none() => Some(arg_real(d, "dt")?),
            _ => None,
        };
        let mut options = EstimateOptions {
            coordinates: coordinates(coords)?,
            smoothing: smoothing(window, batch)?,
            dt,
            integrator: match integrator {
                Some(i) if !i.is_none() => Some(estimate_integrator(i)?),
                _ => None,
            },
            ..EstimateOptions::default()
        };
        options.settings.max_iterations = arg_count(max_iterations, "max_iterations", 1)?;
        let record = match (measurements, columns, values) {
            (Some(path), None, None) => {
                Record::read(&model, &arg_path(path, "measurements")?, dt).map_err(arg_error)?
            }
            (None, Some(columns), Some(values)) => record_from(&model, columns, values, dt)?,
            (m, _, _) => {
                return Err(invalid(format!(
                    "measurements: give a CSV path or a mapping of columns, got {}",
                    m.map_or("neither".to_string(), describe)
                )))
            }
        };
        let mut table = Estimates::for_model(&model);
        let result = py.detach(|| {
            estimate(model.clone(), &record, &options, &mut |e| {
                table.push(e);
                Ok(())
            })
        });
        let out = PyDict::new(py);
        let (rows, w) = (table.rows, table.columns.len());
        out.set_item("columns", table.columns.clone())?;
        out.set_item(
            "values",
            PyArray1::from_vec(py, table.values).reshape([rows, w])?,
        )?;
        let summary = match result {
            Ok(summary) => summary,
            Err(e) => {
                let advice = crate::estimate::finer_step_advice(&e, &options, record.dt);
                return Err(run_error_with(py, e, Some(out), advice));
            }
        };
        let s = PyDict::new(py);
        s.set_item("steps", summary.steps)?;
        s.set_item(
            "coords",
            match summary.coordinates {
                Coordinates::Dependent => "dc",
                Coordinates::Independent => "ic",
            },
        )?;
        s.set_item("dt", summary.dt)?;
        s.set_item("integrator", summary.integrator.name())?;
        match summary.smoothing {
            Smoothing::Window(w) => s.set_item("window", w)?,
            Smoothing::Batch => s.set_item("window", "batch")?,
        }
        s.set_item("readings", summary.readings)?;
        s.set_item("readings_between_steps", summary.between_steps.0)?;
        s.set_item("largest_offset", summary.between_steps.1)?;
        s.set_item("window_longest", summary.longest_window)?;
        s.set_item("window_mean", summary.mean_window)?;
        s.set_item("iterations", summary.iterations)?;
        s.set_item("unsettled", summary.unsettled)?;
        s.set_item("start_refits", summary.refits)?;
        s.set_item("nis_mean", summary.nis.mean())?;
        s.set_item("nis_expected", summary.nis.expected())?;
        s.set_item("nis_bounds", summary.nis.bounds())?;
        s.set_item("nis_consistent", summary.nis.consistent())?;
        s.set_item("process_sigma", summary.process_sigma)?;
        s.set_item(
            "process_sigma_source",
            match summary.process_source {
                ProcessSource::Scene => "scene",
                ProcessSource::Default => "default",
                ProcessSource::Readings { .. } => "readings",
                ProcessSource::Unresponsive { .. } => "default",
                ProcessSource::Correlated { .. } => "default",
                ProcessSource::Identified { .. } => "identification",
            },
        )?;
        s.set_item(
            "undetermined",
            summary
                .undetermined
                .iter()
                .map(|u| model.names[u.coordinate].clone())
                .collect::<Vec<_>>(),
        )?;
        out.set_item("summary", s)?;
        let id = &summary.identification;
        let parameters = PyDict::new(py);
        for p in &id.parameters {
            let d = PyDict::new(py);
            d.set_item("estimate", p.estimate)?;
            d.set_item("sigma", p.sigma)?;
            d.set_item("sigma_lowered", p.sigma_lowered)?;
            d.set_item("prior", p.prior)?;
            d.set_item("prior_sigma", p.prior_sigma)?;
            d.set_item("identifiable", p.undetermined.is_none())?;
            d.set_item("reason", p.undetermined.clone().unwrap_or_default())?;
            parameters.set_item(&p.name, d)?;
        }
        out.set_item("parameters", parameters)?;
        let np = id.parameters.len();
        out.set_item(
            "parameter_names",
            id.parameters
                .iter()
                .map(|p| p.name.clone())
                .collect::<Vec<_>>(),
        )?;
        out.set_item(
            "parameter_correlation",
            PyArray1::from_vec(py, id.correlation.clone()).reshape([np, np])?,
        )?;
        Ok(out)
    })
}

/// A run's error: a solve that did not converge, or an estimate left undetermined,
/// as `SolveError` with the final steps so far as `.result`; anything else as the
/// input error it is.
fn run_error(py: Python<'_>, e: crate::Error, partial: Option<Bound<'_, PyDict>>) -> PyErr {
    run_error_with(py, e, partial, None)
}

/// [`run_error`] with `advice` after the error's message.
fn run_error_with(
    py: Python<'_>,
    e: crate::Error,
    partial: Option<Bound<'_, PyDict>>,
    advice: Option<String>,
) -> PyErr {
    match e {
        e @ (crate::Error::NotConverged { .. }
        | crate::Error::Singular { .. }
        | crate::Error::Diverged { .. }) => {
            let message = match advice {
                Some(a) => format!("{e}; {a}"),
                None => e.to_string(),
            };
            let mut err = SolveError::new_err(one_line(&message));
            if let Ok(failure) = super::failure::error_failure(py, &e) {
                err = super::failure::with_failure(py, err, failure);
            }
            if let Some(p) = partial {
                let _ = err.value(py).setattr("result", p);
            }
            err
        }
        other => arg_error(other),
    }
}

/// A record from columns ("t" first) and row-major values, NaN where no reading.
fn record_from(
    model: &Model,
    columns: &Bound<'_, PyAny>,
    values: &Bound<'_, PyAny>,
    dt: Option<f64>,
) -> PyResult<Record> {
    if columns.is_instance_of::<PyString>() {
        return Err(invalid("columns must be a list of strings"));
    }
    let columns: Vec<String> = columns.extract().map_err(|_| {
        invalid(format!(
            "columns must be a list of strings, got {}",
            describe(columns)
        ))
    })?;
    let values = arg_numbers(values, "values")?;
    let w = columns.len().max(1);
    if values.len() % w != 0 {
        return Err(invalid(format!(
            "values: {} numbers do not fill whole rows of the {w} columns",
            values.len()
        )));
    }
    if values.iter().any(|v| v.is_infinite()) {
        return Err(invalid("measurements: a reading is infinite"));
    }
    let rows: Vec<(f64, Vec<f64>)> = values.chunks_exact(w).map(|r| (r[0], r.to_vec())).collect();
    Record::from_rows(model, &columns, &rows, dt).map_err(|(row, m)| match row {
        Some(i) => invalid(format!("measurements, row {i}: {m}")),
        None => invalid(format!("measurements: {m}")),
    })
}

/// `mbfg.Estimator`: the fixed-lag smoother online. Each `update(t, readings)` adds
/// the steps up to t (the readings at t, none before) and returns the newest step's
/// estimate; its cost does not grow with the record. `integrator` is "trapezoidal" or
/// "hermite-simpson" (default: Hermite–Simpson where the scene identifies parameters).
#[pyclass(name = "Estimator", module = "mbfg", unsendable)]
pub struct PyEstimator {
    model: Arc<Model>,
    est: Estimator,
    t0: f64,
    dt: f64,
    /// The time of the last update's readings (its step's, or between steps).
    last: Option<f64>,
}

#[pymethods]
impl PyEstimator {
    #[new]
    #[pyo3(signature = (scene, dt, window=None, t0=None, coords=None, integrator=None))]
    fn new(
        scene: &Bound<'_, PyAny>,
        dt: &Bound<'_, PyAny>,
        window: Option<&Bound<'_, PyAny>>,
        t0: Option<&Bound<'_, PyAny>>,
        coords: Option<&Bound<'_, PyAny>>,
        integrator: Option<&Bound<'_, PyAny>>,
    ) -> PyResult<Self> {
        guard(|| {
            let model = study_model(scene, &[], &[], &[])?;
            let dt = arg_real(dt, "dt")?;
            if !(dt > 0.0) {
                return Err(invalid(format!("dt must be positive, got {dt}")));
            }
            let t0 = match t0 {
                Some(t) if !t.is_none() => arg_real(t, "t0")?,
                _ => 0.0,
            };
            let coordinates = match coords {
                Some(c) if !c.is_none() => coordinates(c)?,
                _ => Coordinates::Dependent,
            };
            let window = match window {
                Some(w) if !w.is_none() => arg_count(w, "window", 1)?,
                _ => crate::estimate::options::DEFAULT_WINDOW,
            };
            if model.sensors.is_empty() {
                return Err(invalid(
                    "the scene has no sensors: declare them in `sensors:`",
                ));
            }
            let record = Record {
                t0,
                dt,
                steps: Vec::new(),
            };
            let options = EstimateOptions {
                coordinates,
                integrator: match integrator {
                    Some(i) if !i.is_none() => Some(estimate_integrator(i)?),
                    _ => None,
                },
                ..EstimateOptions::default()
            };
            let eg = graph_with(
                &model,
                options.motion(&model),
                &record,
                &Uncertainty::of(&model, dt),
            )
            .map_err(arg_error)?;
            let est = Estimator::new(model.clone(), eg, window, options.settings, false)
                .map_err(arg_error)?;
            Ok(PyEstimator {
                model,
                est,
                t0,
                dt,
                last: None,
            })
        })
    }

    /// Adds the readings at time t ({column: value}; NaN or absent: no reading) and
    /// returns the newest step's estimate: {"t", "q", "dq", "ddq", "sd_q", "sd_dq",
    /// "sd_ddq", "Q", "sd_Q", "nis"}.
    fn update<'py>(
        &mut self,
        py: Python<'py>,
        t: &Bound<'py, PyAny>,
        readings: &Bound<'py, PyDict>,
    ) -> PyResult<Bound<'py, PyDict>> {
        guard(|| {
            let t = arg_real(t, "t")?;
            // Readings between steps are taken at the nearest step, δ before it.
            let k = (t - self.t0) / self.dt;
            let step = k.round();
            if !(0.0..=1e12).contains(&step) {
                return Err(invalid(format!(
                    "t = {t} is before t0 = {} or too far after it for steps of {} s",
                    self.t0, self.dt
                )));
            }
            let before = if (k - step).abs() > 1e-6 * step.abs().max(1.0) {
                self.t0 + step * self.dt - t
            } else {
                0.0
            };
            let step = step as usize;
            let next = self.est.next_step();
            if step < next {
                let held = self.est.time(next.saturating_sub(1));
                return Err(invalid(match self.last {
                    Some(last) if t <= last => {
                        format!("t = {t} is before the last update's time {last}")
                    }
                    _ => format!(
                        "t = {t} is nearest the step at {held}, which the last update \
                         already holds: readings between steps go to their nearest \
                         step, one update per step (a smaller dt gives each its own)"
                    ),
                }));
            }
            let mut columns = vec!["t".to_string()];
            let mut row = vec![t];
            for (key, value) in readings.iter() {
                let name: String = key
                    .extract()
                    .map_err(|_| invalid("readings: keys must be column names (strings)"))?;
                columns.push(name);
                let v: f64 = value.extract().map_err(|_| {
                    invalid(format!(
                        "readings: {} must be a number",
                        columns[columns.len() - 1]
                    ))
                })?;
                if v.is_infinite() {
                    return Err(invalid(format!(
                        "readings: {} is infinite",
                        columns[columns.len() - 1]
                    )));
                }
                row.push(v);
            }
            let mut record = Record::from_rows(&self.model, &columns, &[(t, row)], Some(self.dt))
                .map_err(|(_, m)| invalid(format!("readings: {m}")))?;
            for reading in &mut record.steps[0] {
                reading.before = before;
            }
            if step == 0 {
                let initial_q = Uncertainty::of(&self.model, self.dt).initial_q;
                self.est.begin_near(&record.steps[0], &initial_q);
            }
            let factors = reading_factors(&self.model, &record.steps[0])
                .map_err(|e| run_error(py, e, None))?;
            for _ in next..step {
                self.est
                    .update(Vec::new())
                    .map_err(|e| run_error(py, e, None))?;
            }
            self.est.near_after_gap(&record.steps[0]);
            let u = self
                .est
                .update(factors)
                .map_err(|e| run_error(py, e, None))?;
            self.last = Some(t);
            let e = &u.newest;
            let n = self.model.n();
            let graph = self.est.graph();
            let at = graph.inputs_at();
            let inputs = at..at + graph.inputs.len();
            let parameters = graph.parameters_at().map_or(0..0, |(p, np)| p..p + np);
            let sd = e.sd();
            let out = PyDict::new(py);
            out.set_item("t", e.t)?;
            let arr = |v: &[f64]| PyArray1::from_vec(py, v.to_vec());
            out.set_item("q", arr(&e.x[..n]))?;
            out.set_item("dq", arr(&e.x[n..2 * n]))?;
            out.set_item("ddq", arr(&e.x[2 * n..3 * n]))?;
            out.set_item("Q", arr(&e.x[inputs.clone()]))?;
            out.set_item("p", arr(&e.x[parameters.clone()]))?;
            out.set_item("sd_q", arr(&sd[..n]))?;
            out.set_item("sd_dq", arr(&sd[n..2 * n]))?;
            out.set_item("sd_ddq", arr(&sd[2 * n..3 * n]))?;
            out.set_item("sd_Q", arr(&sd[inputs]))?;
            out.set_item("sd_p", arr(&sd[parameters]))?;
            out.set_item("nis", u.nis)?;
            Ok(out)
        })
    }

    /// The coordinates' names (the order of q).
    #[getter]
    fn names(&self) -> Vec<String> {
        self.model.names.clone()
    }
}
