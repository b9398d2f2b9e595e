//! `mbfg simulate` end to end: the CSV contract of DESIGN.md, the summary line, bad
//! arguments (exit 2, one line naming what is wrong) and a run that does not converge
//! (exit 1, the steps before it kept in `<out>.partial.csv`, never a NaN).

use std::path::PathBuf;
use std::process::{Command, Output};

fn mbfg(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_mbfg"))
        .args(args)
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .output()
        .expect("run mbfg")
}

fn temp(name: &str) -> PathBuf {
    std::env::temp_dir().join(format!("mbfg-cli-{}-{name}", std::process::id()))
}

fn stderr(out: &Output) -> String {
    String::from_utf8_lossy(&out.stderr).into_owned()
}

/// A failing call: the exit code, and exactly one line `error: …` on stderr.
fn one_error_line(out: &Output, code: i32) -> String {
    let err = stderr(out);
    assert_eq!(out.status.code(), Some(code), "stderr: {err}");
    let text = err.strip_suffix('\n').unwrap_or(&err);
    assert!(!text.contains('\n'), "one line expected, got:\n{err}");
    assert!(text.starts_with("error: "), "{text}");
    text.to_string()
}

#[test]
fn writes_the_trajectory_csv_and_a_summary() {
    let csv = temp("fourbar.csv");
    let out = mbfg(&[
        "simulate",
        "scenes/fourbar.yaml",
        "--coords",
        "dc",
        "--dt",
        "0.001",
        "--t-end",
        "0.5",
        "--window",
        "2",
        "--out",
        csv.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    let summary = String::from_utf8_lossy(&out.stdout);
    assert!(
        // Square steps: the plan takes the window of two one step at a time, and says so.
        summary.starts_with(
            "501 steps (dt = 0.001 s, window 2 asked, taken one step at a time, square steps)"
        ),
        "{summary}"
    );
    for part in [
        "iterations per solve",
        "worst |Φ|",
        "worst |Φq q̇|",
        "energy drift",
    ] {
        assert!(summary.contains(part), "summary lacks `{part}`: {summary}");
    }
    let text = std::fs::read_to_string(&csv).unwrap();
    std::fs::remove_file(&csv).ok();
    let mut lines = text.lines();
    let coords = ["P1.x", "P1.y", "P2.x", "P2.y"];
    let mut expect = vec!["t".to_string()];
    for p in ["q", "dq", "ddq"] {
        expect.extend(coords.iter().map(|c| format!("{p}:{c}")));
    }
    assert_eq!(lines.next().unwrap(), expect.join(","));
    let rows: Vec<Vec<f64>> = lines
        .map(|l| l.split(',').map(|v| v.parse().unwrap()).collect())
        .collect();
    assert_eq!(rows.len(), 501);
    assert!(rows.iter().flatten().all(|v| v.is_finite()));
    assert_eq!(rows[500][0], 0.5);
    // Released from rest: P1 starts at (1, 0) and falls.
    assert!(
        (rows[0][1] - 1.0).abs() < 1e-12 && rows[0][5].abs() < 1e-12,
        "{:?}",
        rows[0]
    );
    assert!(rows[500][2] < -0.5, "P1.y after 0.5 s: {}", rows[500][2]);
}

#[test]
fn without_out_the_csv_goes_to_stdout_and_the_summary_to_stderr() {
    let out = mbfg(&[
        "simulate",
        "scenes/fourbar-theta.yaml",
        "--coords",
        "ic",
        "--dt",
        "0.01",
        "--t-end",
        "0.1",
        "--batch",
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    let csv = String::from_utf8_lossy(&out.stdout);
    assert!(csv.starts_with("t,q:P1.x,q:P1.y,q:P2.x,q:P2.y,q:theta,dq:P1.x"));
    assert_eq!(csv.lines().count(), 12);
    assert!(
        stderr(&out).starts_with("11 steps (dt = 0.01 s, batch asked, taken one step at a time")
    );
}

#[test]
fn bad_arguments_exit_2_with_a_clear_message() {
    let unwritable = "/nonexistent-dir/out.csv";
    let cases: [(&[&str], &str); 6] = [
        (&["--dt", "0", "--t-end", "1"], "time step must be positive"),
        (
            &["--dt", "-0.001", "--t-end", "1"],
            "time step must be positive",
        ),
        (
            &["--dt", "0.01", "--t-end", "0.001"],
            "end time must be at least one step",
        ),
        (
            &["--dt", "0.001", "--t-end", "1", "--window", "0"],
            "at least 1 step",
        ),
        (
            &["--dt", "0.001", "--t-end", "1", "--coords", "ic"],
            "independent",
        ),
        (
            &["--dt", "0.001", "--t-end", "1", "--out", unwritable],
            "cannot write",
        ),
    ];
    for (args, expect) in cases {
        let mut all = vec!["simulate", "scenes/fourbar.yaml"];
        all.extend_from_slice(args);
        let line = one_error_line(&mbfg(&all), 2);
        assert!(line.contains(expect), "{args:?}: {line}");
    }
    // Flags clap checks itself: still exit 2.
    let out = mbfg(&[
        "simulate",
        "scenes/fourbar.yaml",
        "--dt",
        "0.001",
        "--t-end",
        "1",
        "--window",
        "2",
        "--batch",
    ]);
    assert_eq!(out.status.code(), Some(2));
    let out = mbfg(&[
        "simulate",
        "scenes/fourbar.yaml",
        "--dt",
        "abc",
        "--t-end",
        "1",
    ]);
    assert_eq!(out.status.code(), Some(2));
}

#[test]
fn a_solve_that_does_not_converge_exits_1_and_keeps_what_converged_apart() {
    let csv = temp("stalled.csv");
    let partial = temp("stalled.partial.csv");
    std::fs::write(&csv, "an earlier run's result\n").unwrap();
    let out = mbfg(&[
        "simulate",
        "scenes/fourbar.yaml",
        "--dt",
        "0.001",
        "--t-end",
        "0.5",
        "--max-iterations",
        "1",
        "--out",
        csv.to_str().unwrap(),
    ]);
    let line = one_error_line(&out, 1);
    assert!(
        line.contains("did not converge") && line.contains("iteration limit"),
        "{line}"
    );
    assert!(line.contains(&*partial.to_string_lossy()), "{line}");
    // The file asked for keeps what it held; the steps that converged are beside it.
    let kept = std::fs::read_to_string(&csv).unwrap();
    let text = std::fs::read_to_string(&partial).unwrap();
    std::fs::remove_file(&csv).ok();
    std::fs::remove_file(&partial).ok();
    assert_eq!(kept, "an earlier run's result\n");
    assert!(!text.contains("NaN") && !text.contains("inf"));
    assert!(
        text.lines().count() >= 2,
        "the initial state at least is written"
    );
}

/// The summary line says what ran: a window asked of square steps is taken one step
/// at a time, and says so; without square steps the window runs, and says that; the
/// passages through a singular configuration (the parallelogram's flat point) are
/// counted, whichever solver took them.
#[test]
fn the_summary_names_the_schedule_that_ran() {
    let summary = |extra: &[&str], scene: &str| -> String {
        let mut args = vec!["simulate", scene, "--dt", "0.001"];
        if !extra.contains(&"--t-end") {
            args.extend(["--t-end", "0.3"]);
        }
        args.extend(extra);
        let out = mbfg(&args);
        assert!(out.status.success(), "{}", stderr(&out));
        stderr(&out).lines().last().unwrap_or_default().to_string()
    };
    let fourbar = "scenes/fourbar.yaml";
    let line = summary(&["--window", "10"], fourbar);
    assert!(
        line.contains("(dt = 0.001 s, window 10 asked, taken one step at a time, square steps)"),
        "{line}"
    );
    let line = summary(&["--window", "10", "--no-square-steps"], fourbar);
    assert!(line.contains("(dt = 0.001 s, window 10)"), "{line}");
    let line = summary(&["--batch", "--dc-integrators", "full"], fourbar);
    assert!(line.contains("(dt = 0.001 s, batch)"), "{line}");
    assert!(!line.contains("general solver"), "{line}");
    // The parallelogram's first flat point is at t = π/6: the square steps pass it,
    // and the summary counts the passage.
    let line = summary(&["--t-end", "0.6"], "scenes/hard/parallelogram.yaml");
    assert!(
        line.contains("1 passage(s) through a singular configuration (the first at t = 0.524 s)"),
        "{line}"
    );
    assert!(!line.contains("general solver"), "{line}");
    let line = summary(
        &["--t-end", "0.6", "--no-square-steps"],
        "scenes/hard/parallelogram.yaml",
    );
    assert!(line.contains("1 passage(s)"), "{line}");
}
