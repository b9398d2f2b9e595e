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
