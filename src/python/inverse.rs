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
    out.set_item("summary", summary)?;
    out.set_item("failures", PyList::empty(py))?;
    Ok(out)
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
#[pyo3(signature = (scene, trajectory, columns, values, coords, start, max_iterations, effects))]
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
