//! A large mechanism's set-up (rank of Φ_q, initial velocities, the inertia check)
//! takes sparse shortcuts where the dense computations cost n³; each shortcut must
//! give the dense answer, and hand the cases it cannot certify back to it.

use mbfg::kinematics;
use mbfg::model::plausibility::inertia_warning;
use mbfg::model::Model;
use mbfg::scene::Scene;
use nalgebra::DVector;
use std::path::Path;

fn load(path: &str) -> Model {
    let scene = Scene::load(Path::new(env!("CARGO_MANIFEST_DIR")).join(path)).unwrap();
    Model::new(&scene).unwrap()
}

/// A hanging chain of `links` rods between points (each rod a body of 0.1 kg),
/// and a tip T on a rod body or a massless rod; `extra_constraints` are added.
fn chain(links: usize, tip_body: bool, extra_constraints: &str) -> Model {
    let mut text = String::from("name: chain\npoints:\n  - {name: P0, x: 0, y: 0, fixed: true}\n");
    for k in 1..=links {
        text += &format!(
            "  - {{name: P{k}, x: {}, y: {}}}\n",
            0.1 * k as f64 * 0.5,
            -0.1 * k as f64 * 0.866
        );
    }
    text += &format!(
        "  - {{name: T, x: {}, y: {}}}\n",
        0.1 * links as f64 * 0.5 + 0.1,
        -0.1 * links as f64 * 0.866
    );
    text += "bodies:\n";
    for k in 1..=links {
        text += &format!(
            "  - {{name: b{k}, points: [P{}, P{k}], mass: 0.1}}\n",
            k - 1
        );
    }
    // The tip hangs on a rod body, or on a bare (massless) distance constraint.
    let mut constraints = extra_constraints.to_string();
    if tip_body {
        text += &format!("  - {{name: tip, points: [P{links}, T], mass: 0.1}}\n");
    } else {
        constraints += &format!("  - {{name: tip-rod, type: distance, points: [P{links}, T]}}\n");
    }
    if !constraints.is_empty() {
        text += &format!("constraints:\n{constraints}");
    }
    text += "coordinates:\n  - {name: a1, type: angle, points: [P0, P1]}\n";
    text += "effects:\n  - {type: gravity, vector: [0, -9.81]}\n";
    let scene = Scene::from_str(&text, Path::new("chain.yaml")).unwrap();
    Model::new(&scene).unwrap()
}

#[test]
fn a_long_chain_is_certified_full_rank_and_a_repeated_rod_is_still_found() {
    let model = load("scenes/scale/n-fourbar-50.yaml");
    assert!(model.m() >= 100);
    assert!(model.redundant.is_empty());
    assert_eq!(
        kinematics::constraint_rank(&model, &model.initial.q).rank,
        model.m()
    );
    // The tip's rod given twice: the second copy is redundant (the certificate
    // fails and the ordered scan names it).
    let model = chain(
        50,
        true,
        "  - {name: again, type: distance, points: [P50, T]}\n",
    );
    assert!(model.m() >= 48);
    let again = model
        .constraints
        .iter()
        .position(|c| c.name == "again")
        .unwrap();
    assert_eq!(model.redundant, vec![again]);
}

#[test]
fn a_large_mechanisms_initial_velocities_are_the_dense_ones() {
    // 203 coordinates: the velocity problem is solved sparse.
    let model = load("scenes/scale/n-fourbar-100.yaml");
    let q = &model.initial.q;
    let dz = [-1.0];
    let sparse = kinematics::solve_velocity(&model, q, &model.independent, &dz).unwrap();
    let (_, r) = kinematics::s_and_r(&model, q, &model.independent).unwrap();
    let dense = r * DVector::from_column_slice(&dz);
    let err = (&sparse - &dense).amax();
    assert!(
        err <= 1e-12 * dense.amax(),
        "sparse and dense velocities differ by {err:e}"
    );
    assert!(sparse.amax() > 0.1, "the chain moves");
}

#[test]
fn the_inertia_check_of_a_large_chain_agrees_with_the_eigendecomposition() {
    // Every point of the chain carries mass through the rods: no warning, by the
    // sparse certificate.
    let model = load("scenes/scale/n-pendulum-32.yaml");
    assert!(model.n() >= 48);
    assert_eq!(inertia_warning(&model), None);
    let model = chain(40, true, "");
    assert_eq!(inertia_warning(&model), None);
    // The tip on a massless rod swings without inertia: the certificate fails and
    // the eigendecomposition names the point.
    let model = chain(40, false, "");
    let warning = inertia_warning(&model).expect("a warning for the massless tip");
    assert!(
        warning.contains("1 of the") && warning.contains("moving without mass: T"),
        "{warning}"
    );
}
