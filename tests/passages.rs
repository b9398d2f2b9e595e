//! The N four-bar (IFToMM A02, scenes/benchmarks/n-fourbar-*.yaml) through its flat
//! configurations, where Φ_q loses N ranks at once: in dependent coordinates the
//! square steps pass them on the parallelogram branch, with the trapezoidal rule's
//! order. The reference is the exact motion on that branch, the one-degree-of-freedom
//! ODE I θ̈ = −c g cos θ (I = (N+1)/3 + N, c = (N+1)/2 + N; docs/benchmarks.md).

mod common;

use common::scene_path;
use mbfg::forward::{simulate, Coordinates, ForwardOptions, Integrator, RunSummary, Trajectory};
use mbfg::smoother::Mode;
use mbfg::{Model, Scene};
use std::sync::Arc;

fn run(loops: usize, dt: f64, t_end: f64) -> (Trajectory, RunSummary) {
    run_with(loops, Integrator::Trapezoidal, dt, t_end)
}

fn run_with(loops: usize, integrator: Integrator, dt: f64, t_end: f64) -> (Trajectory, RunSummary) {
    let folder = match loops {
        1 | 5 | 10 | 40 => "benchmarks",
        _ => "scale",
    };
    let path = scene_path(&format!("{folder}/n-fourbar-{loops}.yaml"));
    let model = Arc::new(Model::new(&Scene::load(path).unwrap()).unwrap());
    let mut options = ForwardOptions::new(Coordinates::Dependent, dt, t_end, Mode::FixedLag(1));
    options.integrator = integrator;
    let (trajectory, summary) = simulate(model, &options, &mut |_, _| {}).unwrap();
    assert!(
        summary.failures.is_empty(),
        "N = {loops}, dt = {dt}: {}",
        summary.failures[0].message()
    );
    (trajectory, summary)
}

/// θ(t) on the parallelogram branch at t = 0, every, 2·every, …, up to t_end: RK4 on
/// the one-degree-of-freedom ODE at a step of every/100.
fn exact_theta(loops: usize, every: f64, t_end: f64) -> Vec<f64> {
    let mut state = (std::f64::consts::FRAC_PI_2, -1.0);
    let rows = (t_end / every).round() as usize + 1;
    let mut out = Vec::with_capacity(rows);
    for row in 0..rows {
        out.push(state.0);
        if row + 1 == rows {
            break;
        }
        state = on_branch(loops, state, every / 100.0, 100);
    }
    out
}

/// (θ, θ̇) after `steps` RK4 steps of `h` on the branch's ODE I θ̈ = −c g cos θ.
fn on_branch(loops: usize, (mut theta, mut omega): (f64, f64), h: f64, steps: usize) -> (f64, f64) {
    let n = loops as f64;
    let (inertia, c) = ((n + 1.0) / 3.0 + n, (n + 1.0) / 2.0 + n);
    let accel = |theta: f64| -c * 9.81 * theta.cos() / inertia;
    for _ in 0..steps {
        let (k1x, k1v) = (omega, accel(theta));
        let (k2x, k2v) = (omega + 0.5 * h * k1v, accel(theta + 0.5 * h * k1x));
        let (k3x, k3v) = (omega + 0.5 * h * k2v, accel(theta + 0.5 * h * k2x));
        let (k4x, k4v) = (omega + h * k3v, accel(theta + h * k3x));
        theta += h / 6.0 * (k1x + 2.0 * k2x + 2.0 * k3x + k4x);
        omega += h / 6.0 * (k1v + 2.0 * k2v + 2.0 * k3v + k4v);
    }
    (theta, omega)
}

/// The largest spread of the loops' heights a run on the parallelogram branch may
/// show, given its B0 error: to rounding with exact projections (the trapezoidal
/// rule's); with Hermite–Simpson's, damped near a rank loss, the lost direction
/// is left to the integrators over the steps that cross its zone, and the loops
/// part by a small fraction of the run's own error (1e-7 m at 25 ms, where B0 is
/// 2e-3 m off). A switch of branch parts them by about a link's length.
fn branch_tolerance(integrator: Integrator, b0: f64) -> f64 {
    match integrator {
        Integrator::HermiteSimpson => 1e-9f64.max(1e-2 * b0),
        _ => 1e-9,
    }
}

/// The benchmark chain of `loops` loops (1 or 40) over `t_end` with rows every
/// `every` s, Hermite–Simpson, DC, with the tolerance `rtol` (= atol) on `scope`.
fn with_tolerance(
    loops: usize,
    every: f64,
    t_end: f64,
    rtol: f64,
    scope: mbfg::forward::ToleranceScope,
) -> (Trajectory, RunSummary) {
    let model = Arc::new(
        Model::new(
            &Scene::load(scene_path(&format!("benchmarks/n-fourbar-{loops}.yaml"))).unwrap(),
        )
        .unwrap(),
    );
    let mut options = ForwardOptions::new(Coordinates::Dependent, every, t_end, Mode::FixedLag(1));
    options.integrator = Integrator::HermiteSimpson;
    options.tolerance = Some(mbfg::forward::Tolerance::new(rtol, None).unwrap());
    options.tolerance_scope = scope;
    simulate(model, &options, &mut |_, _| {}).unwrap()
}

/// max |B0 − (cos θ, sin θ)| over the rows, and the largest spread of the points
/// B_i's heights (0 on the parallelogram branch).
fn errors(loops: usize, tr: &Trajectory, exact: &[f64]) -> (f64, f64) {
    let n = tr.names.len();
    let col = |name: &str| tr.names.iter().position(|c| c == name).unwrap();
    let (x0, y0) = (col("B0.x"), col("B0.y"));
    let heights: Vec<usize> = (0..=loops).map(|i| col(&format!("B{i}.y"))).collect();
    let (mut b0, mut branch) = (0.0f64, 0.0f64);
    assert_eq!(tr.len(), exact.len());
    for (k, theta) in exact.iter().enumerate() {
        let q = &tr.q[k * n..(k + 1) * n];
        b0 = b0.max((q[x0] - theta.cos()).hypot(q[y0] - theta.sin()));
        for &h in &heights {
            branch = branch.max((q[h] - q[y0]).abs());
        }
    }
    (b0, branch)
}

/// Five loops over 2 s, through two flat configurations (t ≈ 0.719 and 1.238 s):
/// on the branch, with an error that falls at second order as dt halves (it did not
/// fall when the steps near a flat configuration went to the regularized general
/// solver: 2.2e-4, 8.6e-2 and 9.5e-5 m at 1, 0.625 and 0.5 ms over 5 s).
#[test]
fn the_n_fourbar_passes_its_flat_configurations_at_second_order() {
    let t_end = 2.0;
    let mut last: Option<f64> = None;
    for dt in [2e-3, 1e-3, 5e-4] {
        let (tr, s) = run(5, dt, t_end);
        let (b0, branch) = errors(5, &tr, &exact_theta(5, dt, t_end));
        assert!(branch <= 1e-9, "dt = {dt}: off the branch by {branch:e} m");
        // (Damped projections leave a fraction of a step's drift in Φ near a
        // rank loss: 3e-12 at 4 ms.)
        assert!(s.worst_phi <= 1e-11, "dt = {dt}: |Φ| {:e}", s.worst_phi);
        if let Some(coarser) = last {
            let ratio = coarser / b0;
            assert!(
                (3.0..6.0).contains(&ratio),
                "dt = {dt}: B0 error {b0:e} m, {ratio:.2} times below dt = {}'s",
                2.0 * dt
            );
        }
        last = Some(b0);
    }
}

/// Hermite–Simpson's square steps pass the same flat configurations (at 0.5 ms the
/// general solver's steps stopped at the sixth, t = 3.194 s): on the branch, every
/// step square, and fourth order where the error is the steps' own (2.3e-9 → 1.4e-10 m
/// from 4 to 2 ms). Finer, the error is that of the steps that end next to a flat
/// configuration, solved only to their rounding amplified, not the integrator's: 5.8e-11
/// and 6.9e-10 m at 1 and 0.5 ms.
#[test]
fn hermite_simpson_passes_the_flat_configurations() {
    let t_end = 2.0;
    let mut errors_at = Vec::new();
    for dt in [4e-3, 2e-3, 1e-3, 5e-4] {
        let (tr, s) = run_with(5, Integrator::HermiteSimpson, dt, t_end);
        let (b0, branch) = errors(5, &tr, &exact_theta(5, dt, t_end));
        println!(
            "dt = {dt}: B0 {b0:.3e} m, branch {branch:.1e} m, {} passages",
            s.passages.count
        );
        assert_eq!(s.passages.count, 2, "dt = {dt}");
        assert_eq!(
            (s.square_steps, s.general_steps),
            (tr.len(), 0),
            "dt = {dt}"
        );
        assert!(branch <= 1e-9, "dt = {dt}: off the branch by {branch:e} m");
        // (Damped projections leave a fraction of a step's drift in Φ near a
        // rank loss: 3e-12 at 4 ms.)
        assert!(s.worst_phi <= 1e-11, "dt = {dt}: |Φ| {:e}", s.worst_phi);
        assert!(b0 <= 1e-8, "dt = {dt}: B0 error {b0:e} m");
        errors_at.push(b0);
    }
    let ratio = errors_at[0] / errors_at[1];
    assert!(
        ratio >= 12.0,
        "B0 error {:e} m at 4 ms, {:e} m at 2 ms: {ratio:.1} times",
        errors_at[0],
        errors_at[1]
    );
}

/// One loop with Hermite–Simpson: at 0.5 ms the step ending at t = 0.7085 s lands
/// at s = 2.1e-4 from the flat configuration. With exact projections its Newton
/// iteration reached the rounding of its residual with updates of 1e-5 still
/// moving the loop's lost direction: the energy jumped by 1.3e-7 J there (and by
/// 5e-9 to 9e-9 J at a passage once such steps were stepped over). Near a rank
/// loss the projections are damped: every landing is resolved, and the energy
/// moves at a passage by what a regular step's error does.
#[test]
fn a_hermite_simpson_landing_next_to_a_rank_loss_is_resolved() {
    for dt in [5e-4, 2.5e-4, 1e-4] {
        let (tr, s) = run_with(1, Integrator::HermiteSimpson, dt, 2.0);
        let (b0, branch) = errors(1, &tr, &exact_theta(1, dt, 2.0));
        let (jump, at) = s.passages.energy_jump.unwrap();
        println!(
            "dt = {dt}: B0 {b0:.2e} m, branch {branch:.1e} m, energy jump {jump:.2e} J at {at} s"
        );
        assert_eq!(s.passages.count, 2, "dt = {dt}");
        assert!(branch <= 1e-9, "dt = {dt}: off the branch by {branch:e} m");
        assert!(
            jump <= 1e-12,
            "dt = {dt}: the energy jumps by {jump:e} J at a passage (t = {at} s)"
        );
        assert!(b0 <= 1e-11, "dt = {dt}: B0 error {b0:e} m");
    }
}

/// Below 2.5 ms Hermite–Simpson's error on the short chains rested on a floor of
/// 1e-8 to 1e-6 m over 20 s that did not fall with dt (two loops: 8.6e-7 m at
/// 1 ms, 1.1e-6 m at 0.5 ms): the rounding of Φ at the landings next to each
/// passage, amplified through the exact projections. Damped, the error falls at
/// fourth order to 1e-10 m.
#[test]
fn hermite_simpson_falls_below_the_floor_of_exact_projections() {
    let (loops, t_end) = (2, 20.0);
    let mut errors_at = Vec::new();
    for dt in [2.5e-3, 1.25e-3, 1e-3, 5e-4] {
        let (tr, s) = run_with(loops, Integrator::HermiteSimpson, dt, t_end);
        let (b0, branch) = errors(loops, &tr, &exact_theta(loops, dt, t_end));
        println!(
            "dt = {dt}: B0 {b0:.2e} m, branch {branch:.1e} m, {} passages",
            s.passages.count
        );
        assert_eq!(s.passages.count, 20, "dt = {dt}");
        assert!(branch <= 1e-9, "dt = {dt}: off the branch by {branch:e} m");
        errors_at.push(b0);
    }
    assert!(
        errors_at[0] / errors_at[1] >= 14.0,
        "2.5 → 1.25 ms: {errors_at:?}"
    );
    assert!(errors_at[2] <= 1e-9, "1 ms: {errors_at:?}");
    assert!(errors_at[3] <= 3e-10, "0.5 ms: {errors_at:?}");
}

/// Where one step crosses the whole zone of a rank loss, a step that lands in it
/// unresolved stands: its own error outweighs the landing's rounding, and a longer
/// step over it errs more. (Held to its resolution, 20 loops at 25 ms over 20 s
/// ended 9.2e-2 m off instead of 1.5e-3 m.)
#[test]
fn a_coarse_hermite_simpson_step_is_not_stepped_over_for_its_resolution() {
    let (loops, dt, t_end) = (20, 0.025, 20.0);
    let (tr, s) = run_with(loops, Integrator::HermiteSimpson, dt, t_end);
    let (b0, branch) = errors(loops, &tr, &exact_theta(loops, dt, t_end));
    println!("B0 {b0:.2e} m, branch {branch:.1e} m");
    assert_eq!(s.passages.count, 20);
    let tolerated = branch_tolerance(Integrator::HermiteSimpson, b0);
    assert!(branch <= tolerated, "off the branch by {branch:e} m");
    assert!(b0 <= 3e-3, "B0 error {b0:e} m");
}

/// The rows a Hermite–Simpson step over spans take q̇ from the quintic through its
/// ends, whose q and q̇ agree to the rule's order: they hold Φ_q q̇ = 0 to 1e-11.
/// (The cubic through the ends' q̇ and q̈, with q̈ solved next to the rank loss,
/// left 1.6e-8 on five loops at 2.5 ms.)
#[test]
fn the_rows_of_a_hermite_simpson_step_over_hold_the_velocity_constraints() {
    for dt in [2.5e-3, 5e-4] {
        let (_, s) = run_with(5, Integrator::HermiteSimpson, dt, 20.0);
        let worst = s.passages.worst_velocity_constraint;
        println!(
            "dt = {dt}: {} passages, |Φq q̇| {worst:.2e}",
            s.passages.count
        );
        assert!(
            s.passages.count >= 20,
            "dt = {dt}: {} passages",
            s.passages.count
        );
        assert!(
            worst <= 1e-10,
            "dt = {dt}: |Φq q̇| {worst:e} around a passage"
        );
    }
}

/// The short chains' Hermite–Simpson error through their passages. Which steps are
/// stepped over is decided by the rows nearest a rank loss, (max (G⁻¹)ᵢᵢ)^(−1/2): s =
/// (tr G⁻¹)^(−1/2) adds up every loop that loses a rank, so a threshold on it that
/// stepped over the 40-loop chain's passages let the 1-loop chain's steps end 5e-5
/// from its flat configuration, where each moved the energy by up to 1.5e-6 J. Over
/// 20 s at 0.625 ms the B0 error was then 1.2e-5, 4.8e-5 and 3.5e-7 m for N = 1, 2
/// and 5; now 1.3e-7, 3.3e-7 and 8.9e-9 m.
#[test]
fn hermite_simpson_keeps_its_accuracy_through_the_short_chains_passages() {
    let (dt, t_end) = (6.25e-4, 20.0);
    for loops in [1, 2, 5] {
        let (tr, s) = run_with(loops, Integrator::HermiteSimpson, dt, t_end);
        let (b0, branch) = errors(loops, &tr, &exact_theta(loops, dt, t_end));
        assert!(
            s.passages.count >= 20,
            "N = {loops}: {} passages",
            s.passages.count
        );
        assert!(
            branch <= 1e-9,
            "N = {loops}: off the branch by {branch:e} m"
        );
        assert!(b0 <= 1e-6, "N = {loops}: B0 error {b0:e} m over {t_end} s");
    }
}

/// A step that would end next to a flat configuration is replaced by the shortest
/// longer step whose end lies clear (and one back onto the grid): the passage errs
/// about as one step does, and the 40-loop chain's error over 20 s falls at fourth
/// order with dt. (Taken by 2Δt, 4Δt or 8Δt steps, a Hermite–Simpson step of that
/// length erring up to 8⁵ times one of Δt, it rose sevenfold from 8.33 to 6.25 ms:
/// 4.1e-6 → 3.0e-5 m.)
#[test]
fn a_passage_errs_about_as_one_step_does() {
    let (loops, t_end) = (40, 20.0);
    let mut last: Option<(f64, f64)> = None;
    for dt in [0.025 / 3.0, 6.25e-3, 5e-3] {
        let (tr, s) = run_with(loops, Integrator::HermiteSimpson, dt, t_end);
        let (b0, branch) = errors(loops, &tr, &exact_theta(loops, dt, t_end));
        println!("dt = {dt}: B0 {b0:.3e} m, {} passages", s.passages.count);
        assert_eq!(s.passages.count, 20, "dt = {dt}");
        let tolerated = branch_tolerance(Integrator::HermiteSimpson, b0);
        assert!(
            branch <= tolerated,
            "dt = {dt}: off the branch by {branch:e} m"
        );
        if let Some((coarser, error)) = last {
            // At least third order from one dt to the next.
            let floor = (coarser / dt).powi(3);
            assert!(
                error / b0 >= floor,
                "dt = {dt}: B0 error {b0:e} m, {:.2} times below dt = {coarser}'s {error:e} m \
                 (at least {floor:.2} expected)",
                error / b0
            );
        }
        last = Some((dt, b0));
    }
}

/// Every chain length passes every flat configuration at coarse and fine steps alike,
/// with both integrators: converged, on the branch, its error falling with dt.
#[test]
fn every_chain_passes_its_flat_configurations_at_every_step() {
    let t_end = 5.0;
    for loops in [1, 2, 5, 10, 20] {
        for integrator in [Integrator::Trapezoidal, Integrator::HermiteSimpson] {
            let mut last: Option<f64> = None;
            for dt in [0.025, 0.025 / 3.0, 2.5e-3] {
                let (tr, s) = run_with(loops, integrator, dt, t_end);
                let (b0, branch) = errors(loops, &tr, &exact_theta(loops, dt, t_end));
                let what = format!("N = {loops}, {integrator:?}, dt = {dt}");
                assert!(
                    s.passages.count >= 4,
                    "{what}: {} passages",
                    s.passages.count
                );
                let tolerated = branch_tolerance(integrator, b0);
                assert!(
                    branch <= tolerated,
                    "{what}: off the branch by {branch:e} m"
                );
                if let Some(coarser) = last {
                    assert!(
                        b0 < coarser,
                        "{what}: B0 error {b0:e} m, {coarser:e} m coarser"
                    );
                }
                last = Some(b0);
            }
        }
    }
}

/// At 0.1 ms the step ending at t = 0.7187 s lands 2.6e-5 rad from the first flat
/// configuration (s = 6e-6), where the step system is solved only to its rounding
/// amplified by ~1/s²: the energy jumped by 2.5e-5 J there and stayed off. Stepped
/// over, no step changes the energy by more than 1e-7 J (the regular steps: 5e-9).
#[test]
fn a_step_that_lands_next_to_a_flat_configuration_is_stepped_over() {
    let (loops, dt, t_end) = (5, 1e-4, 0.75);
    let (tr, _) = run(loops, dt, t_end);
    let (b0, branch) = errors(loops, &tr, &exact_theta(loops, dt, t_end));
    assert!(
        b0 <= 1e-7 && branch <= 1e-9,
        "B0 {b0:e} m, branch {branch:e} m"
    );
    // On the branch the energy is that of the one-degree-of-freedom motion.
    let n = tr.names.len();
    let theta = tr.names.iter().position(|c| c == "theta").unwrap();
    let l = loops as f64;
    let (inertia, c) = ((l + 1.0) / 3.0 + l, (l + 1.0) / 2.0 + l);
    let energy = |k: usize| {
        let (q, dq) = (tr.q[k * n + theta], tr.dq[k * n + theta]);
        0.5 * inertia * dq * dq + c * 9.81 * q.sin()
    };
    let (jump, at) = (1..tr.len())
        .map(|k| ((energy(k) - energy(k - 1)).abs(), tr.t[k]))
        .fold((0.0, 0.0), |a, b| if b.0 > a.0 { b } else { a });
    assert!(jump <= 1e-7, "the energy jumps by {jump:e} J at t = {at} s");
}

/// The summary says how many passages a run made and what they did; a coarse step's
/// energy jump at one is warned of, and `--strict` refuses it (nothing written).
#[test]
fn the_summary_counts_the_passages_and_strict_refuses_an_energy_jump() {
    let scene = scene_path("benchmarks/n-fourbar-5.yaml");
    let scene = scene.to_str().unwrap();
    let dir = common::scratch("passages", "summary");
    let out = dir.join("fine.csv");
    let fine = common::mbfg(&[
        "simulate",
        scene,
        "--dt",
        "1e-3",
        "--t-end",
        "2",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(fine.status.success(), "{}", common::stderr(&fine));
    let line = String::from_utf8_lossy(&fine.stdout).to_string();
    assert!(
        line.contains("2 passage(s) through a singular configuration (the first at t = 0.719 s)"),
        "{line}"
    );
    assert!(
        !common::stderr(&fine).contains("warning"),
        "{}",
        common::stderr(&fine)
    );
    let out = dir.join("coarse.csv");
    let coarse = [
        "simulate",
        scene,
        "--dt",
        "0.025",
        "--t-end",
        "2",
        "--out",
        out.to_str().unwrap(),
    ];
    let warned = common::mbfg(&coarse);
    assert!(warned.status.success(), "{}", common::stderr(&warned));
    assert!(
        common::stderr(&warned)
            .contains("across the passage through a singular configuration at t = 0.725 s"),
        "{}",
        common::stderr(&warned)
    );
    let refused = dir.join("refused.csv");
    let mut strict = coarse;
    strict[7] = refused.to_str().unwrap();
    let strict = common::mbfg(&[&strict[..], &["--strict"]].concat());
    assert!(!strict.status.success());
    assert!(
        common::stderr(&strict).contains("(--strict)"),
        "{}",
        common::stderr(&strict)
    );
    assert!(!refused.exists(), "--strict wrote {}", refused.display());
}

/// The 1-loop chain's B0 point with a tolerance over 20 s at 0.05 s rows: passing
/// near its separatrix every half turn, the motion turns the steps' energy errors
/// into a phase that drifts, so a tolerance on each step ends 600–1300 times off.
/// A tolerance on the run (the default) checks the rows against a run at a coarser
/// step tolerance and makes the run again at a tighter one: it lands within a
/// factor of 10 of the tolerance, and says what it estimated.
#[test]
fn a_tolerance_on_the_run_gives_its_accuracy_through_the_passages() {
    use mbfg::forward::ToleranceScope;
    let (loops, t_end, every) = (1, 20.0, 0.05);
    let exact = exact_theta(loops, every, t_end);
    for rtol in [1e-5, 1e-6] {
        let mut errors_by = Vec::new();
        for scope in [ToleranceScope::Steps, ToleranceScope::Run] {
            let (tr, s) = with_tolerance(loops, every, t_end, rtol, scope);
            assert!(s.failures.is_empty(), "rtol {rtol:e} {scope:?}");
            let (b0, _) = errors(loops, &tr, &exact);
            let c = s.error_control.as_ref().unwrap();
            println!(
                "rtol {rtol:.0e} {scope:?}: B0 {b0:.2e} m, check {:?}",
                c.check
            );
            if scope == ToleranceScope::Run {
                let check = c.check.as_ref().unwrap();
                assert!(check.step_rtols.len() >= 2, "{check:?}");
                assert!(check.estimated.unwrap() <= 1.0, "{check:?}");
                assert_eq!(c.tolerance.rtol, rtol);
            } else {
                assert_eq!(c.check, None);
            }
            errors_by.push(b0);
        }
        let (steps, run) = (errors_by[0], errors_by[1]);
        assert!(
            steps > 100.0 * rtol,
            "rtol {rtol:e}: steps' tolerance {steps:e} m"
        );
        assert!(
            run <= 10.0 * rtol && run >= 0.1 * rtol,
            "rtol {rtol:e}: B0 error {run:e} m with the run's tolerance"
        );
    }
}

/// At a tolerance below what the steps resolve next to a flat configuration, the
/// error estimate of a step with exact projections (the trapezoidal rule's) is the
/// noise of the solves there and no smaller step lowers it: the steps stop
/// shrinking at the smallest size, are kept and counted, and the run ends (it used
/// to take the smallest step again forever).
#[test]
fn a_tolerance_below_the_noise_of_a_passage_ends() {
    use mbfg::forward::{Tolerance, ToleranceScope};
    let model = Arc::new(
        Model::new(&Scene::load(scene_path("benchmarks/n-fourbar-1.yaml")).unwrap()).unwrap(),
    );
    let mut options = ForwardOptions::new(Coordinates::Dependent, 0.05, 0.8, Mode::FixedLag(1));
    options.integrator = Integrator::Trapezoidal;
    options.tolerance = Some(Tolerance::new(1e-9, None).unwrap());
    options.tolerance_scope = ToleranceScope::Steps;
    let (tr, s) = simulate(model, &options, &mut |_, _| {}).unwrap();
    assert!(s.failures.is_empty());
    assert_eq!(tr.len(), 17);
    let c = s.error_control.unwrap();
    assert!(c.at_floor > 0, "{c:?}");
    assert_eq!(c.damped, 0, "{c:?}");
}

/// Hermite–Simpson's error-controlled steps damp their projections next to a flat
/// configuration and keep the size that reached it, unestimated (the estimate
/// there reads q̈'s lost component): no step is kept at the smallest size, and a
/// tolerance on the run is met at 1e-10 over 20 s, where its steps' tolerance may
/// go down to 1e-12 (with exact projections the steps there shrank to the
/// smallest size and the run ended 370 times off, at the step tolerance of 1e-10
/// that the estimates' noise allowed).
#[test]
fn a_tight_tolerance_on_the_run_holds_through_the_passages() {
    let (loops, t_end, every, rtol) = (1, 20.0, 0.05, 1e-10);
    let exact = exact_theta(loops, every, t_end);
    let scope = mbfg::forward::ToleranceScope::Run;
    let (tr, s) = with_tolerance(loops, every, t_end, rtol, scope);
    assert!(s.failures.is_empty());
    let c = s.error_control.as_ref().unwrap();
    let check = c.check.as_ref().unwrap();
    assert!(c.damped > 0, "{c:?}");
    assert_eq!(c.at_floor, 0, "{c:?}");
    assert!(check.step_rtols.iter().any(|&r| r < 1e-10), "{check:?}");
    let (b0, _) = errors(loops, &tr, &exact);
    assert!(
        b0 <= 10.0 * rtol,
        "B0 error {b0:e} m at rtol {rtol:e}: {check:?}"
    );
}

/// An error-controlled run whose step ends next to a flat configuration is given the
/// interpolant of a longer step that clears it: the steps after it follow that long
/// step to its end at the same size, and the run goes on from its end, a state
/// solved. (Stepping on from an interpolant, whose q̈ is not the dynamics' and whose
/// q, q̇ hold the constraints only as the interpolant does, moved the energy by
/// 5e-8 J at a passage and left 40 loops 7.1e-9 m off after 5 s at rtol 1e-10.)
#[test]
fn an_error_controlled_run_goes_on_from_the_end_of_a_step_over() {
    let (loops, t_end, every) = (40, 5.0, 0.05);
    let scope = mbfg::forward::ToleranceScope::Steps;
    let (tr, s) = with_tolerance(loops, every, t_end, 1e-10, scope);
    assert!(s.failures.is_empty());
    let (b0, branch) = errors(loops, &tr, &exact_theta(loops, every, t_end));
    let (jump, at) = s.passages.energy_jump.unwrap();
    println!("B0 {b0:.2e} m, branch {branch:.1e} m, energy jump {jump:.2e} J at {at} s");
    assert!(b0 <= 3e-9, "B0 error {b0:e} m");
    assert!(
        jump <= 3e-8,
        "energy jump {jump:e} J at a passage (t = {at} s)"
    );
}

/// At a coarse tolerance the 40 loops' steps are set by the largest turn a body may
/// make over one step, not by the tolerance: a check run at a coarser tolerance
/// with the same bound took the same steps, agreed with the run, and the rows ended
/// 465 times the tolerance off, unwarned. The check run is coarser in the steps'
/// other bounds too.
#[test]
fn a_coarse_tolerance_is_checked_where_the_turn_sets_the_steps() {
    let (loops, t_end, every, rtol) = (40, 20.0, 0.05, 1e-3);
    let scope = mbfg::forward::ToleranceScope::Run;
    let (tr, s) = with_tolerance(loops, every, t_end, rtol, scope);
    assert!(s.failures.is_empty());
    let (b0, _) = errors(loops, &tr, &exact_theta(loops, every, t_end));
    let check = s.error_control.unwrap().check.unwrap();
    println!("B0 {b0:.2e} m, {check:?}");
    assert!(check.step_rtols.len() >= 2, "{check:?}");
    assert!(b0 <= 10.0 * rtol, "B0 error {b0:e} m at rtol {rtol:e}");
}
