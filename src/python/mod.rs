//! The `mbfg` Python module (PyO3, feature `python`): the scene parser, the assembled
//! model and the forward/inverse runs, for the harness and for users. Arrays cross
//! the boundary as numpy arrays (rust-numpy): a result vector or matrix becomes an
//! array that owns the Rust buffer, a float64 numpy argument is read in place, and a
//! run's table is a buffer of float64s that numpy wraps; `python/mbfg/__init__.py`
//! shapes them.
//!
//! Every entry point runs inside [`guard`](errors::guard): a Rust panic becomes
//! `mbfg.InternalError` instead of pyo3's `PanicException`, which `except Exception`
//! does not catch. Arguments are taken as Python objects and checked here (`arg_*`,
//! in `args`), so a float window or a 2-D q is refused with `mbfg.InvalidArgument`
//! rather than coerced.
//!
//! `errors` holds the exceptions and the panic guard, `args` the argument checks,
//! `model` the `Model` class, `effects` Python callables as effects, `run` what the
//! runs share, `sensors` the sensors and `mbfg.measure`, and `simulate` and `inverse` the two runs.

mod args;
mod effects;
mod errors;
mod estimate;
mod failure;
mod inverse;
mod model;
mod run;
mod sensors;
mod simulate;

use errors::{InternalError, InvalidArgument, SceneError, SolveError};
use pyo3::prelude::*;

#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    let py = m.py();
    m.add_class::<model::PyModel>()?;
    m.add_function(wrap_pyfunction!(model::load, m)?)?;
    m.add_function(wrap_pyfunction!(model::parse_yaml, m)?)?;
    m.add_function(wrap_pyfunction!(simulate::simulate_run, m)?)?;
    m.add_function(wrap_pyfunction!(inverse::inverse_run, m)?)?;
    m.add_function(wrap_pyfunction!(sensors::measure_run, m)?)?;
    m.add_function(wrap_pyfunction!(sensors::read_trajectory, m)?)?;
    m.add_function(wrap_pyfunction!(estimate::estimate_run, m)?)?;
    m.add_class::<estimate::PyEstimator>()?;
    m.add("SceneError", py.get_type::<SceneError>())?;
    // Every SolveError has `.result`: None where nothing was solved.
    py.get_type::<SolveError>().setattr("result", py.None())?;
    // ... and `.failure`: why, as a dict (see failure.rs), or None.
    py.get_type::<SolveError>().setattr("failure", py.None())?;
    m.add("SolveError", py.get_type::<SolveError>())?;
    m.add("InvalidArgument", py.get_type::<InvalidArgument>())?;
    m.add("InternalError", py.get_type::<InternalError>())?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    Ok(())
}
