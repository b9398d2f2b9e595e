//! A sensor's reading as a factor ([`Reading`]): e = h(q, q̇, q̈, t) − datum, with the
//! sensor's closed-form Jacobians; an angle's e taken into (−π, π]; a reading taken
//! between two steps is compared with the motion's Taylor expansion about its nearest
//! step.

use super::shared::key_accessor;
use crate::error::{Error, Result};
use crate::graph::{Factor, Key, VarKind, Workspace};
use crate::model::Model;
use std::sync::Arc;

/// Coordinates whose expanded state a reading between steps keeps on the stack.
const SHIFT_ON_STACK: usize = 32;

/// f_sensor: e = h(q, q̇, q̈, t) − datum for sensor `sensor` of the model, on the
/// step's q, q̇ and q̈. Weighted by the sensor's [`crate::sensors::Sensor::effective_sigma`]
/// where it is added.
pub struct Reading {
    name: String,
    /// The step's q, q̇, q̈, and its identified parameters where the sensor's
    /// expression uses them.
    keys: Vec<Key>,
    model: Arc<Model>,
    sensor: usize,
    datum: Vec<f64>,
    /// How long before its step the reading was taken (negative: after it).
    before: f64,
}

impl Reading {
    /// The reading `datum` (one entry per entry of the sensor's reading) of sensor
    /// `sensor` (an index into `model.sensors`). An index or a datum that does not
    /// fit is reported by the first evaluation.
    pub fn new(model: Arc<Model>, sensor: usize, datum: Vec<f64>) -> Reading {
        let name = match model.sensors.get(sensor) {
            Some(s) => format!("f_sensor({})", s.name),
            None => format!("f_sensor(#{sensor})"),
        };
        let mut keys = vec![
            Key::now(VarKind::Q),
            Key::now(VarKind::Dq),
            Key::now(VarKind::Ddq),
        ];
        let identified = model.parameters.is_some();
        if identified
            && model
                .sensors
                .get(sensor)
                .is_some_and(|s| s.uses_parameters())
        {
            keys.push(Key::now(VarKind::Param));
        }
        Reading {
            name,
            keys,
            model,
            sensor,
            datum,
            before: 0.0,
        }
    }

    /// The reading taken `before` seconds before the factor's step (negative: after
    /// it), compared with the motion there to the step's own order: q − δq̇ + ½δ²q̈,
    /// q̇ − δq̈ and q̈ at t − δ (errors O(δ³ q⃛), O(δ² q⃛) and O(δ q⃛)).
    pub fn taken_before(mut self, before: f64) -> Reading {
        self.before = before;
        self
    }

    /// The reading this factor holds.
    pub fn datum(&self) -> &[f64] {
        &self.datum
    }
}

impl Factor for Reading {
    fn name(&self) -> &str {
        &self.name
    }
    key_accessor!();
    fn size(&self, key: usize) -> usize {
        match key {
            3 => self.model.parameters.as_ref().map_or(0, |p| p.len()),
            _ => self.model.n(),
        }
    }
    fn dim(&self) -> usize {
        self.model
            .sensors
            .get(self.sensor)
            .map_or(self.datum.len(), |s| s.dim())
    }
    fn evaluate(
        &self,
        t: f64,
        x: &[&[f64]],
        r: &mut [f64],
        jac: Option<&mut [Vec<f64>]>,
        _ws: &mut Workspace,
    ) -> Result<()> {
        let sensor = self.model.sensors.get(self.sensor).ok_or_else(|| {
            Error::InvalidArgument(format!(
                "{}: the model has {} sensors",
                self.name,
                self.model.sensors.len()
            ))
        })?;
        let dim = sensor.dim();
        if self.datum.len() != dim || r.len() != dim {
            return Err(Error::InvalidArgument(format!(
                "{}: a reading has {dim} entries, the datum {}",
                self.name,
                self.datum.len()
            )));
        }
        if let Some(i) = self.datum.iter().position(|v| !v.is_finite()) {
            return Err(Error::InvalidArgument(format!(
                "{}: datum entry {i} is not finite ({})",
                self.name, self.datum[i]
            )));
        }
        let b = self.before;
        let n = x[0].len();
        // The expanded q and q̇, on the stack for mechanisms of up to SHIFT_ON_STACK
        // coordinates: this runs at every iteration of every solve.
        let mut on_stack = [0.0; 2 * SHIFT_ON_STACK];
        let mut on_heap = Vec::new();
        let (t, q, dq, ddq) = if b == 0.0 {
            (t, x[0], x[1], x[2])
        } else {
            let shifted = if n <= SHIFT_ON_STACK {
                &mut on_stack[..2 * n]
            } else {
                on_heap.resize(2 * n, 0.0);
                &mut on_heap[..]
            };
            let (q, dq, ddq) = (x[0], x[1], x[2]);
            let (sq, sdq) = shifted.split_at_mut(n);
            for i in 0..n {
                sq[i] = q[i] - b * dq[i] + 0.5 * b * b * ddq[i];
                sdq[i] = dq[i] - b * ddq[i];
            }
            (t - b, &*sq, &*sdq, ddq)
        };
        let p = x.get(3).copied();
        match jac {
            Some(j) => {
                let (jq, jdq, jddq, jp) = match j {
                    [jq, jdq, jddq] => (jq, jdq, jddq, None),
                    [jq, jdq, jddq, jp] => (jq, jdq, jddq, Some(jp)),
                    _ => {
                        return Err(Error::InvalidArgument(format!(
                            "{}: {} Jacobian blocks expected",
                            self.name,
                            self.keys.len()
                        )))
                    }
                };
                let blocks = [&mut jq[..], &mut jdq[..], &mut jddq[..]];
                sensor.jacobians_at(&self.model, t, [q, dq, ddq], p, r, blocks)?;
                if let (Some(jp), Some(p)) = (jp, p) {
                    sensor.parameter_jacobian(&self.model, t, (q, dq), p, jp)?;
                }
                if b != 0.0 {
                    // The chain rule through the expansion: ∂/∂q̈ first, from the
                    // unshifted ∂h/∂q̇.
                    let size = dim * self.model.n();
                    for i in 0..size {
                        jddq[i] += 0.5 * b * b * jq[i] - b * jdq[i];
                        jdq[i] -= b * jq[i];
                    }
                }
            }
            None => sensor.value_at(&self.model, t, [q, dq, ddq], p, r)?,
        }
        for (ri, d) in r.iter_mut().zip(&self.datum) {
            *ri -= d;
        }
        if sensor.reads_an_angle(&self.model) {
            // An angle read whole turns away is the same reading: an absolute encoder
            // wraps into one turn; the motion's coordinate does not.
            let turn = std::f64::consts::TAU;
            r.iter_mut().for_each(|e| *e -= turn * (*e / turn).round());
        }
        Ok(())
    }
}

/// f_input: e = u_k − datum, the reading of an `input` sensor in an estimate: entry
/// `k` of the step's unknown inputs (the input on the sensor's coordinate).
pub struct InputReading {
    name: String,
    keys: [Key; 1],
    inputs: usize,
    k: usize,
    datum: f64,
}

impl InputReading {
    /// The reading `datum` of sensor `sensor` of `model`, on the unknown input its
    /// coordinate carries: an error naming the sensor where the scene declares no
    /// input on that coordinate, or a torque of its own there (the reading would
    /// then be of the two together).
    pub fn new(model: &Model, sensor: usize, datum: f64) -> Result<InputReading> {
        let s = &model.sensors[sensor];
        let crate::sensors::SensorKind::Input { coordinate } = s.kind else {
            return Err(Error::InvalidArgument(format!(
                "sensor '{}' is not an input sensor",
                s.name
            )));
        };
        let inputs: Vec<usize> = model.estimation.inputs.iter().map(|&(c, _)| c).collect();
        let name = &model.names[coordinate];
        let Some(k) = inputs.iter().position(|&c| c == coordinate) else {
            return Err(Error::InvalidArgument(format!(
                "sensor '{}' reads the input on '{name}', which the scene does not estimate: \
                 declare it in `estimation: inputs:` (an estimate reads an input sensor as \
                 the unknown input on its coordinate)",
                s.name
            )));
        };
        if model.forces.iter().any(|f| f.actuates(coordinate)) {
            return Err(Error::InvalidArgument(format!(
                "sensor '{}' reads the input on '{name}', where the scene also has a torque \
                 of its own: an estimate reads an input sensor as the unknown input alone; \
                 remove the scene's torque on '{name}' (the readings carry it)",
                s.name
            )));
        }
        Ok(InputReading {
            name: format!("f_input({})", s.name),
            keys: [Key::now(VarKind::Force)],
            inputs: inputs.len(),
            k,
            datum,
        })
    }
}

impl Factor for InputReading {
    fn name(&self) -> &str {
        &self.name
    }
    key_accessor!();
    fn size(&self, _key: usize) -> usize {
        self.inputs
    }
    fn dim(&self) -> usize {
        1
    }
    fn evaluate(
        &self,
        _t: f64,
        x: &[&[f64]],
        r: &mut [f64],
        jac: Option<&mut [Vec<f64>]>,
        _ws: &mut Workspace,
    ) -> Result<()> {
        r[0] = x[0][self.k] - self.datum;
        if let Some(j) = jac {
            j[0].fill(0.0);
            j[0][self.k] = 1.0;
        }
        Ok(())
    }
}
