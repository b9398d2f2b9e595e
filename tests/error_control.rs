//! Error-controlled steps (`--rtol`, `ForwardOptions::tolerance`): a tolerance gives
//! its accuracy (the RMSE against the committed reference within a factor of 10 of
//! the tolerance asked), the rows stay on the grid of dt, the summary says what the
//! control did, and bad input is refused with one line.

mod common;

use common::{mbfg, one_error_line, reference_rmse, scene_path, scratch, stderr};
use mbfg::forward::{
    simulate, Coordinates, ForwardOptions, Integrator, RunSummary, Tolerance, Trajectory,
};
use mbfg::smoother::Mode;
use mbfg::{Model, Scene};
use std::sync::Arc;

fn run(
    scene: &str,
    coords: Coordinates,
    integrator: Integrator,
    rtol: f64,
    t_end: f64,
) -> (Arc<Model>, Trajectory, RunSummary) {
    let model =
        Arc::new(Model::new(&Scene::load(scene_path(&format!("{scene}.yaml"))).unwrap()).unwrap());
    let mut options = ForwardOptions::new(coords, 1e-3, t_end, Mode::FixedLag(1));
    options.integrator = integrator;
    options.tolerance = Some(Tolerance::new(rtol, None).unwrap());
    let (tr, summary) = simulate(model.clone(), &options, &mut |_, _| {}).unwrap();
    assert!(
        summary.failures.is_empty(),
        "{scene} rtol {rtol:e}: {:?}",
        summary.failures.first()
    );
    (model, tr, summary)
}

/// The RMSE of the four-bar over 5 s lands within a factor of 10 of the tolerance,
/// with both integrators, in both coordinates, over several decades.
#[test]
fn a_tolerance_gives_its_accuracy_on_the_four_bar() {
    for (integrator, tolerances) in [
        (Integrator::HermiteSimpson, &[1e-3, 1e-6, 1e-9][..]),
        (Integrator::Trapezoidal, &[1e-3, 1e-5][..]),
    ] {
        for (scene, coords) in [
            ("fourbar", Coordinates::Dependent),
            ("fourbar-theta", Coordinates::Independent),
        ] {
            // (Each scene has its own reference: the same motion.)
            for &rtol in tolerances {
                let (model, tr, summary) = run(scene, coords, integrator, rtol, 5.0);
                let rmse = reference_rmse(&model, &tr, scene);
                let c = summary.error_control.as_ref().unwrap();
                println!(
                    "{scene} {} rtol {rtol:.0e}: RMSE {rmse:.2e} ({:.2} of it), {} steps, {} rejected",
                    integrator.name(),
                    rmse / rtol,
                    c.accepted,
                    c.rejected
                );
                assert!(
                    rmse <= 10.0 * rtol && rmse >= 0.1 * rtol,
                    "{scene} {coords:?} {} rtol {rtol:e}: RMSE {rmse:e}",
                    integrator.name()
                );
            }
        }
    }
}

/// A run that met no rank loss is made again below a step rtol of 1e-10 where its
/// check asks for it (the floor of 1e-10 is for the noise of solves next to a rank
/// loss): the slider-crank in IC and the double pendulum at 1e-10 ended 10.9 and 8.9
/// times the tolerance off when their runs stopped there.
#[test]
fn a_run_that_met_no_rank_loss_is_made_again_below_a_step_rtol_of_1e_10() {
    let rtol = 1e-10;
    for (scene, coords) in [
        ("slider-crank", Coordinates::Independent),
        ("double-pendulum", Coordinates::Dependent),
    ] {
        let (model, tr, summary) = run(scene, coords, Integrator::HermiteSimpson, rtol, 5.0);
        let rmse = reference_rmse(&model, &tr, scene);
        let c = summary.error_control.as_ref().unwrap();
        let check = c.check.as_ref().unwrap();
        println!(
            "{scene} {coords:?}: RMSE {rmse:.2e} ({:.2} of it), {check:?}",
            rmse / rtol
        );
        assert_eq!(summary.passages.count, 0);
        assert!(
            check.step_rtols.iter().any(|&r| r < 1e-10),
            "{scene}: {check:?}"
        );
        assert!(rmse <= 10.0 * rtol, "{scene} {coords:?}: RMSE {rmse:e}");
    }
}

/// A tighter tolerance takes more and smaller steps; the steps adapt to the motion
/// (the double pendulum's fast swings take steps many times smaller than its slow
/// ones), and the rows are at t = k·dt whatever the steps.
#[test]
fn steps_adapt_and_rows_stay_on_the_grid() {
    let (_, loose_tr, loose) = run(
        "double-pendulum",
        Coordinates::Dependent,
        Integrator::HermiteSimpson,
        1e-4,
        2.0,
    );
    let (_, _, tight) = run(
        "double-pendulum",
        Coordinates::Dependent,
        Integrator::HermiteSimpson,
        1e-8,
        2.0,
    );
    let (l, t) = (
        loose.error_control.as_ref().unwrap(),
        tight.error_control.as_ref().unwrap(),
    );
    assert!(t.accepted > 5 * l.accepted, "{l:?} {t:?}");
    assert!(t.largest < l.largest, "{l:?} {t:?}");
    // Past the first steps (which start small on purpose), the sizes still vary.
    assert!(t.largest > 5.0 * t.smallest, "{t:?}");
    assert_eq!(loose.steps, 2001);
    assert_eq!(loose_tr.len(), 2001);
    for (k, &time) in loose_tr.t.iter().enumerate() {
        assert!((time - k as f64 * 1e-3).abs() < 1e-12, "row {k} at {time}");
    }
    assert!(loose_tr.q.iter().all(|v| v.is_finite()));
}

/// The estimate is only as good as its solves: a step whose solve fails is taken
/// again smaller, and the options that the error control does not take are refused
/// before the run.
#[test]
fn options_the_control_does_not_take_are_refused() {
    let model = Model::new(&Scene::load(scene_path("fourbar.yaml")).unwrap()).unwrap();
    for (mode, full, what) in [
        (Mode::FixedLag(5), false, "window"),
        (Mode::Batch, false, "batch"),
        (Mode::FixedLag(1), true, "full"),
    ] {
        let mut options = ForwardOptions::new(Coordinates::Dependent, 1e-3, 1.0, mode);
        options.tolerance = Some(Tolerance::new(1e-6, None).unwrap());
        if full {
            options.dc_integrators = mbfg::forward::DcIntegrators::Full;
        }
        let e = options.validate(&model).unwrap_err().to_string();
        assert!(e.contains("rtol") && e.contains(what), "{e}");
    }
}

/// `mbfg simulate --rtol`: the rows on the grid of --dt (or --sample-dt), the
/// summary with the tolerance and the steps.
#[test]
fn the_cli_writes_rows_on_the_grid_and_says_what_the_control_did() {
    let csv = scratch("error-control", "grid").join("fourbar.csv");
    // The four-bar simulated with `args`, its rows to the scratch file.
    let fourbar = |args: &[&str]| {
        let mut all = vec!["simulate", "scenes/fourbar.yaml"];
        all.extend_from_slice(args);
        all.extend_from_slice(&["--out", csv.to_str().unwrap()]);
        mbfg(&all)
    };
    let out = fourbar(&[
        "--dt",
        "0.002",
        "--t-end",
        "1",
        "--rtol",
        "1e-6",
        "--atol",
        "1e-7",
        "--integrator",
        "hermite-simpson",
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    let summary = String::from_utf8_lossy(&out.stdout);
    assert!(
        summary.starts_with("501 rows (dt = 0.002 s, error-controlled steps)"),
        "{summary}"
    );
    assert!(
        summary.contains("error control rtol 1.0e-6, atol 1.0e-7: ")
            && summary.contains(" steps taken, ")
            && summary.contains(" rejected")
            && summary.contains(", h from "),
        "{summary}"
    );
    // The rows checked against a coarser run: their estimated error, in units of
    // the tolerance.
    assert!(
        summary.contains("; the rows' estimated error "),
        "{summary}"
    );
    let text = std::fs::read_to_string(&csv).unwrap();
    let times: Vec<f64> = text
        .lines()
        .skip(1)
        .map(|l| l.split(',').next().unwrap().parse().unwrap())
        .collect();
    assert_eq!(times.len(), 501);
    for (k, t) in times.iter().enumerate() {
        assert!((t - k as f64 * 0.002).abs() < 1e-12, "row {k} at {t}");
    }
    // A tolerance on the steps only: one run, nothing checked.
    let out = fourbar(&[
        "--dt",
        "0.002",
        "--t-end",
        "1",
        "--rtol",
        "1e-6",
        "--tolerance-scope",
        "steps",
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    let summary = String::from_utf8_lossy(&out.stdout);
    assert!(
        summary.contains("error control rtol 1.0e-6") && !summary.contains("estimated error"),
        "{summary}"
    );
    // --sample-dt alone sets the grid.
    let out = fourbar(&["--t-end", "1", "--rtol", "1e-5", "--sample-dt", "0.01"]);
    assert!(out.status.success(), "{}", stderr(&out));
    let rows = std::fs::read_to_string(&csv).unwrap().lines().count() - 1;
    assert_eq!(rows, 101);
    // Neither: t_end/1000, and a note says so.
    let out = fourbar(&["--t-end", "0.5", "--rtol", "1e-5"]);
    assert!(out.status.success(), "{}", stderr(&out));
    assert!(
        stderr(&out).contains("rows written every 0.0005 s"),
        "{}",
        stderr(&out)
    );
    let rows = std::fs::read_to_string(&csv).unwrap().lines().count() - 1;
    assert_eq!(rows, 1001);
    std::fs::remove_file(&csv).ok();
}

#[test]
fn bad_tolerances_are_one_line_errors() {
    let csv = scratch("error-control", "bad").join("bad.csv");
    for (extra, says) in [
        (&["--rtol", "0"][..], "--rtol must be"),
        (&["--rtol", "-1e-6"][..], "--rtol must be"),
        (&["--rtol", "nan"][..], "--rtol must be"),
        (&["--rtol", "2"][..], "--rtol must be"),
        (&["--rtol", "1e-6", "--atol", "inf"][..], "--atol must be"),
        (&["--rtol", "1e-6", "--window", "5"][..], "--window"),
        (&["--rtol", "1e-6", "--batch"][..], "--batch"),
        (
            &["--rtol", "1e-6", "--dc-integrators", "full"][..],
            "integrator factors",
        ),
        (&["--atol", "1e-6", "--dt", "0.01"][..], "--rtol"),
        (
            &["--rtol", "1e-6", "--tolerance-scope", "rows"][..],
            "--tolerance-scope",
        ),
        (
            &["--tolerance-scope", "steps", "--dt", "0.01"][..],
            "--rtol",
        ),
    ] {
        let mut args = vec![
            "simulate",
            "scenes/fourbar.yaml",
            "--t-end",
            "1",
            "--out",
            csv.to_str().unwrap(),
        ];
        args.extend(extra);
        let line = one_error_line(&mbfg(&args), 2);
        assert!(line.contains(says), "{extra:?}: {line}");
        assert!(!csv.exists(), "{extra:?} wrote a file");
    }
}
