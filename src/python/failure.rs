//! Why a run failed, as data: the `.failure` dict of a `SolveError`, so that a
//! caller reads the step, the time and the cause instead of parsing the message.
//!
//! Every dict has `kind`, `message`, `step` and `t` (None where not known). By kind:
//! - `"singular-configuration"`: independent coordinates stop determining the
//!   others ahead: `located_t` (extrapolated), `independent`, `dependent`, `rank`,
//!   `full_rank`, `distance`;
//! - `"not-converged"`: `termination`, `iterations`, `cost`, `cause` (the effect
//!   or evaluation at fault, or None), `batch`, `warm_start`,
//!   `constraint_conditioning`, `fast_body` (name, turn per step) or None;
//! - `"too-coarse"`: the step converged but a body turned more than half a radian
//!   over it (refinement off): `fast_body` (name, turn per step);
//! - `"singular"`: `what`;
//! - `"data"`: `file`, `line`;
//! - `"position-problem"`: `violated` (name, |Φ|) pairs;
//! - `"invalid-argument"`, `"scene"`, `"io"`: the message says it all.

use crate::forward::StepFailure;
use crate::Error;
use pyo3::prelude::*;
use pyo3::types::PyDict;

/// A failed step of a forward run.
pub(super) fn step_failure<'py>(py: Python<'py>, f: &StepFailure) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("message", f.message())?;
    d.set_item("step", f.step)?;
    d.set_item("t", crate::trajectory::round_time(f.t))?;
    if f.is_too_coarse() {
        d.set_item("kind", "too-coarse")?;
        d.set_item("fast_body", f.fast_body.clone())?;
        return Ok(d);
    }
    match &f.singular {
        Some(c) => {
            d.set_item("kind", "singular-configuration")?;
            d.set_item("located_t", c.t_singular)?;
            d.set_item("independent", c.independent.clone())?;
            d.set_item("dependent", c.dependent.clone())?;
            d.set_item("rank", c.rank)?;
            d.set_item("full_rank", c.full_rank)?;
            d.set_item("distance", c.distance)?;
        }
        None => {
            d.set_item("kind", "not-converged")?;
            d.set_item("termination", f.report.termination.to_string())?;
            d.set_item("iterations", f.report.iterations)?;
            d.set_item("cost", f.report.cost)?;
            d.set_item("cause", f.cause.clone())?;
            d.set_item("batch", f.batch)?;
            d.set_item("warm_start", f.warm_start)?;
            d.set_item("constraint_conditioning", f.constraint_conditioning)?;
            d.set_item("fast_body", f.fast_body.clone())?;
        }
    }
    Ok(d)
}

/// A library error.
pub(super) fn error_failure<'py>(py: Python<'py>, e: &Error) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("message", e.to_string())?;
    d.set_item("step", py.None())?;
    d.set_item("t", py.None())?;
    let kind = match e {
        Error::Singular { what, step, t } => {
            d.set_item("what", what)?;
            d.set_item("step", *step)?;
            d.set_item("t", *t)?;
            "singular"
        }
        Error::NotConverged { report, .. } => {
            d.set_item("termination", report.termination.to_string())?;
            d.set_item("iterations", report.iterations)?;
            d.set_item("cost", report.cost)?;
            d.set_item("cause", report.cause.clone())?;
            "not-converged"
        }
        Error::Data { file, line, .. } => {
            d.set_item("file", file.clone())?;
            d.set_item("line", *line)?;
            "data"
        }
        Error::PositionProblem { violated, .. } => {
            d.set_item("violated", violated.clone())?;
            "position-problem"
        }
        Error::Diverged { step, t, .. } => {
            d.set_item("step", *step)?;
            d.set_item("t", *t)?;
            "diverged"
        }
        Error::InvalidArgument(_) => "invalid-argument",
        Error::Scene(_) => "scene",
        Error::Io { .. } => "io",
    };
    d.set_item("kind", kind)?;
    Ok(d)
}

/// `err` with its `.failure` set.
pub(super) fn with_failure(py: Python<'_>, err: PyErr, failure: Bound<'_, PyDict>) -> PyErr {
    // Setting an attribute on an exception instance does not fail in practice; if it
    // did, the exception's message still says what happened.
    let _ = err.value(py).setattr("failure", failure);
    err
}
