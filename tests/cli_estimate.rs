//! `mbfg estimate` end to end: readings of the benchmark four-bar's crank encoder
//! made by `mbfg measure`, estimated on the bad scene (the columns of the output
//! contract, σ's that hold the truth, the summary line), and bad input (exit 2, one
//! line naming what is wrong).

mod common;
use common::{mbfg, measured, one_error_line, scratch, stderr};
use std::path::{Path, PathBuf};

fn scene(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("scenes/estimation")
        .join(name)
}

fn run(args: &[&str]) -> std::process::Output {
    mbfg(args)
}

/// The true motion over 2 s at 5 ms and the encoder's readings of it (seed 3).
fn readings(dir: &Path) -> PathBuf {
    let all = measured(dir, &scene("fourbar.yaml"), "0.005", "3");
    // The encoder's column alone.
    let text = std::fs::read_to_string(&all).unwrap();
    let enc: String = text
        .lines()
        .map(|l| l.split(',').take(2).collect::<Vec<_>>().join(",") + "\n")
        .collect();
    let path = dir.join("enc.csv");
    std::fs::write(&path, enc).unwrap();
    path
}

fn column(text: &str, name: &str) -> Vec<f64> {
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    let j = header
        .iter()
        .position(|c| *c == name)
        .unwrap_or_else(|| panic!("no column {name}"));
    lines
        .map(|l| l.split(',').nth(j).unwrap().parse().unwrap())
        .collect()
}

#[test]
fn estimates_the_bad_model_with_honest_sigmas() {
    let dir = scratch("cli-estimate", "run");
    let enc = readings(&dir);
    let out_path = dir.join("est.csv");
    let out = run(&[
        "estimate",
        scene("fourbar-bad.yaml").to_str().unwrap(),
        "--measurements",
        enc.to_str().unwrap(),
        "--window",
        "20",
        "--out",
        out_path.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    let summary = String::from_utf8_lossy(&out.stdout);
    assert!(
        summary.contains("401 steps (dt = 0.005 s, DC, window 20) from 401 readings"),
        "{summary}"
    );
    assert!(summary.contains("mean NIS"), "{summary}");
    assert!(summary.contains("process σ 3 (the default)"), "{summary}");
    // The encoder reads θ itself: nothing is left undetermined.
    assert!(!stderr(&out).contains("undetermined"), "{}", stderr(&out));
    let est = std::fs::read_to_string(&out_path).unwrap();
    let header = est.lines().next().unwrap();
    for c in [
        "t",
        "q:theta",
        "dq:theta",
        "ddq:theta",
        "sd:q:theta",
        "sd:dq:theta",
        "sd:q:P2.y",
    ] {
        assert!(
            header.split(',').any(|h| h == c),
            "no column {c} in {header}"
        );
    }
    let truth = std::fs::read_to_string(dir.join("truth.csv")).unwrap();
    let (z, sd, zt) = (
        column(&est, "q:theta"),
        column(&est, "sd:q:theta"),
        column(&truth, "q:theta"),
    );
    assert_eq!(z.len(), 401);
    // The bad model starts π/16 ≈ 0.196 rad off; the estimate follows the truth.
    let rms =
        (z.iter().zip(&zt).map(|(a, b)| (a - b).powi(2)).sum::<f64>() / z.len() as f64).sqrt();
    assert!(rms < 1e-2, "θ RMSE {rms}");
    let inside = z
        .iter()
        .zip(&zt)
        .zip(&sd)
        .filter(|((a, b), s)| (*a - *b).abs() <= 2.0 * **s)
        .count();
    assert!(
        inside as f64 >= 0.9 * z.len() as f64,
        "{inside} of {} within 2σ",
        z.len()
    );
}

#[test]
fn readings_off_the_grid_are_taken_at_their_own_times_and_named() {
    // Times that jitter: the step is the readings' mean interval (13 ms in 3 steps),
    // each reading at its nearest step, and the summary says how far from it.
    let dir = scratch("cli-estimate", "offgrid");
    let path = dir.join("offgrid.csv");
    std::fs::write(&path, "t,enc\n0,1.04\n0.005,1.04\n0.01,1.03\n0.013,1.03\n").unwrap();
    let out = run(&[
        "estimate",
        scene("fourbar-bad.yaml").to_str().unwrap(),
        "--measurements",
        path.to_str().unwrap(),
        "--out",
        dir.join("estimate.csv").to_str().unwrap(),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        text.contains("4 steps (dt = 0.004333")
            && text
                .contains("from 4 readings (2 between steps, up to 0.00133 s from their nearest"),
        "{text}"
    );
}

#[test]
fn bad_readings_are_refused_naming_what_is_wrong() {
    let dir = scratch("cli-estimate", "errors");
    let bad = scene("fourbar-bad.yaml");
    let check = |name: &str, text: &str, expect: &str| {
        let path = dir.join(name);
        std::fs::write(&path, text).unwrap();
        let out = run(&[
            "estimate",
            bad.to_str().unwrap(),
            "--measurements",
            path.to_str().unwrap(),
        ]);
        let line = one_error_line(&out, 2);
        assert!(line.contains(expect), "{name}: {line}");
    };
    check(
        "nan.csv",
        "t,enc\n0,1.0\n0.005,NaN\n",
        "nan.csv:3: column `enc`: NaN is not finite",
    );
    check(
        "unknown.csv",
        "t,enc,lidar\n0,1.0,2\n",
        "column `lidar` is no sensor of the scene",
    );
    check(
        "order.csv",
        "t,enc\n0,1.0\n0.01,1.0\n0.005,1.0\n",
        "does not increase",
    );
    check("half.csv", "t,enc\n", "no rows");
    check(
        "comment.csv",
        "# logged at 200 Hz\nt,enc\n0,1.0\n",
        "comment.csv:1: begins with `#`, a comment",
    );
    check(
        "empty.csv",
        "t,enc\n0,\n0.005,\n",
        "no readings: every sensor cell is empty",
    );
    // A scene without sensors.
    let plain = dir.join("plain.csv");
    std::fs::write(&plain, "t,enc\n0,1\n").unwrap();
    let out = run(&[
        "estimate",
        Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("scenes/fourbar.yaml")
            .to_str()
            .unwrap(),
        "--measurements",
        plain.to_str().unwrap(),
    ]);
    let line = one_error_line(&out, 2);
    assert!(line.contains("has no sensors"), "{line}");
}

#[test]
fn a_failed_estimate_names_its_step_and_keeps_the_final_steps() {
    let dir = scratch("cli-estimate", "partial");
    readings(&dir);
    // A corrupted gyroscope reading at step 100 (10⁶ rad/s): no estimate explains it.
    // (An encoder's 10⁶ rad is an angle like any other: compared on the circle.)
    let text = std::fs::read_to_string(dir.join("all.csv")).unwrap();
    assert!(text.starts_with("t,enc,gyro\n"), "{}", &text[..40]);
    let corrupt: String = text
        .lines()
        .enumerate()
        .map(|(i, l)| match i {
            101 => {
                let cells: Vec<&str> = l.split(',').collect();
                format!("{},{},1000000\n", cells[0], cells[1])
            }
            _ => format!("{l}\n"),
        })
        .collect();
    let bad_readings = dir.join("corrupt.csv");
    std::fs::write(&bad_readings, corrupt).unwrap();
    let out_path = dir.join("est.csv");
    let out = run(&[
        "estimate",
        scene("fourbar-bad.yaml").to_str().unwrap(),
        "--measurements",
        bad_readings.to_str().unwrap(),
        "--window",
        "5",
        "--out",
        out_path.to_str().unwrap(),
    ]);
    let line = one_error_line(&out, 1);
    assert!(
        line.contains("the estimate at step 100 (t = 0.5 s) did not converge"),
        "{line}"
    );
    // Steps 0..=80 had left the window, final (with the gyroscope the start is
    // determined slowly: the window of five grows to 20 while its oldest step is less
    // certain than its newest, and holds 81..=100 at step 100).
    assert!(line.contains("81 steps kept in"), "{line}");
    assert!(
        !out_path.exists(),
        "the target holds only complete estimates"
    );
    let partial = std::fs::read_to_string(dir.join("est.partial.csv")).unwrap();
    assert_eq!(partial.lines().count(), 82, "a header and 81 rows");
    assert!(
        partial.lines().last().unwrap().starts_with("0.4,"),
        "{}",
        partial.lines().last().unwrap()
    );
}

/// A bar spinning freely, without gravity, read by a gyroscope alone: its angle
/// enters neither the readings nor the dynamics. The estimate still runs (the start's
/// prior holds the angle), and the summary names the angle as undetermined.
#[test]
fn an_angle_no_sensor_observes_is_named_undetermined() {
    let dir = scratch("estimate", "undetermined");
    let scene = dir.join("spin.yaml");
    std::fs::write(
        &scene,
        "name: spin\n\
         points:\n  - {name: O, x: 0, y: 0, fixed: true}\n  - {name: P, x: 1, y: 0}\n\
         bodies:\n  - {name: bar, points: [O, P], mass: 1}\n\
         coordinates:\n  - {name: th, type: angle, points: [O, P]}\n\
         independent: [th]\n\
         initial:\n  positions: {th: 0}\n  velocities: {th: 1}\n\
         sensors:\n  - {name: gyro, type: gyroscope, body: bar, sigma: 1e-3}\n",
    )
    .unwrap();
    let (truth, readings, est) = (dir.join("t.csv"), dir.join("m.csv"), dir.join("e.csv"));
    let s = scene.to_str().unwrap();
    let out = run(&[
        "simulate",
        s,
        "--dt",
        "0.01",
        "--t-end",
        "2",
        "--out",
        truth.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    let out = run(&[
        "measure",
        s,
        "--trajectory",
        truth.to_str().unwrap(),
        "--seed",
        "1",
        "--out",
        readings.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    let out = run(&[
        "estimate",
        s,
        "--measurements",
        readings.to_str().unwrap(),
        "--out",
        est.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    let err = stderr(&out);
    assert!(
        err.contains("warning: the readings leave 'th' undetermined"),
        "{err}"
    );
}

/// An identification whose misfits are far beyond the sensors' σ's says its parameters
/// are no identification: here the encoder's σ written 10 times below its noise (mean
/// NIS near 100); with the σ right, the warning has no such sentence. Written 100 times
/// below, the run stops as diverged, naming the sensors' σ's first.
#[test]
fn an_identification_far_from_its_readings_says_so() {
    let dir = scratch("estimate", "far-misfit");
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/identification");
    let readings = measured(&dir, &root.join("pendulum-friction.yaml"), "0.001", "1");
    let bad = std::fs::read_to_string(root.join("pendulum-friction-bad.yaml")).unwrap();
    let estimate = |text: &str| {
        let path = dir.join("bad.yaml");
        std::fs::write(&path, text).unwrap();
        let out = run(&[
            "estimate",
            path.to_str().unwrap(),
            "--measurements",
            readings.to_str().unwrap(),
            "--batch",
            "--out",
            dir.join("estimate.csv").to_str().unwrap(),
        ]);
        (out.status.success(), stderr(&out))
    };
    let with_sigma = |s: &str| {
        let text = bad.replace("sigma: 0.001, rate: 200", &format!("sigma: {s}, rate: 200"));
        assert_ne!(text, bad);
        text
    };
    let (ok, err) = estimate(&with_sigma("0.0001"));
    assert!(ok, "{err}");
    assert!(
        err.contains("the parameters are the best fit of a wrong model, not an identification"),
        "{err}"
    );
    let (ok, err) = estimate(&bad);
    assert!(ok && !err.contains("not an identification"), "{err}");
    let (ok, err) = estimate(&with_sigma("0.00001"));
    assert!(
        !ok && err.contains("diverged") && err.contains("check the sensors' `sigma`"),
        "{err}"
    );
    std::fs::remove_dir_all(&dir).ok();
}

/// A motion too fast for the readings' period (a 1 cm link whipped by a stiff spring,
/// read at 200 Hz): at the default step the run fails and says to step finer; at the
/// step it suggests, it holds.
#[test]
fn a_motion_too_fast_for_the_readings_period_is_told_to_step_finer() {
    let dir = scratch("estimate", "too-fast");
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let text = std::fs::read_to_string(root.join("scenes/hard/mixed-scale-pendulum.yaml")).unwrap()
        + "sensors:\n"
        + "  - {name: enc1, type: encoder, coordinate: a1, sigma: 0.001, rate: 200}\n"
        + "  - {name: enc2, type: encoder, coordinate: a2, sigma: 0.001, rate: 200}\n"
        + "  - {name: enc3, type: encoder, coordinate: a3, sigma: 0.001, rate: 200}\n";
    let scene = dir.join("whip.yaml");
    std::fs::write(&scene, text).unwrap();
    let readings = measured(&dir, &scene, "0.001", "1");
    let estimate = |extra: &[&str]| {
        let out_csv = dir.join("estimate.csv");
        let mut args = vec![
            "estimate",
            scene.to_str().unwrap(),
            "--measurements",
            readings.to_str().unwrap(),
            "--out",
            out_csv.to_str().unwrap(),
        ];
        args.extend_from_slice(extra);
        run(&args)
    };
    let line = one_error_line(&estimate(&[]), 1);
    assert!(
        line.contains("did not converge")
            && line
                .contains("the motion may be too fast for steps of the readings' period (0.005 s)")
            && line.contains("--dt 0.001"),
        "{line}"
    );
    let out = estimate(&["--dt", "0.001"]);
    assert!(out.status.success(), "{}", stderr(&out));
    std::fs::remove_dir_all(&dir).ok();
}
