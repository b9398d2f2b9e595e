//! `mbfg inverse` end to end: the suite's four-bar prescription, bad trajectory files
//! (exit 2, one line naming the file and what is wrong) and a prescription out of the
//! mechanism's reach (exit 1, naming the sample where it first fails).

use std::path::PathBuf;
use std::process::{Command, Output};

fn mbfg(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_mbfg"))
        .args(args)
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .output()
        .expect("run mbfg")
}

fn temp(name: &str, text: &str) -> PathBuf {
    let p = std::env::temp_dir().join(format!("mbfg-inv-{}-{name}", std::process::id()));
    std::fs::write(&p, text).unwrap();
    p
}

fn one_error_line(out: &Output, code: i32) -> String {
    let err = String::from_utf8_lossy(&out.stderr).into_owned();
    assert_eq!(out.status.code(), Some(code), "stderr: {err}");
    let text = err.strip_suffix('\n').unwrap_or(&err);
    assert!(!text.contains('\n'), "one line expected, got:\n{err}");
    assert!(text.starts_with("error: "), "{text}");
    text.to_string()
}

fn rows(f: impl Fn(usize) -> String, count: usize) -> String {
    (0..count).map(f).collect::<Vec<_>>().join("\n")
}

#[test]
fn solves_the_suite_prescription_and_writes_forces() {
    let out_csv = std::env::temp_dir().join(format!("mbfg-inv-{}-out.csv", std::process::id()));
    let out = mbfg(&[
        "inverse",
        "scenes/fourbar-theta.yaml",
        "--trajectory",
        "scenes/trajectories/fourbar-theta.csv",
        "--coords",
        "dc",
        "--out",
        out_csv.to_str().unwrap(),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let summary = String::from_utf8_lossy(&out.stdout);
    assert!(
        summary.starts_with("2001 steps (dt = 0.005 s, batch)"),
        "{summary}"
    );
    assert!(summary.contains("worst tracking error") && summary.contains("worst |Φ|"));
    let text = std::fs::read_to_string(&out_csv).unwrap();
    std::fs::remove_file(&out_csv).ok();
    let header = text.lines().next().unwrap();
    assert!(
        header.ends_with(",Q:P1.x,Q:P1.y,Q:P2.x,Q:P2.y,Q:theta"),
        "{header}"
    );
    assert_eq!(text.lines().count(), 2002);
}

#[test]
fn bad_trajectory_files_exit_2_with_a_clear_message() {
    let uniform = |k: usize| format!("{},{}", k as f64 * 0.01, 0.001 * k as f64);
    let cases: Vec<(&str, String, &str)> = vec![
        (
            "only-t.csv",
            format!("t\n{}", rows(|k| format!("{}", k as f64 * 0.01), 6)),
            "no prescribed coordinate",
        ),
        (
            "unknown.csv",
            format!("t,phi\n{}", rows(uniform, 6)),
            "unknown coordinate `phi`",
        ),
        (
            "twice.csv",
            format!(
                "t,theta,theta\n{}",
                rows(|k| format!("{},0,0", k as f64 * 0.01), 6)
            ),
            "appears twice",
        ),
        (
            "few.csv",
            format!("t,theta\n{}", rows(uniform, 3)),
            "at least 5",
        ),
        (
            "uneven.csv",
            "t,theta\n0,0\n0.01,0\n0.02,0\n0.04,0\n0.05,0\n0.06,0".into(),
            ":3: times are not uniformly spaced (step 0.01 s where the mean step is 0.012 s): exact samples need a uniform grid; measured ones are smoothed at their own times with a sample σ (--sample-sigma S or auto; sample_sigma in Python)",
        ),
        (
            "repeated.csv",
            "t,theta\n0,0\n0.01,0\n0.010001,0\n0.02,0\n0.03,0\n0.04,0".into(),
            "line 4: time 0.010001 follows the previous sample by only",
        ),
        (
            "back.csv",
            "t,theta\n0,0\n0.01,0\n0.02,0\n0.01,0\n0.04,0\n0.05,0".into(),
            "does not increase",
        ),
        (
            "nan.csv",
            "t,theta\n0,0\n0.01,0\n0.02,NaN\n0.03,0\n0.04,0\n0.05,0".into(),
            "not finite",
        ),
        (
            "text.csv",
            "t,theta\n0,0\n0.01,x\n0.02,0\n0.03,0\n0.04,0\n0.05,0".into(),
            "not a number",
        ),
        (
            "not-t.csv",
            format!("time,theta\n{}", rows(uniform, 6)),
            "first column must be `t`",
        ),
        // Finite samples whose solve overflowed (exit 1, "non-finite values"): the
        // row (line 4) and the column are named.
        (
            "huge.csv",
            "t,theta\n0,0\n0.01,0\n0.02,1e300\n0.03,0\n0.04,0\n0.05,0".into(),
            ":4: column `theta`: 1e300 is beyond ±1000000",
        ),
        (
            "tiny-dt.csv",
            "t,theta\n0,0\n1e-200,0\n2e-200,1\n3e-200,0\n4e-200,0\n5e-200,0".into(),
            "column `theta`: the samples' rate or acceleration there is not finite",
        ),
        // An angle turning more than π from one sample to the next: an outlier
        // (its solve took minutes), or an angle wrapped to (−π, π].
        (
            "outlier.csv",
            "t,theta\n0,0\n0.01,0.01\n0.02,0.02\n0.03,100\n0.04,0.04\n0.05,0.05".into(),
            ":5: column `theta`: the angle changes by 99.98 rad from the sample before, more than π in one time step (an outlier",
        ),
        (
            "wrapped.csv",
            "t,theta\n0,3.1\n0.01,3.12\n0.02,3.14\n0.03,-3.12\n0.04,-3.1\n0.05,-3.08".into(),
            "an angle wrapped to (−π, π]; unwrap it",
        ),
        (
            "far-time.csv",
            "t,theta\n0,0\n0.01,0\n1e300,0\n0.03,0\n0.04,0\n0.05,0".into(),
            "line 5: time 0.03 does not increase (previous 1e300)",
        ),
    ];
    for (name, text, expect) in cases {
        let path = temp(name, &text);
        let out = mbfg(&[
            "inverse",
            "scenes/fourbar-theta.yaml",
            "--trajectory",
            path.to_str().unwrap(),
        ]);
        std::fs::remove_file(&path).ok();
        let line = one_error_line(&out, 2);
        assert!(line.contains(expect), "{name}: {line}");
        assert!(
            line.contains(name),
            "{name}: the message must name the file: {line}"
        );
    }
    let out = mbfg(&[
        "inverse",
        "scenes/fourbar-theta.yaml",
        "--trajectory",
        "no/such/file.csv",
    ]);
    one_error_line(&out, 2);
}

/// The one error line of `mbfg inverse SCENE` on the trajectory `text` (exit 1).
fn failed_inverse(scene: &str, name: &str, text: &str) -> String {
    let path = temp(name, text);
    let out = mbfg(&["inverse", scene, "--trajectory", path.to_str().unwrap()]);
    std::fs::remove_file(&path).ok();
    one_error_line(&out, 1)
}

#[test]
fn a_prescription_out_of_reach_names_the_sample() {
    // P1 is on a unit crank: P1.y cannot exceed 1; it does after 0.5 s here.
    let text = format!(
        "t,P1.y\n{}",
        rows(
            |k| format!("{},{}", k as f64 * 0.01, 2.0 * k as f64 * 0.01),
            101
        )
    );
    let line = failed_inverse("scenes/fourbar-theta.yaml", "reach.csv", &text);
    assert!(line.contains("out of the mechanism's reach"), "{line}");
    let sample: usize = line
        .split("(sample ")
        .nth(1)
        .and_then(|r| r.split(')').next())
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("no sample in: {line}"));
    assert!(
        (45..=51).contains(&sample),
        "fails at sample {sample}: {line}"
    );
}

#[test]
fn independent_coordinates_need_the_prescribed_ones_to_be_independent() {
    let out = mbfg(&[
        "inverse",
        "scenes/fourbar-theta.yaml",
        "--trajectory",
        "scenes/trajectories/fourbar-theta.csv",
        "--coords",
        "ic",
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = format!(
        "t,P1.y\n{}",
        rows(|k| format!("{},{}", k as f64 * 0.01, 0.001 * k as f64), 10)
    );
    let path = temp("ic.csv", &text);
    let out = mbfg(&[
        "inverse",
        "scenes/fourbar-theta.yaml",
        "--trajectory",
        path.to_str().unwrap(),
        "--coords",
        "ic",
    ]);
    std::fs::remove_file(&path).ok();
    let line = one_error_line(&out, 2);
    assert!(line.contains("independent ones (theta)"), "{line}");
}

#[test]
fn a_first_sample_unreachable_from_the_placement_says_how_to_place_it() {
    // The pendulum is drawn horizontal: with P.x prescribed, P.y is undetermined
    // there (the constraint's derivative along y is 0), on either branch.
    let text = format!("t,P.x\n{}", rows(|k| format!("{},0.9", k as f64 * 0.01), 6));
    let line = failed_inverse("scenes/pendulum.yaml", "placement.csv", &text);
    assert!(
        line.contains("first sample (t = 0) cannot be reached from the scene's placement"),
        "{line}"
    );
    assert!(line.contains("place the mechanism off it"), "{line}");
}

/// Without `--sample-sigma` the output is today's, bit for bit: the files were written
/// by `mbfg inverse` before the option existed (commit 628d281), DC and IC.
#[test]
fn without_sample_sigma_the_output_is_unchanged() {
    for coords in ["dc", "ic"] {
        let out_csv =
            std::env::temp_dir().join(format!("mbfg-inv-{}-same-{coords}.csv", std::process::id()));
        let out = mbfg(&[
            "inverse",
            "scenes/fourbar-theta.yaml",
            "--trajectory",
            "tests/data/inverse/fourbar-theta-1s.csv",
            "--coords",
            coords,
            "--out",
            out_csv.to_str().unwrap(),
        ]);
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        let written = std::fs::read(&out_csv).unwrap();
        std::fs::remove_file(&out_csv).ok();
        let expected =
            std::fs::read(format!("tests/data/inverse/fourbar-theta-1s-{coords}.csv")).unwrap();
        assert!(
            written == expected,
            "{coords}: the CSV differs from the recorded one"
        );
    }
}

/// `--sample-sigma` adds the σ columns after the standard ones, names the smoothing
/// in the summary, and refuses a malformed value with exit 2.
#[test]
fn sample_sigma_writes_standard_deviations() {
    let out_csv = std::env::temp_dir().join(format!("mbfg-inv-{}-sd.csv", std::process::id()));
    let out = mbfg(&[
        "inverse",
        "scenes/fourbar-theta.yaml",
        "--trajectory",
        "tests/data/inverse/fourbar-theta-1s.csv",
        "--sample-sigma",
        "theta=1e-6",
        "--out",
        out_csv.to_str().unwrap(),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let summary = String::from_utf8_lossy(&out.stdout);
    assert!(
        summary.contains("samples smoothed: theta σ 1.000e-6 (given)"),
        "{summary}"
    );
    let text = std::fs::read_to_string(&out_csv).unwrap();
    std::fs::remove_file(&out_csv).ok();
    let header: Vec<&str> = text.lines().next().unwrap().split(',').collect();
    let q = header.iter().position(|c| *c == "Q:theta").unwrap();
    let sd = header.iter().position(|c| *c == "sd:Q:theta").unwrap();
    assert_eq!(header[q + 1], "sd:q:P1.x", "{header:?}");
    assert_eq!(sd, header.len() - 1);
    for line in text.lines().skip(1) {
        let v: Vec<f64> = line.split(',').map(|x| x.parse().unwrap()).collect();
        assert!(v[sd] > 0.0 && v[sd] < 0.1, "{line}");
    }
    for (bad, says) in [
        ("phi=1e-4", "`phi` is not a prescribed coordinate"),
        ("0", "must be a positive number"),
        ("theta=1e-4,theta=1e-4", "given twice"),
        ("1e-300", "below the samples' round-off"),
        ("1e300", "exceeds 1e6 times the samples' spread"),
    ] {
        let out = mbfg(&[
            "inverse",
            "scenes/fourbar-theta.yaml",
            "--trajectory",
            "tests/data/inverse/fourbar-theta-1s.csv",
            "--sample-sigma",
            bad,
        ]);
        let line = one_error_line(&out, 2);
        assert!(line.contains(says), "{line}");
    }
}

/// A file `t,theta` of `count` samples of the paper's crank motion
/// θ = 1.2 (1 − cos 2t): sample j at the time `at(j).0`, off the motion by `at(j).1`.
fn crank_samples(name: &str, count: usize, at: impl Fn(usize) -> (f64, f64)) -> PathBuf {
    let text = rows(
        |k| {
            if k == 0 {
                return "t,theta".into();
            }
            let (t, off) = at(k - 1);
            format!("{t},{}", 1.2 * (1.0 - (2.0 * t).cos()) + off)
        },
        count + 1,
    );
    temp(name, &text)
}

/// A sample far from the smoothed motion (a glitch) is named in a warning.
#[test]
fn sample_sigma_warns_of_a_glitch() {
    let path = crank_samples("glitch.csv", 601, |j| {
        let glitch = if j == 300 { 0.01 } else { 0.0 };
        (j as f64 * 0.005, glitch)
    });
    let out = mbfg(&[
        "inverse",
        "scenes/fourbar-theta.yaml",
        "--trajectory",
        path.to_str().unwrap(),
        "--sample-sigma",
        "auto",
    ]);
    std::fs::remove_file(&path).ok();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    assert!(
        err.contains("warning: the sample of theta at t = 1.5 (line 302) is "),
        "{err}"
    );
}

/// The Q:<c> columns of an output CSV, row-major rows × columns.
fn forces(path: &std::path::Path) -> Vec<Vec<f64>> {
    let text = std::fs::read_to_string(path).unwrap();
    let mut lines = text.lines().filter(|l| !l.starts_with('#'));
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    let cols: Vec<usize> = ["Q:motor1", "Q:motor2"]
        .iter()
        .map(|c| header.iter().position(|h| h == c).expect("a Q column"))
        .collect();
    lines
        .map(|l| {
            let v: Vec<&str> = l.split(',').collect();
            cols.iter().map(|&c| v[c].parse().unwrap()).collect()
        })
        .collect()
}

/// One sample 3 rad off (below the π a step may jump): the DC solve stays on
/// Gauss-Newton's model, whose reduced Hessian is the exact one for an inverse
/// graph, and stops once the steps are at the round-off of the 1e8 forces they
/// move (not iterating on it); the forces away from the outlier's difference
/// stencil are the clean run's, and at it those of the IC solve to 1e-12.
#[test]
fn an_outlier_sample_is_solved_without_the_finite_difference_hessian() {
    let clean = std::fs::read_to_string(
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("scenes/trajectories/pick-and-place.csv"),
    )
    .unwrap();
    let outlier = 499;
    let text: Vec<String> = clean
        .lines()
        .enumerate()
        .map(|(i, l)| {
            if i != outlier + 1 {
                return l.to_string();
            }
            let mut v: Vec<String> = l.split(',').map(str::to_string).collect();
            v[1] = (v[1].parse::<f64>().unwrap() + 3.0).to_string();
            v.join(",")
        })
        .collect();
    let traj = temp("pick-and-place-outlier.csv", &(text.join("\n") + "\n"));
    let run = |trajectory: &str, coords: &str, name: &str| {
        let out_csv = std::env::temp_dir().join(format!("mbfg-inv-{}-{name}", std::process::id()));
        let out = mbfg(&[
            "inverse",
            "scenes/pick-and-place.yaml",
            "--trajectory",
            trajectory,
            "--coords",
            coords,
            "--trace-solver",
            "--out",
            out_csv.to_str().unwrap(),
        ]);
        let err = String::from_utf8_lossy(&out.stderr).into_owned();
        assert!(out.status.success(), "{err}");
        assert!(String::from_utf8_lossy(&out.stdout).contains("(converged)"));
        let q = forces(&out_csv);
        std::fs::remove_file(&out_csv).ok();
        (err, q)
    };
    let (trace, dc) = run(traj.to_str().unwrap(), "dc", "outlier-dc.csv");
    let (_, ic) = run(traj.to_str().unwrap(), "ic", "outlier-ic.csv");
    let (_, reference) = run("scenes/trajectories/pick-and-place.csv", "dc", "clean.csv");
    std::fs::remove_file(&traj).ok();
    let iterations = trace.lines().filter(|l| l.starts_with("k0=")).count();
    assert!((1..=2).contains(&iterations), "{trace}");
    assert!(!trace.contains("newton=true"), "{trace}");
    let peak = dc.iter().flatten().fold(0.0f64, |m, v| m.max(v.abs()));
    let clean_peak = reference
        .iter()
        .flatten()
        .fold(0.0f64, |m, v| m.max(v.abs()));
    assert!(peak > 1e8, "the outlier's forces: {peak}");
    for (k, ((d, i), r)) in dc.iter().zip(&ic).zip(&reference).enumerate() {
        for c in 0..2 {
            assert!(
                (d[c] - i[c]).abs() <= 1e-9 * peak,
                "row {k}: DC {d:?}, IC {i:?}"
            );
            if k + 2 < outlier || k > outlier + 2 {
                let off = (d[c] - r[c]).abs();
                assert!(off <= 1e-9 * clean_peak, "row {k}: {d:?} against {r:?}");
            }
        }
    }
}

/// Measured samples whose times jitter are smoothed at their own times: the summary
/// says so, and the output's rows are on the grid of their mean interval.
#[test]
fn sample_sigma_smooths_samples_at_their_own_times() {
    // ±1 ms off a 5 ms grid, the ends on it.
    let path = crank_samples("jittered.csv", 401, |j| {
        let jitter = if j == 0 || j == 400 {
            0.0
        } else {
            [1e-3, -0.6e-3, 0.2e-3][j % 3]
        };
        (j as f64 * 0.005 + jitter, 0.0)
    });
    let refused = mbfg(&[
        "inverse",
        "scenes/fourbar-theta.yaml",
        "--trajectory",
        path.to_str().unwrap(),
    ]);
    let line = one_error_line(&refused, 2);
    assert!(
        line.contains("jittered.csv:3: times are not uniformly spaced")
            && line.contains("--sample-sigma S or auto"),
        "{line}"
    );
    let out_csv = std::env::temp_dir().join(format!("mbfg-inv-{}-jit.csv", std::process::id()));
    let out = mbfg(&[
        "inverse",
        "scenes/fourbar-theta.yaml",
        "--trajectory",
        path.to_str().unwrap(),
        "--sample-sigma",
        "auto",
        "--out",
        out_csv.to_str().unwrap(),
    ]);
    std::fs::remove_file(&path).ok();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let summary = String::from_utf8_lossy(&out.stdout);
    assert!(
        summary.contains(
            "401 steps (dt = 0.005 s, batch)"
        ) && summary.contains(
            "samples smoothed at their own times (intervals 0.0034 to 0.0058 s), read on the grid of their mean interval: theta σ"
        ),
        "{summary}"
    );
    let written = std::fs::read_to_string(&out_csv).unwrap();
    std::fs::remove_file(&out_csv).ok();
    let times: Vec<f64> = written
        .lines()
        .skip(1)
        .map(|l| l.split(',').next().unwrap().parse().unwrap())
        .collect();
    assert_eq!(times.len(), 401);
    for (k, t) in times.iter().enumerate() {
        assert!((t - k as f64 * 0.005).abs() < 1e-12, "row {k}: t = {t}");
    }
}
