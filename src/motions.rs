//! The suite's prescribed motions with their exact derivatives (the formulas behind
//! `scenes/trajectories/`, written by `harness/prescribed_motions.py`), so that tests
//! and reports compare inverse dynamics against the classical solution computed from
//! exact velocities and accelerations. Each returns [value, rate, second rate] per
//! prescribed coordinate.

use std::f64::consts::PI;

/// The paper's four-bar (section 7.2): θ(t) = 1.2(1 − cos 2t).
pub fn fourbar_crank(t: f64) -> [f64; 3] {
    [
        1.2 * (1.0 - (2.0 * t).cos()),
        2.4 * (2.0 * t).sin(),
        4.8 * (2.0 * t).cos(),
    ]
}

/// The pick-and-place robot's cycle from rest at the scene's configuration: with
/// τ = 2πt/5 and c = (1 − cos τ)/2, motor1 = −3π/4 + 0.3c + 0.2c·sin τ and
/// motor2 = −π/4 − 0.3c + 0.2c·sin τ.
pub fn robot_cycle(t: f64) -> [[f64; 3]; 2] {
    let w = 2.0 * PI / 5.0;
    let (s, c) = ((w * t).sin(), (w * t).cos());
    let u = [(1.0 - c) / 2.0, w * s / 2.0, w * w * c / 2.0];
    let v = [
        s * u[0],
        w * c * u[0] + s * u[1],
        -w * w * s * u[0] + 2.0 * w * c * u[1] + s * u[2],
    ];
    let f = |m: f64, sign: f64| {
        [
            m + sign * 0.3 * u[0] + 0.2 * v[0],
            sign * 0.3 * u[1] + 0.2 * v[1],
            sign * 0.3 * u[2] + 0.2 * v[2],
        ]
    };
    [f(-0.75 * PI, 1.0), f(-0.25 * PI, -1.0)]
}

/// The double pendulum's absolute link angles from rest, horizontal:
/// φ₁ = −0.8(1 − cos 1.5t), φ₂ = −1.1(1 − cos 2.3t).
pub fn double_pendulum(t: f64) -> [[f64; 3]; 2] {
    let f = |a: f64, w: f64| {
        [
            -a * (1.0 - (w * t).cos()),
            -a * w * (w * t).sin(),
            -a * w * w * (w * t).cos(),
        ]
    };
    [f(0.8, 1.5), f(1.1, 2.3)]
}

/// The motion as the (values, rates, second rates) triple of
/// [`crate::inverse::classical`].
pub fn split<const P: usize>(m: [[f64; 3]; P]) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
    (
        m.iter().map(|c| c[0]).collect(),
        m.iter().map(|c| c[1]).collect(),
        m.iter().map(|c| c[2]).collect(),
    )
}
