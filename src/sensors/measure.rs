//! Simulated readings of a known motion: each sensor's h at its reading times, plus
//! seeded Gaussian noise, then quantized; and the measurement CSV they are written
//! to and read from (`t`, then one column per reading entry, an empty cell where a
//! sensor does not read at that time).

use super::Sensor;
use crate::error::{Error, Result};
use crate::io::{number, read_table_with_gaps, TableLimits};
use crate::model::Model;
use crate::rng::Rng;
use crate::trajectory::Trajectory;
use std::io::Write;
use std::path::Path;

/// Readings at a set of times: `values` row-major times × columns, NaN where a
/// sensor does not read at that time.
#[derive(Debug, Clone, PartialEq)]
pub struct Measurements {
    /// The reading columns (`enc`, `acc.x`, `acc.y`, …), without `t`.
    pub columns: Vec<String>,
    pub t: Vec<f64>,
    pub values: Vec<f64>,
}

impl Measurements {
    /// The values of column `name` (NaN where none), if present.
    pub fn column(&self, name: &str) -> Option<Vec<f64>> {
        let j = self.columns.iter().position(|c| c == name)?;
        let w = self.columns.len();
        Some((0..self.t.len()).map(|i| self.values[i * w + j]).collect())
    }

    /// Writes the CSV: `t`, then the columns; numbers in shortest round-trip form,
    /// an empty cell for no reading.
    pub fn write_csv<W: Write>(&self, mut out: W) -> Result<()> {
        let err = |e: std::io::Error| Error::data(format!("cannot write the measurements: {e}"));
        let mut line = String::from("t");
        for c in &self.columns {
            line.push(',');
            line.push_str(c);
        }
        line.push('\n');
        out.write_all(line.as_bytes()).map_err(err)?;
        let w = self.columns.len();
        for (k, t) in self.t.iter().enumerate() {
            line.clear();
            line.push_str(&number(*t));
            for v in &self.values[k * w..(k + 1) * w] {
                line.push(',');
                if !v.is_nan() {
                    line.push_str(&number(*v));
                }
            }
            line.push('\n');
            out.write_all(line.as_bytes()).map_err(err)?;
        }
        out.flush().map_err(err)
    }

    /// Reads a measurement CSV written by [`Measurements::write_csv`] (or by hand):
    /// a column `t` and reading columns, empty cells for no reading. With a model,
    /// every column but `t` must be a column of one of its sensors.
    pub fn read(path: &Path, model: Option<&Model>) -> Result<Measurements> {
        let file = path.display().to_string();
        let table = read_table_with_gaps(path, &TableLimits::default(), &mut |columns| {
            if !columns.iter().any(|c| c == "t") {
                return Err(Error::data_in(&file, Some(1), "no column `t`"));
            }
            if let Some(model) = model {
                let known: Vec<String> = model.sensors.iter().flat_map(Sensor::columns).collect();
                if let Some(c) = columns.iter().find(|c| *c != "t" && !known.contains(c)) {
                    return Err(Error::data_in(
                        &file,
                        Some(1),
                        format!(
                            "column `{}` is not a reading of the scene's sensors ({})",
                            crate::expr::excerpt(c, 40),
                            crate::expr::abbreviated(
                                &known.iter().map(String::as_str).collect::<Vec<_>>()
                            )
                        ),
                    ));
                }
            }
            Ok(())
        })?;
        let t = table.column("t").unwrap_or_default();
        if let Some(k) = t.iter().position(|v| v.is_nan()) {
            return Err(Error::data_in(&file, Some(k as u64 + 2), "no time in `t`"));
        }
        if let Some(k) = (1..t.len()).find(|&k| !(t[k] > t[k - 1])) {
            return Err(Error::data_in(
                &file,
                Some(k as u64 + 2),
                format!("t = {} does not come after t = {}", t[k], t[k - 1]),
            ));
        }
        let columns: Vec<String> = table
            .columns
            .iter()
            .filter(|c| *c != "t")
            .cloned()
            .collect();
        let w = table.columns.len();
        let keep: Vec<usize> = (0..w).filter(|&j| table.columns[j] != "t").collect();
        let values = (0..table.rows)
            .flat_map(|i| keep.iter().map(move |&j| (i, j)))
            .map(|(i, j)| table.values[i * w + j])
            .collect();
        Ok(Measurements { columns, t, values })
    }
}

/// Noisy, quantized readings of every sensor of `model` along `trajectory`.
///
/// A sensor reads at t₀ + k/rate (t₀ the trajectory's first time; rate its own,
/// else `rate`, else at every row of the trajectory); each such time must be a
/// row of the trajectory (to 1e-9 of its span). A reading is
/// quantize(h(q, q̇, q̈, t) + σ·N(0, 1)): the noise is added before the rounding.
/// Each sensor draws from its own stream of `seed`, so the same seed gives the
/// same readings and adding a sensor leaves the others' unchanged.
pub fn measure(
    model: &Model,
    trajectory: &Trajectory,
    seed: u64,
    rate: Option<f64>,
) -> Result<Measurements> {
    if model.sensors.is_empty() {
        return Err(Error::InvalidArgument(format!(
            "scene {} has no sensors: declare them in a `sensors:` section (docs/scene-format.md)",
            model.scene.file
        )));
    }
    if let Some(r) = rate {
        if !(r > 0.0 && r.is_finite()) {
            return Err(Error::InvalidArgument(format!(
                "the rate must be a positive number of readings per second, got {r}"
            )));
        }
    }
    let n = model.n();
    if trajectory.names != model.names {
        return Err(Error::InvalidArgument(format!(
            "the trajectory's coordinates ({}) are not the model's ({})",
            trajectory.names.join(", "),
            model.names.join(", ")
        )));
    }
    let times = &trajectory.t;
    if times.is_empty() {
        return Err(Error::InvalidArgument("the trajectory has no rows".into()));
    }
    let (t0, t_end) = (times[0], times[times.len() - 1]);
    let tol = 1e-9 * t0.abs().max(t_end.abs()).max(t_end - t0);

    // Per sensor: the rows it reads at.
    let mut reads: Vec<Vec<usize>> = Vec::with_capacity(model.sensors.len());
    for sensor in &model.sensors {
        let Some(r) = sensor.rate.or(rate) else {
            reads.push((0..times.len()).collect());
            continue;
        };
        let mut rows = Vec::new();
        let mut j = 0;
        for k in 0u64.. {
            let tk = t0 + k as f64 / r;
            if tk > t_end + tol {
                break;
            }
            while j < times.len() && times[j] < tk - tol {
                j += 1;
            }
            let hit = j < times.len() && (times[j] - tk).abs() <= tol;
            if !hit || rows.last() == Some(&j) {
                let near = times[j.min(times.len() - 1)];
                return Err(Error::InvalidArgument(format!(
                    "sensor '{}' reads at {r} Hz from t = {t0} s: t = {} s is not a time of the trajectory (the nearest row after it is at t = {near} s); give a rate whose period is a multiple of the trajectory's step",
                    sensor.name,
                    crate::trajectory::round_time(tk)
                )));
            }
            rows.push(j);
        }
        reads.push(rows);
    }

    let mut used: Vec<usize> = reads.iter().flatten().copied().collect();
    used.sort_unstable();
    used.dedup();
    let columns: Vec<String> = model.sensors.iter().flat_map(Sensor::columns).collect();
    let w = columns.len();
    let mut values = vec![f64::NAN; used.len() * w];
    let mut col = 0;
    let mut h = [0.0; 2];
    for (sensor, rows) in model.sensors.iter().zip(&reads) {
        let dim = sensor.dim();
        let mut rng = Rng::stream(seed, &sensor.name);
        for &j in rows {
            let state = |v: &[f64]| v[j * n..(j + 1) * n].to_vec();
            let (q, dq, ddq) = (
                state(&trajectory.q),
                state(&trajectory.dq),
                state(&trajectory.ddq),
            );
            sensor.value(model, times[j], &q, &dq, &ddq, &mut h[..dim])?;
            let row = used.binary_search(&j).unwrap_or_default();
            for (i, hi) in h[..dim].iter().enumerate() {
                values[row * w + col + i] = sensor.quantize(hi + sensor.sigma * rng.normal());
            }
        }
        col += dim;
    }
    Ok(Measurements {
        columns,
        t: used.iter().map(|&j| times[j]).collect(),
        values,
    })
}
