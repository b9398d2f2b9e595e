//! Arguments checked at the boundary: each is taken as a Python object and refused
//! with `mbfg.InvalidArgument` unless it has the right type, shape and value (no
//! float for a count, no bool for a number, no string for a sequence).

use super::errors::invalid;
use numpy::{PyArray1, PyArrayMethods};
use pyo3::exceptions::PyOverflowError;
use pyo3::prelude::*;
use pyo3::types::{PyBool, PyBytes, PyDict, PyFloat, PyInt, PySet, PyString};
use std::path::PathBuf;

/// A short description of a value for a message: its repr (clipped) and type.
pub(super) fn describe(obj: &Bound<'_, PyAny>) -> String {
    let repr = obj
        .repr()
        .and_then(|r| r.extract::<String>())
        .unwrap_or_else(|_| "?".into());
    let repr = if repr.chars().count() > 60 {
        format!("{}…", repr.chars().take(59).collect::<String>())
    } else {
        repr
    };
    let ty = obj
        .get_type()
        .name()
        .and_then(|n| n.extract::<String>())
        .unwrap_or_else(|_| "?".into());
    format!("{repr} ({ty})")
}

/// Python's bool, or numpy's (named `bool_`, or `bool` in numpy 2): ints to Python,
/// but never a count or a coordinate here.
fn is_bool(obj: &Bound<'_, PyAny>) -> bool {
    obj.is_instance_of::<PyBool>()
        || obj
            .get_type()
            .name()
            .and_then(|n| n.extract::<String>())
            .is_ok_and(|n| n == "bool" || n == "bool_")
}

/// A scalar number: not a bool, a string, or a container (a size-1 numpy array
/// converts to float, silently flattening a wrong shape).
fn is_number(obj: &Bound<'_, PyAny>) -> bool {
    if obj.is_instance_of::<PyFloat>() || obj.is_instance_of::<PyInt>() {
        return !is_bool(obj);
    }
    !is_bool(obj)
        && !obj.is_instance_of::<PyString>()
        && !obj.get_type().hasattr("__len__").unwrap_or(true)
        && obj.hasattr("__float__").unwrap_or(false)
}

/// A count ≥ `min`: an int (numpy's too), not a float or a bool.
pub(super) fn arg_count(obj: &Bound<'_, PyAny>, name: &str, min: usize) -> PyResult<usize> {
    let not_int = || invalid(format!("{name} must be an integer, got {}", describe(obj)));
    if is_bool(obj) || obj.is_instance_of::<PyFloat>() {
        return Err(not_int());
    }
    let v = obj.extract::<i64>().map_err(|e: PyErr| {
        if e.is_instance_of::<PyOverflowError>(obj.py()) {
            invalid(format!("{name} is out of range, got {}", describe(obj)))
        } else {
            not_int()
        }
    })?;
    match usize::try_from(v) {
        Ok(v) if v >= min => Ok(v),
        _ => Err(invalid(format!("{name} must be at least {min}, got {v}"))),
    }
}

/// True or False (Python's or numpy's), nothing else.
pub(super) fn arg_bool(obj: &Bound<'_, PyAny>, name: &str) -> PyResult<bool> {
    if !is_bool(obj) {
        return Err(invalid(format!(
            "{name} must be True or False, got {}",
            describe(obj)
        )));
    }
    obj.is_truthy()
}

/// A finite real number (an int is one).
pub(super) fn arg_real(obj: &Bound<'_, PyAny>, name: &str) -> PyResult<f64> {
    let v = if is_number(obj) {
        obj.extract::<f64>().ok()
    } else {
        None
    };
    match v {
        Some(v) if v.is_finite() => Ok(v),
        Some(v) => Err(invalid(format!("{name} must be finite, got {v}"))),
        None => Err(invalid(format!(
            "{name} must be a number, got {}",
            describe(obj)
        ))),
    }
}

pub(super) fn arg_str(obj: &Bound<'_, PyAny>, name: &str) -> PyResult<String> {
    if obj.is_instance_of::<PyString>() {
        obj.extract()
    } else {
        Err(invalid(format!(
            "{name} must be a string, got {}",
            describe(obj)
        )))
    }
}

/// One of `choices`, named in the message.
pub(super) fn arg_choice<'a>(
    obj: &Bound<'_, PyAny>,
    name: &str,
    choices: &[&'a str],
) -> PyResult<&'a str> {
    let given = obj
        .is_instance_of::<PyString>()
        .then(|| obj.extract::<String>().ok())
        .flatten();
    if let Some(c) = choices.iter().find(|c| given.as_deref() == Some(**c)) {
        return Ok(c);
    }
    let listed: Vec<String> = choices.iter().map(|c| format!("'{c}'")).collect();
    let listed = match listed.split_last() {
        Some((last, [])) => last.clone(),
        Some((last, rest)) => format!("{} or {last}", rest.join(", ")),
        None => String::new(),
    };
    let got = match given {
        Some(s) if s.chars().count() <= 60 => format!("'{s}'"),
        _ => describe(obj),
    };
    Err(invalid(format!("{name} must be {listed}, not {got}")))
}

/// A file path: a str or an os.PathLike.
pub(super) fn arg_path(obj: &Bound<'_, PyAny>, name: &str) -> PyResult<PathBuf> {
    let bad = || {
        invalid(format!(
            "{name} must be a path (str or os.PathLike), got {}",
            describe(obj)
        ))
    };
    if is_bool(obj) || obj.is_instance_of::<PyBytes>() {
        return Err(bad());
    }
    obj.extract::<PathBuf>().map_err(|_| bad())
}

/// A flat sequence of numbers (a list, tuple or 1-D array), as floats; NaN and Inf
/// are left to the caller.
pub(super) fn arg_numbers(obj: &Bound<'_, PyAny>, name: &str) -> PyResult<Vec<f64>> {
    // A contiguous 1-D float64 array is read in place, without a call per entry.
    if let Ok(a) = obj.cast::<PyArray1<f64>>() {
        if let Ok(r) = a.try_readonly() {
            if let Ok(s) = r.as_slice() {
                return Ok(s.to_vec());
            }
        }
    }
    let not_seq = || {
        invalid(format!(
            "{name} must be a 1-D sequence of numbers, got {}",
            describe(obj)
        ))
    };
    if obj.is_instance_of::<PyString>()
        || obj.is_instance_of::<PyBytes>()
        || obj.is_instance_of::<PyDict>()
        || obj.is_instance_of::<PySet>()
        || !obj.hasattr("__len__").unwrap_or(false)
    {
        return Err(not_seq());
    }
    let mut out = Vec::with_capacity(obj.len().unwrap_or(0));
    for (i, item) in obj.try_iter().map_err(|_| not_seq())?.enumerate() {
        let item = item?;
        let v = if is_number(&item) {
            item.extract::<f64>().ok()
        } else {
            None
        };
        let Some(v) = v else {
            return Err(invalid(format!(
                "{name} must be a 1-D sequence of numbers; entry {i} is {}",
                describe(&item)
            )));
        };
        out.push(v);
    }
    Ok(out)
}

/// `{name: number}` (None: empty), every value a finite real.
pub(super) fn arg_values(
    obj: Option<&Bound<'_, PyAny>>,
    name: &str,
) -> PyResult<Vec<(String, f64)>> {
    let Some(obj) = obj.filter(|o| !o.is_none()) else {
        return Ok(Vec::new());
    };
    let dict = obj.cast::<PyDict>().map_err(|_| {
        invalid(format!(
            "{name} must be a dict {{name: number}}, got {}",
            describe(obj)
        ))
    })?;
    let mut out = Vec::with_capacity(dict.len());
    for (k, v) in dict.iter() {
        let key: String = k.extract().map_err(|_| {
            invalid(format!(
                "{name}: keys must be strings, got {}",
                describe(&k)
            ))
        })?;
        let value = arg_real(&v, &format!("{name}[{key:?}]"))?;
        out.push((key, value));
    }
    Ok(out)
}
