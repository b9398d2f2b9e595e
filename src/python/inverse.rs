//! `mbfg.inverse`: inverse dynamics from a CSV file or from a table given as columns
//! and values, and its result as a dict.

use super::args::{arg_choice, arg_count, arg_numbers, arg_path, describe};
use super::effects::{arg_effects, interrupted, raised, with_loads};
use super::errors::{arg_error, guard, invalid, one_line, SolveError};
use super::failure::{error_failure, with_failure};
use super::model::study_model;
use super::run::{coordinates, run_table, with_result};
use crate::inverse::{self, InverseOptions, InverseSolution, Prescription, Start};
use crate::io::{read_table, Table};
use crate::solver::Termination;
use crate::Error;
use numpy::PyArray1;
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList, PyString};

/// An inverse solve's result; `converged` False marks the last iterate of a solve
/// that did not converge.
fn inverse_result<'py>(py: Python<'py>, sol: &InverseSolution) -> PyResult<Bound<'py, PyDict>> {
    let s = &sol.summary;
    let out = run_table(py, &sol.trajectory, Some(&sol.forces))?;
    let converged = s.report.termination == Termination::Converged;
    let summary = PyDict::new(py);
    summary.set_item("steps", s.steps)?;
    summary.set_item("requested_steps", s.steps)?;
    summary.set_item("wall_time", s.wall_time.as_secs_f64())?;
    summary.set_item("iterations", s.report.iterations)?;
    summary.set_item("worst_tracking", s.worst_tracking)?;
    summary.set_item("worst_phi", s.worst_phi)?;
    summary.set_item("converged", converged)?;
    summary.set_item("termination", s.report.termination.to_string())?;
    summary.set_item("cost", s.report.cost)?;
    summary.set_item("interrupted", py.None())?;
    summary.set_item("complete", converged)?;
    if let (Some(fits), Some(sd)) = (&s.smoothing, &sol.sigmas) {
        let list = PyList::empty(py);
        for f in fits {
            let d = PyDict::new(py);
            d.set_item("sigma", f.sigma)?;
            d.set_item("from_data", f.from_data)?;
            let (noise, digits) = match f.noise {
                inverse::NoiseShape::Uniform => ("uniform", None),
                inverse::NoiseShape::Rounding { digits } => ("rounding", Some(digits)),
            };
            d.set_item("noise", noise)?;
            d.set_item("digits", digits)?;
            d.set_item("intensity", f.intensity)?;
            d.set_item("residual_rms", f.residual_rms)?;
            d.set_item("worst_residual", f.worst_residual.0)?;
            d.set_item("worst_sample", f.worst_residual.1)?;
            list.append(d)?;
        }
        summary.set_item("smoothing", list)?;
        summary.set_item("sample_intervals", s.off_grid.map(|(a, b)| vec![a, b]))?;
        // The standard deviations as the CLI writes them: sd:q, sd:dq, sd:ddq, sd:Q.
        let names = &sol.trajectory.names;
        let n = names.len();
        let mut columns = Vec::with_capacity(4 * n);
        for part in ["q", "dq", "ddq", "Q"] {
            columns.extend(names.iter().map(|c| format!("sd:{part}:{c}")));
        }
        let steps = sd.q.len().checked_div(n).unwrap_or(0);
        let mut values = Vec::with_capacity(steps * 4 * n);
        for k in 0..steps {
            for part in [&sd.q, &sd.dq, &sd.ddq, &sd.forces] {
                values.extend_from_slice(&part[k * n..(k + 1) * n]);
            }
        }
        out.set_item("extra_columns", columns)?;
        out.set_item("extra", PyArray1::from_vec(py, values))?;
    } else {
        summary.set_item("smoothing", py.None())?;
        summary.set_item("sample_intervals", py.None())?;
    }
    out.set_item("summary", summary)?;
    out.set_item("failures", PyList::empty(py))?;
    Ok(out)
}

/// `sample_sigma`: None, a number for every prescribed column, "auto", or a dict
/// {coordinate: σ} naming every prescribed column.
fn arg_sample_sigma(
    value: &Bound<'_, PyAny>,
    columns: &[&str],
) -> PyResult<Option<inverse::SampleSigma>> {
    use inverse::SampleSigma;
    if value.is_none() {
        return Ok(None);
    }
    let positive = |v: &Bound<'_, PyAny>, what: &str| -> PyResult<f64> {
        match v.extract::<f64>() {
            Ok(x) if x.is_finite() && x > 0.0 && !v.is_instance_of::<pyo3::types::PyBool>() => {
                Ok(x)
            }
            _ => Err(invalid(format!(
                "{what} must be a positive number, got {}",
                describe(v)
            ))),
        }
    };
    if let Ok(text) = value.extract::<String>() {
        if text == "auto" {
            return Ok(Some(SampleSigma::FromData));
        }
        return Err(invalid(format!(
            "sample_sigma must be None, a positive number, \"auto\" or a dict {{coordinate: σ}}, got {}",
            describe(value)
        )));
    }
    if let Ok(dict) = value.cast::<PyDict>() {
        let mut given: Vec<Option<f64>> = vec![None; columns.len()];
        for (k, v) in dict.iter() {
            let name: String = k.extract().map_err(|_| {
                invalid(format!(
                    "sample_sigma: keys must be coordinate names, got {}",
                    describe(&k)
                ))
            })?;
            let Some(c) = columns.iter().position(|c| *c == name) else {
                return Err(invalid(format!(
                    "sample_sigma: '{}' is not a prescribed coordinate; the trajectory's are {}",
                    one_line(&name).chars().take(60).collect::<String>(),
                    columns.join(", ")
                )));
            };
            given[c] = Some(positive(&v, &format!("sample_sigma['{name}']"))?);
        }
        return SampleSigma::per_column(columns, given)
            .map(Some)
            .map_err(|why| invalid(format!("sample_sigma: {why}")));
    }
    let v = positive(value, "sample_sigma")?;
    Ok(Some(SampleSigma::Given(vec![v; columns.len()])))
}

/// The prescribed motion given as columns and row-major values.
pub(super) fn table_from(columns: &Bound<'_, PyAny>, values: &Bound<'_, PyAny>) -> PyResult<Table> {
    let bad_columns = || {
        invalid(format!(
            "columns must be a list of strings, got {}",
            describe(columns)
        ))
    };
    if columns.is_instance_of::<PyString>() {
        return Err(bad_columns());
    }
    let columns: Vec<String> = columns.extract().map_err(|_| bad_columns())?;
    if columns.is_empty() {
        return Err(invalid(
            "columns is empty: the trajectory needs `t` and a coordinate",
        ));
    }
    let values = arg_numbers(values, "values")?;
    let w = columns.len();
    if values.len() % w != 0 {
        return Err(invalid(format!(
            "values: {} numbers do not fill whole rows of the {w} columns",
            values.len()
        )));
    }
    if let Some(i) = values.iter().position(|v| !v.is_finite()) {
        return Err(invalid(format!(
            "trajectory: column '{}' holds NaN or Inf at row {}",
            one_line(&columns[i % w])
                .chars()
                .take(60)
                .collect::<String>(),
            i / w
        )));
    }
    let rows = values.len() / w;
    Ok(Table {
        columns,
        values,
        rows,
    })
}

/// Inverse dynamics: `trajectory` is a CSV path, or `columns` and row-major `values`
/// of a table. Every argument is required (`mbfg.inverse` gives the defaults). One
/// batch solve: Ctrl-C takes effect when it returns.
#[pyfunction]
#[pyo3(signature = (scene, trajectory, columns, values, coords, start, max_iterations, effects, sample_sigma=None))]
#[pyo3(name = "inverse")]
#[allow(clippy::too_many_arguments)] // the CLI's options, one keyword each
pub(super) fn inverse_run<'py>(
    py: Python<'py>,
    scene: &Bound<'py, PyAny>,
    trajectory: Option<&Bound<'py, PyAny>>,
    columns: Option<&Bound<'py, PyAny>>,
    values: Option<&Bound<'py, PyAny>>,
    coords: &Bound<'py, PyAny>,
    start: &Bound<'py, PyAny>,
    max_iterations: &Bound<'py, PyAny>,
    effects: &Bound<'py, PyAny>,
    sample_sigma: Option<&Bound<'py, PyAny>>,
) -> PyResult<Bound<'py, PyDict>> {
    guard(|| {
        let loads = arg_effects(effects)?;
        let model = with_loads(study_model(scene, &[], &[], &[])?, &loads)?;
        let coordinates = coordinates(coords)?;
        let start = match arg_choice(start, "start", &["kinematic", "staged"])? {
            "kinematic" => Start::Kinematic,
            _ => Start::Staged,
        };
        let max_iterations = arg_count(max_iterations, "max_iterations", 1)?;
        let (table, source) = match (trajectory, columns, values) {
            (Some(path), None, None) => {
                let path = arg_path(path, "trajectory")?;
                let table = read_table(&path)
                    .map_err(|e| invalid(format!("trajectory: {}", one_line(&e.to_string()))))?;
                (table, path.display().to_string())
            }
            (None, Some(columns), Some(values)) => {
                (table_from(columns, values)?, "trajectory".to_string())
            }
            _ => {
                return Err(invalid(
                    "trajectory: give a CSV path, or columns and values",
                ))
            }
        };
        let prescription = Prescription::from_table(&model, &table, &source).map_err(arg_error)?;
        let mut options = InverseOptions {
            coordinates,
            start,
            ..InverseOptions::default()
        };
        options.settings.max_iterations = max_iterations;
        if let Some(sigma) = sample_sigma {
            let names: Vec<&str> = prescription
                .indices
                .iter()
                .map(|&i| model.names[i].as_str())
                .collect();
            options.sample_sigma = arg_sample_sigma(sigma, &names)?;
        }
        if options.sample_sigma.is_none() {
            prescription.check_grid(&source).map_err(arg_error)?;
        }
        let sol = py
            .detach(|| inverse::solve(model, &prescription, &options))
            .map_err(
                |e| match (interrupted(&loads).or_else(|| raised(&loads)), e) {
                    (Some(python), _) => with_result(py, python, None),
                    (None, e @ Error::InvalidArgument(_)) => arg_error(e),
                    (None, other) => {
                        let err = SolveError::new_err(other.to_string());
                        let err = match error_failure(py, &other) {
                            Ok(failure) => with_failure(py, err, failure),
                            Err(e) => e,
                        };
                        with_result(py, err, None)
                    }
                },
            )?;
        let out = inverse_result(py, &sol)?;
        // The solve cannot stop midway: a Ctrl-C during it is raised now, with it
        // (one that a Python effect's call received included).
        if let Some(signal) = interrupted(&loads) {
            return Err(with_result(py, signal, Some(&out)));
        }
        py.check_signals()
            .map_err(|e| with_result(py, e, Some(&out)))?;
        let s = &sol.summary;
        if s.report.termination != Termination::Converged {
            let e = crate::Error::NotConverged {
                what: "the inverse solve".into(),
                report: s.report.clone(),
            };
            let err = with_failure(
                py,
                SolveError::new_err(e.to_string()),
                error_failure(py, &e)?,
            );
            return Err(with_result(py, err, Some(&out)));
        }
        Ok(out)
    })
}
