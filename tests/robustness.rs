//! Four-bar forward dynamics on plain, non-singular motion must converge at every
//! step, at large steps and over long runs too (less accurate, but converged, with
//! |Φ| ≤ 1e-9). These runs used to stall (docs/dc-stall.md has the diagnosis and
//! the fix: priors on the constraints' tangent space, the exact reduced Hessian
//! when Gauss-Newton converges slowly, backtracking, integrators weighted above f_dyn).

use mbfg::forward::{simulate, Coordinates, ForwardOptions};
use mbfg::smoother::Mode;
use mbfg::{Model, Scene};
use std::path::PathBuf;
use std::sync::Arc;

fn scene(file: &str) -> Arc<Model> {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join(file);
    Arc::new(Model::new(&Scene::load(path).unwrap()).unwrap())
}

fn fourbar() -> Arc<Model> {
    scene("scenes/fourbar.yaml")
}

fn converges(dt: f64, t_end: f64, window: usize) {
    converges_in(Coordinates::Dependent, dt, t_end, window);
}

fn converges_in(coordinates: Coordinates, dt: f64, t_end: f64, window: usize) {
    let opts = ForwardOptions::new(coordinates, dt, t_end, Mode::FixedLag(window));
    let model = match coordinates {
        Coordinates::Dependent => fourbar(),
        Coordinates::Independent => scene("scenes/fourbar-theta.yaml"),
    };
    let (tr, summary) = simulate(model, &opts, &mut |_, _| {}).unwrap();
    let first = summary
        .failures
        .first()
        .map(|f| (f.step, f.t, f.report.clone()));
    assert!(
        summary.failures.is_empty(),
        "dt = {dt}, N_w = {window}: first stalled solve {first:?}"
    );
    assert_eq!(tr.len(), opts.steps());
    assert!(
        summary.worst_phi <= 1e-9,
        "dt = {dt}: |Φ| = {:e}",
        summary.worst_phi
    );
}

#[test]
fn dependent_coordinates_converge_at_20_ms() {
    converges(2e-2, 5.0, 1);
}

#[test]
fn dependent_coordinates_converge_at_10_ms() {
    converges(1e-2, 5.0, 1);
}

#[test]
fn dependent_coordinates_converge_at_5_ms() {
    converges(5e-3, 5.0, 1);
}

#[test]
fn dependent_coordinates_converge_for_60_s_at_1_ms() {
    converges(1e-3, 60.0, 1);
    converges(1e-3, 60.0, 2);
}

#[test]
fn independent_coordinates_converge_for_60_s_at_1_ms() {
    converges_in(Coordinates::Independent, 1e-3, 60.0, 1);
}

#[test]
fn windows_converge_at_10_ms() {
    converges(1e-2, 5.0, 2);
    converges(1e-2, 5.0, 10);
    converges_in(Coordinates::Independent, 2e-2, 5.0, 10);
}

/// Mass does not change a pendulum's motion: 1 kg and 1e9 kg on the same rod swing
/// alike in DC and IC. The KKT system's pivot test is relative to its largest entry,
/// and 1e8 kg and more made the constraint block's pivots, |Φ_q|²/m, look singular
/// ("the augmented (KKT) system is singular" at step 0) until K is factored with M in
/// units of its scale.
#[test]
fn a_heavy_pendulum_swings_as_a_light_one() {
    let text = std::fs::read_to_string(
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("scenes/pendulum.yaml"),
    )
    .unwrap();
    assert!(text.contains("mass: 1}"), "the pendulum's rod is 1 kg");
    let heavy = Scene::from_str(
        &text.replace("mass: 1}", "mass: 1e9}"),
        std::path::Path::new("heavy.yaml"),
    )
    .unwrap();
    let heavy = Arc::new(Model::new(&heavy).unwrap());
    for coords in [Coordinates::Dependent, Coordinates::Independent] {
        let opts = ForwardOptions::new(coords, 1e-3, 1.0, Mode::FixedLag(1));
        let (light, s) = simulate(scene("scenes/pendulum.yaml"), &opts, &mut |_, _| {}).unwrap();
        assert!(s.failures.is_empty());
        let (tr, s) = simulate(heavy.clone(), &opts, &mut |_, _| {}).unwrap();
        assert!(
            s.failures.is_empty(),
            "{:?}",
            s.failures.first().map(|f| f.message())
        );
        for (a, b) in tr.q.iter().zip(&light.q) {
            assert!((a - b).abs() <= 1e-12, "{a} against {b}");
        }
    }
}
