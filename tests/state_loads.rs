//! Loads that depend on the state: expressions in the coordinates, their rates and
//! point and body kinematics (`20 - 0.8*rate(theta)`), and loads computed outside the
//! scene ([`mbfg::ExternalLoad`], what a Python controller becomes).

mod common;

use common::scene_path;
use mbfg::forward::{simulate, Coordinates, ForwardOptions, Trajectory};
use mbfg::smoother::Mode;
use mbfg::{ExternalLoad, Model, Scene};
use std::path::Path;
use std::sync::Arc;

fn run(model: Model, coords: Coordinates, dt: f64, t_end: f64, mode: Mode) -> Trajectory {
    let opts = ForwardOptions::new(coords, dt, t_end, mode);
    let (tr, summary) = simulate(Arc::new(model), &opts, &mut |_, _| {}).unwrap();
    assert!(
        summary.failures.is_empty(),
        "dt = {dt}, {mode:?}: {:?}",
        summary.failures.first().map(|f| f.message())
    );
    assert_eq!(tr.len(), opts.steps());
    assert!(summary.worst_phi <= 1e-9, "|Φ| = {:e}", summary.worst_phi);
    tr
}

fn scene_text(file: &str) -> String {
    std::fs::read_to_string(scene_path(file)).unwrap()
}

fn model_of(text: &str) -> Model {
    Model::new(&Scene::from_str(text, Path::new("scene.yaml")).unwrap()).unwrap()
}

fn largest_difference(a: &Trajectory, b: &Trajectory) -> f64 {
    a.q.iter()
        .zip(&b.q)
        .chain(a.dq.iter().zip(&b.dq))
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f64::max)
}

/// The DC motor written as an expression in the crank's rate is the `dc_motor`
/// effect: the same forces and the same closed-form ∂Q/∂q̇, so the same run to the bit.
#[test]
fn a_motor_written_as_an_expression_is_the_motor_effect() {
    let text = scene_text("driven/dc-motor-crank-rocker.yaml");
    let written = text.replace(
        "type: dc_motor, coordinate: theta, stall_torque: 60, no_load_speed: 30",
        "type: torque, coordinate: theta, value: 60*(1 - rate(theta)/30)",
    );
    assert_ne!(text, written);
    for coords in [Coordinates::Dependent, Coordinates::Independent] {
        let a = run(model_of(&text), coords, 1e-3, 1.0, Mode::FixedLag(1));
        let b = run(model_of(&written), coords, 1e-3, 1.0, Mode::FixedLag(1));
        assert_eq!(largest_difference(&a, &b), 0.0, "{coords:?}");
    }
}

/// The PD controller of `controlled-crank-rocker.yaml`, as Rust code outside the scene.
#[derive(Debug)]
struct Controller {
    theta: usize,
}

impl ExternalLoad for Controller {
    fn add_to(&self, t: f64, q: &[f64], dq: &[f64], out: &mut [f64]) -> mbfg::Result<()> {
        let (kp, kd, w) = (400.0, 40.0, 2.0 * std::f64::consts::PI);
        out[self.theta] += kp * (w * t - q[self.theta]) + kd * (w - dq[self.theta]);
        Ok(())
    }
}

/// An external load (finite-difference Jacobians) gives the run the expression gives
/// (symbolic Jacobians): the Jacobians steer Newton's steps, not the solution.
#[test]
fn an_external_load_matches_the_same_law_written_in_the_scene() {
    let text = scene_text("driven/controlled-crank-rocker.yaml");
    let without: String = text
        .lines()
        .filter(|l| !l.contains("name: controller"))
        .map(|l| format!("{l}\n"))
        .collect();
    assert_ne!(text, without);
    for (coords, mode) in [
        (Coordinates::Dependent, Mode::FixedLag(1)),
        (Coordinates::Independent, Mode::FixedLag(1)),
        (Coordinates::Dependent, Mode::FixedLag(5)),
    ] {
        let written = run(model_of(&text), coords, 1e-3, 1.0, mode);
        let mut model = model_of(&without);
        let theta = model.names.iter().position(|n| n == "theta").unwrap();
        model
            .add_external_load("controller", Arc::new(Controller { theta }))
            .unwrap();
        let external = run(model, coords, 1e-3, 1.0, mode);
        let d = largest_difference(&written, &external);
        assert!(d <= 1e-10, "{coords:?} {mode:?}: {d:e}");
    }
    // A name already taken is refused.
    let mut model = model_of(&text);
    let err = model
        .add_external_load("drag", Arc::new(Controller { theta: 0 }))
        .unwrap_err()
        .to_string();
    assert!(err.contains("already has an effect named 'drag'"), "{err}");
}

/// The state-dependent scenes converge at the defaults in DC and IC, at fine and
/// coarse steps, one window, several, and batch.
#[test]
fn state_dependent_scenes_converge_in_every_mode() {
    for file in [
        "driven/controlled-crank-rocker.yaml",
        "driven/compressor-slider-crank.yaml",
    ] {
        let text = scene_text(file);
        for coords in [Coordinates::Dependent, Coordinates::Independent] {
            for dt in [1e-3, 2e-2] {
                for mode in [Mode::FixedLag(1), Mode::FixedLag(5), Mode::Batch] {
                    run(model_of(&text), coords, dt, 1.0, mode);
                }
            }
        }
    }
}

/// The controller holds the crank on its reference ω_ref t: the state feedback acts.
#[test]
fn the_controller_tracks_its_reference() {
    let text = scene_text("driven/controlled-crank-rocker.yaml");
    let model = model_of(&text);
    let (n, theta) = (
        model.n(),
        model.names.iter().position(|x| x == "theta").unwrap(),
    );
    let tr = run(model, Coordinates::Dependent, 1e-3, 3.0, Mode::FixedLag(1));
    let k = tr.len() - 1;
    let w = 2.0 * std::f64::consts::PI;
    let lag = w * tr.t[k] - tr.q[k * n + theta];
    // Steady lag of a PD loop against gravity and drag: small beside a turn.
    assert!(lag.abs() < 0.2, "lag {lag} rad");
    assert!((tr.dq[k * n + theta] - w).abs() < 0.5 * w);
}

fn scene_error(effects: &str) -> String {
    let text = scene_text("fourbar-theta.yaml");
    let text = match text.find("effects:") {
        Some(i) => format!("{}effects:\n{effects}\n", &text[..i]),
        None => format!("{text}\neffects:\n{effects}\n"),
    };
    Scene::from_str(&text, Path::new("scene.yaml"))
        .unwrap_err()
        .to_string()
}

#[test]
fn unknown_state_quantities_are_named_with_what_exists() {
    let e = scene_error("  - {name: m, type: torque, coordinate: theta, value: \"rate(psi)\"}");
    assert!(e.contains("no relative coordinate named 'psi'"), "{e}");
    assert!(e.contains("theta"), "{e}");
    let e = scene_error("  - {name: m, type: torque, coordinate: theta, value: \"vx(Q)\"}");
    assert!(e.contains("no point named 'Q'") && e.contains("P1"), "{e}");
    let e = scene_error("  - {name: m, type: torque, coordinate: theta, value: \"omega(wheel)\"}");
    assert!(e.contains("no body named 'wheel'"), "{e}");
    let e = scene_error("  - {name: m, type: torque, coordinate: theta, value: \"rate(1)\"}");
    assert!(e.contains("no relative coordinate named '1'"), "{e}");
}

#[test]
fn state_quantities_elsewhere_say_where_they_belong() {
    let text = scene_text("fourbar-theta.yaml").replacen(
        "points:",
        "parameters:\n  k: 2*rate(theta)\npoints:",
        1,
    );
    let e = Scene::from_str(&text, Path::new("scene.yaml"))
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("may appear only in the value of a torque or a force"),
        "{e}"
    );
}

#[test]
fn a_parameter_named_like_a_coordinate_is_refused_in_a_load() {
    let text =
        scene_text("fourbar-theta.yaml").replacen("points:", "parameters:\n  theta: 1\npoints:", 1);
    let text =
        format!("{text}\n  - {{name: m, type: torque, coordinate: theta, value: \"2*theta\"}}\n");
    let e = Scene::from_str(&text, Path::new("scene.yaml"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("both a parameter and a coordinate"), "{e}");
}

/// The four-bar with a torque `name` = `value` on θ, run in DC for `t_end`: the
/// error or the first failure's message (nothing written is ever NaN).
fn failure_with_torque(name: &str, value: &str, t_end: f64) -> String {
    let text = scene_text("fourbar-theta.yaml");
    let text = format!(
        "{}\n  - {{name: {name}, type: torque, coordinate: theta, value: \"{value}\"}}\n",
        text.trim_end()
    );
    let model = Arc::new(model_of(&text));
    let opts = ForwardOptions::new(Coordinates::Dependent, 1e-3, t_end, Mode::FixedLag(1));
    match simulate(model, &opts, &mut |_, _| {}) {
        Err(e) => e.to_string(),
        Ok((tr, s)) => {
            assert!(tr.q.iter().all(|v| v.is_finite()));
            s.failures.first().map(|f| f.message()).unwrap_or_default()
        }
    }
}

/// A load that goes non-finite is reported by the run, naming the effect, never
/// written as NaN.
#[test]
fn a_load_that_goes_non_finite_names_itself() {
    let message = failure_with_torque("singular", "sqrt(0.5 - t)*rate(theta)", 2.0);
    assert!(
        message.contains("effect singular")
            && message.contains("non-finite")
            && message.contains("t = 0.501"),
        "{message}"
    );
}

/// A value that is finite where its derivative is not (a square root of a rate that
/// starts at 0, and is not a number once the rate turns negative) stops the run
/// naming the effect and why, not as a bare divergence.
#[test]
fn a_load_whose_derivative_is_not_finite_names_itself() {
    let message = failure_with_torque("root", "rate(theta)^0.5", 0.1);
    assert!(
        message.contains("effect root")
            && (message.contains("derivative") || message.contains("non-finite number")),
        "{message}"
    );
}
