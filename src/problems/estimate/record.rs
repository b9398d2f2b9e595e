//! A record of sensor readings on the estimate's time grid ([`Record`]): read from
//! the measurements CSV (`t`, then one column per reading, an empty cell where a
//! sensor did not read) and checked against the model's sensors.

use crate::error::{Error, Result};
use crate::io::{read_table_with_gaps, TableLimits};
use crate::model::Model;
use std::path::Path;

/// One reading of a step: its sensor, its values, and how long before the step's
/// time it was taken (negative: after it; 0 on the step).
#[derive(Debug, Clone, PartialEq)]
pub struct StepReading {
    pub sensor: usize,
    pub values: Vec<f64>,
    pub before: f64,
}

/// The readings of one step.
pub type StepReadings = Vec<StepReading>;

/// Readings on a uniform grid t₀ + k·dt, each at its nearest step.
#[derive(Debug, Clone, PartialEq)]
pub struct Record {
    pub t0: f64,
    pub dt: f64,
    /// The readings of every step, steps without any included (empty).
    pub steps: Vec<StepReadings>,
}

/// Why a record without a single reading is refused.
pub const NO_READINGS: &str =
    "no readings: every sensor cell is empty, and an estimate without readings is the model's own simulation";

/// How far from a step a reading's time may be and still be on it, as a fraction of dt.
const ON_STEP: f64 = 1e-6;
/// The most steps per row a default step may make: a grid of the shortest interval
/// finer than this (rows 1 ns apart among 5 ms ones) gives way to the readings' period.
const STEPS_PER_ROW: f64 = 10.0;

impl Record {
    /// The record of a measurements CSV for `model`'s sensors, on the grid of step
    /// `dt` from the first row's time: by default the smallest interval between rows,
    /// or, where readings fall off that grid, their mean interval (gaps left out).
    pub fn read(model: &Model, path: &Path, dt: Option<f64>) -> Result<Record> {
        let file = path.display().to_string();
        let table = read_table_with_gaps(path, &TableLimits::default(), &mut |columns| {
            check_columns(model, columns).map_err(|m| Error::data_in(&file, Some(1), m))
        })?;
        let w = table.columns.len();
        let rows: Vec<(f64, Vec<f64>)> = (0..table.rows)
            .map(|i| {
                let row = &table.values[i * w..(i + 1) * w];
                (row[0], row.to_vec())
            })
            .collect();
        let columns = table.columns.clone();
        let record = Record::from_rows(model, &columns, &rows, dt)
            .map_err(|(line, m)| Error::data_in(&file, line.map(|l| l as u64 + 2), m))?;
        if record.readings() == 0 {
            return Err(Error::data_in(&file, None, NO_READINGS));
        }
        Ok(record)
    }

    /// The record of rows (t, then the cells of `columns`, `columns[0]` = "t", NaN
    /// where no reading); errors carry the row (from 0) they are about.
    pub fn from_rows(
        model: &Model,
        columns: &[String],
        rows: &[(f64, Vec<f64>)],
        dt: Option<f64>,
    ) -> std::result::Result<Record, (Option<usize>, String)> {
        check_columns(model, columns).map_err(|m| (None, m))?;
        if rows.is_empty() {
            return Err((None, "no readings: the file has no rows".into()));
        }
        let (rows, origin) = merge_equal_times(columns, rows)?;
        let rows = &rows[..];
        let t0 = rows[0].0;
        let dt = match dt {
            Some(dt) => dt,
            None if rows.len() >= 2 => {
                // The span divided into whole steps of about the shortest interval:
                // 10 s of 5 ms rows is 0.005, not the 0.004999… of one difference of
                // rounded times. Where that grid misses rows (times that jitter), or
                // would hold far more steps than rows (two times a glitch apart), the
                // readings' own period: the mean interval, gaps (beyond 1.5 times the
                // median) left out.
                let mut intervals: Vec<f64> = rows.windows(2).map(|w| w[1].0 - w[0].0).collect();
                let span = rows[rows.len() - 1].0 - rows[0].0;
                let shortest = intervals.iter().copied().fold(f64::INFINITY, f64::min);
                let grid = span / (span / shortest).round();
                let sparse = span / grid > STEPS_PER_ROW * rows.len() as f64;
                if !sparse && rows.iter().all(|(t, _)| on_step(t - t0, grid)) {
                    grid
                } else {
                    intervals.sort_by(f64::total_cmp);
                    let median = intervals[intervals.len() / 2];
                    let usual: Vec<f64> = intervals
                        .into_iter()
                        .filter(|&d| d <= 1.5 * median)
                        .collect();
                    let period = usual.iter().sum::<f64>() / usual.len() as f64;
                    span / (span / period).round().max(1.0)
                }
            }
            None => {
                return Err((
                    None,
                    "one row of readings gives no period; give the step (--dt)".into(),
                ))
            }
        };
        let last = rows[rows.len() - 1].0;
        let count = ((last - t0) / dt).round();
        if count > 1e8 {
            return Err((None, format!("{count} steps of {dt} s: too many")));
        }
        let mut steps: Vec<StepReadings> = vec![Vec::new(); count as usize + 1];
        // Each column's sensor and its place among the sensor's values.
        let slots: Vec<Option<(usize, usize)>> =
            columns.iter().map(|c| column_slot(model, c)).collect();
        for (i, (t, cells)) in rows.iter().enumerate() {
            let k = ((t - t0) / dt).round();
            // A reading off the grid is taken at its nearest step, δ before it.
            let before = if on_step(t - t0, dt) {
                0.0
            } else {
                t0 + k * dt - t
            };
            let k = (k as usize).min(steps.len() - 1);
            for (s, sensor) in model.sensors.iter().enumerate() {
                let mut values = vec![f64::NAN; sensor.dim()];
                for (j, slot) in slots.iter().enumerate() {
                    if let Some((si, at)) = slot {
                        if *si == s {
                            values[*at] = cells[j];
                        }
                    }
                }
                let given = values.iter().filter(|v| !v.is_nan()).count();
                if given == 0 {
                    continue;
                }
                if given < values.len() {
                    return Err((
                        Some(origin[i]),
                        format!(
                            "sensor {}: some of its columns ({}) are empty and some not",
                            sensor.name,
                            sensor.columns().join(", ")
                        ),
                    ));
                }
                steps[k].push(StepReading {
                    sensor: s,
                    values,
                    before,
                });
            }
        }
        Ok(Record { t0, dt, steps })
    }

    /// Readings in the record.
    pub fn readings(&self) -> usize {
        self.steps.iter().map(Vec::len).sum()
    }

    /// The readings taken between steps, and the largest |δ| of their times from
    /// their steps' (0 where every reading is on a step).
    pub fn between_steps(&self) -> (usize, f64) {
        self.steps
            .iter()
            .flatten()
            .filter(|r| r.before != 0.0)
            .fold((0, 0.0), |(n, most), r| {
                (n + 1, f64::max(most, r.before.abs()))
            })
    }
}

/// Whether a time `since` the record's start falls on a step of `dt`, to within
/// rounding ([`ON_STEP`] of a step, relative to the step's index).
fn on_step(since: f64, dt: f64) -> bool {
    let k = since / dt;
    (k - k.round()).abs() <= ON_STEP * k.abs().max(1.0)
}

/// Which sensor a column belongs to, and which of its values it is.
fn column_slot(model: &Model, column: &str) -> Option<(usize, usize)> {
    model.sensors.iter().enumerate().find_map(|(s, sensor)| {
        sensor
            .columns()
            .iter()
            .position(|c| c == column)
            .map(|at| (s, at))
    })
}

/// The columns must be `t` then readings of the model's sensors, each once.
fn check_columns(model: &Model, columns: &[String]) -> std::result::Result<(), String> {
    if columns.first().map(String::as_str) != Some("t") {
        return Err("the first column must be `t`".into());
    }
    if model.sensors.is_empty() {
        return Err(
            "the scene has no sensors: a `sensors:` section says what the columns read".into(),
        );
    }
    for (j, c) in columns.iter().enumerate().skip(1) {
        if column_slot(model, c).is_none() {
            let known: Vec<String> = model.sensors.iter().flat_map(|s| s.columns()).collect();
            return Err(format!(
                "column `{c}` is no sensor of the scene (its sensors read: {})",
                known.join(", ")
            ));
        }
        if columns[..j].contains(c) {
            return Err(format!("column `{c}` appears twice"));
        }
    }
    Ok(())
}

/// The rows with those that share a time merged into one (a logger that writes a row
/// per sensor: `0.005,0.1,` then `0.005,,0.02`), each row's index in `rows` beside it;
/// or why not: a time not finite, or below the one before, or a cell given twice at
/// one time.
#[allow(clippy::type_complexity)]
fn merge_equal_times(
    columns: &[String],
    rows: &[(f64, Vec<f64>)],
) -> std::result::Result<(Vec<(f64, Vec<f64>)>, Vec<usize>), (Option<usize>, String)> {
    let mut merged: Vec<(f64, Vec<f64>)> = Vec::with_capacity(rows.len());
    let mut origin = Vec::with_capacity(rows.len());
    for (i, (t, cells)) in rows.iter().enumerate() {
        if !t.is_finite() {
            return Err((Some(i), "t is empty or not finite".into()));
        }
        match merged.last_mut() {
            Some((last, into)) if *t == *last => {
                for (j, (cell, held)) in cells.iter().zip(into.iter_mut()).enumerate().skip(1) {
                    if cell.is_nan() {
                        continue;
                    }
                    if !held.is_nan() {
                        return Err((
                            Some(i),
                            format!(
                                "t = {t} repeats with a second value of column `{}` (rows \
                                 that share a time are merged, each cell given once)",
                                columns[j]
                            ),
                        ));
                    }
                    *held = *cell;
                }
            }
            Some((last, _)) if *t < *last => {
                return Err((Some(i), format!("t = {t} does not increase")));
            }
            _ => {
                merged.push((*t, cells.clone()));
                origin.push(i);
            }
        }
    }
    Ok((merged, origin))
}
