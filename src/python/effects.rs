//! Python callables f(t, q, q̇) → Q as effects of a run's model, and the exception
//! one raised, to be raised again in place of the run's own error.

use super::args::{arg_numbers, describe};
use super::errors::{arg_error, invalid, one_line};
use crate::{Error, Model};
use numpy::PyArray1;
use pyo3::exceptions::PyException;
use pyo3::prelude::*;
use pyo3::types::PyDict;
use std::sync::Arc;

/// A Python callable f(t, q, q̇) → Q (n generalized forces in q's order) as an effect
/// of the model. The first exception it raises is kept, to be raised again in place of
/// the failed run's SolveError.
#[derive(Debug)]
pub(super) struct PyLoad {
    name: String,
    callable: Py<PyAny>,
    raised: std::sync::Mutex<Option<PyErr>>,
    /// A KeyboardInterrupt (or SystemExit) raised inside the callable: Python ran the
    /// Ctrl-C handler there, so the run must stop on it rather than lose it.
    interrupted: std::sync::Mutex<Option<PyErr>>,
    /// q's names, for messages (set when the load joins a model).
    names: std::sync::OnceLock<Vec<String>>,
}

impl crate::model::forces::ExternalLoad for PyLoad {
    fn add_to(&self, t: f64, q: &[f64], dq: &[f64], out: &mut [f64]) -> crate::Result<()> {
        let name = &self.name;
        Python::attach(|py| {
            let args = (t, PyArray1::from_slice(py, q), PyArray1::from_slice(py, dq));
            let value = self
                .callable
                .call1(py, args)
                .and_then(|v| arg_numbers(v.bind(py), &format!("effect '{name}''s return")));
            let v = match value {
                Ok(v) => v,
                Err(e) => {
                    let message = one_line(&e.to_string());
                    if !message.contains(&format!("effect '{name}'")) {
                        // The callable's own exception, raised again as it came: a note
                        // says which effect raised it (shown under its traceback).
                        let note = format!("raised by effect '{name}' at t = {t}");
                        let _ = e.value(py).call_method1("add_note", (note,));
                    }
                    let slot = match e.is_instance_of::<PyException>(py) {
                        true => &self.raised,
                        false => &self.interrupted,
                    };
                    if let Ok(mut slot) = slot.lock() {
                        slot.get_or_insert(e);
                    }
                    return Err(Error::InvalidArgument(format!(
                        "effect '{name}' at t = {t}: {message}"
                    )));
                }
            };
            if v.len() != out.len() {
                return Err(Error::InvalidArgument(format!(
                    "effect '{name}' returned {} values at t = {t}; it must return one generalized force per coordinate of q ({})",
                    v.len(),
                    out.len()
                )));
            }
            if let Some(k) = v.iter().position(|x| !x.is_finite()) {
                let coordinate = self
                    .names
                    .get()
                    .and_then(|n| n.get(k))
                    .map_or(format!("{k}"), |n| format!("{k} ({n})"));
                return Err(Error::InvalidArgument(format!(
                    "effect '{name}' returned {} for coordinate {coordinate} at t = {t}",
                    v[k]
                )));
            }
            for (o, x) in out.iter_mut().zip(&v) {
                *o += x;
            }
            Ok(())
        })
    }
}

/// `effects` of a study: None or a dict {name: callable(t, q, dq) -> Q}.
pub(super) fn arg_effects(effects: &Bound<'_, PyAny>) -> PyResult<Vec<Arc<PyLoad>>> {
    if effects.is_none() {
        return Ok(Vec::new());
    }
    let dict = effects.cast::<PyDict>().map_err(|_| {
        invalid(format!(
            "effects must be a dict {{name: callable(t, q, dq)}}, got {}",
            describe(effects)
        ))
    })?;
    let mut out = Vec::new();
    for (k, v) in dict.iter() {
        let name: String = k.extract().map_err(|_| {
            invalid(format!(
                "effects: names must be strings, got {}",
                describe(&k)
            ))
        })?;
        if !v.is_callable() {
            return Err(invalid(format!(
                "effects: '{name}' must be a callable f(t, q, dq) returning the generalized forces, got {}",
                describe(&v)
            )));
        }
        out.push(Arc::new(PyLoad {
            name,
            callable: v.unbind(),
            raised: std::sync::Mutex::new(None),
            interrupted: std::sync::Mutex::new(None),
            names: std::sync::OnceLock::new(),
        }));
    }
    Ok(out)
}

/// `model` with the Python effects added.
pub(super) fn with_loads(model: Arc<Model>, loads: &[Arc<PyLoad>]) -> PyResult<Arc<Model>> {
    if loads.is_empty() {
        return Ok(model);
    }
    let mut m = Arc::unwrap_or_clone(model);
    for load in loads {
        let _ = load.names.set(m.names.clone());
        m.add_external_load(&load.name, load.clone())
            .map_err(|e| match e {
                Error::InvalidArgument(m) => invalid(format!("effects: {m}")),
                other => arg_error(other),
            })?;
    }
    Ok(Arc::new(m))
}

/// A KeyboardInterrupt (or SystemExit) a Python effect's call received, if any.
pub(super) fn interrupted(loads: &[Arc<PyLoad>]) -> Option<PyErr> {
    loads
        .iter()
        .find_map(|l| l.interrupted.lock().ok().and_then(|mut e| e.take()))
}

/// Whether a Python effect's call received a KeyboardInterrupt (or SystemExit).
pub(super) fn is_interrupted(loads: &[Arc<PyLoad>]) -> bool {
    loads
        .iter()
        .any(|l| l.interrupted.lock().is_ok_and(|e| e.is_some()))
}

/// The first exception a Python effect raised, if any.
pub(super) fn raised(loads: &[Arc<PyLoad>]) -> Option<PyErr> {
    loads
        .iter()
        .find_map(|l| l.raised.lock().ok().and_then(|mut e| e.take()))
}
