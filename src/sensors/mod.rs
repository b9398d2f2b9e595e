//! Sensors: what each reads of the state (its measurement function h(q, q̇, q̈, t)
//! with closed-form Jacobians), its noise and quantization, resolved against the
//! model's layout from the scene's `sensors:`; and what an estimator assumes beyond
//! them (`estimation:`). [`measure`] makes noisy readings of a known trajectory.

pub mod measure;

use crate::error::{Error, Result};
use crate::model::forces::Load;
use crate::model::{Model, PointSlot};
use crate::scene::{EstimationDef, SensorDef, SensorDefKind};

/// What a sensor reads, located in the model.
#[derive(Debug, Clone)]
pub enum SensorKind {
    /// q[coordinate].
    Encoder { coordinate: usize },
    /// The angular velocity of a body (index into the scene's bodies).
    Gyroscope { body: usize },
    /// The specific force at a point of a body, in the body's frame.
    Accelerometer { body: usize, point: usize },
    /// A point's position (index into the scene's points).
    Marker { point: usize },
    /// An expression of t and the state, compiled as an effect's value is.
    Expression { value: Load },
    /// The generalized force the actuators put on q[coordinate]: the sum of the
    /// scene's torque and motor effects on it (what `measure` reads), or in an
    /// estimate the unknown input on it ([`crate::factors::InputReading`]).
    Input { coordinate: usize },
}

/// A sensor of the model.
#[derive(Debug, Clone)]
pub struct Sensor {
    pub name: String,
    pub kind: SensorKind,
    /// Standard deviation of the noise of a reading.
    pub sigma: f64,
    /// Counts per turn (an encoder).
    pub resolution: Option<u64>,
    /// Readings per second, when the scene gives it.
    pub rate: Option<f64>,
}

/// What an estimator assumes beyond the sensors, with coordinates as indices in q.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct EstimationSpec {
    /// σ of the dynamics factor.
    pub process_sigma: Option<f64>,
    /// (coordinate, σ) of the prior on initial positions.
    pub initial_sigma: Vec<(usize, f64)>,
    /// (coordinate, σ) of the prior on initial velocities.
    pub initial_velocity_sigma: Vec<(usize, f64)>,
    /// (coordinate, σ of the rate) of unknown generalized forces, random walks.
    pub inputs: Vec<(usize, f64)>,
}

/// The Jacobian blocks a sensor writes: row-major dim × n each.
struct Blocks<'a> {
    q: &'a mut [f64],
    dq: &'a mut [f64],
    ddq: &'a mut [f64],
}

impl Sensor {
    /// Entries of a reading: 2 for an accelerometer and a marker, else 1.
    pub fn dim(&self) -> usize {
        match self.kind {
            SensorKind::Accelerometer { .. } | SensorKind::Marker { .. } => 2,
            _ => 1,
        }
    }

    /// The reading's columns in a measurement file: the name, or `<name>.x`,
    /// `<name>.y`.
    pub fn columns(&self) -> Vec<String> {
        if self.dim() == 2 {
            vec![format!("{}.x", self.name), format!("{}.y", self.name)]
        } else {
            vec![self.name.clone()]
        }
    }

    /// The scene's `type` of the sensor.
    pub fn type_name(&self) -> &'static str {
        match self.kind {
            SensorKind::Encoder { .. } => "encoder",
            SensorKind::Gyroscope { .. } => "gyroscope",
            SensorKind::Accelerometer { .. } => "accelerometer",
            SensorKind::Marker { .. } => "marker",
            SensorKind::Expression { .. } => "expression",
            SensorKind::Input { .. } => "input",
        }
    }

    /// A one-line description for `mbfg check`.
    pub fn describe(&self, model: &Model) -> String {
        let v = crate::io::number;
        let point = |p: usize| model.scene.points[p].name.as_str();
        let body = |b: usize| model.scene.bodies[b].name.as_str();
        let (what, unit) = match &self.kind {
            SensorKind::Encoder { coordinate } => (
                format!("encoder on {}", model.names[*coordinate]),
                if self.reads_an_angle(model) {
                    "rad"
                } else {
                    "m"
                },
            ),
            SensorKind::Gyroscope { body: b } => (format!("gyroscope on {}", body(*b)), "rad/s"),
            SensorKind::Accelerometer { body: b, point: p } => (
                format!("accelerometer at {} of {}", point(*p), body(*b)),
                "m/s²",
            ),
            SensorKind::Marker { point: p } => (format!("marker at {}", point(*p)), "m"),
            SensorKind::Expression { value } => (format!("expression {}", value.text()), ""),
            SensorKind::Input { coordinate } => {
                (format!("input on {}", model.names[*coordinate]), "N or N·m")
            }
        };
        let mut line = format!("{}: {what}, σ = {}", self.name, v(self.sigma));
        if !unit.is_empty() {
            line.push(' ');
            line.push_str(unit);
        }
        if let Some(r) = self.resolution {
            line.push_str(&format!(", {r} counts per turn"));
        }
        if let Some(r) = self.rate {
            line.push_str(&format!(", {} Hz", v(r)));
        }
        line
    }

    /// Which of q, q̇, q̈ the reading depends on.
    pub fn reads(&self) -> [bool; 3] {
        match &self.kind {
            SensorKind::Encoder { .. } | SensorKind::Marker { .. } => [true, false, false],
            SensorKind::Gyroscope { .. } => [true, true, false],
            SensorKind::Accelerometer { .. } => [true, false, true],
            SensorKind::Expression { value } => {
                let [q, dq] = value.reads();
                [q, dq, false]
            }
            SensorKind::Input { .. } => [true, true, false],
        }
    }

    /// h(q, q̇, q̈, t) into `out` (length [`Sensor::dim`]).
    pub fn value(
        &self,
        model: &Model,
        t: f64,
        q: &[f64],
        dq: &[f64],
        ddq: &[f64],
        out: &mut [f64],
    ) -> Result<()> {
        self.evaluate(model, t, [q, dq, ddq], None, out, None)
    }

    /// Whether the reading's expression uses a parameter an estimate identifies (an
    /// encoder's offset, a scale): its value and Jacobians then take the parameters'
    /// estimate ([`Sensor::value_at`]).
    pub fn uses_parameters(&self) -> bool {
        matches!(&self.kind, SensorKind::Expression { value } if value.uses_parameters())
    }

    /// The identified parameters the reading uses (indices in the model's order).
    pub fn parameter_indices(&self) -> Vec<usize> {
        match &self.kind {
            SensorKind::Expression { value } => value.parameter_indices().collect(),
            _ => Vec::new(),
        }
    }

    /// [`Sensor::value`] with the identified parameters at `p` (all of them, in the
    /// model's order; `None`: the scene's values).
    pub fn value_at(
        &self,
        model: &Model,
        t: f64,
        state: [&[f64]; 3],
        p: Option<&[f64]>,
        out: &mut [f64],
    ) -> Result<()> {
        self.evaluate(model, t, state, p, out, None)
    }

    /// [`Sensor::jacobians`] with the identified parameters at `p`.
    pub fn jacobians_at(
        &self,
        model: &Model,
        t: f64,
        state: [&[f64]; 3],
        p: Option<&[f64]>,
        out: &mut [f64],
        [jq, jdq, jddq]: [&mut [f64]; 3],
    ) -> Result<()> {
        let size = self.dim() * model.n();
        for (block, what) in [(&*jq, "∂h/∂q"), (&*jdq, "∂h/∂q̇"), (&*jddq, "∂h/∂q̈")]
        {
            if block.len() < size {
                return Err(self.error(format!(
                    "{what} has room for {} entries, {size} are needed",
                    block.len()
                )));
            }
        }
        let blocks = Blocks {
            q: &mut jq[..size],
            dq: &mut jdq[..size],
            ddq: &mut jddq[..size],
        };
        self.evaluate(model, t, state, p, out, Some(blocks))
    }

    /// ∂h/∂p at the state and the parameters `p` into `out` (row-major dim × P, P the
    /// model's identified parameters): zero for a reading that uses none.
    pub fn parameter_jacobian(
        &self,
        model: &Model,
        t: f64,
        (q, dq): (&[f64], &[f64]),
        p: &[f64],
        out: &mut [f64],
    ) -> Result<()> {
        out.fill(0.0);
        if let SensorKind::Expression { value } = &self.kind {
            value
                .add_parameter_gradient(model, (q, dq, t), p, 1.0, &mut out[..p.len()])
                .map_err(|e| self.error(plain(e)))?;
        }
        Ok(())
    }

    /// h and its Jacobians ∂h/∂q, ∂h/∂q̇, ∂h/∂q̈, row-major dim × n each (zeros where
    /// it does not read).
    #[allow(clippy::too_many_arguments)]
    pub fn jacobians(
        &self,
        model: &Model,
        t: f64,
        q: &[f64],
        dq: &[f64],
        ddq: &[f64],
        out: &mut [f64],
        jq: &mut [f64],
        jdq: &mut [f64],
        jddq: &mut [f64],
    ) -> Result<()> {
        self.jacobians_at(model, t, [q, dq, ddq], None, out, [jq, jdq, jddq])
    }

    /// The quantum of the reading: 2π/resolution, 0 without a resolution.
    pub fn quantum(&self) -> f64 {
        self.resolution
            .map_or(0.0, |r| std::f64::consts::TAU / r as f64)
    }

    /// Whether the reading is an angle (an encoder on an angle coordinate): a value
    /// on the circle, equal to itself plus any whole turn.
    pub fn reads_an_angle(&self, model: &Model) -> bool {
        match self.kind {
            SensorKind::Encoder { coordinate } => {
                coordinate >= model.relative_offset
                    && model.scene.coordinates[coordinate - model.relative_offset]
                        .kind
                        .is_angle()
            }
            _ => false,
        }
    }

    /// The σ an estimator weights this reading with: √(σ² + quantum²/12), the noise
    /// and the rounding's uniform error together (σ without a resolution).
    pub fn effective_sigma(&self) -> f64 {
        let quantum = self.quantum();
        (self.sigma * self.sigma + quantum * quantum / 12.0).sqrt()
    }

    /// `v` rounded to the nearest multiple of the quantum (`v` without a resolution).
    pub fn quantize(&self, v: f64) -> f64 {
        let quantum = self.quantum();
        if quantum > 0.0 {
            (v / quantum).round() * quantum
        } else {
            v
        }
    }

    fn error(&self, message: impl std::fmt::Display) -> Error {
        Error::InvalidArgument(format!("sensor '{}': {message}", self.name))
    }

    fn evaluate(
        &self,
        model: &Model,
        t: f64,
        [q, dq, ddq]: [&[f64]; 3],
        p: Option<&[f64]>,
        out: &mut [f64],
        blocks: Option<Blocks>,
    ) -> Result<()> {
        let n = model.n();
        let dim = self.dim();
        if q.len() != n || dq.len() != n || ddq.len() != n {
            return Err(self.error(format!(
                "the state has {}, {} and {} entries, the model {n} coordinates",
                q.len(),
                dq.len(),
                ddq.len()
            )));
        }
        if out.len() < dim {
            return Err(self.error(format!(
                "a reading has {dim} entries, room for {}",
                out.len()
            )));
        }
        let mut blocks = blocks;
        if let Some(b) = blocks.as_mut() {
            b.q.fill(0.0);
            b.dq.fill(0.0);
            b.ddq.fill(0.0);
        }
        let slot = |p: usize| match model.points[p] {
            PointSlot::Free(i) => Some(i),
            PointSlot::Fixed(_) => None,
        };
        match &self.kind {
            SensorKind::Encoder { coordinate } => {
                out[0] = q[*coordinate];
                if let Some(b) = blocks {
                    b.q[*coordinate] = 1.0;
                }
            }
            SensorKind::Marker { point } => {
                out[..2].copy_from_slice(&model.point_position(q, *point));
                if let (Some(b), Some(i)) = (blocks, slot(*point)) {
                    b.q[i] = 1.0;
                    b.q[n + i + 1] = 1.0;
                }
            }
            SensorKind::Gyroscope { body } => {
                let [a, c] = self.frame_points(model, *body);
                let (d, vd, l2) = self.segment(model, *body, q, dq)?;
                // ω = (d × ḋ)/|d|²: ∂ω/∂ḋ = (−d_y, d_x)/|d|²,
                // ∂ω/∂d = (ḋ_y − 2ω d_x, −ḋ_x − 2ω d_y)/|d|².
                let w = (d[0] * vd[1] - d[1] * vd[0]) / l2;
                out[0] = w;
                if let Some(b) = blocks {
                    let gv = [-d[1] / l2, d[0] / l2];
                    let gq = [
                        (vd[1] - 2.0 * w * d[0]) / l2,
                        (-vd[0] - 2.0 * w * d[1]) / l2,
                    ];
                    spread(model, &mut b.dq[..n], [a, c], gv);
                    spread(model, &mut b.q[..n], [a, c], gq);
                }
            }
            SensorKind::Accelerometer { body, point } => {
                let [a, c] = self.frame_points(model, *body);
                let (d, _, l2) = self.segment(model, *body, q, dq)?;
                let l = l2.sqrt();
                let g = gravity(model);
                let acc = model.point_velocity(ddq, *point);
                let s = [acc[0] - g[0], acc[1] - g[1]];
                let ex = [d[0] / l, d[1] / l];
                let ey = [-ex[1], ex[0]];
                let f = [ex[0] * s[0] + ex[1] * s[1], ey[0] * s[0] + ey[1] * s[1]];
                out[..2].copy_from_slice(&f);
                if let Some(b) = blocks {
                    if let Some(i) = slot(*point) {
                        b.ddq[i] = ex[0];
                        b.ddq[i + 1] = ex[1];
                        b.ddq[n + i] = ey[0];
                        b.ddq[n + i + 1] = ey[1];
                    }
                    // f₀ = d·s/|d|, f₁ = d×s/|d|: ∂f₀/∂d = (s − f₀ e_x)/|d|,
                    // ∂f₁/∂d = ((s_y, −s_x) − f₁ e_x)/|d|.
                    let g0 = [(s[0] - f[0] * ex[0]) / l, (s[1] - f[0] * ex[1]) / l];
                    let g1 = [(s[1] - f[1] * ex[0]) / l, (-s[0] - f[1] * ex[1]) / l];
                    spread(model, &mut b.q[..n], [a, c], g0);
                    spread(model, &mut b.q[n..2 * n], [a, c], g1);
                }
            }
            SensorKind::Expression { value } => {
                out[0] = value
                    .value_at(model, q, dq, (t, p))
                    .map_err(|e| self.error(plain(e)))?;
                if let Some(b) = blocks {
                    value
                        .add_gradient_at(model, (q, dq, t), (p, 1.0), 0, b.q, b.dq)
                        .map_err(|e| self.error(plain(e)))?;
                }
            }
            SensorKind::Input { coordinate } => {
                let c = *coordinate;
                let mut force = vec![0.0; n];
                let (mut kq, mut kv) = (vec![0.0; n * n], vec![0.0; n * n]);
                for f in model.forces.iter().filter(|f| f.actuates(c)) {
                    f.add_to(model, q, dq, t, &mut force)
                        .map_err(|e| self.error(plain(e)))?;
                    if blocks.is_some() {
                        f.add_jacobians(model, (q, dq, t), &mut kq, &mut kv)
                            .map_err(|e| self.error(plain(e)))?;
                    }
                }
                out[0] = force[c];
                if let Some(b) = blocks {
                    b.q.copy_from_slice(&kq[c * n..(c + 1) * n]);
                    b.dq.copy_from_slice(&kv[c * n..(c + 1) * n]);
                }
            }
        }
        if let Some(i) = out[..dim].iter().position(|v| !v.is_finite()) {
            return Err(self.error(format!(
                "its reading is not finite at t = {t} s (entry {i}: {})",
                out[i]
            )));
        }
        Ok(())
    }

    /// The first two points of a body: its frame.
    fn frame_points(&self, model: &Model, body: usize) -> [usize; 2] {
        let points = &model.scene.bodies[body].points;
        [points[0], points[1]]
    }

    /// d = r₁ − r₀, ḋ and |d|² of a body's first two points; an error where they
    /// coincide (the body has no direction).
    fn segment(
        &self,
        model: &Model,
        body: usize,
        q: &[f64],
        dq: &[f64],
    ) -> Result<([f64; 2], [f64; 2], f64)> {
        let [a, c] = self.frame_points(model, body);
        let (ra, rc) = (model.point_position(q, a), model.point_position(q, c));
        let (va, vc) = (model.point_velocity(dq, a), model.point_velocity(dq, c));
        let d = [rc[0] - ra[0], rc[1] - ra[1]];
        let l2 = d[0] * d[0] + d[1] * d[1];
        if !(l2 > 0.0 && l2.is_finite()) {
            let body = &model.scene.bodies[body];
            return Err(self.error(format!(
                "the first two points of body '{}' coincide: its frame has no direction",
                body.name
            )));
        }
        Ok((d, [vc[0] - va[0], vc[1] - va[1]], l2))
    }
}

/// Adds g·∂/∂d to a row, d = r_c − r_a: +g on c's coordinates, −g on a's.
fn spread(model: &Model, row: &mut [f64], [a, c]: [usize; 2], g: [f64; 2]) {
    for (point, sign) in [(c, 1.0), (a, -1.0)] {
        if let PointSlot::Free(i) = model.points[point] {
            row[i] += sign * g[0];
            row[i + 1] += sign * g[1];
        }
    }
}

/// The scene's gravity vector, 0 without one.
fn gravity(model: &Model) -> [f64; 2] {
    model
        .scene
        .effects
        .iter()
        .find_map(|e| match e {
            crate::scene::Effect::Gravity { vector } => Some(*vector),
            _ => None,
        })
        .unwrap_or([0.0, 0.0])
}

/// An error's message without the "invalid argument: " of its display.
fn plain(e: Error) -> String {
    match e {
        Error::InvalidArgument(m) => m,
        other => other.to_string(),
    }
}

/// The model's sensors from the scene's definitions.
pub(crate) fn resolve(model: &Model, defs: &[SensorDef]) -> Result<Vec<Sensor>> {
    defs.iter()
        .map(|def| {
            let kind = match &def.kind {
                SensorDefKind::Encoder { coordinate } => SensorKind::Encoder {
                    coordinate: index(model, coordinate)?,
                },
                SensorDefKind::Gyroscope { body } => SensorKind::Gyroscope { body: *body },
                SensorDefKind::Accelerometer { body, point } => SensorKind::Accelerometer {
                    body: *body,
                    point: *point,
                },
                SensorDefKind::Marker { point } => SensorKind::Marker { point: *point },
                SensorDefKind::Input { coordinate } => SensorKind::Input {
                    coordinate: index(model, coordinate)?,
                },
                SensorDefKind::Expression { value } => SensorKind::Expression {
                    value: Load::compile(model, value).map_err(|e| {
                        Error::InvalidArgument(format!("sensor '{}': {}", def.name, plain(e)))
                    })?,
                },
            };
            Ok(Sensor {
                name: def.name.clone(),
                kind,
                sigma: def.sigma,
                resolution: def.resolution,
                rate: def.rate,
            })
        })
        .collect()
}

/// The estimation section with names resolved to indices in q.
pub(crate) fn resolve_estimation(model: &Model, def: &EstimationDef) -> Result<EstimationSpec> {
    let indices = |list: &[(String, f64)]| {
        list.iter()
            .map(|(name, v)| Ok((index(model, name)?, *v)))
            .collect::<Result<Vec<_>>>()
    };
    Ok(EstimationSpec {
        process_sigma: def.process_sigma,
        initial_sigma: indices(&def.initial_sigma)?,
        initial_velocity_sigma: indices(&def.initial_velocity_sigma)?,
        inputs: indices(&def.inputs)?,
    })
}

fn index(model: &Model, name: &str) -> Result<usize> {
    model
        .index_of(name)
        .ok_or_else(|| Error::InvalidArgument(format!("'{name}' is not a coordinate of q")))
}

impl Model {
    /// The sensor of this name, by index.
    pub fn sensor_index(&self, name: &str) -> Option<usize> {
        self.sensors.iter().position(|s| s.name == name)
    }
}
