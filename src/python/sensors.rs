//! Sensors from Python: their descriptions and readings with Jacobians (methods of
//! `Model`, whose bodies are here), and `mbfg.measure`.

use super::args::{arg_count, arg_path, arg_real, describe};
use super::errors::{arg_error, guard, invalid};
use super::inverse::table_from;
use super::model::study_model;
use crate::io::{read_table, trajectory_from_table};
use crate::Model;
use numpy::{PyArray1, PyArray2, PyArrayMethods};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};

/// `Model.sensors()`: one dict per sensor.
pub(super) fn sensor_list<'py>(py: Python<'py>, model: &Model) -> PyResult<Bound<'py, PyList>> {
    let list = PyList::empty(py);
    for s in &model.sensors {
        let d = PyDict::new(py);
        d.set_item("name", &s.name)?;
        d.set_item("type", s.type_name())?;
        d.set_item("columns", s.columns())?;
        d.set_item("sigma", s.sigma)?;
        d.set_item("rate", s.rate)?;
        d.set_item("resolution", s.resolution)?;
        d.set_item("effective_sigma", s.effective_sigma())?;
        d.set_item("reads", s.reads().to_vec())?;
        list.append(d)?;
    }
    Ok(list)
}

/// A row-major dim × n block as a 2-D array.
fn block(py: Python<'_>, v: Vec<f64>, dim: usize, n: usize) -> PyResult<Bound<'_, PyArray2<f64>>> {
    PyArray1::from_vec(py, v).reshape([dim, n])
}

type Reading<'py> = (
    Bound<'py, PyArray1<f64>>,
    Bound<'py, PyArray2<f64>>,
    Bound<'py, PyArray2<f64>>,
    Bound<'py, PyArray2<f64>>,
);

/// `Model.sensor_value`: the reading h and ∂h/∂q, ∂h/∂q̇, ∂h/∂q̈.
pub(super) fn sensor_value<'py>(
    py: Python<'py>,
    model: &Model,
    name: &str,
    state: [&[f64]; 3],
    t: f64,
) -> PyResult<Reading<'py>> {
    let s = model.sensor_index(name).ok_or_else(|| {
        let known: Vec<&str> = model.sensors.iter().map(|s| s.name.as_str()).collect();
        invalid(format!(
            "no sensor named '{}' (sensors: {})",
            name.chars().take(60).collect::<String>(),
            if known.is_empty() {
                "none".to_string()
            } else {
                known.join(", ")
            }
        ))
    })?;
    let sensor = &model.sensors[s];
    let (n, dim) = (model.n(), sensor.dim());
    let mut h = vec![0.0; dim];
    let (mut jq, mut jdq, mut jddq) = (vec![0.0; dim * n], vec![0.0; dim * n], vec![0.0; dim * n]);
    let [q, dq, ddq] = state;
    sensor
        .jacobians(model, t, q, dq, ddq, &mut h, &mut jq, &mut jdq, &mut jddq)
        .map_err(arg_error)?;
    Ok((
        PyArray1::from_vec(py, h),
        block(py, jq, dim, n)?,
        block(py, jdq, dim, n)?,
        block(py, jddq, dim, n)?,
    ))
}

/// `mbfg.measure`: noisy readings of the scene's sensors along a trajectory (a CSV
/// path, or `columns` and row-major `values`), as {"columns", "t", "values"} with NaN
/// where a sensor does not read.
#[pyfunction]
#[pyo3(signature = (scene, trajectory, columns, values, seed, rate))]
#[pyo3(name = "measure")]
pub(super) fn measure_run<'py>(
    py: Python<'py>,
    scene: &Bound<'py, PyAny>,
    trajectory: Option<&Bound<'py, PyAny>>,
    columns: Option<&Bound<'py, PyAny>>,
    values: Option<&Bound<'py, PyAny>>,
    seed: &Bound<'py, PyAny>,
    rate: Option<&Bound<'py, PyAny>>,
) -> PyResult<Bound<'py, PyDict>> {
    guard(|| {
        let model = study_model(scene, &[], &[], &[])?;
        let seed = arg_count(seed, "seed", 0)? as u64;
        let rate = match rate {
            Some(r) if !r.is_none() => Some(arg_real(r, "rate")?),
            _ => None,
        };
        let (table, source) = match (trajectory, columns, values) {
            (Some(path), None, None) => {
                let path = arg_path(path, "trajectory")?;
                (
                    read_table(&path).map_err(arg_error)?,
                    path.display().to_string(),
                )
            }
            (None, Some(columns), Some(values)) => {
                (table_from(columns, values)?, "trajectory".to_string())
            }
            (t, _, _) => {
                return Err(invalid(format!(
                    "trajectory: give a CSV path or a mapping of columns, got {}",
                    t.map_or("neither".to_string(), describe)
                )))
            }
        };
        let mut needed = [true, false, false];
        for s in &model.sensors {
            for (n, r) in needed.iter_mut().zip(s.reads()) {
                *n |= r;
            }
        }
        let truth =
            trajectory_from_table(&model.names, &table, &source, needed).map_err(arg_error)?;
        let m = crate::sensors::measure::measure(&model, &truth, seed, rate).map_err(arg_error)?;
        let out = PyDict::new(py);
        let (rows, w) = (m.t.len(), m.columns.len());
        out.set_item("columns", m.columns)?;
        out.set_item("t", PyArray1::from_vec(py, m.t))?;
        out.set_item("values", block(py, m.values, rows, w)?)?;
        Ok(out)
    })
}

/// `mbfg._native.read_trajectory`: a trajectory CSV (as `mbfg simulate` writes it)
/// read for the model of `scene`, as {"t", "q", "dq", "ddq"} (rows × n; q̇ and q̈
/// zero where the file has none), with mbfg's own errors: the file, the row, the
/// column.
#[pyfunction]
#[pyo3(signature = (scene, path))]
pub(super) fn read_trajectory<'py>(
    py: Python<'py>,
    scene: &Bound<'py, PyAny>,
    path: &Bound<'py, PyAny>,
) -> PyResult<Bound<'py, PyDict>> {
    guard(|| {
        let model = study_model(scene, &[], &[], &[])?;
        let path = arg_path(path, "trajectory")?;
        let table = read_table(&path).map_err(arg_error)?;
        let tr = trajectory_from_table(
            &model.names,
            &table,
            &path.display().to_string(),
            [true, false, false],
        )
        .map_err(arg_error)?;
        let (rows, n) = (tr.t.len(), model.n());
        let out = PyDict::new(py);
        out.set_item("t", PyArray1::from_vec(py, tr.t))?;
        out.set_item("q", block(py, tr.q, rows, n)?)?;
        out.set_item("dq", block(py, tr.dq, rows, n)?)?;
        out.set_item("ddq", block(py, tr.ddq, rows, n)?)?;
        Ok(out)
    })
}
