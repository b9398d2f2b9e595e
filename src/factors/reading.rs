//! A sensor's reading as a factor ([`Reading`]): e = h(q, q̇, q̈, t) − datum, with the
//! sensor's closed-form Jacobians.

use super::shared::key_accessor;
use crate::error::{Error, Result};
use crate::graph::{Factor, Key, VarKind, Workspace};
use crate::model::Model;
use std::sync::Arc;

/// f_sensor: e = h(q, q̇, q̈, t) − datum for sensor `sensor` of the model, on the
/// step's q, q̇ and q̈. Weighted by the sensor's [`crate::sensors::Sensor::effective_sigma`]
/// where it is added.
pub struct Reading {
    name: String,
    keys: [Key; 3],
    model: Arc<Model>,
    sensor: usize,
    datum: Vec<f64>,
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
        Reading {
            name,
            keys: [
                Key::now(VarKind::Q),
                Key::now(VarKind::Dq),
                Key::now(VarKind::Ddq),
            ],
            model,
            sensor,
            datum,
        }
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
    fn size(&self, _key: usize) -> usize {
        self.model.n()
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
        let (q, dq, ddq) = (x[0], x[1], x[2]);
        match jac {
            Some(j) => {
                let [jq, jdq, jddq] = j else {
                    return Err(Error::InvalidArgument(format!(
                        "{}: three Jacobian blocks expected",
                        self.name
                    )));
                };
                sensor.jacobians(&self.model, t, q, dq, ddq, r, jq, jdq, jddq)?
            }
            None => sensor.value(&self.model, t, q, dq, ddq, r)?,
        }
        for (ri, d) in r.iter_mut().zip(&self.datum) {
            *ri -= d;
        }
        Ok(())
    }
}
