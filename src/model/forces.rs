//! Generalized forces Q(q, q̇, t) assembled from the scene's effects, and only from
//! them: an absent effect is not in the list and costs nothing.

use super::{mass, Model, PointSlot};
use crate::error::{Error, Result};
use crate::scene::{Effect, TimeFunction};

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
        name: String,
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
        value: TimeFunction,
    },
    PointForce {
        index: usize,
        value: [TimeFunction; 2],
    },
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
                name: name.clone(),
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
                value: value.clone(),
            },
            Effect::Force { point, value, .. } => match model.points[*point] {
                PointSlot::Free(index) => Force::PointForce {
                    index,
                    value: value.clone(),
                },
                PointSlot::Fixed(_) => {
                    return Err(Error::InvalidArgument(format!(
                        "force at fixed point '{}'",
                        scene.points[*point].name
                    )))
                }
            },
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
            return Err(Error::Singular(format!(
                "spring-damper '{name}' has zero length: its direction is undefined"
            )));
        }
        Ok(())
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
            Force::Torque { index, value } => out[*index] += value.at(t)?,
            Force::PointForce { index, value } => {
                out[*index] += value[0].at(t)?;
                out[*index + 1] += value[1].at(t)?;
            }
        }
        Ok(())
    }

    /// Adds ∂Q/∂q to `kq` and ∂Q/∂q̇ to `kv` (row-major n × n).
    pub fn add_jacobians(
        &self,
        model: &Model,
        q: &[f64],
        dq: &[f64],
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
            Force::Gravity { .. } | Force::Torque { .. } | Force::PointForce { .. } => {}
        }
        Ok(())
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
            Force::Torque { .. } | Force::PointForce { .. } | Force::Motor { .. } => 0.0,
        }
    }
}
