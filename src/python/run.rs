//! What the forward and inverse runs share: the coordinates
//! argument, the result table, a result attached to the exception of a run that
//! failed, and a run with the GIL released that Ctrl-C can stop.

use super::args::arg_choice;
use crate::forward::{Coordinates, Trajectory};
use pyo3::prelude::*;
use pyo3::types::{PyByteArray, PyDict};
use std::ops::ControlFlow;
use std::time::{Duration, Instant};

/// How often a run looks for a pending signal (Ctrl-C): each look takes the GIL.
const SIGNAL_CHECK: Duration = Duration::from_millis(25);

pub(super) fn coordinates(obj: &Bound<'_, PyAny>) -> PyResult<Coordinates> {
    Ok(match arg_choice(obj, "coords", &["dc", "ic"])? {
        "dc" => Coordinates::Dependent,
        _ => Coordinates::Independent,
    })
}

/// `err` with a run's result (or None) as its `result` attribute, so that a failed or
/// interrupted run does not lose the steps it solved.
pub(super) fn with_result(py: Python<'_>, err: PyErr, result: Option<&Bound<'_, PyDict>>) -> PyErr {
    let value = err.value(py);
    // Setting an attribute on an exception instance does not fail in practice; if it
    // did, the exception itself still says what happened.
    let _ = match result {
        Some(r) => value.setattr("result", r),
        None => value.setattr("result", py.None()),
    };
    err
}

/// The run's table in the CSV contract: columns, row-major values, rows. The values
/// are float64s in native byte order in a bytearray, which numpy wraps without a copy:
/// a list of a million floats would hold an interrupted run's KeyboardInterrupt back.
pub(super) fn run_table<'py>(
    py: Python<'py>,
    tr: &Trajectory,
    forces: Option<&[f64]>,
) -> PyResult<Bound<'py, PyDict>> {
    let columns = crate::io::header(&tr.names, forces.is_some());
    let n = tr.n();
    let row = 8 * columns.len();
    let data = PyByteArray::new_with(py, tr.len() * row, |buf| {
        for (k, out) in buf.chunks_exact_mut(row).enumerate() {
            let f = forces.map(|f| &f[k * n..(k + 1) * n]);
            let values = std::iter::once(&tr.t[k])
                .chain(tr.q_at(k))
                .chain(tr.dq_at(k))
                .chain(&tr.ddq[k * n..(k + 1) * n])
                .chain(f.into_iter().flatten());
            for (o, v) in out.chunks_exact_mut(8).zip(values) {
                o.copy_from_slice(&v.to_ne_bytes());
            }
        }
        Ok(())
    })?;
    let d = PyDict::new(py);
    d.set_item("columns", columns)?;
    d.set_item("data", data)?;
    d.set_item("rows", tr.len())?;
    Ok(d)
}

/// Runs `work` with the GIL released, giving it a `progress` callback that, at most
/// every [`SIGNAL_CHECK`], takes the GIL to run Python's signal handlers: the error
/// one raises (KeyboardInterrupt for Ctrl-C) stops the run and is returned beside
/// the run's own outcome. A run whose Python callables run the handlers themselves
/// says so through `caught`, looked at every step: it stops the run the same way.
pub(super) fn interruptible<T: Send>(
    py: Python<'_>,
    caught: impl Sync + Fn() -> bool,
    work: impl Send + FnOnce(&mut dyn FnMut(usize, usize) -> ControlFlow<()>) -> T,
) -> (T, Option<PyErr>) {
    let mut signal = None;
    let mut last = Instant::now();
    let out = py.detach(|| {
        work(&mut |_, _| {
            if caught() {
                return ControlFlow::Break(());
            }
            if last.elapsed() < SIGNAL_CHECK {
                return ControlFlow::Continue(());
            }
            last = Instant::now();
            match Python::attach(|py| py.check_signals()) {
                Ok(()) => ControlFlow::Continue(()),
                Err(e) => {
                    signal = Some(e);
                    ControlFlow::Break(())
                }
            }
        })
    });
    (out, signal)
}
