//! DC steps with tangent integrators taken as a sparse square system (from 20
//! coordinates on, away from singular configurations): the same solution as the
//! general solver's, to the step tolerance, and the one of every window length.

mod common;

use common::scene_path;
use mbfg::forward::{simulate, Coordinates, ForwardOptions, RunSummary, Trajectory};
use mbfg::smoother::Mode;
use mbfg::{Model, Scene};
use std::sync::Arc;

fn run(scene: &str, dt: f64, t_end: f64, mode: Mode, exact: bool) -> (Trajectory, RunSummary) {
    let model = Arc::new(Model::new(&Scene::load(scene_path(scene)).unwrap()).unwrap());
    let mut options = ForwardOptions::new(Coordinates::Dependent, dt, t_end, mode);
    options.exact_steps = exact;
    let (trajectory, summary) = simulate(model, &options, &mut |_, _| {}).unwrap();
    assert!(
        summary.failures.is_empty(),
        "{scene} {mode:?} exact {exact}: {}",
        summary.failures[0].message()
    );
    (trajectory, summary)
}

fn largest_difference(a: &[f64], b: &[f64]) -> f64 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f64::max)
}

/// A chain of ten square loops through its flat configuration (t ≈ 0.72 s, where
/// the steps go back to the general solver) and an eight-link pendulum (angle
/// coordinates): positions, velocities and accelerations as the general solver
/// takes them, step by step.
#[test]
fn sparse_steps_are_the_general_solvers_steps() {
    for (scene, t_end) in [
        ("benchmarks/n-fourbar-10.yaml", 0.8),
        ("scale/n-pendulum-8.yaml", 0.5),
    ] {
        let (sparse, s) = run(scene, 1e-3, t_end, Mode::FixedLag(1), true);
        let (general, g) = run(scene, 1e-3, t_end, Mode::FixedLag(1), false);
        assert_eq!(sparse.len(), general.len());
        let dq = largest_difference(&sparse.q, &general.q);
        let ddq = largest_difference(&sparse.dq, &general.dq);
        let dddq = largest_difference(&sparse.ddq, &general.ddq);
        assert!(
            dq <= 1e-9 && ddq <= 1e-7 && dddq <= 1e-5,
            "{scene}: q {dq:e}, q̇ {ddq:e}, q̈ {dddq:e} apart"
        );
        assert!(s.worst_phi <= 1e-12, "{scene}: |Φ| {:e}", s.worst_phi);
        // The sparse steps reuse their factors from step to step: far fewer
        // factorizations than the general solver's (one per linear solve).
        assert!(
            s.mean_factorizations <= 0.5 * g.mean_factorizations,
            "{scene}: {} factorizations a step, the general solver {}",
            s.mean_factorizations,
            g.mean_factorizations
        );
    }
}

/// Each step holds all its equations, so every window length and the batch have
/// the one-step solution; with sparse steps they are that solution.
#[test]
fn every_window_and_the_batch_are_the_one_step_solution() {
    let scene = "scale/n-pendulum-8.yaml";
    let (one, _) = run(scene, 1e-3, 0.3, Mode::FixedLag(1), true);
    for mode in [Mode::FixedLag(5), Mode::Batch] {
        let (other, s) = run(scene, 1e-3, 0.3, mode, true);
        assert_eq!(one.q, other.q, "{mode:?}");
        assert_eq!(one.ddq, other.ddq, "{mode:?}");
        assert!(s.max_iterations >= 1, "{mode:?}: no iterations reported");
        // And the general solver's window of five agrees to its tolerance.
        let (general, _) = run(scene, 1e-3, 0.3, mode, false);
        let d = largest_difference(&one.q, &general.q);
        assert!(d <= 1e-9, "{mode:?}: the general solver's is {d:e} m away");
    }
}

/// A large mechanism's first accelerations come from the sparse LU of the augmented
/// system (160 unknowns on): its solution as the dense, equilibrated one gives it.
#[test]
fn the_sparse_first_accelerations_are_the_augmented_systems() {
    for scene in ["scale/n-pendulum-64.yaml", "scale/n-fourbar-100.yaml"] {
        let model = Model::new(&Scene::load(scene_path(scene)).unwrap()).unwrap();
        assert!(
            mbfg::dynamics::KktStructure::for_model(&model).is_some(),
            "{scene}: its augmented system is not factored sparse"
        );
        let (q, dq) = (&model.initial.q, &model.initial.dq);
        let sparse = mbfg::dynamics::accelerations_guess(&model, q, dq, 0.0).unwrap();
        let dense = mbfg::dynamics::lagrange(&model, q, dq, 0.0).unwrap().ddq;
        let scale = dense.amax();
        let d = largest_difference(sparse.as_slice(), dense.as_slice());
        assert!(
            d <= 1e-10 * scale,
            "{scene}: {d:e} apart (largest {scale:e})"
        );
    }
}

/// The simplified iteration factors afresh only above the step tolerance (1e-8):
/// below it the updates approach the residual's rounding and their contraction is
/// noise. A 32-link pendulum's updates bottom out near 1e-12 with contractions of
/// 0.3 to 1, where 66 of 90 fresh factorizations in 0.3 s came after an update
/// below the tolerance; none may now (read from `--trace-solver`: a line without
/// `chord` past a step's first iteration is a fresh factorization).
#[test]
fn no_fresh_factorization_after_an_update_below_the_tolerance() {
    let dir = common::scratch("exact", "refactor");
    let out = dir.join("out.csv");
    let run = common::mbfg(&[
        "simulate",
        "scenes/scale/n-pendulum-32.yaml",
        "--dt",
        "0.001",
        "--t-end",
        "0.3",
        "--out",
        out.to_str().unwrap(),
        "--trace-solver",
    ]);
    assert!(run.status.success(), "{}", common::stderr(&run));
    let field = |line: &str, key: &str| -> String {
        let start = line.find(key).unwrap() + key.len();
        line[start..].split(' ').next().unwrap().to_string()
    };
    let (mut fresh, mut previous): (usize, Option<(String, f64)>) = (0, None);
    for line in common::stderr(&run)
        .lines()
        .filter(|l| l.starts_with("k0="))
    {
        let step = field(line, "k1=");
        let iteration: usize = field(line, " it=").parse().unwrap();
        let update: f64 = field(line, "|d|=").parse().unwrap();
        if let Some((before, last_update)) = &previous {
            if *before == step && iteration >= 2 && !line.ends_with("chord") {
                fresh += 1;
                assert!(
                    *last_update > 1e-8,
                    "step {step} factored afresh after an update of {last_update:e}: {line}"
                );
            }
        }
        previous = Some((step, update));
    }
    // The trace shows fresh factorizations at all (the check above is not vacuous).
    assert!(
        fresh >= 10,
        "{fresh} fresh factorizations past a step's first iteration"
    );
    std::fs::remove_dir_all(&dir).ok();
}
