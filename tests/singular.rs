//! The parallelogram through its flat, singular configuration (scenes/hard/
//! parallelogram.yaml: exact motion θ = π/2 + 3t with the coupler horizontal, the
//! first flat point at t = π/6, where Φ_q loses a rank and the anti-parallelogram
//! branch crosses). In dependent coordinates the run must pass it on the
//! parallelogram branch; in independent coordinates (θ alone) the problem is
//! ill-posed there, and the run must stop ahead of it saying so (exit code 1 from the
//! CLI), never with a NaN.

use mbfg::forward::{simulate, Coordinates, ForwardOptions, RunSummary, Trajectory};
use mbfg::kinematics::{Watch, Watched};
use mbfg::smoother::Mode;
use mbfg::{Model, Scene};
use std::f64::consts::{FRAC_PI_2, PI};
use std::path::PathBuf;
use std::process::Command;
use std::sync::Arc;

const SCENE: &str = "scenes/hard/parallelogram.yaml";

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

fn load(scene: &str) -> Arc<Model> {
    Arc::new(Model::new(&Scene::load(root().join(scene)).unwrap()).unwrap())
}

fn parallelogram() -> Arc<Model> {
    load(SCENE)
}

fn run(coords: Coordinates, dt: f64, t_end: f64, mode: Mode) -> (Trajectory, RunSummary) {
    let opts = ForwardOptions::new(coords, dt, t_end, mode);
    simulate(parallelogram(), &opts, &mut |_, _| {}).unwrap()
}

/// max |θ − (π/2 + 3t)| and max |y₁ − y₂| over a trajectory (q = P1.x, P1.y, P2.x,
/// P2.y, θ), after checking every value is finite.
fn errors(tr: &Trajectory) -> (f64, f64) {
    assert!(
        tr.q.iter()
            .chain(&tr.dq)
            .chain(&tr.ddq)
            .all(|v| v.is_finite()),
        "a value that is not finite"
    );
    let (mut theta, mut branch) = (0.0f64, 0.0f64);
    for k in 0..tr.len() {
        let q = tr.q_at(k);
        theta = theta.max((q[4] - (FRAC_PI_2 + 3.0 * tr.t[k])).abs());
        branch = branch.max((q[1] - q[3]).abs());
    }
    (theta, branch)
}

/// Dependent coordinates, Δt = 0.1 ms, N_w = 1, through the first flat point
/// (t = π/6 ≈ 0.5236 s; the steps at t = 0.5236 s and the ones around it come within
/// 4e-6 rad of it): every step converges, the branch is kept, θ follows the exact
/// motion, energy and constraints hold.
#[test]
fn dependent_coordinates_pass_the_flat_point_on_the_parallelogram_branch() {
    let (tr, s) = run(Coordinates::Dependent, 1e-4, 0.7, Mode::FixedLag(1));
    assert!(s.failures.is_empty(), "{}", s.failures[0].message());
    assert_eq!(tr.len(), 7001);
    let (theta, branch) = errors(&tr);
    assert!(tr.q_at(tr.len() - 1)[4] > PI + 0.5, "past the flat point");
    assert!(branch <= 1e-6, "|y₁ − y₂| = {branch:e}: left the branch");
    assert!(theta <= 1e-3, "|θ − (π/2 + 3t)| = {theta:e}");
    let energy = s.energy_drift.unwrap();
    assert!(energy <= 1e-3, "energy error {energy:e} J");
    assert!(s.worst_phi <= 1e-9, "|Φ| = {:e}", s.worst_phi);
    // What the run achieves today (θ 4e-8 rad, y₁ − y₂ 8e-13 m, 5e-7 J), with margin:
    // a regression shows long before the criteria above are at stake.
    assert!(
        theta <= 1e-6 && branch <= 1e-10 && energy <= 5e-6,
        "{theta:e} {branch:e} {energy:e}"
    );
}

/// The same at Δt = 1 ms with a two-step window and in batch.
#[test]
fn dependent_coordinates_pass_it_with_a_window_and_in_batch() {
    for mode in [Mode::FixedLag(2), Mode::Batch] {
        let (tr, s) = run(Coordinates::Dependent, 1e-3, 0.7, mode);
        assert!(
            s.failures.is_empty(),
            "{mode:?}: {}",
            s.failures[0].message()
        );
        let (theta, branch) = errors(&tr);
        assert!(
            branch <= 1e-6 && theta <= 1e-3,
            "{mode:?}: {theta:e} {branch:e}"
        );
        assert!(
            s.energy_drift.unwrap() <= 1e-3 && s.worst_phi <= 1e-9,
            "{mode:?}"
        );
    }
}

/// Fine steps come closer to the flat points, where the nearly dependent equations'
/// damped correction takes over: DC at 0.1 ms through the first four (t = 3.665 s
/// the last) and at 0.01 ms through the first two (t = 1.571 s), on the branch.
#[test]
fn dependent_coordinates_pass_several_flat_points_at_fine_steps() {
    for (dt, t_end) in [(1e-4, 3.7), (1e-5, 1.6)] {
        let (tr, s) = run(Coordinates::Dependent, dt, t_end, Mode::FixedLag(1));
        assert!(
            s.failures.is_empty(),
            "dt = {dt}: {}",
            s.failures[0].message()
        );
        let (theta, branch) = errors(&tr);
        assert!(
            branch <= 1e-6 && theta <= 1e-3,
            "dt = {dt}: {theta:e} {branch:e}"
        );
        assert!(
            s.energy_drift.unwrap() <= 1e-3 && s.worst_phi <= 1e-9,
            "dt = {dt}"
        );
    }
}

/// A chain of ten square four-bar loops (scenes/benchmarks/n-fourbar-10.yaml) in
/// dependent coordinates at 0.1 ms, through its flat configuration at t ≈ 0.72 s:
/// a step lands a few 1e-6 (σ_r/σ₁) from it, where the velocity constraints' pivot is
/// far below the damping's threshold. Their residual there (4e-8) is real, not
/// round-off, and is corrected exactly; damped, it stalled the solve at step 7203.
#[test]
fn dependent_coordinates_pass_the_flat_point_of_ten_loops_at_a_fine_step() {
    let model = load("scenes/benchmarks/n-fourbar-10.yaml");
    let opts = ForwardOptions::new(Coordinates::Dependent, 1e-4, 0.75, Mode::FixedLag(1));
    let (_, s) = simulate(model, &opts, &mut |_, _| {}).unwrap();
    assert!(s.failures.is_empty(), "{}", s.failures[0].message());
    assert!(s.worst_phi <= 1e-9, "|Φ| = {:e}", s.worst_phi);
}

/// An open chain has no singular configuration: the mixed-scale triple pendulum
/// (1 m, 0.1 m and 1 cm links, absolute angles independent) runs in IC at 1 ms
/// without naming one. With each column of Φ_q scaled apart, the 1 cm link placed
/// level gave its tip's x column a scale of 0.02 and its y column 1, and a turn of
/// 0.2 rad read as a rank loss at t ≈ 2.7 ms.
#[test]
fn an_open_chain_of_mixed_scales_names_no_singular_configuration() {
    let model = load("scenes/hard/mixed-scale-pendulum.yaml");
    for mode in [Mode::FixedLag(1), Mode::Batch] {
        let opts = ForwardOptions::new(Coordinates::Independent, 1e-3, 0.5, mode);
        let (_, s) = simulate(model.clone(), &opts, &mut |_, _| {}).unwrap();
        assert!(
            s.failures.is_empty(),
            "{mode:?}: {}",
            s.failures[0].message()
        );
        assert!(s.reselections.is_empty(), "{mode:?}: {:?}", s.reselections);
    }
}

/// A chain of N square loops loses N ranks at once at its flat configuration, and
/// the stop says so: with N = 40, 40 of the 82 dependent coordinates' ranks. Their
/// singular values fall at different rates, and a count of those already small at
/// the stop found 5.
#[test]
fn the_stop_names_every_rank_a_chain_of_loops_loses() {
    let model = load("scenes/benchmarks/n-fourbar-40.yaml");
    let opts = ForwardOptions::new(Coordinates::Independent, 1e-2, 1.0, Mode::FixedLag(1));
    let (_, s) = simulate(model, &opts, &mut |_, _| {}).unwrap();
    let c = s.failures[0].singular.as_ref().expect("an ill-posed stop");
    assert_eq!(
        (c.rank, c.full_rank),
        (42, 82),
        "{}",
        s.failures[0].message()
    );
    assert!((c.t_singular - 0.722).abs() < 2e-3, "{}", c.t_singular);
    let message = s.failures[0].message();
    assert!(message.contains("(rank 42 < 82)"), "{message}");
}

/// Independent coordinates: the run stops a few milliseconds before the flat
/// point, with the singular configuration located to within a step of π/6, and the
/// steps before it sound.
#[test]
fn independent_coordinates_stop_ahead_of_the_flat_point_and_say_why() {
    for dt in [1e-3, 1e-4, 1e-5] {
        let (tr, s) = run(Coordinates::Independent, dt, 1.0, Mode::FixedLag(1));
        assert_eq!(s.failures.len(), 1, "Δt = {dt}");
        let f = &s.failures[0];
        let c = f.singular.as_ref().expect("a singular configuration");
        assert!(
            (c.t_singular - PI / 6.0).abs() <= dt,
            "Δt = {dt}: located at t = {}",
            c.t_singular
        );
        assert!(
            f.t < PI / 6.0 && f.t > PI / 6.0 - 0.01,
            "Δt = {dt}: stopped at {}",
            f.t
        );
        assert_eq!((c.rank, c.full_rank), (3, 4));
        assert_eq!(c.independent, ["theta"]);
        assert_eq!(tr.len(), f.step, "the steps before the stop are kept");
        let (theta, branch) = errors(&tr);
        assert!(
            theta <= 1e-3 && branch <= 1e-6,
            "Δt = {dt}: {theta:e} {branch:e}"
        );
        assert!(s.worst_phi <= 1e-9);
    }
}

/// The CLI: exit code 1, one line naming the cause, the time, the coordinates and
/// the step, and the steps before the stop kept in `<out>.partial.csv` without a NaN.
#[test]
fn the_cli_reports_the_ill_posed_configuration_with_exit_code_1() {
    let csv = std::env::temp_dir().join(format!("mbfg-singular-{}.csv", std::process::id()));
    let out = Command::new(env!("CARGO_BIN_EXE_mbfg"))
        .args([
            "simulate",
            SCENE,
            "--coords",
            "ic",
            "--dt",
            "0.001",
            "--t-end",
            "5",
            "--out",
            csv.to_str().unwrap(),
        ])
        .current_dir(root())
        .output()
        .expect("run mbfg");
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{err}");
    let line = err.trim_end();
    assert!(
        !line.contains('\n') && line.starts_with("error: "),
        "{line}"
    );
    let located: f64 = line
        .split("singular configuration at t ≈ ")
        .nth(1)
        .and_then(|rest| rest.split(' ').next())
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("no location in: {line}"));
    assert!((located - PI / 6.0).abs() <= 1e-3, "located at {located}");
    assert!(
        line.contains(
            "independent coordinates [theta] stop determining [P1.x, P1.y, P2.x, P2.y] (rank 3 < 4)"
        ),
        "{line}"
    );
    // Stopped within 2 ms (6e-3 rad of the crank) ahead of the flat point, with the
    // steps before it kept.
    let step: usize = line
        .split("stopped at step ")
        .nth(1)
        .and_then(|rest| rest.split(' ').next())
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("no step in: {line}"));
    assert!(
        (521..=523).contains(&step),
        "stopped at step {step}: {line}"
    );
    for part in [format!("(t = 0.{step} s)"), format!("{step} steps kept in")] {
        assert!(line.contains(&part), "missing «{part}» in: {line}");
    }
    let summary = String::from_utf8_lossy(&out.stdout);
    assert!(
        summary.contains("stopped ahead of a singular configuration"),
        "{summary}"
    );
    // The steps before the stop sit beside the file asked for, which is not written.
    let partial = csv.with_file_name(format!("mbfg-singular-{}.partial.csv", std::process::id()));
    assert!(!csv.exists(), "{} must not be written", csv.display());
    assert!(
        line.chars().count() <= 300,
        "{} characters: {line}",
        line.chars().count()
    );
    let text = std::fs::read_to_string(&partial).unwrap();
    std::fs::remove_file(&partial).ok();
    assert_eq!(text.lines().count(), 1 + step);
    assert!(!text.to_lowercase().contains("nan") && !text.contains("inf"));
}

/// Pick-and-place in independent coordinates: its motor angles stop determining the
/// other coordinates at t ≈ 0.33 s while Φ_q keeps its rank, so the run switches to
/// better-conditioned coordinates ahead of it (and again where those degrade),
/// reports each switch, and passes; its RMSE against the reference is held by
/// tests/data/rmse-bounds.csv.
#[test]
fn independent_coordinates_reselect_themselves_where_the_mechanism_is_regular() {
    let path = root().join("scenes/pick-and-place.yaml");
    let model = Arc::new(Model::new(&Scene::load(path).unwrap()).unwrap());
    for mode in [Mode::FixedLag(1), Mode::FixedLag(5), Mode::Batch] {
        let opts = ForwardOptions::new(Coordinates::Independent, 1e-3, 1.0, mode);
        let (tr, s) = simulate(model.clone(), &opts, &mut |_, _| {}).unwrap();
        assert!(
            s.failures.is_empty(),
            "{mode:?}: {}",
            s.failures[0].message()
        );
        assert_eq!(tr.len(), 1001);
        let first = s.reselections.first().expect("a switch");
        assert_eq!(first.from, ["motor1", "motor2"]);
        assert!(first.t < 0.33, "{mode:?}: switched at {}", first.t);
        assert!(s
            .reselections
            .iter()
            .all(|r| r.to != r.from && r.to.len() == 2));
        assert!(s.worst_phi <= 1e-9 && s.worst_velocity_constraint <= 1e-9);
    }
}

/// A long chain reads a small distance to rank loss everywhere (about 0.6/k for k
/// links: 4.7e-3 for 128), below the threshold where a run in independent
/// coordinates searches for better ones. That search tries every one-coordinate
/// swap (32768 per round at 128 links, each a Cholesky of 256 equations) and ran
/// for hours before it was bounded; the run must now go on, with no failure and
/// no singular configuration named.
#[test]
fn a_long_chain_in_independent_coordinates_is_not_taken_for_a_singular_one() {
    let model = load("scenes/scale/n-pendulum-128.yaml");
    assert_eq!(model.independent.len(), 128);
    let opts = ForwardOptions::new(Coordinates::Independent, 1e-3, 2e-3, Mode::FixedLag(1));
    let (tr, summary) = simulate(model, &opts, &mut |_, _| {}).unwrap();
    assert!(summary.failures.is_empty(), "{:?}", summary.failures);
    assert_eq!(tr.t.len(), 3);
    assert!(tr.q.iter().all(|v| v.is_finite()));
}

/// Where the declared independent coordinate runs out (a crank-rocker's rocker angle
/// at its extreme), the run switches to the crank angle, which follows the crank
/// through every turn, once, and then matches the run that declared it from the
/// start; before, it took a point's x or y, which lose rank twice a turn, and switched
/// 29 times in 3 s, ending 6.7e-2 m from IDA (now 1.5e-3 m).
#[test]
fn a_switch_of_independent_coordinates_prefers_an_angle() {
    let opts = ForwardOptions::new(Coordinates::Independent, 1e-3, 3.0, Mode::FixedLag(1));
    let (tr, s) = simulate(
        load("tests/data/crank-rocker-phi.yaml"),
        &opts,
        &mut |_, _| {},
    )
    .unwrap();
    assert!(s.failures.is_empty());
    assert_eq!(s.reselections.len(), 1, "{:?}", s.reselections);
    assert_eq!(s.reselections[0].to, ["theta"]);
    let (reference, _) = simulate(
        load("scenes/driven/dc-motor-crank-rocker.yaml"),
        &opts,
        &mut |_, _| {},
    )
    .unwrap();
    // The points' coordinates come first in both (P1.x, P1.y, P2.x, P2.y), then θ, φ
    // here and θ there.
    let (n, m) = (6, 5);
    let worst = (0..tr.len())
        .flat_map(|k| (0..4).map(move |i| (k, i)))
        .map(|(k, i)| (tr.q[k * n + i] - reference.q[k * m + i]).abs())
        .fold(0.0f64, f64::max);
    assert!(worst <= 5e-3, "{worst} m from the run with θ independent");
}

/// The watch alone, fed the positions of a DC run (which does not watch):
/// the parallelogram's own coordinate θ stops determining the others at its
/// flat configuration (t = π/6), where Φ_q loses a rank, so the watch stops
/// ahead of it; pick-and-place's motor angles stop determining the others at
/// t ≈ 0.33 s while Φ_q keeps its rank, so it switches sets ahead of that.
#[test]
fn a_watch_stops_ahead_of_a_rank_loss_and_switches_ahead_of_a_poor_set() {
    let watched = |scene: &str, t_end: f64| -> (Watched, f64) {
        let path = root().join("scenes").join(scene);
        let model = Arc::new(Model::new(&Scene::load(path).unwrap()).unwrap());
        let options = ForwardOptions::new(Coordinates::Dependent, 1e-3, t_end, Mode::FixedLag(1));
        let (run, _) = simulate(model.clone(), &options, &mut |_, _| {}).unwrap();
        let n = model.n();
        let q = |k: usize| &run.q[k * n..(k + 1) * n];
        let mut watch = Watch::new(&model, &model.independent, model.initial.q.as_slice());
        for k in 0..run.len() {
            let verdict = watch.observe(&model, k, run.t[k], q(k.max(1) - 1), q(k));
            if verdict != Watched::Continue {
                return (verdict, run.t[k]);
            }
        }
        (Watched::Continue, t_end)
    };
    let (verdict, t) = watched("hard/parallelogram.yaml", 0.6);
    let flat = std::f64::consts::PI / 6.0;
    match verdict {
        Watched::Stop(singular) => {
            assert!(t < flat && t > flat - 0.05, "stopped at t = {t}");
            assert!(singular.rank < singular.full_rank, "{singular:?}");
            assert!((singular.t_singular - flat).abs() < 0.05, "{singular:?}");
        }
        other => panic!("{other:?} at t = {t}"),
    }
    let (verdict, t) = watched("pick-and-place.yaml", 0.4);
    assert!(
        matches!(&verdict, Watched::Reselect(set) if set.len() == 2),
        "{verdict:?}"
    );
    assert!(t < 0.33, "switched at t = {t}");
}

/// An error-controlled run in independent coordinates watches them as a run of fixed
/// steps does: the crank-rocker whose declared rocker angle runs out switches to the
/// crank angle once and matches the run that declared it from the start (without
/// the watch, at rtol 1e-7, its steps shrank to the smallest size at the rocker's
/// extreme: 1.9 million steps, 53 s, 0.11 m off); the 5-loop chain stops ahead of
/// its flat configuration with the singular configuration named (it used to pass it
/// and fail at the next one, its message blaming an effect).
#[test]
fn an_error_controlled_run_watches_its_independent_coordinates() {
    use mbfg::forward::{Integrator, Tolerance};
    let tolerant = |t_end: f64, rtol: f64| {
        let mut o = ForwardOptions::new(Coordinates::Independent, 1e-3, t_end, Mode::FixedLag(1));
        o.integrator = Integrator::HermiteSimpson;
        o.tolerance = Some(Tolerance::new(rtol, None).unwrap());
        o
    };
    let (tr, s) = simulate(
        load("tests/data/crank-rocker-phi.yaml"),
        &tolerant(3.0, 1e-7),
        &mut |_, _| {},
    )
    .unwrap();
    assert!(s.failures.is_empty(), "{}", s.failures[0].message());
    assert_eq!(s.reselections.len(), 1, "{:?}", s.reselections);
    assert_eq!(s.reselections[0].to, ["theta"]);
    let mut fine = ForwardOptions::new(Coordinates::Independent, 1e-4, 3.0, Mode::FixedLag(1));
    fine.integrator = Integrator::HermiteSimpson;
    let (reference, _) = simulate(
        load("scenes/driven/dc-motor-crank-rocker.yaml"),
        &fine,
        &mut |_, _| {},
    )
    .unwrap();
    let (n, m) = (6, 5);
    let worst = (0..tr.len())
        .flat_map(|k| (0..4).map(move |i| (k, i)))
        .map(|(k, i)| (tr.q[k * n + i] - reference.q[10 * k * m + i]).abs())
        .fold(0.0f64, f64::max);
    assert!(worst <= 1e-5, "{worst} m from the run with θ independent");

    let (tr, s) = simulate(
        load("scenes/benchmarks/n-fourbar-5.yaml"),
        &tolerant(5.0, 1e-5),
        &mut |_, _| {},
    )
    .unwrap();
    let f = s
        .failures
        .first()
        .expect("a stop ahead of the flat configuration");
    assert!(f.singular.is_some(), "{}", f.message());
    assert!(
        f.message().contains("singular configuration"),
        "{}",
        f.message()
    );
    assert!(
        tr.t.last().unwrap() < &0.722,
        "rows up to {}",
        tr.t.last().unwrap()
    );
}

/// A singular configuration no shipped scene has: the isosceles slider-crank, whose
/// slider reaches the crank's pivot twice a turn (a bifurcation onto x_S = 0). In DC,
/// with fixed steps and with error-controlled ones, both integrators, the run passes
/// every one on the branch x_S = 2 r cos θ, counts them, and keeps its energy across
/// them.
#[test]
fn the_isosceles_slider_crank_keeps_its_branch_at_the_pivot() {
    use mbfg::forward::{Integrator, Tolerance};
    let model = load("tests/data/isosceles-slider-crank.yaml");
    let col = |name: &str| model.names.iter().position(|c| c == name).unwrap();
    let (theta, sx) = (col("theta"), col("S.x"));
    for integrator in [Integrator::Trapezoidal, Integrator::HermiteSimpson] {
        for rtol in [None, Some(1e-6)] {
            let mut o = ForwardOptions::new(Coordinates::Dependent, 1e-3, 5.0, Mode::FixedLag(1));
            o.integrator = integrator;
            o.tolerance = rtol.map(|r| Tolerance::new(r, None).unwrap());
            let (tr, s) = simulate(model.clone(), &o, &mut |_, _| {}).unwrap();
            let what = format!("{} rtol {rtol:?}", integrator.name());
            assert!(s.failures.is_empty(), "{what}: {}", s.failures[0].message());
            assert_eq!(tr.len(), 5001, "{what}");
            let n = model.n();
            let off = (0..tr.len())
                .map(|k| (tr.q[k * n + sx] - 2.0 * tr.q[k * n + theta].cos()).abs())
                .fold(0.0f64, f64::max);
            let turned = tr.q[(tr.len() - 1) * n + theta] - tr.q[theta];
            println!(
                "{what}: off the branch {off:.1e} m, turned {turned:.2} rad, {:?}",
                s.passages
            );
            assert!(off <= 1e-6, "{what}: {off:e} m off the branch");
            // From π/3 at about 3 rad/s: past 5 upright positions (π/2 + kπ).
            assert!(s.passages.count >= 5, "{what}: {:?}", s.passages);
            assert!(turned > 5.0 * PI - PI / 3.0, "{what}: turned {turned}");
            let jump = s.passages.energy_jump.map_or(0.0, |(j, _)| j);
            assert!(jump <= 1e-6, "{what}: energy moved {jump:e} J at a passage");
        }
    }
}
