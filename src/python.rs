//! The `mbfg` Python module (PyO3, feature `python`): the scene parser, the assembled
//! model and the forward/inverse runs, for the harness and for users. Arrays cross
//! the boundary as flat lists; `python/mbfg/__init__.py` shapes them into numpy.

use crate::forward::{self, Coordinates, ForwardOptions, Integrator, NoiseModels, Trajectory};
use crate::inverse::{self, InverseOptions, Prescription, Start};
use crate::io::{read_table, Table};
use crate::model::PointSlot;
use crate::scene::{ConstraintKind, Effect, RelativeKind};
use crate::smoother::Mode;
use crate::solver::Past;
use crate::{Error, Model, Scene};
use nalgebra::{DMatrix, DVector};
use pyo3::create_exception;
use pyo3::exceptions::{PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};
use std::path::PathBuf;
use std::sync::Arc;

create_exception!(
    _native,
    SceneError,
    PyValueError,
    "A scene that cannot be read or assembled."
);
create_exception!(
    _native,
    SolveError,
    PyRuntimeError,
    "A solve that did not converge."
);

fn value_error(e: Error) -> PyErr {
    match e {
        Error::InvalidArgument(m) | Error::Data(m) => PyValueError::new_err(m),
        other => PyValueError::new_err(other.to_string()),
    }
}

fn load_model(path: &PathBuf) -> PyResult<Model> {
    let scene = Scene::load(path).map_err(|e| SceneError::new_err(e.to_string()))?;
    Model::new(&scene).map_err(|e| SceneError::new_err(e.to_string()))
}

/// An assembled model, immutable.
#[pyclass(name = "Model", module = "mbfg", frozen)]
struct PyModel {
    model: Arc<Model>,
}

impl PyModel {
    fn vector(&self, v: Vec<f64>, what: &str) -> PyResult<DVector<f64>> {
        let n = self.model.n();
        if v.len() != n {
            return Err(PyValueError::new_err(format!(
                "{what} has {} entries, the model has {n} coordinates",
                v.len()
            )));
        }
        if v.iter().any(|x| !x.is_finite()) {
            return Err(PyValueError::new_err(format!("{what} holds NaN or Inf")));
        }
        Ok(DVector::from_vec(v))
    }

    fn point_index(&self, name: &str) -> PyResult<usize> {
        self.model
            .scene
            .point_index(name)
            .ok_or_else(|| PyValueError::new_err(format!("no point named '{name}'")))
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

#[pymethods]
impl PyModel {
    #[getter]
    fn file(&self) -> String {
        self.model.scene.file.clone()
    }
    #[getter]
    fn names(&self) -> Vec<String> {
        self.model.names.clone()
    }
    #[getter]
    fn n(&self) -> usize {
        self.model.n()
    }
    #[getter]
    fn m(&self) -> usize {
        self.model.m()
    }
    #[getter]
    fn dof(&self) -> usize {
        self.model.dof()
    }
    #[getter]
    fn points<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyList>> {
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
    }
    #[getter]
    fn bodies<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyList>> {
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
    }
    #[getter]
    fn coordinates<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyList>> {
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
    }
    #[getter]
    fn constraints<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyList>> {
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
    }
    #[getter]
    fn equations(&self) -> Vec<String> {
        self.model
            .constraints
            .iter()
            .map(|c| c.name.clone())
            .collect()
    }
    #[getter]
    fn redundant(&self) -> Vec<String> {
        self.model
            .redundant
            .iter()
            .map(|&i| self.model.constraints[i].name.clone())
            .collect()
    }
    #[getter]
    fn effects<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyList>> {
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
                Effect::Torque {
                    name,
                    coordinate: c,
                    value,
                } => {
                    d.set_item("type", "torque")?;
                    d.set_item("name", name)?;
                    d.set_item("coordinate", coordinate(*c))?;
                    d.set_item("value", &value.text)?;
                }
                Effect::Force { name, point, value } => {
                    d.set_item("type", "force")?;
                    d.set_item("name", name)?;
                    d.set_item("point", self.point_name(*point))?;
                    d.set_item("value", (&value[0].text, &value[1].text))?;
                }
            }
            list.append(d)?;
        }
        Ok(list)
    }
    /// Value of effect `i` at time t: a torque (float) or a force (fx, fy).
    fn effect_value<'py>(&self, py: Python<'py>, i: usize, t: f64) -> PyResult<Bound<'py, PyAny>> {
        let effects = &self.model.scene.effects;
        let e = effects.get(i).ok_or_else(|| {
            PyValueError::new_err(format!(
                "effect {i} does not exist ({} effects)",
                effects.len()
            ))
        })?;
        match e {
            Effect::Torque { value, .. } => Ok(value
                .at(t)
                .map_err(value_error)?
                .into_pyobject(py)?
                .into_any()),
            Effect::Force { value, .. } => {
                let f = (
                    value[0].at(t).map_err(value_error)?,
                    value[1].at(t).map_err(value_error)?,
                );
                Ok(f.into_pyobject(py)?.into_any())
            }
            _ => Err(PyValueError::new_err(format!(
                "effect {i} is not a torque or a force"
            ))),
        }
    }
    #[getter]
    fn independent(&self) -> Vec<String> {
        self.model
            .independent
            .iter()
            .map(|&i| self.model.names[i].clone())
            .collect()
    }
    #[getter]
    fn initial_q(&self) -> Vec<f64> {
        self.model.initial.q.as_slice().to_vec()
    }
    #[getter]
    fn initial_dq(&self) -> Vec<f64> {
        self.model.initial.dq.as_slice().to_vec()
    }
    #[getter]
    fn is_conservative(&self) -> bool {
        self.model.scene.is_conservative()
    }
    fn mass_matrix(&self) -> Vec<f64> {
        rows(&self.model.mass)
    }
    fn phi(&self, q: Vec<f64>) -> PyResult<Vec<f64>> {
        let q = self.vector(q, "q")?;
        Ok(self.model.phi(&q).as_slice().to_vec())
    }
    fn phi_q(&self, q: Vec<f64>) -> PyResult<Vec<f64>> {
        let q = self.vector(q, "q")?;
        Ok(rows(&self.model.jacobian(&q)))
    }
    fn phi_q_dot(&self, q: Vec<f64>, dq: Vec<f64>) -> PyResult<Vec<f64>> {
        let (q, dq) = (self.vector(q, "q")?, self.vector(dq, "dq")?);
        Ok(rows(&self.model.jacobian_dot(&q, &dq)))
    }
    fn generalized_forces(&self, q: Vec<f64>, dq: Vec<f64>, t: f64) -> PyResult<Vec<f64>> {
        let (q, dq) = (self.vector(q, "q")?, self.vector(dq, "dq")?);
        let f = self
            .model
            .generalized_forces(&q, &dq, t)
            .map_err(value_error)?;
        Ok(f.as_slice().to_vec())
    }
    fn accelerations(&self, q: Vec<f64>, dq: Vec<f64>, t: f64) -> PyResult<Vec<f64>> {
        let (q, dq) = (self.vector(q, "q")?, self.vector(dq, "dq")?);
        let s = crate::dynamics::lagrange(&self.model, &q, &dq, t).map_err(value_error)?;
        Ok(s.ddq.as_slice().to_vec())
    }
    fn point_position(&self, q: Vec<f64>, name: &str) -> PyResult<(f64, f64)> {
        let q = self.vector(q, "q")?;
        let p = self
            .model
            .point_position(q.as_slice(), self.point_index(name)?);
        Ok((p[0], p[1]))
    }
    fn point_velocity(&self, dq: Vec<f64>, name: &str) -> PyResult<(f64, f64)> {
        let dq = self.vector(dq, "dq")?;
        let p = self
            .model
            .point_velocity(dq.as_slice(), self.point_index(name)?);
        Ok((p[0], p[1]))
    }
    fn kinetic_energy(&self, dq: Vec<f64>) -> PyResult<f64> {
        Ok(self.model.kinetic_energy(&self.vector(dq, "dq")?))
    }
    fn potential_energy(&self, q: Vec<f64>) -> PyResult<f64> {
        Ok(self.model.potential_energy(&self.vector(q, "q")?))
    }
    fn __repr__(&self) -> String {
        format!(
            "<mbfg.Model '{}': n = {}, m = {}, dof = {}>",
            self.model.scene.file,
            self.model.n(),
            self.model.m(),
            self.model.dof()
        )
    }
}

#[pyfunction]
fn load(path: PathBuf) -> PyResult<PyModel> {
    Ok(PyModel {
        model: Arc::new(load_model(&path)?),
    })
}

fn coordinates(name: &str) -> PyResult<Coordinates> {
    match name {
        "dc" => Ok(Coordinates::Dependent),
        "ic" => Ok(Coordinates::Independent),
        _ => Err(PyValueError::new_err(format!(
            "coords must be 'dc' or 'ic', not '{name}'"
        ))),
    }
}

/// The run's table in the CSV contract: (columns, row-major values, rows).
fn run_table<'py>(
    py: Python<'py>,
    tr: &Trajectory,
    forces: Option<&[f64]>,
) -> PyResult<Bound<'py, PyDict>> {
    let columns = crate::io::header(&tr.names, forces.is_some());
    let n = tr.n();
    let mut data = Vec::with_capacity(tr.len() * columns.len());
    for k in 0..tr.len() {
        data.push(tr.t[k]);
        data.extend_from_slice(tr.q_at(k));
        data.extend_from_slice(tr.dq_at(k));
        data.extend_from_slice(&tr.ddq[k * n..(k + 1) * n]);
        if let Some(f) = forces {
            data.extend_from_slice(&f[k * n..(k + 1) * n]);
        }
    }
    let d = PyDict::new(py);
    d.set_item("columns", columns)?;
    d.set_item("data", data)?;
    d.set_item("rows", tr.len())?;
    Ok(d)
}

#[pyfunction]
#[pyo3(signature = (scene, coords="dc", dt=1e-3, t_end=5.0, window=1, batch=false,
    max_iterations=50, integrator="trapezoidal", noise="default", continue_on_failure=false, past="adaptive"))]
#[pyo3(name = "simulate")]
#[allow(clippy::too_many_arguments)] // the CLI's options, one keyword each
fn simulate_run<'py>(
    py: Python<'py>,
    scene: PathBuf,
    coords: &str,
    dt: f64,
    t_end: f64,
    window: usize,
    batch: bool,
    max_iterations: usize,
    integrator: &str,
    noise: &str,
    continue_on_failure: bool,
    past: &str,
) -> PyResult<Bound<'py, PyDict>> {
    let model = load_model(&scene)?;
    let mode = if batch {
        Mode::Batch
    } else {
        Mode::FixedLag(window)
    };
    let mut options = ForwardOptions::new(coordinates(coords)?, dt, t_end, mode);
    options.integrator = match integrator {
        "trapezoidal" => Integrator::Trapezoidal,
        "euler" => Integrator::Euler,
        _ => {
            return Err(PyValueError::new_err(format!(
                "integrator must be 'trapezoidal' or 'euler', not '{integrator}'"
            )))
        }
    };
    options.noise = match noise {
        "default" => NoiseModels::default(),
        "paper" => NoiseModels::paper(),
        _ => {
            return Err(PyValueError::new_err(format!(
                "noise must be 'default' or 'paper', not '{noise}'"
            )))
        }
    };
    options.settings.max_iterations = max_iterations;
    options.settings.past = match past {
        "adaptive" => Past::Adaptive,
        "conditioned" => Past::Conditioned,
        "marginalized" => Past::Marginalized,
        _ => {
            return Err(PyValueError::new_err(format!(
                "past must be 'adaptive', 'conditioned' or 'marginalized', not '{past}'"
            )))
        }
    };
    options.continue_on_failure = continue_on_failure;
    options.validate(&model).map_err(value_error)?;
    let model = Arc::new(model);
    let (tr, s) = py
        .detach(|| forward::simulate(model, &options, &mut |_, _| {}))
        .map_err(|e| SolveError::new_err(e.to_string()))?;
    let stopped = s.failures.iter().find(|f| f.singular.is_some());
    if let Some(f) = stopped.or(s.failures.first().filter(|_| !continue_on_failure)) {
        return Err(SolveError::new_err(f.message()));
    }
    let out = run_table(py, &tr, None)?;
    let summary = PyDict::new(py);
    summary.set_item("steps", s.steps)?;
    summary.set_item("wall_time", s.wall_time.as_secs_f64())?;
    summary.set_item("mean_iterations", s.mean_iterations)?;
    summary.set_item("max_iterations", s.max_iterations)?;
    summary.set_item("worst_phi", s.worst_phi)?;
    summary.set_item("worst_velocity_constraint", s.worst_velocity_constraint)?;
    summary.set_item("energy_drift", s.energy_drift)?;
    summary.set_item("conditioned_from", s.conditioned_from)?;
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

/// `trajectory` is a CSV path, or the columns and row-major values of a table.
#[pyfunction]
#[pyo3(signature = (scene, trajectory=None, columns=None, values=None, coords="dc",
    start="kinematic", max_iterations=50))]
#[pyo3(name = "inverse")]
#[allow(clippy::too_many_arguments)] // the CLI's options, one keyword each
fn inverse_run<'py>(
    py: Python<'py>,
    scene: PathBuf,
    trajectory: Option<PathBuf>,
    columns: Option<Vec<String>>,
    values: Option<Vec<f64>>,
    coords: &str,
    start: &str,
    max_iterations: usize,
) -> PyResult<Bound<'py, PyDict>> {
    let model = load_model(&scene)?;
    let (table, source) = match (trajectory, columns, values) {
        (Some(path), None, None) => (
            read_table(&path).map_err(value_error)?,
            path.display().to_string(),
        ),
        (None, Some(columns), Some(values)) => {
            let w = columns.len().max(1);
            if values.len() % w != 0 {
                return Err(PyValueError::new_err(
                    "values do not fill whole rows of the columns",
                ));
            }
            let rows = values.len() / w;
            (
                Table {
                    columns,
                    values,
                    rows,
                },
                "trajectory".to_string(),
            )
        }
        _ => {
            return Err(PyValueError::new_err(
                "give a trajectory path, or columns and values",
            ))
        }
    };
    let prescription = Prescription::from_table(&model, &table, &source).map_err(value_error)?;
    let start = match start {
        "kinematic" => Start::Kinematic,
        "staged" => Start::Staged,
        _ => {
            return Err(PyValueError::new_err(format!(
                "start must be 'kinematic' or 'staged', not '{start}'"
            )))
        }
    };
    if max_iterations == 0 {
        return Err(PyValueError::new_err("max_iterations must be at least 1"));
    }
    let mut options = InverseOptions {
        coordinates: coordinates(coords)?,
        start,
        ..InverseOptions::default()
    };
    options.settings.max_iterations = max_iterations;
    let model = Arc::new(model);
    let sol = py
        .detach(|| inverse::solve(model, &prescription, &options))
        .map_err(|e| match e {
            Error::InvalidArgument(m) => PyValueError::new_err(m),
            other => SolveError::new_err(other.to_string()),
        })?;
    let s = &sol.summary;
    if s.report.termination != crate::solver::Termination::Converged {
        return Err(SolveError::new_err(format!(
            "the inverse solve did not converge: {}, cost {:.3e} after {} iterations",
            s.report.termination, s.report.cost, s.report.iterations
        )));
    }
    let out = run_table(py, &sol.trajectory, Some(&sol.forces))?;
    let summary = PyDict::new(py);
    summary.set_item("steps", s.steps)?;
    summary.set_item("wall_time", s.wall_time.as_secs_f64())?;
    summary.set_item("iterations", s.report.iterations)?;
    summary.set_item("worst_tracking", s.worst_tracking)?;
    summary.set_item("worst_phi", s.worst_phi)?;
    out.set_item("summary", summary)?;
    out.set_item("failures", PyList::empty(py))?;
    Ok(out)
}

#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<PyModel>()?;
    m.add_function(wrap_pyfunction!(load, m)?)?;
    m.add_function(wrap_pyfunction!(simulate_run, m)?)?;
    m.add_function(wrap_pyfunction!(inverse_run, m)?)?;
    m.add("SceneError", m.py().get_type::<SceneError>())?;
    m.add("SolveError", m.py().get_type::<SolveError>())?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    Ok(())
}
