//! Tests of the sparse DC step: its Jacobian against finite differences, its
//! distance to rank loss against the dynamics kernel's.

use super::*;
use crate::dynamics::DynamicsKernel;
use crate::scene::Scene;

fn model_of(scene: &str) -> Arc<Model> {
    let path = format!("{}/scenes/{scene}", env!("CARGO_MANIFEST_DIR"));
    Arc::new(Model::new(&Scene::load(&path).unwrap()).unwrap())
}

fn step_of(scene: &str, integrator: Integrator) -> SquareStep {
    SquareStep::dependent(model_of(scene), integrator, 1e-3).unwrap()
}

fn ic_step_of(scene: &str, integrator: Integrator) -> SquareStep {
    let model = model_of(scene);
    let independent = model.independent.clone();
    SquareStep::independent(model, integrator, 1e-3, &independent).unwrap()
}

/// A deterministic spread of values in (−1, 1).
fn wobble(i: usize) -> f64 {
    ((i as f64 + 1.0) * 0.754_877_666).fract() * 2.0 - 1.0
}

/// The assembled Jacobian against central differences of the residual, at a
/// state off the manifold with nonzero multipliers (every term of every block).
fn check_jacobian(scene: &str, mut step: SquareStep) {
    let model = step.equations.system.model.clone();
    let n = model.n();
    let size = step.equations.system.size();
    let mut x: Vec<f64> = (0..size).map(|i| 0.3 * wobble(i)).collect();
    for i in 0..n {
        x[i] = model.initial.q[i] + 0.01 * wobble(i + 7);
    }
    let before: Vec<f64> = (0..3 * n).map(|i| x[i % n] + 0.1 * wobble(i + 3)).collect();
    let t = 0.37;
    let work = &mut step.work;
    work.near_rank_loss = true;
    step.equations.prepare(&before, work);
    if step.equations.system.damped() {
        assert!(
            work.damping.iter().all(|d| *d > 0.0),
            "{scene}: undamped rows"
        );
    }
    work.x.copy_from_slice(&x);
    step.equations.linearize(t, &before, work).unwrap();
    let mut dense = vec![0.0; size * size];
    let pattern = step.equations.pattern(work.active_damped);
    for col in 0..size {
        for e in pattern.col_ptr[col]..pattern.col_ptr[col + 1] {
            dense[pattern.row_idx[e] * size + col] = work.values[e];
        }
    }
    let mut worst: f64 = 0.0;
    for col in 0..size {
        let h = 1e-6 * (1.0 + x[col].abs());
        let mut residual_at = |value: f64| {
            work.x.copy_from_slice(&x);
            work.x[col] = value;
            step.equations.linearize(t, &before, work).unwrap();
            work.residual.clone()
        };
        let (plus, minus) = (residual_at(x[col] + h), residual_at(x[col] - h));
        for row in 0..size {
            let fd = (plus[row] - minus[row]) / (2.0 * h);
            let err = (fd - dense[row * size + col]).abs() / (1.0 + fd.abs());
            worst = worst.max(err);
            assert!(
                err < 1e-6,
                "{scene}: d(row {row})/d(col {col}): {} assembled, {fd} by differences",
                dense[row * size + col]
            );
        }
    }
    assert!(worst.is_finite());
}

#[test]
fn distance_to_rank_loss_is_the_kernels() {
    // Chains of loops and of links (their G ill-conditioned like 1/N²), a
    // mechanism with angle coordinates and springs, and configurations off the
    // initial one.
    for scene in [
        "scale/n-fourbar-10.yaml",
        "scale/n-pendulum-16.yaml",
        "benchmarks/andrews-squeezer.yaml",
        "driven/watt-six-bar.yaml",
    ] {
        let mut step = step_of(scene, Integrator::Trapezoidal);
        let model = step.equations.system.model.clone();
        for shift in [0.0, 0.05, 0.3] {
            let q: Vec<f64> = (0..model.n())
                .map(|i| model.initial.q[i] + shift * wobble(i))
                .collect();
            let work = &mut step.work;
            let sparse =
                step.equations
                    .regularity
                    .distance_to_rank_loss(&model, &q, &mut work.gram);
            let (dense, _, _) = DynamicsKernel::regularization_at(&model, &q);
            assert!(
                (sparse - dense).abs() <= 1e-9 * dense,
                "{scene} shifted by {shift}: s = {sparse} sparse, {dense} dense"
            );
        }
    }
}

#[test]
fn jacobian_matches_finite_differences() {
    // Springs and state-dependent torques; angle coordinates (third-order terms);
    // a controller reading rates; both integration rules; in DC (projected
    // integrators with μ) and in IC (integrators on z alone, no μ).
    for (scene, rule, independent) in [
        (
            "benchmarks/andrews-squeezer.yaml",
            Integrator::Trapezoidal,
            false,
        ),
        ("scale/n-pendulum-4.yaml", Integrator::Trapezoidal, false),
        (
            "driven/controlled-crank-rocker.yaml",
            Integrator::Euler,
            false,
        ),
        ("driven/watt-six-bar.yaml", Integrator::Trapezoidal, false),
        (
            "benchmarks/andrews-squeezer.yaml",
            Integrator::Trapezoidal,
            true,
        ),
        (
            "driven/controlled-crank-rocker.yaml",
            Integrator::Euler,
            true,
        ),
        ("driven/watt-six-bar.yaml", Integrator::Trapezoidal, true),
        ("double-pendulum.yaml", Integrator::Trapezoidal, true),
        // Hermite–Simpson: the stage's rows and columns, through the ends'
        // q, q̇, q̈ its state is interpolated from.
        (
            "benchmarks/andrews-squeezer.yaml",
            Integrator::HermiteSimpson,
            false,
        ),
        ("scale/n-pendulum-4.yaml", Integrator::HermiteSimpson, false),
        (
            "driven/controlled-crank-rocker.yaml",
            Integrator::HermiteSimpson,
            false,
        ),
        ("driven/watt-six-bar.yaml", Integrator::HermiteSimpson, true),
        (
            "driven/controlled-crank-rocker.yaml",
            Integrator::HermiteSimpson,
            true,
        ),
    ] {
        let step = if independent {
            ic_step_of(scene, rule)
        } else {
            step_of(scene, rule)
        };
        check_jacobian(scene, step);
    }
}

/// An IC step is square only where the constraints have full rank: a scene with a
/// redundant bar leaves it to the general solver.
#[test]
fn independent_steps_need_independent_constraints() {
    let model = model_of("hard/redundant-fourbar.yaml");
    assert!(
        model.active.len() < model.m(),
        "the coupler is constrained twice"
    );
    let independent = model.independent.clone();
    assert!(SquareStep::independent(model, Integrator::Trapezoidal, 1e-3, &independent).is_none());
    let model = model_of("fourbar-theta.yaml");
    let independent = model.independent.clone();
    let step = SquareStep::independent(model.clone(), Integrator::Trapezoidal, 1e-3, &independent)
        .unwrap();
    assert_eq!(step.equations.system.size(), 3 * model.n() + model.m());
}

/// A step solved after another far from it: the earlier step's factors, kept for
/// the simplified iteration, are refreshed where they do not carry it, and the step
/// is the one a step with fresh factors finds.
#[test]
fn factors_of_a_distant_step_do_not_change_the_solution() {
    let limits = StepLimits {
        max_iterations: 50,
        step_tolerance: 1e-8,
    };
    let scene = "benchmarks/andrews-squeezer.yaml";
    let mut kept = step_of(scene, Integrator::Trapezoidal);
    let model = kept.equations.system.model.clone();
    let n = model.n();
    // The squeezer 40 ms into its motion: the crank has turned through a radian.
    let options = crate::forward::ForwardOptions::new(
        crate::coordinates::Coordinates::Dependent,
        1e-3,
        0.04,
        crate::smoother::Mode::FixedLag(1),
    );
    let (trajectory, _) =
        crate::forward::simulate(model.clone(), &options, &mut |_, _| {}).unwrap();
    let state = |k: usize| -> Vec<f64> {
        let row = k * n..(k + 1) * n;
        let mut v = trajectory.q[row.clone()].to_vec();
        v.extend(&trajectory.dq[row.clone()]);
        v.extend(&trajectory.ddq[row]);
        v
    };
    // A first step from the start, which leaves its factors behind.
    let before = state(0);
    let mut block = before.clone();
    assert!(kept
        .solve(0.001, &before, &mut block, limits, None)
        .is_some());
    // The step after the last: with the kept factors and with none.
    let last = trajectory.len() - 1;
    let before = state(last);
    let t = trajectory.t[last] + 1e-3;
    let mut with_kept = before.clone();
    let work = kept
        .solve(t, &before, &mut with_kept, limits, None)
        .unwrap();
    assert!(work.factorizations >= 1, "the kept factors were refreshed");
    let mut fresh = step_of(scene, Integrator::Trapezoidal);
    let mut with_fresh = before.clone();
    fresh
        .solve(t, &before, &mut with_fresh, limits, None)
        .unwrap();
    for i in 0..3 * n {
        let scale = 1.0 + with_fresh[i].abs();
        assert!(
            (with_kept[i] - with_fresh[i]).abs() <= 1e-9 * scale,
            "unknown {i}: {} with the kept factors, {} with fresh ones",
            with_kept[i],
            with_fresh[i]
        );
    }
}

/// The four-lane max_abs is the one-lane fold's value, bit for bit, NaNs and
/// infinities included, at every length of the tail.
#[test]
fn max_abs_is_the_fold() {
    let fold = |v: &[f64]| v.iter().fold(0.0f64, |m, x| m.max(x.abs()));
    let mut v: Vec<f64> = Vec::new();
    for i in 0..23 {
        assert_eq!(max_abs(&v).to_bits(), fold(&v).to_bits(), "{v:?}");
        v.push(match i % 7 {
            3 => f64::NAN,
            5 => -0.0,
            _ => 10.0 * wobble(i),
        });
    }
    v.push(f64::NEG_INFINITY);
    assert_eq!(max_abs(&v), f64::INFINITY);
    assert_eq!(max_abs(&[f64::NAN, f64::NAN]), 0.0);
}
