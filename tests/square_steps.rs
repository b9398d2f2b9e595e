//! DC steps with tangent integrators taken as a sparse square system (from 20
//! coordinates on, away from singular configurations): the same solution as the
//! general solver's, to the step tolerance, and the one of every window length.

mod common;

use common::scene_path;
use mbfg::forward::{
    simulate, Coordinates, ForwardOptions, Integrator, Observers, RunSummary, Schedule, Trajectory,
};
use mbfg::smoother::Mode;
use mbfg::solver::{self, Observer};
use mbfg::{Model, Scene};
use std::sync::{Arc, Mutex};

fn run(scene: &str, dt: f64, t_end: f64, mode: Mode, exact: bool) -> (Trajectory, RunSummary) {
    run_with(scene, Integrator::Trapezoidal, dt, t_end, mode, exact)
}

fn run_with(
    scene: &str,
    integrator: Integrator,
    dt: f64,
    t_end: f64,
    mode: Mode,
    exact: bool,
) -> (Trajectory, RunSummary) {
    let model = Arc::new(Model::new(&Scene::load(scene_path(scene)).unwrap()).unwrap());
    let mut options = ForwardOptions::new(Coordinates::Dependent, dt, t_end, mode);
    options.square_steps = exact;
    options.integrator = integrator;
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

/// A chain of ten square loops up to its flat configuration (t ≈ 0.72 s: near it the
/// general solver's dynamics are regularized, the square steps' are not; see
/// tests/passages.rs) and an eight-link pendulum (angle coordinates): positions,
/// velocities and accelerations as the general solver takes them, step by step.
#[test]
fn square_steps_are_the_general_solvers_steps() {
    for (scene, t_end) in [
        ("benchmarks/n-fourbar-10.yaml", 0.7),
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
        // The square steps reuse their factors from step to step: far fewer
        // factorizations than the general solver's (one per linear solve).
        assert!(
            s.mean_factorizations <= 0.5 * g.mean_factorizations,
            "{scene}: {} factorizations a step, the general solver {}",
            s.mean_factorizations,
            g.mean_factorizations
        );
    }
}

/// Hermite–Simpson's steps, with the stage's dynamics as unknowns and equations of
/// the square system, are the general solver's, whose collocation factors solve the
/// stage's augmented system inside themselves: on a chain of loops up to its flat
/// configuration, an angle-coordinate pendulum, and Andrews' squeezer (a stiff
/// spring, seven bodies).
#[test]
fn hermite_simpson_square_steps_are_the_general_solvers_steps() {
    for (scene, dt, t_end) in [
        ("benchmarks/n-fourbar-10.yaml", 1e-3, 0.7),
        ("scale/n-pendulum-8.yaml", 1e-3, 0.5),
        ("benchmarks/andrews-squeezer.yaml", 1e-4, 0.01),
    ] {
        let hs = Integrator::HermiteSimpson;
        let (sparse, s) = run_with(scene, hs, dt, t_end, Mode::FixedLag(1), true);
        let (general, g) = run_with(scene, hs, dt, t_end, Mode::FixedLag(1), false);
        assert_eq!(s.square_steps, sparse.len(), "{scene}: every step square");
        assert_eq!(g.square_steps, 0);
        assert_eq!(sparse.len(), general.len());
        let dq = largest_difference(&sparse.q, &general.q);
        let ddq = largest_difference(&sparse.dq, &general.dq);
        let dddq = largest_difference(&sparse.ddq, &general.ddq);
        println!("{scene}: q {dq:e}, q̇ {ddq:e}, q̈ {dddq:e} apart");
        assert!(
            dq <= 1e-9 && ddq <= 1e-7 && dddq <= 1e-5,
            "{scene}: q {dq:e}, q̇ {ddq:e}, q̈ {dddq:e} apart"
        );
        assert!(s.worst_phi <= 1e-12, "{scene}: |Φ| {:e}", s.worst_phi);
    }
}

/// In IC Hermite–Simpson's steps stay with the general solver: on the slider-crank at
/// 20 ms (the crank turns 1.4 rad a step) a step fails and the run is refined, not
/// stopped at a root off the motion.
#[test]
fn hermite_simpson_in_ic_is_refined_by_the_general_solver() {
    let path = scene_path("driven/slider-crank-mm.yaml");
    let model = Arc::new(Model::new(&Scene::load(path).unwrap()).unwrap());
    let mut options = ForwardOptions::new(Coordinates::Independent, 0.02, 1.0, Mode::FixedLag(1));
    options.integrator = Integrator::HermiteSimpson;
    let (trajectory, summary) = simulate(model, &options, &mut |_, _| {}).unwrap();
    assert!(!summary.plan.square_step);
    assert_eq!(summary.square_steps, 0);
    assert!(summary.failures.is_empty());
    assert!(
        summary.refinement.is_some(),
        "the coarse run was not refined"
    );
    assert_eq!(trajectory.len(), 51);
}

/// Each step holds all its equations, so every window length and the batch have
/// the one-step solution; with square steps they are that solution.
#[test]
fn every_window_and_the_batch_are_the_one_step_solution() {
    let scene = "scale/n-pendulum-8.yaml";
    let (one, _) = run(scene, 1e-3, 0.3, Mode::FixedLag(1), true);
    for mode in [Mode::FixedLag(5), Mode::Batch] {
        let (other, s) = run(scene, 1e-3, 0.3, mode, true);
        // The plan says what ran: one step at a time, every step a square step.
        assert_eq!(s.plan.asked, mode);
        assert_eq!(s.plan.schedule, Schedule::Stepwise, "{mode:?}");
        assert_eq!((s.square_steps, s.general_steps), (other.len(), 0));
        assert_eq!(one.q, other.q, "{mode:?}");
        assert_eq!(one.ddq, other.ddq, "{mode:?}");
        assert!(s.max_iterations >= 1, "{mode:?}: no iterations reported");
        // And the general solver's window of five agrees to its tolerance.
        let (general, g) = run(scene, 1e-3, 0.3, mode, false);
        // With the square step off, the window and the batch asked run.
        let asked = match mode {
            Mode::FixedLag(n) => Schedule::FixedLag(n),
            Mode::Batch => Schedule::Batch,
        };
        assert_eq!(g.plan.schedule, asked);
        assert_eq!(g.square_steps, 0);
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

/// One iteration of a step, as an observer of the run sees it.
struct Iteration {
    update: f64,
    /// Taken with the factors of an earlier Jacobian (`chord`); past a step's
    /// first iteration, one without it is a fresh factorization.
    chord: bool,
}

/// The iterations of every step of a 32-link pendulum's run over `t_end` (dt = 1
/// ms), from an observer of its solves.
fn traced_steps(t_end: f64) -> Vec<Vec<Iteration>> {
    let seen: Arc<Mutex<Vec<solver::Iteration>>> = Arc::default();
    struct Collect(Arc<Mutex<Vec<solver::Iteration>>>);
    impl Observer for Collect {
        fn iteration(&mut self, it: &solver::Iteration) {
            self.0.lock().unwrap().push(*it);
        }
    }
    let sink = seen.clone();
    let scene = "scale/n-pendulum-32.yaml";
    let model = Arc::new(Model::new(&Scene::load(scene_path(scene)).unwrap()).unwrap());
    let mut options = ForwardOptions::new(Coordinates::Dependent, 1e-3, t_end, Mode::FixedLag(1));
    options.observer = Some(Observers::new(move || Box::new(Collect(sink.clone()))));
    let (_, summary) = simulate(model, &options, &mut |_, _| {}).unwrap();
    assert!(summary.failures.is_empty());
    assert_eq!(summary.general_steps, 0, "every step a square step");
    let seen = seen.lock().unwrap();
    // A step's iterations start at 1.
    let mut steps: Vec<Vec<Iteration>> = Vec::new();
    for it in seen.iter() {
        let iteration = Iteration {
            update: it.largest_step,
            chord: it.chord,
        };
        match steps.last_mut() {
            Some(iterations) if it.iteration > 1 => iterations.push(iteration),
            _ => steps.push(vec![iteration]),
        }
    }
    steps
}

/// The simplified iteration factors afresh only above the step tolerance (1e-8):
/// below it the updates approach the residual's rounding and their contraction is
/// noise. A 32-link pendulum's updates bottom out near 1e-12 with contractions of
/// 0.3 to 1, where 66 of 90 fresh factorizations in 0.3 s came after an update
/// below the tolerance; none may now.
#[test]
fn no_fresh_factorization_after_an_update_below_the_tolerance() {
    let mut fresh = 0;
    for (k, step) in traced_steps(0.3).iter().enumerate() {
        for pair in step.windows(2).filter(|pair| !pair[1].chord) {
            fresh += 1;
            assert!(
                pair[0].update > 1e-8,
                "step {k} factored afresh after an update of {:e}",
                pair[0].update
            );
        }
    }
    // The trace shows fresh factorizations at all (the check above is not vacuous).
    assert!(
        fresh >= 10,
        "{fresh} fresh factorizations past a step's first iteration"
    );
}

/// A stiff chain's error alternates under the simplified iteration: an update
/// shrinks by 0.01, the next by 0.4. The iteration is judged by the mean
/// contraction of its last two updates, and factors afresh only where that is
/// slower than 0.25 (or the last update did not shrink at all). Judged by the last
/// update alone, a 32-link pendulum factored afresh 0.21 times a step, 113 times
/// in 0.6 s after two updates contracting by 0.02 to 0.19 on average.
#[test]
fn an_alternating_iteration_is_judged_by_its_mean_contraction() {
    let (mut fresh, mut alternating) = (0, 0);
    for (k, step) in traced_steps(0.6).iter().enumerate() {
        // The updates taken with the factors held: from the step's first
        // iteration or its last fresh factorization, up to the one rejected.
        let mut held: Vec<f64> = Vec::new();
        for (i, iteration) in step.iter().enumerate() {
            let rejected = step.get(i + 1).is_some_and(|next| !next.chord);
            if !iteration.chord {
                held.clear();
            }
            let one = held.last().map(|last| iteration.update / last);
            let two = (held.len() >= 2).then(|| (iteration.update / held[held.len() - 2]).sqrt());
            if rejected && iteration.update > 1e-8 {
                fresh += 1;
                let slow = match (one, two) {
                    (Some(one), Some(two)) => one >= 1.0 || two > 0.25,
                    (Some(one), None) => one > 0.25,
                    _ => false,
                };
                assert!(slow, "step {k}: factored afresh after contractions {one:?} (last) and {two:?} (mean of two)");
            } else if iteration.chord && one.is_some_and(|one| one > 0.25) {
                alternating += 1;
            }
            if !rejected {
                held.push(iteration.update);
            }
        }
    }
    // Slow single updates were accepted on their mean (the rule was exercised),
    // and the iteration still factors afresh where it must.
    assert!(alternating >= 20, "{alternating} slow updates accepted");
    assert!(
        fresh >= 5,
        "{fresh} fresh factorizations past a step's first iteration"
    );
}

/// A large mechanism's updates bottom out at the residual's rounding, above the
/// simplified iteration's target (SETTLED × the tolerance, 1e-14): a 32-link
/// pendulum's near 1e-12. Once a step has found that floor, later steps settle
/// at it instead of finding it again: before, each step took 2.2 iterations
/// after an update below 1e-10 (of 11.5 a step); now few may.
#[test]
fn steps_settle_at_the_rounding_an_earlier_step_found() {
    let steps = traced_steps(0.6);
    let (mut inside, mut reached) = (0, 0);
    for step in &steps {
        let updates: Vec<f64> = step.iter().map(|i| i.update).collect();
        inside += updates[..updates.len() - 1]
            .iter()
            .filter(|u| **u <= 1e-10)
            .count();
        reached += usize::from(updates.iter().any(|u| *u <= 1e-10));
    }
    // The iteration gets that far on many steps (the check is not vacuous).
    assert!(
        reached * 4 >= steps.len(),
        "{reached} of {} steps below 1e-10",
        steps.len()
    );
    let per_step = inside as f64 / steps.len() as f64;
    assert!(
        per_step <= 0.25,
        "{per_step:.2} iterations a step after an update below 1e-10"
    );
}

/// A batch asked of square steps is taken one step at a time: its plan holds the
/// stepwise buffer and two steps' systems, whatever the horizon (10^5 steps of the
/// 40-loop chain), where the general solver's batch holds every step's system.
#[test]
fn a_batch_of_square_steps_is_planned_at_what_it_holds() {
    use mbfg::forward::{DcIntegrators, Plan};
    let path = common::scene_path("benchmarks/n-fourbar-40.yaml");
    let model = Model::new(&Scene::load(path).unwrap()).unwrap();
    let mut options = ForwardOptions::new(Coordinates::Dependent, 1e-4, 10.0, Mode::Batch);
    let plan = Plan::new(&model, &options).unwrap();
    assert_eq!(plan.schedule, Schedule::Stepwise);
    let mib = plan.memory.streamed / (1024.0 * 1024.0);
    assert!(mib < 64.0, "{mib:.1} MiB streamed");
    options.t_end = 0.01;
    options.dc_integrators = DcIntegrators::Full;
    let general = Plan::new(&model, &options).unwrap();
    assert_eq!(general.schedule, Schedule::Batch);
    assert!(general.memory.streamed > 500.0 * 1024.0 * 1024.0);
}
