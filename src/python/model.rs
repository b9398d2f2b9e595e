//! The `Model` class: an assembled model, its structure (points, bodies,
//! coordinates, constraints, effects) and its quantities at a given state, and
//! `mbfg.load`, and the model of a run (a loaded `Model` or a scene path).

use super::args::{arg_count, arg_numbers, arg_path, arg_real, arg_str, arg_values};
use super::errors::{arg_error, guard, invalid, one_line, SceneError};
use crate::model::PointSlot;
use crate::scene::{ConstraintKind, Effect, RelativeKind};
use crate::{Model, Scene};
use nalgebra::{DMatrix, DVector};
use numpy::{PyArray1, PyArray2, PyArrayMethods};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};
use std::path::PathBuf;
use std::sync::Arc;

/// An assembled model, immutable.
#[pyclass(name = "Model", module = "mbfg", frozen)]
pub(super) struct PyModel {
    pub(super) model: Arc<Model>,
    /// The scene text a model loaded from text (not a file) was read from, to read it
    /// again with other parameters.
    pub(super) text: Option<Arc<String>>,
}

impl PyModel {
    /// q, q̇, q̈: three state vectors.
    fn motion(
        &self,
        q: &Bound<'_, PyAny>,
        dq: &Bound<'_, PyAny>,
        ddq: &Bound<'_, PyAny>,
    ) -> PyResult<(DVector<f64>, DVector<f64>, DVector<f64>)> {
        Ok((
            self.vector(q, "q")?,
            self.vector(dq, "dq")?,
            self.vector(ddq, "ddq")?,
        ))
    }

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
            let (q, dq, ddq) = self.motion(q, dq, ddq)?;
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
    /// The force each of the scene's `constraints` carries: (name, N) in their order
    /// (`reactions::constraint_forces`: a distance's tension, a slider's normal force).
    fn constraint_forces(
        &self,
        q: &Bound<'_, PyAny>,
        dq: &Bound<'_, PyAny>,
        ddq: &Bound<'_, PyAny>,
        t: &Bound<'_, PyAny>,
    ) -> PyResult<Vec<(String, f64)>> {
        guard(|| {
            let (q, dq, ddq) = self.motion(q, dq, ddq)?;
            let t = arg_real(t, "t")?;
            let forces = crate::reactions::constraint_forces(
                &self.model,
                q.as_slice(),
                dq.as_slice(),
                ddq.as_slice(),
                t,
                None,
            )
            .map_err(arg_error)?;
            let names = self.model.scene.constraints.iter().map(|c| c.name.clone());
            Ok(names.zip(forces).collect())
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
    /// One dict per sensor: name, type, columns, sigma, rate, resolution,
    /// effective_sigma, reads.
    fn sensors<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyList>> {
        guard(|| super::sensors::sensor_list(py, &self.model))
    }
    /// The reading of sensor `name` at (q, q̇, q̈, t) and its Jacobians.
    #[pyo3(signature = (name, q, dq, ddq, t=None))]
    #[allow(clippy::type_complexity)] // four arrays
    fn sensor_value<'py>(
        &self,
        py: Python<'py>,
        name: &Bound<'py, PyAny>,
        q: &Bound<'py, PyAny>,
        dq: &Bound<'py, PyAny>,
        ddq: &Bound<'py, PyAny>,
        t: Option<&Bound<'py, PyAny>>,
    ) -> PyResult<(
        Bound<'py, PyArray1<f64>>,
        Bound<'py, PyArray2<f64>>,
        Bound<'py, PyArray2<f64>>,
        Bound<'py, PyArray2<f64>>,
    )> {
        guard(|| {
            let name = arg_str(name, "name")?;
            let (q, dq, ddq) = self.motion(q, dq, ddq)?;
            let t = match t {
                Some(t) => arg_real(t, "t")?,
                None => 0.0,
            };
            super::sensors::sensor_value(
                py,
                &self.model,
                &name,
                [q.as_slice(), dq.as_slice(), ddq.as_slice()],
                t,
            )
        })
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

/// A scene file, a loaded `Model` (read again with `params`), or with `text`, scene
/// text that `path` only names in messages (its folder resolves `mechanism:`).
#[pyfunction]
#[pyo3(signature = (path, params=None, text=None))]
pub(super) fn load(
    path: &Bound<'_, PyAny>,
    params: Option<&Bound<'_, PyAny>>,
    text: Option<&Bound<'_, PyAny>>,
) -> PyResult<PyModel> {
    guard(|| {
        let params = arg_values(params, "params")?;
        let Some(text) = text.filter(|t| !t.is_none()) else {
            let text = path
                .cast::<PyModel>()
                .ok()
                .and_then(|m| m.get().text.clone());
            return Ok(PyModel {
                model: study_model(path, &params, &[], &[])?,
                text,
            });
        };
        let text = Arc::new(arg_str(text, "text")?);
        let name = arg_path(path, "name")?;
        let scene = Scene::from_str_with(&text, &name, &params)
            .map_err(|e| SceneError::new_err(e.to_string()))?;
        let model = Model::new(&scene).map_err(|e| SceneError::new_err(e.to_string()))?;
        Ok(PyModel {
            model: Arc::new(model),
            text: Some(text),
        })
    })
}

/// A YAML document as Python values (dict, list, str, float, bool, None), read as
/// scene files are: for `mbfg.Scene.from_yaml`.
#[pyfunction]
pub(super) fn parse_yaml<'py>(
    py: Python<'py>,
    text: &Bound<'py, PyAny>,
) -> PyResult<Bound<'py, PyAny>> {
    guard(|| {
        let text = arg_str(text, "text")?;
        let root = crate::scene::yaml::parse(&text).map_err(|e| {
            let line = e.line.map(|l| format!(":{l}")).unwrap_or_default();
            let key = match e.key.is_empty() {
                true => String::new(),
                false => format!(" {}:", e.key),
            };
            SceneError::new_err(format!("<yaml>{line}:{key} {}", e.message))
        })?;
        python_value(py, &root)
    })
}

fn python_value<'py>(
    py: Python<'py>,
    node: &crate::scene::yaml::Node,
) -> PyResult<Bound<'py, PyAny>> {
    use crate::scene::yaml::Value;
    Ok(match &node.value {
        Value::Null => py.None().into_bound(py),
        Value::Bool(b) => b.into_pyobject(py)?.to_owned().into_any(),
        Value::Number(v) => v.into_pyobject(py)?.into_any(),
        Value::String(s) => s.into_pyobject(py)?.into_any(),
        Value::Seq(items) => {
            let list = PyList::empty(py);
            for item in items {
                list.append(python_value(py, item)?)?;
            }
            list.into_any()
        }
        Value::Map(pairs) => {
            let dict = PyDict::new(py);
            for (k, v) in pairs {
                dict.set_item(python_value(py, k)?, python_value(py, v)?)?;
            }
            dict.into_any()
        }
    })
}

/// The model of a run: a path, or a `Model` already loaded; re-read from its file
/// when parameters are overridden, and re-assembled when the initial state is
/// (positions of coordinates of q, velocities of independent coordinates).
pub(super) fn study_model(
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
    let text = scene
        .cast::<PyModel>()
        .ok()
        .and_then(|m| m.get().text.clone());
    let path = match &loaded {
        Some(m) => PathBuf::from(&m.scene.file),
        None => arg_path(scene, "scene")?,
    };
    let mut sc = match (&loaded, params.is_empty(), &text) {
        (Some(m), true, _) => m.scene.clone(),
        (_, _, Some(text)) => Scene::from_str_with(text, &path, params)
            .map_err(|e| SceneError::new_err(e.to_string()))?,
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
