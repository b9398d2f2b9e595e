//! Four-bar forward dynamics in dependent coordinates on plain, non-singular motion
//! must converge at every step, at large steps too (less accurate, but converged,
//! with |Φ| ≤ 1e-9). These runs stall today (see docs/dc-stall.md for the diagnosis),
//! so the tests are ignored until the solver is fixed; run them with
//! `cargo test --release --test robustness -- --ignored`.

use mbfg::forward::{simulate, Coordinates, ForwardOptions};
use mbfg::smoother::Mode;
use mbfg::{Model, Scene};
use std::path::PathBuf;
use std::sync::Arc;

fn fourbar() -> Arc<Model> {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("scenes/fourbar.yaml");
    Arc::new(Model::new(&Scene::load(path).unwrap()).unwrap())
}

fn converges(dt: f64, t_end: f64, window: usize) {
    let opts = ForwardOptions::new(Coordinates::Dependent, dt, t_end, Mode::FixedLag(window));
    let (tr, summary) = simulate(fourbar(), &opts, &mut |_, _| {}).unwrap();
    let first = summary.failures.first().map(|f| (f.step, f.t, f.report));
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
#[ignore = "stalls at t = 1.44 s: GN curvature along the motion (docs/dc-stall.md)"]
fn dependent_coordinates_converge_at_20_ms() {
    converges(2e-2, 5.0, 1);
}

#[test]
#[ignore = "stalls at t = 1.45 s: GN curvature along the motion (docs/dc-stall.md)"]
fn dependent_coordinates_converge_at_10_ms() {
    converges(1e-2, 5.0, 1);
}

#[test]
#[ignore = "stalls at t = 3.495 s: GN curvature along the motion (docs/dc-stall.md)"]
fn dependent_coordinates_converge_at_5_ms() {
    converges(5e-3, 5.0, 1);
}

#[test]
#[ignore = "stalls at t = 8.884 s (N_w = 1), 9.699 s (N_w = 2) (docs/dc-stall.md)"]
fn dependent_coordinates_converge_for_60_s_at_1_ms() {
    converges(1e-3, 60.0, 1);
    converges(1e-3, 60.0, 2);
}
