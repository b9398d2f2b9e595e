//! The module's exceptions, and how Rust errors and panics become them: one clipped
//! line of message, a panic caught at the boundary as `mbfg.InternalError`.

use crate::Error;
use pyo3::create_exception;
use pyo3::exceptions::{PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use std::any::Any;
use std::panic::{catch_unwind, AssertUnwindSafe};

create_exception!(
    mbfg,
    SceneError,
    PyValueError,
    "A scene that cannot be read or assembled."
);
create_exception!(
    mbfg,
    SolveError,
    PyRuntimeError,
    "A run that stopped because a solve did not converge; `.result` holds what was \
     solved (or None)."
);
create_exception!(
    mbfg,
    InvalidArgument,
    PyValueError,
    "An argument of the wrong type, shape or value; the message names it."
);
create_exception!(
    mbfg,
    InternalError,
    PyRuntimeError,
    "A bug in mbfg (a Rust panic), caught at the module's boundary."
);

/// Longest message of an `InvalidArgument`.
const MESSAGE_LIMIT: usize = 300;

/// The panic's message, as the default hook prints it.
fn panic_message(payload: &(dyn Any + Send)) -> String {
    if let Some(s) = payload.downcast_ref::<&str>() {
        s.to_string()
    } else if let Some(s) = payload.downcast_ref::<String>() {
        s.clone()
    } else {
        "a panic without a message".to_string()
    }
}

/// Runs `f`, returning a panic's message as an error. Unwind safety is asserted: after
/// a panic nothing `f` touched is used again (models are immutable and shared).
fn catch_panic<T>(f: impl FnOnce() -> T) -> Result<T, String> {
    catch_unwind(AssertUnwindSafe(f)).map_err(|p| panic_message(&*p))
}

/// An entry point's body, with a panic turned into `mbfg.InternalError`.
pub(super) fn guard<T>(f: impl FnOnce() -> PyResult<T>) -> PyResult<T> {
    catch_panic(f).unwrap_or_else(|m| {
        Err(InternalError::new_err(one_line(&format!(
            "internal error (a bug in mbfg, please report it): {m}"
        ))))
    })
}

/// One line of at most [`MESSAGE_LIMIT`] characters.
pub(super) fn one_line(m: &str) -> String {
    let flat = m.split_whitespace().collect::<Vec<_>>().join(" ");
    if flat.chars().count() <= MESSAGE_LIMIT {
        flat
    } else {
        let cut: String = flat.chars().take(MESSAGE_LIMIT - 1).collect();
        format!("{cut}…")
    }
}

pub(super) fn invalid(m: impl AsRef<str>) -> PyErr {
    InvalidArgument::new_err(one_line(m.as_ref()))
}

/// A library error about the caller's input, as `InvalidArgument`.
pub(super) fn arg_error(e: Error) -> PyErr {
    match e {
        Error::InvalidArgument(m) => invalid(m),
        e @ Error::Data { .. } => invalid(e.to_string()),
        other => invalid(other.to_string()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_panic_becomes_its_message() {
        let r: Result<(), String> = catch_panic(|| panic!("Singular value was {}", "NaN"));
        assert_eq!(r, Err("Singular value was NaN".to_string()));
        let r: Result<(), String> = catch_panic(|| std::panic::panic_any(7u8));
        assert_eq!(r, Err("a panic without a message".to_string()));
        assert_eq!(catch_panic(|| 3), Ok(3));
    }

    #[test]
    fn messages_are_one_clipped_line() {
        assert_eq!(one_line("a\n  b\tc"), "a b c");
        let long = one_line(&"x".repeat(1000));
        assert_eq!(long.chars().count(), MESSAGE_LIMIT);
        assert!(long.ends_with('…'));
    }
}
