//! The `mbfg` Python module (PyO3, feature `python`): the scene parser, the assembled
//! model and the forward/inverse runs, for the harness and for users. Arrays cross
//! the boundary as numpy arrays (rust-numpy): a result vector or matrix becomes an
//! array that owns the Rust buffer, a float64 numpy argument is read in place, and a
//! run's table is a buffer of float64s that numpy wraps; `python/mbfg/__init__.py`
//! shapes them.
//!
//! Every entry point runs inside [`guard`]: a Rust panic becomes `mbfg.InternalError`
//! instead of pyo3's `PanicException`, which `except Exception` does not catch.
//! Arguments are taken as Python objects and checked here (`arg_*`), so a float
//! window or a 2-D q is refused with `mbfg.InvalidArgument` rather than coerced.

use crate::forward::{
    self, Coordinates, DcIntegrators, ForwardOptions, Integrator, NoiseModels, RunSummary,
    Trajectory,
};
use crate::inverse::{self, InverseOptions, InverseSolution, Prescription, Start};
use crate::io::{read_table, Table};
use crate::model::PointSlot;
use crate::scene::{ConstraintKind, Effect, RelativeKind};
use crate::smoother::Mode;
use crate::solver::{Past, Termination};
use crate::{Error, Model, Scene};
use nalgebra::{DMatrix, DVector};
use numpy::{PyArray1, PyArray2, PyArrayMethods};
use pyo3::create_exception;
use pyo3::exceptions::{PyOverflowError, PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::{PyBool, PyByteArray, PyBytes, PyDict, PyFloat, PyInt, PyList, PySet, PyString};
use std::any::Any;
use std::ops::ControlFlow;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

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
/// How often a run looks for a pending signal (Ctrl-C): each look takes the GIL.
const SIGNAL_CHECK: Duration = Duration::from_millis(25);

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
fn guard<T>(f: impl FnOnce() -> PyResult<T>) -> PyResult<T> {
    catch_panic(f).unwrap_or_else(|m| {
        Err(InternalError::new_err(one_line(&format!(
            "internal error (a bug in mbfg, please report it): {m}"
        ))))
    })
}

/// One line of at most [`MESSAGE_LIMIT`] characters.
fn one_line(m: &str) -> String {
    let flat = m.split_whitespace().collect::<Vec<_>>().join(" ");
    if flat.chars().count() <= MESSAGE_LIMIT {
        flat
    } else {
        let cut: String = flat.chars().take(MESSAGE_LIMIT - 1).collect();
        format!("{cut}…")
    }
}

fn invalid(m: impl AsRef<str>) -> PyErr {
    InvalidArgument::new_err(one_line(m.as_ref()))
}

/// A library error about the caller's input, as `InvalidArgument`.
fn arg_error(e: Error) -> PyErr {
    match e {
        Error::InvalidArgument(m) | Error::Data(m) => invalid(m),
        other => invalid(other.to_string()),
    }
}

/// A short description of a value for a message: its repr (clipped) and type.
fn describe(obj: &Bound<'_, PyAny>) -> String {
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
fn arg_count(obj: &Bound<'_, PyAny>, name: &str, min: usize) -> PyResult<usize> {
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
fn arg_bool(obj: &Bound<'_, PyAny>, name: &str) -> PyResult<bool> {
    if !is_bool(obj) {
        return Err(invalid(format!(
            "{name} must be True or False, got {}",
            describe(obj)
        )));
    }
    obj.is_truthy()
}

/// A finite real number (an int is one).
fn arg_real(obj: &Bound<'_, PyAny>, name: &str) -> PyResult<f64> {
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

fn arg_str(obj: &Bound<'_, PyAny>, name: &str) -> PyResult<String> {
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
fn arg_choice<'a>(obj: &Bound<'_, PyAny>, name: &str, choices: &[&'a str]) -> PyResult<&'a str> {
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
fn arg_path(obj: &Bound<'_, PyAny>, name: &str) -> PyResult<PathBuf> {
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
fn arg_numbers(obj: &Bound<'_, PyAny>, name: &str) -> PyResult<Vec<f64>> {
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
fn arg_values(obj: Option<&Bound<'_, PyAny>>, name: &str) -> PyResult<Vec<(String, f64)>> {
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

/// The model of a run: a path, or a `Model` already loaded; re-read from its file
/// when parameters are overridden, and re-assembled when the initial state is
/// (positions of coordinates of q, velocities of independent coordinates).
fn study_model(
    scene: &Bound<'_, PyAny>,
    params: &[(String, f64)],
    q0: &[(String, f64)],
    dq0: &[(String, f64)],
) -> PyResult<Arc<Model>> {
    let loaded = scene.cast::<PyModel>().ok().map(|m| m.get().model.clone());
    if let Some(model) = &loaded {
        if params.is_empty() && q0.is_empty() && dq0.is_empty() {
            return Ok(model.clone());
        }
    }
    let path = match &loaded {
        Some(m) => PathBuf::from(&m.scene.file),
        None => arg_path(scene, "scene")?,
    };
    let mut sc = match (&loaded, params.is_empty()) {
        (Some(m), true) => m.scene.clone(),
        _ => Scene::load_with(&path, params).map_err(|e| SceneError::new_err(e.to_string()))?,
    };
    let names = crate::scene::coordinate_names(&sc);
    for (name, v) in q0 {
        if !names.contains(name) {
            return Err(invalid(format!(
                "q0: no coordinate '{name}' in the scene (Model.names lists them)"
            )));
        }
        sc.initial_positions.retain(|(n, _)| n != name);
        sc.initial_positions.push((name.clone(), *v));
    }
    for (name, v) in dq0 {
        if !sc.independent.contains(name) {
            return Err(invalid(format!(
                "dq0: '{name}' is not an independent coordinate; initial velocities are given for those ({})",
                sc.independent.join(", ")
            )));
        }
        sc.initial_velocities.retain(|(n, _)| n != name);
        sc.initial_velocities.push((name.clone(), *v));
    }
    Model::new(&sc)
        .map(Arc::new)
        .map_err(|e| SceneError::new_err(e.to_string()))
}

/// An assembled model, immutable.
#[pyclass(name = "Model", module = "mbfg", frozen)]
struct PyModel {
    model: Arc<Model>,
}

impl PyModel {
    /// A state vector: n finite numbers.
    fn vector(&self, obj: &Bound<'_, PyAny>, what: &str) -> PyResult<DVector<f64>> {
        let v = arg_numbers(obj, what)?;
        let n = self.model.n();
        if v.len() != n {
            return Err(invalid(format!(
                "{what} has {} entries, the model has {n} coordinates",
                v.len()
            )));
        }
        if let Some(i) = v.iter().position(|x| !x.is_finite()) {
            return Err(invalid(format!(
                "{what} holds NaN or Inf (entry {i}: {})",
                v[i]
            )));
        }
        Ok(DVector::from_vec(v))
    }

    fn point_index(&self, obj: &Bound<'_, PyAny>) -> PyResult<usize> {
        let name = arg_str(obj, "name")?;
        self.model.scene.point_index(&name).ok_or_else(|| {
            let name = one_line(&name).chars().take(60).collect::<String>();
            invalid(format!("no point named '{name}'"))
        })
    }

    fn point_name(&self, p: usize) -> String {
        self.model.scene.points[p].name.clone()
    }

    fn point_names(&self, ps: &[usize]) -> Vec<String> {
        ps.iter().map(|&p| self.point_name(p)).collect()
    }
}

/// Row-major entries of a matrix.
fn rows(m: &DMatrix<f64>) -> Vec<f64> {
    m.transpose().as_slice().to_vec()
}

/// A vector as a numpy array that takes over its buffer.
fn array(py: Python<'_>, v: Vec<f64>) -> Bound<'_, PyArray1<f64>> {
    PyArray1::from_vec(py, v)
}

/// A matrix as a C-ordered numpy array (its one transpose written into the array's
/// own buffer).
fn matrix<'py>(py: Python<'py>, m: &DMatrix<f64>) -> PyResult<Bound<'py, PyArray2<f64>>> {
    array(py, rows(m)).reshape([m.nrows(), m.ncols()])
}

#[pymethods]
impl PyModel {
    #[getter]
    fn file(&self) -> PyResult<String> {
        guard(|| Ok(self.model.scene.file.clone()))
    }
    #[getter]
    fn names(&self) -> PyResult<Vec<String>> {
        guard(|| Ok(self.model.names.clone()))
    }
    #[getter]
    fn n(&self) -> PyResult<usize> {
        guard(|| Ok(self.model.n()))
    }
    #[getter]
    fn m(&self) -> PyResult<usize> {
        guard(|| Ok(self.model.m()))
    }
    #[getter]
    fn dof(&self) -> PyResult<usize> {
        guard(|| Ok(self.model.dof()))
    }
    #[getter]
    fn points<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyList>> {
        guard(|| {
            let list = PyList::empty(py);
            for (p, slot) in self.model.scene.points.iter().zip(&self.model.points) {
                let d = PyDict::new(py);
                d.set_item("name", &p.name)?;
                d.set_item("x", p.x)?;
                d.set_item("y", p.y)?;
                d.set_item("fixed", p.fixed)?;
                d.set_item("mass", p.mass)?;
                match slot {
                    PointSlot::Free(i) => d.set_item("index", *i)?,
                    PointSlot::Fixed(_) => d.set_item("index", py.None())?,
                }
                list.append(d)?;
            }
            Ok(list)
        })
    }
    #[getter]
    fn bodies<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyList>> {
        guard(|| {
            let list = PyList::empty(py);
            for b in &self.model.scene.bodies {
                let d = PyDict::new(py);
                d.set_item("name", &b.name)?;
                d.set_item("points", self.point_names(&b.points))?;
                d.set_item("mass", b.mass)?;
                d.set_item("cog", (b.cog[0], b.cog[1]))?;
                d.set_item("i0", b.i0)?;
                d.set_item("inertia_cog", b.inertia_at_cog())?;
                d.set_item("length", b.length)?;
                list.append(d)?;
            }
            Ok(list)
        })
    }
    #[getter]
    fn coordinates<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyList>> {
        guard(|| {
            let list = PyList::empty(py);
            for (k, c) in self.model.scene.coordinates.iter().enumerate() {
                let d = PyDict::new(py);
                d.set_item("name", &c.name)?;
                d.set_item("index", self.model.relative_offset + k)?;
                let (kind, points) = match c.kind {
                    RelativeKind::AbsoluteAngle { from, to } => ("angle", vec![from, to]),
                    RelativeKind::RelativeAngle { a, b } => {
                        ("relative_angle", vec![a[0], a[1], b[0], b[1]])
                    }
                    RelativeKind::Distance { point, along } => {
                        ("distance", vec![point, along[0], along[1]])
                    }
                };
                d.set_item("type", kind)?;
                d.set_item("points", self.point_names(&points))?;
                list.append(d)?;
            }
            Ok(list)
        })
    }
    #[getter]
    fn constraints<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyList>> {
        guard(|| {
            let list = PyList::empty(py);
            for c in &self.model.scene.constraints {
                let d = PyDict::new(py);
                d.set_item("name", &c.name)?;
                let (kind, points, length) = match c.kind {
                    ConstraintKind::Distance { points, length } => {
                        ("distance", points.to_vec(), Some(length))
                    }
                    ConstraintKind::FixedSlider { point, line } => {
                        ("fixed_slider", vec![point, line[0], line[1]], None)
                    }
                    ConstraintKind::MobileSlider { point, line } => {
                        ("mobile_slider", vec![point, line[0], line[1]], None)
                    }
                };
                d.set_item("type", kind)?;
                d.set_item("points", self.point_names(&points))?;
                d.set_item("length", length)?;
                list.append(d)?;
            }
            Ok(list)
        })
    }
    #[getter]
    fn equations(&self) -> PyResult<Vec<String>> {
        guard(|| {
            Ok(self
                .model
                .constraints
                .iter()
                .map(|c| c.name.clone())
                .collect())
        })
    }
    #[getter]
    fn redundant(&self) -> PyResult<Vec<String>> {
        guard(|| {
            Ok(self
                .model
                .redundant
                .iter()
                .map(|&i| self.model.constraints[i].name.clone())
                .collect())
        })
    }
    #[getter]
    fn effects<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyList>> {
        guard(|| {
            let list = PyList::empty(py);
            let coordinate = |i: usize| self.model.names[self.model.relative_offset + i].clone();
            for e in &self.model.scene.effects {
                let d = PyDict::new(py);
                match e {
                    Effect::Gravity { vector } => {
                        d.set_item("type", "gravity")?;
                        d.set_item("vector", (vector[0], vector[1]))?;
                    }
                    Effect::SpringDamper {
                        name,
                        points,
                        stiffness,
                        rest_length,
                        damping,
                    } => {
                        d.set_item("type", "spring_damper")?;
                        d.set_item("name", name)?;
                        d.set_item("points", self.point_names(points))?;
                        d.set_item("stiffness", stiffness)?;
                        d.set_item("rest_length", rest_length)?;
                        d.set_item("damping", damping)?;
                    }
                    Effect::RotationalSpringDamper {
                        name,
                        coordinate: c,
                        stiffness,
                        rest_angle,
                        damping,
                    } => {
                        d.set_item("type", "rotational_spring_damper")?;
                        d.set_item("name", name)?;
                        d.set_item("coordinate", coordinate(*c))?;
                        d.set_item("stiffness", stiffness)?;
                        d.set_item("rest_angle", rest_angle)?;
                        d.set_item("damping", damping)?;
                    }
                    Effect::Motor {
                        name,
                        coordinate: c,
                        stall_torque,
                        no_load_speed,
                    } => {
                        d.set_item("type", "dc_motor")?;
                        d.set_item("name", name)?;
                        d.set_item("coordinate", coordinate(*c))?;
                        d.set_item("stall_torque", stall_torque)?;
                        d.set_item("no_load_speed", no_load_speed)?;
                    }
                    Effect::Torque {
                        name,
                        coordinate: c,
                        value,
                    } => {
                        d.set_item("type", "torque")?;
                        d.set_item("name", name)?;
                        d.set_item("coordinate", coordinate(*c))?;
                        d.set_item("value", &value.text)?;
                        d.set_item("state_dependent", value.is_state_dependent())?;
                    }
                    Effect::Force { name, point, value } => {
                        d.set_item("type", "force")?;
                        d.set_item("name", name)?;
                        d.set_item("point", self.point_name(*point))?;
                        d.set_item("value", (&value[0].text, &value[1].text))?;
                        d.set_item(
                            "state_dependent",
                            value.iter().any(|v| v.is_state_dependent()),
                        )?;
                    }
                    Effect::External { name } => {
                        d.set_item("type", "external")?;
                        d.set_item("name", name)?;
                        d.set_item("state_dependent", true)?;
                    }
                }
                list.append(d)?;
            }
            Ok(list)
        })
    }
    /// Value of effect `i` at time t: a torque (float) or a force (fx, fy).
    fn effect_value<'py>(
        &self,
        py: Python<'py>,
        i: &Bound<'py, PyAny>,
        t: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyAny>> {
        guard(|| {
            let (i, t) = (arg_count(i, "i", 0)?, arg_real(t, "t")?);
            let effects = &self.model.scene.effects;
            let e = effects.get(i).ok_or_else(|| {
                invalid(format!(
                    "i: effect {i} does not exist ({} effects)",
                    effects.len()
                ))
            })?;
            match e {
                Effect::Torque { value, .. } => Ok(value
                    .at(t)
                    .map_err(arg_error)?
                    .into_pyobject(py)?
                    .into_any()),
                Effect::Force { value, .. } => {
                    let f = (
                        value[0].at(t).map_err(arg_error)?,
                        value[1].at(t).map_err(arg_error)?,
                    );
                    Ok(f.into_pyobject(py)?.into_any())
                }
                _ => Err(invalid(format!("i: effect {i} is not a torque or a force"))),
            }
        })
    }
    #[getter]
    fn independent(&self) -> PyResult<Vec<String>> {
        guard(|| {
            Ok(self
                .model
                .independent
                .iter()
                .map(|&i| self.model.names[i].clone())
                .collect())
        })
    }
    #[getter]
    fn initial_q<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray1<f64>>> {
        guard(|| Ok(array(py, self.model.initial.q.as_slice().to_vec())))
    }
    #[getter]
    fn initial_dq<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray1<f64>>> {
        guard(|| Ok(array(py, self.model.initial.dq.as_slice().to_vec())))
    }
    #[getter]
    fn is_conservative(&self) -> PyResult<bool> {
        guard(|| Ok(self.model.scene.is_conservative()))
    }
    fn mass_matrix<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f64>>> {
        guard(|| matrix(py, &self.model.mass))
    }
    fn phi<'py>(
        &self,
        py: Python<'py>,
        q: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyArray1<f64>>> {
        guard(|| {
            let q = self.vector(q, "q")?;
            Ok(array(py, self.model.phi(&q).as_slice().to_vec()))
        })
    }
    fn phi_q<'py>(
        &self,
        py: Python<'py>,
        q: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyArray2<f64>>> {
        guard(|| {
            let q = self.vector(q, "q")?;
            matrix(py, &self.model.jacobian(&q))
        })
    }
    fn phi_q_dot<'py>(
        &self,
        py: Python<'py>,
        q: &Bound<'py, PyAny>,
        dq: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyArray2<f64>>> {
        guard(|| {
            let (q, dq) = (self.vector(q, "q")?, self.vector(dq, "dq")?);
            matrix(py, &self.model.jacobian_dot(&q, &dq))
        })
    }
    fn generalized_forces<'py>(
        &self,
        py: Python<'py>,
        q: &Bound<'py, PyAny>,
        dq: &Bound<'py, PyAny>,
        t: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyArray1<f64>>> {
        guard(|| {
            let (q, dq) = (self.vector(q, "q")?, self.vector(dq, "dq")?);
            let t = arg_real(t, "t")?;
            let f = self
                .model
                .generalized_forces(&q, &dq, t)
                .map_err(arg_error)?;
            Ok(array(py, f.as_slice().to_vec()))
        })
    }
    /// (∂Q/∂q, ∂Q/∂q̇), each n × n.
    #[allow(clippy::type_complexity)] // a pair of arrays
    fn force_jacobians<'py>(
        &self,
        py: Python<'py>,
        q: &Bound<'py, PyAny>,
        dq: &Bound<'py, PyAny>,
        t: &Bound<'py, PyAny>,
    ) -> PyResult<(Bound<'py, PyArray2<f64>>, Bound<'py, PyArray2<f64>>)> {
        guard(|| {
            let (q, dq) = (self.vector(q, "q")?, self.vector(dq, "dq")?);
            let t = arg_real(t, "t")?;
            let (kq, kv) = self.model.force_jacobians(&q, &dq, t).map_err(arg_error)?;
            Ok((matrix(py, &kq)?, matrix(py, &kv)?))
        })
    }
    fn accelerations<'py>(
        &self,
        py: Python<'py>,
        q: &Bound<'py, PyAny>,
        dq: &Bound<'py, PyAny>,
        t: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyArray1<f64>>> {
        guard(|| {
            let (q, dq) = (self.vector(q, "q")?, self.vector(dq, "dq")?);
            let t = arg_real(t, "t")?;
            let s = crate::dynamics::lagrange(&self.model, &q, &dq, t).map_err(arg_error)?;
            Ok(array(py, s.ddq.as_slice().to_vec()))
        })
    }
    /// Joint forces: (body, point, fx, fy) for every body and each of its points.
    fn joint_forces(
        &self,
        q: &Bound<'_, PyAny>,
        dq: &Bound<'_, PyAny>,
        ddq: &Bound<'_, PyAny>,
        t: &Bound<'_, PyAny>,
    ) -> PyResult<Vec<(String, String, f64, f64)>> {
        guard(|| {
            let (q, dq, ddq) = (
                self.vector(q, "q")?,
                self.vector(dq, "dq")?,
                self.vector(ddq, "ddq")?,
            );
            let t = arg_real(t, "t")?;
            let forces = crate::reactions::joint_forces(
                &self.model,
                q.as_slice(),
                dq.as_slice(),
                ddq.as_slice(),
                t,
                None,
            )
            .map_err(arg_error)?;
            let scene = &self.model.scene;
            let mut out = Vec::new();
            for (b, per_point) in forces.iter().enumerate() {
                let body = &scene.bodies[b];
                for (&p, f) in body.points.iter().zip(per_point) {
                    out.push((body.name.clone(), scene.points[p].name.clone(), f[0], f[1]));
                }
            }
            Ok(out)
        })
    }
    fn point_position(
        &self,
        q: &Bound<'_, PyAny>,
        name: &Bound<'_, PyAny>,
    ) -> PyResult<(f64, f64)> {
        guard(|| {
            let q = self.vector(q, "q")?;
            let p = self
                .model
                .point_position(q.as_slice(), self.point_index(name)?);
            Ok((p[0], p[1]))
        })
    }
    fn point_velocity(
        &self,
        dq: &Bound<'_, PyAny>,
        name: &Bound<'_, PyAny>,
    ) -> PyResult<(f64, f64)> {
        guard(|| {
            let dq = self.vector(dq, "dq")?;
            let p = self
                .model
                .point_velocity(dq.as_slice(), self.point_index(name)?);
            Ok((p[0], p[1]))
        })
    }
    fn kinetic_energy(&self, dq: &Bound<'_, PyAny>) -> PyResult<f64> {
        guard(|| Ok(self.model.kinetic_energy(&self.vector(dq, "dq")?)))
    }
    fn potential_energy(&self, q: &Bound<'_, PyAny>) -> PyResult<f64> {
        guard(|| Ok(self.model.potential_energy(&self.vector(q, "q")?)))
    }
    fn __repr__(&self) -> PyResult<String> {
        guard(|| {
            Ok(format!(
                "<mbfg.Model '{}': n = {}, m = {}, dof = {}>",
                self.model.scene.file,
                self.model.n(),
                self.model.m(),
                self.model.dof()
            ))
        })
    }
}

#[pyfunction]
#[pyo3(signature = (path, params=None))]
fn load(path: &Bound<'_, PyAny>, params: Option<&Bound<'_, PyAny>>) -> PyResult<PyModel> {
    guard(|| {
        let params = arg_values(params, "params")?;
        Ok(PyModel {
            model: study_model(path, &params, &[], &[])?,
        })
    })
}

fn coordinates(obj: &Bound<'_, PyAny>) -> PyResult<Coordinates> {
    Ok(match arg_choice(obj, "coords", &["dc", "ic"])? {
        "dc" => Coordinates::Dependent,
        _ => Coordinates::Independent,
    })
}

/// `err` with a run's result (or None) as its `result` attribute, so that a failed or
/// interrupted run does not lose the steps it solved.
fn with_result(py: Python<'_>, err: PyErr, result: Option<&Bound<'_, PyDict>>) -> PyErr {
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
fn run_table<'py>(
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

/// A forward run's result, complete or not: `requested` is the number of steps asked
/// for, so that a partial one says so in its summary.
fn forward_result<'py>(
    py: Python<'py>,
    tr: &Trajectory,
    s: &RunSummary,
    requested: usize,
) -> PyResult<Bound<'py, PyDict>> {
    let out = run_table(py, tr, None)?;
    let summary = PyDict::new(py);
    summary.set_item("steps", s.steps)?;
    summary.set_item("requested_steps", requested)?;
    summary.set_item("wall_time", s.wall_time.as_secs_f64())?;
    summary.set_item("mean_iterations", s.mean_iterations)?;
    summary.set_item("max_iterations", s.max_iterations)?;
    summary.set_item("worst_phi", s.worst_phi)?;
    summary.set_item("worst_velocity_constraint", s.worst_velocity_constraint)?;
    summary.set_item("energy_drift", s.energy_drift)?;
    summary.set_item("conditioned_from", s.conditioned_from)?;
    summary.set_item(
        "tangent_after",
        s.tangent_after.as_ref().map(|f| (f.step, f.t)),
    )?;
    let refinement = match &s.refinement {
        Some(r) => {
            let d = PyDict::new(py);
            d.set_item("factor", r.factor)?;
            d.set_item("dt", r.dt)?;
            d.set_item("after", (r.after.step, r.after.t))?;
            d.set_item("message", r.after.message())?;
            Some(d)
        }
        None => None,
    };
    summary.set_item("refinement", refinement)?;
    let reselections = PyList::empty(py);
    for r in &s.reselections {
        let d = PyDict::new(py);
        d.set_item("step", r.step)?;
        d.set_item("t", r.t)?;
        d.set_item("from", &r.from)?;
        d.set_item("to", &r.to)?;
        reselections.append(d)?;
    }
    summary.set_item("reselections", reselections)?;
    let converged = s.failures.is_empty();
    summary.set_item("converged", converged)?;
    summary.set_item("interrupted", s.interrupted)?;
    summary.set_item(
        "complete",
        converged && s.interrupted.is_none() && tr.len() == requested,
    )?;
    out.set_item("summary", summary)?;
    let failures = PyList::empty(py);
    for f in &s.failures {
        let d = PyDict::new(py);
        d.set_item("step", f.step)?;
        d.set_item("t", f.t)?;
        let reason = match f.singular {
            Some(_) => "singular configuration".to_string(),
            None => f.report.termination.to_string(),
        };
        d.set_item("reason", reason)?;
        d.set_item("cost", f.report.cost)?;
        failures.append(d)?;
    }
    out.set_item("failures", failures)?;
    Ok(out)
}

/// Runs `work` with the GIL released, giving it a `progress` callback that, at most
/// every [`SIGNAL_CHECK`], takes the GIL to run Python's signal handlers: the error
/// one raises (KeyboardInterrupt for Ctrl-C) stops the run and is returned beside
/// the run's own outcome.
fn interruptible<T: Send>(
    py: Python<'_>,
    work: impl Send + FnOnce(&mut dyn FnMut(usize, usize) -> ControlFlow<()>) -> T,
) -> (T, Option<PyErr>) {
    let mut signal = None;
    let mut last = Instant::now();
    let out = py.detach(|| {
        work(&mut |_, _| {
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

/// A Python callable f(t, q, q̇) → Q (n generalized forces in q's order) as an effect
/// of the model. The first exception it raises is kept, to be raised again in place of
/// the failed run's SolveError.
#[derive(Debug)]
struct PyLoad {
    name: String,
    callable: Py<PyAny>,
    raised: std::sync::Mutex<Option<PyErr>>,
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
                    if let Ok(mut slot) = self.raised.lock() {
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
fn arg_effects(effects: &Bound<'_, PyAny>) -> PyResult<Vec<Arc<PyLoad>>> {
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
            names: std::sync::OnceLock::new(),
        }));
    }
    Ok(out)
}

/// `model` with the Python effects added.
fn with_loads(model: Arc<Model>, loads: &[Arc<PyLoad>]) -> PyResult<Arc<Model>> {
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

/// The first exception a Python effect raised, if any.
fn raised(loads: &[Arc<PyLoad>]) -> Option<PyErr> {
    loads
        .iter()
        .find_map(|l| l.raised.lock().ok().and_then(|mut e| e.take()))
}

/// Forward dynamics. Every argument is required (`mbfg.simulate` gives the defaults).
#[pyfunction]
#[pyo3(name = "simulate")]
#[allow(clippy::too_many_arguments)] // the CLI's options, one keyword each
fn simulate_run<'py>(
    py: Python<'py>,
    scene: &Bound<'py, PyAny>,
    coords: &Bound<'py, PyAny>,
    dt: &Bound<'py, PyAny>,
    t_end: &Bound<'py, PyAny>,
    window: &Bound<'py, PyAny>,
    batch: &Bound<'py, PyAny>,
    max_iterations: &Bound<'py, PyAny>,
    integrator: &Bound<'py, PyAny>,
    noise: &Bound<'py, PyAny>,
    continue_on_failure: &Bound<'py, PyAny>,
    past: &Bound<'py, PyAny>,
    dc_integrators: &Bound<'py, PyAny>,
    refine: &Bound<'py, PyAny>,
    params: &Bound<'py, PyAny>,
    q0: &Bound<'py, PyAny>,
    dq0: &Bound<'py, PyAny>,
    effects: &Bound<'py, PyAny>,
) -> PyResult<Bound<'py, PyDict>> {
    guard(|| {
        let loads = arg_effects(effects)?;
        let params = arg_values(Some(params), "params")?;
        let q0 = arg_values(Some(q0), "q0")?;
        let dq0 = arg_values(Some(dq0), "dq0")?;
        let coordinates = coordinates(coords)?;
        let dt = arg_real(dt, "dt")?;
        if dt <= 0.0 {
            return Err(invalid(format!(
                "dt: the time step must be positive, got {dt}"
            )));
        }
        let t_end = arg_real(t_end, "t_end")?;
        if t_end < dt {
            return Err(invalid(format!(
                "t_end must be at least one time step (dt = {dt}), got {t_end}"
            )));
        }
        let window = arg_count(window, "window", 1)?;
        let batch = arg_bool(batch, "batch")?;
        let max_iterations = arg_count(max_iterations, "max_iterations", 1)?;
        let integrator = arg_choice(
            integrator,
            "integrator",
            &["trapezoidal", "euler", "hermite-simpson"],
        )?;
        let noise = arg_choice(noise, "noise", &["default", "paper"])?;
        let continue_on_failure = arg_bool(continue_on_failure, "continue_on_failure")?;
        let refine = arg_bool(refine, "refine")?;
        let past = arg_choice(past, "past", &["adaptive", "conditioned", "marginalized"])?;
        let dc_integrators = arg_choice(
            dc_integrators,
            "dc_integrators",
            &["auto", "tangent", "full"],
        )?;

        let mode = if batch {
            Mode::Batch
        } else {
            Mode::FixedLag(window)
        };
        let mut options = ForwardOptions::new(coordinates, dt, t_end, mode);
        options.integrator = match integrator {
            "trapezoidal" => Integrator::Trapezoidal,
            "hermite-simpson" => Integrator::HermiteSimpson,
            _ => Integrator::Euler,
        };
        options.dc_integrators = match dc_integrators {
            "auto" => DcIntegrators::Auto,
            "tangent" => DcIntegrators::Tangent,
            _ => DcIntegrators::Full,
        };
        options.noise = match noise {
            "default" => NoiseModels::default(),
            _ => NoiseModels::paper(),
        };
        options.settings.max_iterations = max_iterations;
        options.settings.past = match past {
            "adaptive" => Past::Adaptive,
            "conditioned" => Past::Conditioned,
            _ => Past::Marginalized,
        };
        options.continue_on_failure = continue_on_failure;
        options.refine = refine;
        let model = with_loads(study_model(scene, &params, &q0, &dq0)?, &loads)?;
        // What is left to refuse depends on the scene (its independent coordinates)
        // or on dt and t_end together (the number of steps).
        options.validate(&model).map_err(arg_error)?;
        let requested = options.steps();
        let step_warning: Vec<String> = crate::plausibility::idle_warning(&model)
            .into_iter()
            .chain(crate::plausibility::step_warning(&model, options.dt))
            .collect();
        let model_for_checks = model.clone();
        let (run, signal) = interruptible(py, |progress| {
            forward::simulate_interruptible(model, &options, progress)
        });
        let (tr, s) = match run {
            Ok(run) => run,
            // No trajectory comes back from a library error; an interrupt came first.
            Err(e) => {
                let err = match (signal, raised(&loads), e) {
                    (Some(signal), _, _) => signal,
                    (None, Some(python), _) => python,
                    (None, None, e @ Error::InvalidArgument(_)) => return Err(arg_error(e)),
                    (None, None, e) => SolveError::new_err(e.to_string()),
                };
                return Err(with_result(py, err, None));
            }
        };
        let out = forward_result(py, &tr, &s, requested)?;
        // What converged but may not be right (mbfg simulate prints these as warnings).
        let euler =
            crate::plausibility::euler_warning(&model_for_checks, &tr, &s, options.integrator);
        let warnings: Vec<String> = step_warning
            .iter()
            .cloned()
            .chain(crate::plausibility::energy_warning(&s))
            .chain(euler)
            .collect();
        out.get_item("summary")?
            .ok_or_else(|| PyRuntimeError::new_err("a result without a summary"))?
            .set_item("warnings", warnings)?;
        if let Some(signal) = signal {
            return Err(with_result(py, signal, Some(&out)));
        }
        // A singular configuration stops the run whatever continue_on_failure says; so
        // does a diverged solve, and then the trajectory ends short.
        let stopped = s.failures.iter().find(|f| f.singular.is_some());
        let short = (tr.len() < requested).then(|| s.failures.last()).flatten();
        let fatal = stopped
            .or(s.failures.first().filter(|_| !continue_on_failure))
            .or(short);
        if let Some(f) = fatal {
            let err = raised(&loads).unwrap_or_else(|| SolveError::new_err(f.message()));
            return Err(with_result(py, err, Some(&out)));
        }
        if tr.len() < requested {
            let m = format!(
                "the run ended after {} of {requested} steps without naming a failure",
                tr.len()
            );
            return Err(with_result(py, SolveError::new_err(m), Some(&out)));
        }
        // A Ctrl-C after the last look: raise it here, with the run, rather than lose
        // the run to it on the next Python instruction.
        py.check_signals()
            .map_err(|e| with_result(py, e, Some(&out)))?;
        Ok(out)
    })
}

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
fn table_from(columns: &Bound<'_, PyAny>, values: &Bound<'_, PyAny>) -> PyResult<Table> {
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
fn inverse_run<'py>(
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
            .map_err(|e| match (raised(&loads), e) {
                (Some(python), _) => with_result(py, python, None),
                (None, e @ Error::InvalidArgument(_)) => arg_error(e),
                (None, other) => with_result(py, SolveError::new_err(other.to_string()), None),
            })?;
        let out = inverse_result(py, &sol)?;
        // The solve cannot stop midway: a Ctrl-C during it is raised now, with it.
        py.check_signals()
            .map_err(|e| with_result(py, e, Some(&out)))?;
        let s = &sol.summary;
        if s.report.termination != Termination::Converged {
            let m = format!(
                "the inverse solve did not converge: {}, cost {:.3e} after {} iterations",
                s.report.termination, s.report.cost, s.report.iterations
            );
            return Err(with_result(py, SolveError::new_err(m), Some(&out)));
        }
        Ok(out)
    })
}

#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    let py = m.py();
    m.add_class::<PyModel>()?;
    m.add_function(wrap_pyfunction!(load, m)?)?;
    m.add_function(wrap_pyfunction!(simulate_run, m)?)?;
    m.add_function(wrap_pyfunction!(inverse_run, m)?)?;
    m.add("SceneError", py.get_type::<SceneError>())?;
    // Every SolveError has `.result`: None where nothing was solved.
    py.get_type::<SolveError>().setattr("result", py.None())?;
    m.add("SolveError", py.get_type::<SolveError>())?;
    m.add("InvalidArgument", py.get_type::<InvalidArgument>())?;
    m.add("InternalError", py.get_type::<InternalError>())?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    Ok(())
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
