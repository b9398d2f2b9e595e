//! The Hermite–Simpson integrator factors are fourth order, measured, not assumed:
//! against the committed references, the position error falls by ≥ 14× per halving
//! of dt over three halvings, and so does the energy drift of conservative scenes, in
//! dependent and independent coordinates; every window and the batch keep N_w = 1's
//! accuracy.

mod common;

use common::{reference_rmse, scene_path};
use mbfg::forward::{simulate, Coordinates, ForwardOptions, Integrator, RunSummary, Trajectory};
use mbfg::smoother::Mode;
use mbfg::{Model, Scene};
use std::sync::Arc;

fn run(
    scene: &str,
    coords: Coordinates,
    dt: f64,
    t_end: f64,
    mode: Mode,
) -> (Arc<Model>, Trajectory, RunSummary) {
    let model = Arc::new(Model::new(&Scene::load(scene_path(scene)).unwrap()).unwrap());
    let mut options = ForwardOptions::new(coords, dt, t_end, mode);
    options.integrator = Integrator::HermiteSimpson;
    let (tr, summary) = simulate(model.clone(), &options, &mut |_, _| {}).unwrap();
    assert!(
        summary.failures.is_empty(),
        "{scene} dt = {dt}: {:?}",
        summary.failures.first()
    );
    assert!(
        summary.worst_phi <= 1e-9,
        "{scene}: |Φ| = {:e}",
        summary.worst_phi
    );
    (model, tr, summary)
}

fn list(values: &[f64]) -> String {
    let items: Vec<String> = values.iter().map(|v| format!("{v:.3e}")).collect();
    items.join(", ")
}

/// Errors and energy drifts over dt = 8, 4, 2, 1 ms (1 s), with the ratios between
/// consecutive halvings.
fn halvings(scene: &str, reference: &str, coords: Coordinates) {
    let mut errors = Vec::new();
    let mut drifts = Vec::new();
    for dt in [8e-3, 4e-3, 2e-3, 1e-3] {
        let (model, tr, summary) = run(scene, coords, dt, 1.0, Mode::FixedLag(1));
        errors.push(reference_rmse(&model, &tr, reference));
        drifts.push(summary.energy_drift.expect("a conservative scene"));
    }
    println!(
        "{scene} {coords:?}: errors {}, energy drifts {}",
        list(&errors),
        list(&drifts)
    );
    for k in 1..errors.len() {
        let (e, d) = (errors[k - 1] / errors[k], drifts[k - 1] / drifts[k]);
        assert!(
            e >= 14.0,
            "{scene} {coords:?}: error ratio {e:.1} at halving {k}: {}",
            list(&errors)
        );
        assert!(
            d >= 14.0,
            "{scene} {coords:?}: drift ratio {d:.1} at halving {k}: {}",
            list(&drifts)
        );
    }
}

#[test]
fn fourbar_is_fourth_order() {
    halvings("fourbar.yaml", "fourbar", Coordinates::Dependent);
    halvings(
        "fourbar-theta.yaml",
        "fourbar-theta",
        Coordinates::Independent,
    );
}

#[test]
fn slider_crank_is_fourth_order() {
    halvings("slider-crank.yaml", "slider-crank", Coordinates::Dependent);
    halvings(
        "slider-crank.yaml",
        "slider-crank",
        Coordinates::Independent,
    );
}

#[test]
fn double_pendulum_is_fourth_order() {
    halvings(
        "double-pendulum.yaml",
        "double-pendulum",
        Coordinates::Dependent,
    );
    halvings(
        "double-pendulum.yaml",
        "double-pendulum",
        Coordinates::Independent,
    );
}

/// The four-bar over its 5 s: ≤ 1e-9 m at 1 ms and ≤ 1e-11 m at 0.25 ms, DC and IC,
/// one step, a window of five and the batch.
#[test]
fn fourbar_reaches_1e_9_at_1_ms_in_every_mode() {
    for (scene, coords) in [
        ("fourbar.yaml", Coordinates::Dependent),
        ("fourbar-theta.yaml", Coordinates::Independent),
    ] {
        let reference = scene.trim_end_matches(".yaml");
        for mode in [Mode::FixedLag(1), Mode::FixedLag(5), Mode::Batch] {
            for (dt, bound) in [(1e-3, 1e-9), (2.5e-4, 1e-11)] {
                let (model, tr, _) = run(scene, coords, dt, 5.0, mode);
                let e = reference_rmse(&model, &tr, reference);
                println!("{scene} {coords:?} {mode:?} dt = {dt}: {e:.3e} m");
                assert!(
                    e <= bound,
                    "{scene} {coords:?} {mode:?} dt = {dt}: {e:.3e} m > {bound:e}"
                );
            }
        }
    }
}
