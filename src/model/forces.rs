//! Generalized forces Q(q, q̇, t) assembled from the scene's effects, and only from
//! them: an absent effect is not in the list and costs nothing.

use super::{mass, Model, PointSlot};
use crate::error::{Error, Result};
use crate::expr::Expr;
use crate::scene::{Effect, LoadFunction, Scene, StateQuantity};
use std::sync::Arc;

/// Generalized forces computed outside the scene, Q_ext(t, q, q̇) (a Python callable).
/// Its Jacobians are taken by forward differences: 2n + 1 calls per linearization.
pub trait ExternalLoad: Send + Sync + std::fmt::Debug {
    /// Adds the load's generalized forces at (q, q̇, t) to `out` (length n, q's order).
    fn add_to(&self, t: f64, q: &[f64], dq: &[f64], out: &mut [f64]) -> Result<()>;
}

/// One effect, ready to evaluate.
#[derive(Debug, Clone)]
pub enum Force {
    /// Uniform gravity: a constant generalized force (precomputed) with potential
    /// −Σ m g·r_G.
    Gravity {
        vector: [f64; 2],
        /// (index in q, value) of the nonzero entries.
        entries: Vec<(usize, f64)>,
    },
    /// Spring k(ℓ − ℓ₀) and damper c ℓ̇ along the line between two points.
    SpringDamper {
        /// Shared: an estimate makes copies with other constants at every evaluation.
        name: Arc<str>,
        points: [usize; 2],
        stiffness: f64,
        rest_length: f64,
        damping: f64,
    },
    /// −k(θ − θ₀) − c θ̇ on the coordinate at `index`.
    RotationalSpringDamper {
        index: usize,
        stiffness: f64,
        rest_angle: f64,
        damping: f64,
    },
    /// T_s (1 − θ̇/ω₀) on the coordinate at `index`.
    Motor {
        index: usize,
        stall_torque: f64,
        no_load_speed: f64,
    },
    Torque {
        index: usize,
        value: Load,
    },
    PointForce {
        index: usize,
        value: [Load; 2],
    },
    External {
        name: String,
        load: Arc<dyn ExternalLoad>,
    },
}

/// A state quantity located in q.
#[derive(Debug, Clone, Copy)]
enum Quantity {
    Coordinate(usize),
    Rate(usize),
    Position {
        point: usize,
        axis: usize,
    },
    Velocity {
        point: usize,
        axis: usize,
    },
    /// The angle of the segment between a body's first two points, and its rate.
    Angle([usize; 2]),
    Omega([usize; 2]),
}

/// An effect's value compiled against q's layout: slot 0 of its expression is `t`,
/// slot k + 1 the k-th state quantity, and `partials[k]` is ∂value/∂(quantity k),
/// derived symbolically.
#[derive(Debug, Clone)]
pub struct Load {
    value: Expr,
    quantities: Vec<Quantity>,
    partials: Vec<Expr>,
    /// The identified parameters the value uses, in the slots after the quantities:
    /// (index among the model's identified parameters, value in the file,
    /// ∂value/∂p), derived symbolically.
    parameters: Vec<(usize, f64, Expr)>,
    text: String,
}

/// Slots on the stack for expressions of up to this many state quantities.
const STACK_SLOTS: usize = 16;

impl Load {
    pub(crate) fn compile(model: &Model, function: &LoadFunction) -> Result<Load> {
        let scene = &model.scene;
        let names = function.state_names();
        let quantities = names
            .iter()
            .map(|name| locate(model, scene, name))
            .collect::<Result<Vec<_>>>()?;
        let identified = &scene.identified.names;
        let value = function
            .expr()
            .resolve(&|n| {
                if n == "t" {
                    Some(0)
                } else if let Some(k) = names.iter().position(|m| m == n) {
                    Some(k + 1)
                } else {
                    let k = function.parameters.iter().position(|(p, _)| p == n)?;
                    Some(names.len() + 1 + k)
                }
            })
            .map_err(|e| Error::InvalidArgument(format!("'{}': {e}", function.text)))?;
        let derivative = |slot: usize| {
            value.derivative_slot(slot).map_err(|e| {
                let text = crate::expr::excerpt(&function.text, 40);
                Error::InvalidArgument(format!("'{text}': {e}"))
            })
        };
        let partials = (1..=quantities.len())
            .map(derivative)
            .collect::<Result<Vec<_>>>()?;
        let parameters = function
            .parameters
            .iter()
            .enumerate()
            .map(|(k, (name, v))| {
                let j = identified.iter().position(|p| p == name).ok_or_else(|| {
                    Error::InvalidArgument(format!(
                        "'{}': '{name}' is not among the identified parameters",
                        function.text
                    ))
                })?;
                Ok((j, *v, derivative(names.len() + 1 + k)?))
            })
            .collect::<Result<Vec<_>>>()?;
        Ok(Load {
            value,
            quantities,
            partials,
            parameters,
            text: function.text.clone(),
        })
    }

    /// Whether the value uses a parameter an estimate identifies.
    pub fn uses_parameters(&self) -> bool {
        !self.parameters.is_empty()
    }

    /// The identified parameters the value uses (indices in the model's order).
    pub fn parameter_indices(&self) -> impl Iterator<Item = usize> + '_ {
        self.parameters.iter().map(|&(j, ..)| j)
    }

    /// Calls `f` with the slot values at (q, q̇, t), the identified parameters at `p`
    /// (all of them, in the model's order), or at their file values.
    fn with_slots<R>(
        &self,
        model: &Model,
        q: &[f64],
        dq: &[f64],
        (t, p): (f64, Option<&[f64]>),
        f: impl FnOnce(&[f64]) -> R,
    ) -> R {
        let nq = self.quantities.len();
        let fill = |slots: &mut [f64]| {
            slots[0] = t;
            for (s, quantity) in slots[1..].iter_mut().zip(&self.quantities) {
                *s = quantity.value(model, q, dq);
            }
            for (s, &(j, file, _)) in slots[nq + 1..].iter_mut().zip(&self.parameters) {
                *s = p.map_or(file, |p| p[j]);
            }
        };
        let m = nq + self.parameters.len() + 1;
        if m <= STACK_SLOTS {
            let mut buf = [0.0; STACK_SLOTS];
            fill(&mut buf[..m]);
            f(&buf[..m])
        } else {
            let mut buf = vec![0.0; m];
            fill(&mut buf);
            f(&buf)
        }
    }

    pub(crate) fn value(&self, model: &Model, q: &[f64], dq: &[f64], t: f64) -> Result<f64> {
        self.value_at(model, q, dq, (t, None))
    }

    /// The value with the identified parameters at `p` (`None`: the file's).
    pub(crate) fn value_at(
        &self,
        model: &Model,
        q: &[f64],
        dq: &[f64],
        (t, p): (f64, Option<&[f64]>),
    ) -> Result<f64> {
        if self.quantities.is_empty() && self.parameters.is_empty() {
            if let Some(c) = self.value.as_constant() {
                return Ok(c);
            }
        }
        let v = self.with_slots(model, q, dq, (t, p), |s| self.value.eval_slots(s));
        self.finite(v, t)
    }

    /// ∂value/∂pⱼ at the state and the parameters `p`, for every identified
    /// parameter j, added to `out` (length P) times `scale`.
    pub(crate) fn add_parameter_gradient(
        &self,
        model: &Model,
        (q, dq, t): (&[f64], &[f64], f64),
        p: &[f64],
        scale: f64,
        out: &mut [f64],
    ) -> Result<()> {
        self.with_slots(model, q, dq, (t, Some(p)), |slots| {
            for (j, _, partial) in &self.parameters {
                out[*j] += scale * self.finite(partial.eval_slots(slots), t)?;
            }
            Ok(())
        })
    }

    fn finite(&self, v: f64, t: f64) -> Result<f64> {
        if v.is_finite() {
            Ok(v)
        } else {
            let text = crate::expr::excerpt(&self.text, 40);
            Err(Error::InvalidArgument(format!(
                "'{text}' at t = {t}: evaluates to a non-finite number"
            )))
        }
    }

    /// Adds ∂value/∂q and ∂value/∂q̇ at the state (q, q̇, t) to row `row` of `kq` and
    /// `kv`.
    pub(crate) fn add_gradient(
        &self,
        model: &Model,
        state: (&[f64], &[f64], f64),
        row: usize,
        kq: &mut [f64],
        kv: &mut [f64],
    ) -> Result<()> {
        self.add_gradient_at(model, state, (None, 1.0), row, kq, kv)
    }

    /// [`Load::add_gradient`] with the identified parameters at `p` (`None`: the
    /// file's), times `scale`.
    pub(crate) fn add_gradient_at(
        &self,
        model: &Model,
        (q, dq, t): (&[f64], &[f64], f64),
        (p, scale): (Option<&[f64]>, f64),
        row: usize,
        kq: &mut [f64],
        kv: &mut [f64],
    ) -> Result<()> {
        if self.quantities.is_empty() {
            return Ok(());
        }
        let n = model.n();
        let (kq, kv) = (
            &mut kq[row * n..(row + 1) * n],
            &mut kv[row * n..(row + 1) * n],
        );
        self.with_slots(model, q, dq, (t, p), |slots| {
            for (quantity, partial) in self.quantities.iter().zip(&self.partials) {
                let d = scale * self.finite(partial.eval_slots(slots), t)?;
                if d != 0.0 {
                    quantity.add_gradient(model, q, dq, d, kq, kv);
                }
            }
            Ok(())
        })
    }

    pub fn is_state_dependent(&self) -> bool {
        !self.quantities.is_empty()
    }

    /// Whether the value depends on q, and on q̇.
    pub fn reads(&self) -> [bool; 2] {
        let mut reads = [false; 2];
        for quantity in &self.quantities {
            match quantity {
                Quantity::Coordinate(_) | Quantity::Position { .. } | Quantity::Angle(_) => {
                    reads[0] = true
                }
                Quantity::Rate(_) | Quantity::Velocity { .. } => reads[1] = true,
                Quantity::Omega(_) => reads = [true, true],
            }
        }
        reads
    }

    /// The expression as the scene wrote it.
    pub fn text(&self) -> &str {
        &self.text
    }
}

/// Where in q a state quantity of the scene lives.
fn locate(model: &Model, scene: &Scene, name: &str) -> Result<Quantity> {
    let rel = |c: usize| model.relative_offset + c;
    let body = |b: usize| -> Result<[usize; 2]> {
        let points = &scene.bodies[b].points;
        Ok([points[0], points[1]])
    };
    Ok(
        match scene.state_quantity(name).ok_or_else(|| {
            Error::InvalidArgument(format!("'{name}' is not a state quantity of the scene"))
        })? {
            StateQuantity::Coordinate(c) => Quantity::Coordinate(rel(c)),
            StateQuantity::Rate(c) => Quantity::Rate(rel(c)),
            StateQuantity::X(p) => Quantity::Position { point: p, axis: 0 },
            StateQuantity::Y(p) => Quantity::Position { point: p, axis: 1 },
            StateQuantity::Vx(p) => Quantity::Velocity { point: p, axis: 0 },
            StateQuantity::Vy(p) => Quantity::Velocity { point: p, axis: 1 },
            StateQuantity::Angle(b) => Quantity::Angle(body(b)?),
            StateQuantity::Omega(b) => Quantity::Omega(body(b)?),
        },
    )
}

/// d = r_b − r_a and ḋ of a body's first two points, and |d|².
fn segment(model: &Model, q: &[f64], dq: &[f64], [a, b]: [usize; 2]) -> ([f64; 2], [f64; 2], f64) {
    let (ra, rb) = (model.point_position(q, a), model.point_position(q, b));
    let (va, vb) = (model.point_velocity(dq, a), model.point_velocity(dq, b));
    let d = [rb[0] - ra[0], rb[1] - ra[1]];
    let vd = [vb[0] - va[0], vb[1] - va[1]];
    (d, vd, d[0] * d[0] + d[1] * d[1])
}

impl Quantity {
    fn value(&self, model: &Model, q: &[f64], dq: &[f64]) -> f64 {
        match *self {
            Quantity::Coordinate(i) => q[i],
            Quantity::Rate(i) => dq[i],
            Quantity::Position { point, axis } => model.point_position(q, point)[axis],
            Quantity::Velocity { point, axis } => model.point_velocity(dq, point)[axis],
            Quantity::Angle(points) => {
                let (d, _, _) = segment(model, q, dq, points);
                d[1].atan2(d[0])
            }
            Quantity::Omega(points) => {
                let (d, vd, l2) = segment(model, q, dq, points);
                (d[0] * vd[1] - d[1] * vd[0]) / l2
            }
        }
    }

    /// Adds p·∂(quantity)/∂q to `kq` and p·∂(quantity)/∂q̇ to `kv` (one row each).
    fn add_gradient(
        &self,
        model: &Model,
        q: &[f64],
        dq: &[f64],
        p: f64,
        kq: &mut [f64],
        kv: &mut [f64],
    ) {
        let slot = |point: usize| match model.points[point] {
            PointSlot::Free(i) => Some(i),
            PointSlot::Fixed(_) => None,
        };
        // ∂/∂d of a body quantity lands on its second point, minus on its first.
        let spread = |row: &mut [f64], [a, b]: [usize; 2], g: [f64; 2]| {
            for (point, sign) in [(b, 1.0), (a, -1.0)] {
                if let Some(i) = slot(point) {
                    row[i] += sign * p * g[0];
                    row[i + 1] += sign * p * g[1];
                }
            }
        };
        match *self {
            Quantity::Coordinate(i) => kq[i] += p,
            Quantity::Rate(i) => kv[i] += p,
            Quantity::Position { point, axis } => {
                if let Some(i) = slot(point) {
                    kq[i + axis] += p;
                }
            }
            Quantity::Velocity { point, axis } => {
                if let Some(i) = slot(point) {
                    kv[i + axis] += p;
                }
            }
            Quantity::Angle(points) => {
                // θ = atan2(d_y, d_x): ∂θ/∂d = (−d_y, d_x)/|d|².
                let (d, _, l2) = segment(model, q, dq, points);
                spread(kq, points, [-d[1] / l2, d[0] / l2]);
            }
            Quantity::Omega(points) => {
                // ω = (d × ḋ)/|d|²: ∂ω/∂ḋ = (−d_y, d_x)/|d|², and
                // ∂ω/∂d = (ḋ_y − 2ω d_x, −ḋ_x − 2ω d_y)/|d|².
                let (d, vd, l2) = segment(model, q, dq, points);
                let w = (d[0] * vd[1] - d[1] * vd[0]) / l2;
                spread(kv, points, [-d[1] / l2, d[0] / l2]);
                spread(
                    kq,
                    points,
                    [
                        (vd[1] - 2.0 * w * d[0]) / l2,
                        (-vd[0] - 2.0 * w * d[1]) / l2,
                    ],
                );
            }
        }
    }
}

impl Force {
    /// A load computed outside the scene.
    pub fn external(name: &str, load: Arc<dyn ExternalLoad>) -> Force {
        Force::External {
            name: name.to_string(),
            load,
        }
    }
}

pub fn assemble(model: &Model) -> Result<Vec<Force>> {
    let scene = &model.scene;
    let rel = |c: usize| model.relative_offset + c;
    let mut out = Vec::new();
    for e in &scene.effects {
        out.push(match e {
            Effect::Gravity { vector } => {
                let mut q = vec![0.0; model.n()];
                for body in &scene.bodies {
                    let f = mass::body_gravity_force(body, *vector);
                    for (k, &p) in body.points[..2].iter().enumerate() {
                        if let PointSlot::Free(i) = model.points[p] {
                            q[i] += f[2 * k];
                            q[i + 1] += f[2 * k + 1];
                        }
                    }
                }
                for (p, point) in scene.points.iter().enumerate() {
                    if let PointSlot::Free(i) = model.points[p] {
                        q[i] += point.mass * vector[0];
                        q[i + 1] += point.mass * vector[1];
                    }
                }
                Force::Gravity {
                    vector: *vector,
                    entries: q
                        .iter()
                        .enumerate()
                        .filter(|(_, v)| **v != 0.0)
                        .map(|(i, v)| (i, *v))
                        .collect(),
                }
            }
            Effect::SpringDamper {
                name,
                points,
                stiffness,
                rest_length,
                damping,
            } => Force::SpringDamper {
                name: Arc::from(name.as_str()),
                points: *points,
                stiffness: *stiffness,
                rest_length: *rest_length,
                damping: *damping,
            },
            Effect::RotationalSpringDamper {
                coordinate,
                stiffness,
                rest_angle,
                damping,
                ..
            } => Force::RotationalSpringDamper {
                index: rel(*coordinate),
                stiffness: *stiffness,
                rest_angle: *rest_angle,
                damping: *damping,
            },
            Effect::Motor {
                coordinate,
                stall_torque,
                no_load_speed,
                ..
            } => Force::Motor {
                index: rel(*coordinate),
                stall_torque: *stall_torque,
                no_load_speed: *no_load_speed,
            },
            Effect::Torque {
                coordinate, value, ..
            } => Force::Torque {
                index: rel(*coordinate),
                value: Load::compile(model, value)?,
            },
            Effect::Force { point, value, .. } => match model.points[*point] {
                PointSlot::Free(index) => Force::PointForce {
                    index,
                    value: [
                        Load::compile(model, &value[0])?,
                        Load::compile(model, &value[1])?,
                    ],
                },
                PointSlot::Fixed(_) => {
                    return Err(Error::InvalidArgument(format!(
                        "force at fixed point '{}'",
                        scene.points[*point].name
                    )))
                }
            },
            Effect::External { name } => {
                return Err(Error::InvalidArgument(format!(
                    "effect '{name}': an external load is added to a model, not read from a scene"
                )))
            }
        });
    }
    Ok(out)
}

/// Geometry of a spring: d = r₂ − r₁, its length ℓ, unit vector e, and ℓ̇.
struct SpringState {
    d: [f64; 2],
    len: f64,
    e: [f64; 2],
    vd: [f64; 2],
    rate: f64,
}

impl Force {
    fn spring_state(model: &Model, q: &[f64], dq: &[f64], points: [usize; 2]) -> SpringState {
        let (r1, r2) = (
            model.point_position(q, points[0]),
            model.point_position(q, points[1]),
        );
        let (v1, v2) = (
            model.point_velocity(dq, points[0]),
            model.point_velocity(dq, points[1]),
        );
        let d = [r2[0] - r1[0], r2[1] - r1[1]];
        let vd = [v2[0] - v1[0], v2[1] - v1[1]];
        let len = d[0].hypot(d[1]);
        let e = if len > 0.0 {
            [d[0] / len, d[1] / len]
        } else {
            [0.0, 0.0]
        };
        SpringState {
            d,
            len,
            e,
            vd,
            rate: e[0] * vd[0] + e[1] * vd[1],
        }
    }

    /// A spring whose direction is needed but whose points coincide has no
    /// defined force: report it instead of writing NaN.
    fn check_length(name: &str, s: &SpringState, rest_length: f64, damping: f64) -> Result<()> {
        let needs_direction = rest_length != 0.0 || damping != 0.0;
        if needs_direction && !(s.len > 1e-12) {
            return Err(Error::singular(format!(
                "spring-damper '{name}' has zero length: its direction is undefined"
            )));
        }
        Ok(())
    }

    /// Whether this is an actuator on q[index]: a torque or a motor there (what an
    /// `input` sensor reads).
    pub fn actuates(&self, index: usize) -> bool {
        matches!(self, Force::Torque { index: i, .. } | Force::Motor { index: i, .. } if *i == index)
    }

    /// A spring-damper (linear or rotational) with other stiffness and damping, or a
    /// DC motor with another stall torque, its geometry kept: its force is linear in
    /// them, so the constants' derivatives give the force's. `None` for any other
    /// effect.
    pub fn with_constants(&self, k: f64, c: f64) -> Option<Force> {
        match self {
            Force::SpringDamper {
                name,
                points,
                rest_length,
                ..
            } => Some(Force::SpringDamper {
                name: name.clone(),
                points: *points,
                stiffness: k,
                rest_length: *rest_length,
                damping: c,
            }),
            Force::RotationalSpringDamper {
                index, rest_angle, ..
            } => Some(Force::RotationalSpringDamper {
                index: *index,
                stiffness: k,
                rest_angle: *rest_angle,
                damping: c,
            }),
            // A DC motor's torque, linear in its stall torque (k; c unused).
            Force::Motor {
                index,
                no_load_speed,
                ..
            } => Some(Force::Motor {
                index: *index,
                stall_torque: k,
                no_load_speed: *no_load_speed,
            }),
            _ => None,
        }
    }

    /// Adds this effect's generalized force at (q, q̇, t) to `out`.
    pub fn add_to(
        &self,
        model: &Model,
        q: &[f64],
        dq: &[f64],
        t: f64,
        out: &mut [f64],
    ) -> Result<()> {
        match self {
            Force::Gravity { entries, .. } => {
                for &(i, v) in entries {
                    out[i] += v;
                }
            }
            Force::SpringDamper {
                name,
                points,
                stiffness,
                rest_length,
                damping,
            } => {
                let s = Self::spring_state(model, q, dq, *points);
                Self::check_length(name, &s, *rest_length, *damping)?;
                // Force on the second point; the first gets the opposite.
                let f2 = if *rest_length == 0.0 && *damping == 0.0 {
                    [-stiffness * s.d[0], -stiffness * s.d[1]]
                } else {
                    let tension = stiffness * (s.len - rest_length) + damping * s.rate;
                    [-tension * s.e[0], -tension * s.e[1]]
                };
                for (k, sign) in [(1, 1.0), (0, -1.0)] {
                    if let PointSlot::Free(i) = model.points[points[k]] {
                        out[i] += sign * f2[0];
                        out[i + 1] += sign * f2[1];
                    }
                }
            }
            Force::RotationalSpringDamper {
                index,
                stiffness,
                rest_angle,
                damping,
            } => {
                out[*index] -= stiffness * (q[*index] - rest_angle) + damping * dq[*index];
            }
            Force::Motor {
                index,
                stall_torque,
                no_load_speed,
            } => out[*index] += stall_torque * (1.0 - dq[*index] / no_load_speed),
            Force::Torque { index, value } => out[*index] += value.value(model, q, dq, t)?,
            Force::PointForce { index, value } => {
                out[*index] += value[0].value(model, q, dq, t)?;
                out[*index + 1] += value[1].value(model, q, dq, t)?;
            }
            Force::External { load, .. } => load.add_to(t, q, dq, out)?,
        }
        Ok(())
    }

    /// The expressions of a torque's or a force's value, each with the row of Q it
    /// adds to (none for other effects).
    pub fn value_loads(&self) -> [Option<(usize, &Load)>; 2] {
        match self {
            Force::Torque { index, value } => [Some((*index, value)), None],
            Force::PointForce { index, value } => {
                [Some((*index, &value[0])), Some((index + 1, &value[1]))]
            }
            _ => [None, None],
        }
    }

    /// Adds ∂Q/∂q to `kq` and ∂Q/∂q̇ to `kv` (row-major n × n) at (q, q̇, t).
    pub fn add_jacobians(
        &self,
        model: &Model,
        (q, dq, t): (&[f64], &[f64], f64),
        kq: &mut [f64],
        kv: &mut [f64],
    ) -> Result<()> {
        let n = model.n();
        match self {
            Force::SpringDamper {
                name,
                points,
                stiffness: k,
                rest_length,
                damping: c,
            } => {
                let s = Self::spring_state(model, q, dq, *points);
                Self::check_length(name, &s, *rest_length, *c)?;
                // F₂ = −f e with f = k(ℓ−ℓ₀) + c ℓ̇; ∂e/∂d = P/ℓ, P = I − eeᵀ,
                // ∂ℓ̇/∂d = vdᵀP/ℓ, ∂ℓ̇/∂vd = eᵀ.
                let (a, b) = if *rest_length == 0.0 && *c == 0.0 {
                    ([[-k, 0.0], [0.0, -k]], [[0.0; 2]; 2])
                } else {
                    let e = s.e;
                    let f = k * (s.len - rest_length) + c * s.rate;
                    let p = [
                        [1.0 - e[0] * e[0], -e[0] * e[1]],
                        [-e[1] * e[0], 1.0 - e[1] * e[1]],
                    ];
                    let vp = [
                        (s.vd[0] * p[0][0] + s.vd[1] * p[1][0]) / s.len,
                        (s.vd[0] * p[0][1] + s.vd[1] * p[1][1]) / s.len,
                    ];
                    let mut a = [[0.0; 2]; 2];
                    let mut b = [[0.0; 2]; 2];
                    for r in 0..2 {
                        for col in 0..2 {
                            let df = k * e[col] + c * vp[col];
                            a[r][col] = -e[r] * df - f * p[r][col] / s.len;
                            b[r][col] = -c * e[r] * e[col];
                        }
                    }
                    (a, b)
                };
                // d = r₂ − r₁: ∂F₂/∂r₂ = A, ∂F₂/∂r₁ = −A, and F₁ = −F₂.
                let slots = [model.points[points[0]], model.points[points[1]]];
                for (ri, si) in [(0usize, -1.0), (1, 1.0)] {
                    let PointSlot::Free(i) = slots[ri] else {
                        continue;
                    };
                    for (cj, sj) in [(0usize, -1.0), (1, 1.0)] {
                        let PointSlot::Free(j) = slots[cj] else {
                            continue;
                        };
                        for r in 0..2 {
                            for col in 0..2 {
                                kq[(i + r) * n + j + col] += si * sj * a[r][col];
                                kv[(i + r) * n + j + col] += si * sj * b[r][col];
                            }
                        }
                    }
                }
            }
            Force::RotationalSpringDamper {
                index,
                stiffness,
                damping,
                ..
            } => {
                kq[index * n + index] -= stiffness;
                kv[index * n + index] -= damping;
            }
            Force::Motor {
                index,
                stall_torque,
                no_load_speed,
            } => kv[index * n + index] -= stall_torque / no_load_speed,
            Force::Torque { index, value } => {
                value.add_gradient(model, (q, dq, t), *index, kq, kv)?;
            }
            Force::PointForce { index, value } => {
                for (axis, v) in value.iter().enumerate() {
                    v.add_gradient(model, (q, dq, t), index + axis, kq, kv)?;
                }
            }
            Force::External { load, .. } => external_jacobians(load.as_ref(), (q, dq, t), kq, kv)?,
            Force::Gravity { .. } => {}
        }
        Ok(())
    }

    /// The rows and columns of Q that [`Force::add_jacobians`] can write (the same for
    /// ∂Q/∂q and ∂Q/∂q̇, whatever the state): `None` where any entry may be (a load
    /// computed outside the scene). What a sparse Jacobian of Q reserves room for.
    pub fn jacobian_pattern(&self, model: &Model) -> Option<(Vec<usize>, Vec<usize>)> {
        let point = |p: usize| match model.points[p] {
            PointSlot::Free(i) => vec![i, i + 1],
            PointSlot::Fixed(_) => Vec::new(),
        };
        let load = |rows: Vec<usize>, loads: &[&Load]| {
            let mut cols: Vec<usize> = loads
                .iter()
                .flat_map(|l| &l.quantities)
                .flat_map(|quantity| match *quantity {
                    Quantity::Coordinate(i) | Quantity::Rate(i) => vec![i],
                    Quantity::Position { point: p, .. } | Quantity::Velocity { point: p, .. } => {
                        point(p)
                    }
                    Quantity::Angle([a, b]) | Quantity::Omega([a, b]) => {
                        [point(a), point(b)].concat()
                    }
                })
                .collect();
            cols.sort_unstable();
            cols.dedup();
            (rows, cols)
        };
        Some(match self {
            Force::Gravity { .. } => (Vec::new(), Vec::new()),
            Force::SpringDamper { points, .. } => {
                let slots = [point(points[0]), point(points[1])].concat();
                (slots.clone(), slots)
            }
            Force::RotationalSpringDamper { index, .. } | Force::Motor { index, .. } => {
                (vec![*index], vec![*index])
            }
            Force::Torque { index, value } => load(vec![*index], &[value]),
            Force::PointForce { index, value } => {
                load(vec![*index, index + 1], &[&value[0], &value[1]])
            }
            Force::External { .. } => return None,
        })
    }

    /// Potential energy of conservative effects (0 for the others).
    pub fn potential(&self, model: &Model, q: &[f64]) -> f64 {
        match self {
            Force::Gravity { vector, .. } => {
                let g = vector;
                let mut v = 0.0;
                for body in &model.scene.bodies {
                    let r1 = model.point_position(q, body.points[0]);
                    let r2 = model.point_position(q, body.points[1]);
                    let rg = mass::body_cog_position(body, r1, r2);
                    v -= body.mass * (g[0] * rg[0] + g[1] * rg[1]);
                }
                for (p, point) in model.scene.points.iter().enumerate() {
                    let r = model.point_position(q, p);
                    v -= point.mass * (g[0] * r[0] + g[1] * r[1]);
                }
                v
            }
            Force::SpringDamper {
                points,
                stiffness,
                rest_length,
                ..
            } => {
                let (r1, r2) = (
                    model.point_position(q, points[0]),
                    model.point_position(q, points[1]),
                );
                let len = (r2[0] - r1[0]).hypot(r2[1] - r1[1]);
                0.5 * stiffness * (len - rest_length).powi(2)
            }
            Force::RotationalSpringDamper {
                index,
                stiffness,
                rest_angle,
                ..
            } => 0.5 * stiffness * (q[*index] - rest_angle).powi(2),
            Force::Torque { .. }
            | Force::PointForce { .. }
            | Force::Motor { .. }
            | Force::External { .. } => 0.0,
        }
    }
}

/// ∂Q/∂q and ∂Q/∂q̇ of an external load by forward differences, each column a step
/// of √ε·max(1, |x|): about eight digits, enough for Newton's steps (the residual
/// itself stays exact, so the solution does not lose them).
fn external_jacobians(
    load: &dyn ExternalLoad,
    (q, dq, t): (&[f64], &[f64], f64),
    kq: &mut [f64],
    kv: &mut [f64],
) -> Result<()> {
    let n = q.len();
    let mut base = vec![0.0; n];
    load.add_to(t, q, dq, &mut base)?;
    let mut x = [q.to_vec(), dq.to_vec()];
    let mut shifted = vec![0.0; n];
    for which in 0..2 {
        for j in 0..n {
            let saved = x[which][j];
            let h = f64::EPSILON.sqrt() * saved.abs().max(1.0);
            x[which][j] = saved + h;
            shifted.fill(0.0);
            load.add_to(t, &x[0], &x[1], &mut shifted)?;
            x[which][j] = saved;
            let k = if which == 0 { &mut *kq } else { &mut *kv };
            for i in 0..n {
                k[i * n + j] += (shifted[i] - base[i]) / h;
            }
        }
    }
    Ok(())
}
