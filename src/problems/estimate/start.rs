//! Where the first solve of an estimate begins when the first encoder readings lie far
//! from the scene's start. Gauss–Newton from a start a few radians off can stall on
//! the constraints' curvature (a pendulum placed 2.6 rad from its first reading ran
//! out of iterations at step 0) or cross to the other assembly of a closed loop (a
//! four-bar placed 2.5 rad off its crank reading was fitted upside down, with
//! g = −10.3 ± 0.012). The start prior is unchanged: only the first guess moves, along
//! the mechanism from the start to the first step's own best guess, so the start's
//! assembly is kept.

use super::record::StepReading;
use crate::kinematics;
use crate::model::{Model, State};
use crate::sensors::SensorKind;
use std::f64::consts::PI;

/// A read coordinate this far (rad or m) from the start moves the first guess.
const FAR: f64 = 0.25;

/// The largest move of a read coordinate per position solve on the way.
const STRIDE: f64 = 0.05;

/// The first step's guess where its encoders read coordinates more than [`FAR`] from
/// `start` (priors of σ `initial_q`): each read coordinate at its precision-weighted
/// mean of start and reading (the reading's misfit on an angle taken into (−π, π],
/// as the estimate compares it), reached by position solves in strides of at most
/// [`STRIDE`] with the read coordinates held, the velocities the start's for the read
/// coordinates and the velocity problem's for the others. None where nothing is far,
/// or where the way there fails (the start is then the guess, as always).
pub fn toward_readings(
    model: &Model,
    start: &State,
    readings: &[StepReading],
    initial_q: &[f64],
) -> Option<State> {
    moved(
        model,
        start,
        &moves_toward(model, start, readings, initial_q)?,
    )
}

/// The moves of [`toward_readings`]: each read coordinate and its shift from
/// `start`, None where none is farther than [`FAR`].
pub fn moves_toward(
    model: &Model,
    start: &State,
    readings: &[StepReading],
    initial_q: &[f64],
) -> Option<Vec<(usize, f64)>> {
    let mut moves: Vec<(usize, f64)> = Vec::new();
    for reading in readings {
        let sensor = &model.sensors[reading.sensor];
        let SensorKind::Encoder { coordinate: c } = sensor.kind else {
            continue;
        };
        let (Some(&value), Some(&prior)) = (reading.values.first(), initial_q.get(c)) else {
            continue;
        };
        if moves.iter().any(|&(i, _)| i == c) || !value.is_finite() {
            continue;
        }
        let mut misfit = value - start.q[c];
        if model.is_angle(c) {
            misfit -= 2.0 * PI * (misfit / (2.0 * PI)).round();
        }
        let (sp, sr) = (prior * prior, sensor.effective_sigma().powi(2));
        let shift = misfit * sp / (sp + sr);
        if shift.is_finite() {
            moves.push((c, shift));
        }
    }
    let largest = moves.iter().fold(0.0f64, |m, &(_, d)| m.max(d.abs()));
    (largest > FAR).then_some(moves)
}

/// `start` with each coordinate of `moves` shifted by its amount, reached by position
/// solves in strides of at most [`STRIDE`] with the moved coordinates held, their
/// velocities the start's and the others' the velocity problem's. None where the way
/// there fails.
pub fn moved(model: &Model, start: &State, moves: &[(usize, f64)]) -> Option<State> {
    let largest = moves.iter().fold(0.0f64, |m, &(_, d)| m.max(d.abs()));
    let held: Vec<usize> = moves.iter().map(|&(c, _)| c).collect();
    let strides = (largest / STRIDE).ceil() as usize;
    let mut q = start.q.clone();
    for j in 1..=strides {
        let f = j as f64 / strides as f64;
        for &(c, shift) in moves {
            q[c] = start.q[c] + f * shift;
        }
        kinematics::solve_position(model, &mut q, &held).ok()?;
    }
    let rates: Vec<f64> = held.iter().map(|&c| start.dq[c]).collect();
    let dq = kinematics::solve_velocity(model, &q, &held, &rates).ok()?;
    (q.iter().chain(dq.iter()).all(|v| v.is_finite())).then_some(State { q, dq })
}
