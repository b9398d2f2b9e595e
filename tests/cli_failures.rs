//! The command line under abuse: every bad input exits 2 with one line of at most 300
//! characters; no run that failed or ended early exits 0 or leaves an output that
//! looks complete; the file asked for is replaced only by a complete result.

use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

mod common;
use common::{mbfg, mbfg_env as mbfg_in};

/// A fresh directory for one test's files.
fn scratch(name: &str) -> PathBuf {
    common::scratch("failures", name)
}

fn text(p: &Path) -> String {
    std::fs::read_to_string(p).unwrap_or_else(|e| panic!("{}: {e}", p.display()))
}

/// Exit `code` and exactly one line `error: …` of at most 300 characters.
fn error_line(out: &Output, code: i32) -> String {
    let err = String::from_utf8_lossy(&out.stderr).into_owned();
    assert_eq!(out.status.code(), Some(code), "stderr: {err}");
    let line = err.lines().last().unwrap_or("").to_string();
    assert!(line.starts_with("error: "), "{err}");
    assert!(
        line.chars().count() <= 300,
        "{} chars: {line}",
        line.chars().count()
    );
    assert!(
        !line.contains("panicked") && !line.contains(" { "),
        "{line}"
    );
    line
}

/// Bad input: exit 2 and nothing but the error line on stderr.
fn bad_input(args: &[&str]) -> String {
    let out = mbfg(args);
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(
        err.lines().count(),
        1,
        "{args:?}: one line expected:\n{err}"
    );
    error_line(&out, 2)
}

const FOURBAR: &str = "scenes/fourbar.yaml";

#[test]
fn step_counts_that_overflow_are_bad_input() {
    for (dt, t_end) in [("1e-300", "1"), ("0.001", "1e300"), ("1", "1e18")] {
        let line = bad_input(&["simulate", FOURBAR, "--dt", dt, "--t-end", t_end]);
        assert!(line.contains("steps, more than"), "{line}");
    }
}

#[test]
fn runs_beyond_the_memory_are_refused_before_they_start() {
    let started = Instant::now();
    // 9e8 steps fit the step limit but not the memory (their rows held for standard
    // output): refused at once, with the estimate.
    let line = bad_input(&["simulate", FOURBAR, "--dt", "1e-4", "--t-end", "9e4"]);
    assert!(
        line.contains("needs about") && line.contains("GB of memory"),
        "{line}"
    );
    // The limit can be lowered, for shared machines: a 10 001-step run then does not fit.
    let out = mbfg_in(
        &["simulate", FOURBAR, "--dt", "1e-3", "--t-end", "10"],
        &[("MBFG_MEMORY_LIMIT", "1e5")],
    );
    let line = error_line(&out, 2);
    assert!(line.contains("more than the 100.0 kB available"), "{line}");
    assert!(started.elapsed() < Duration::from_secs(10));
}

#[test]
fn a_window_longer_than_the_run_is_the_whole_run() {
    for window in ["10000000", "18446744073709551615"] {
        let out = mbfg(&[
            "simulate", FOURBAR, "--dt", "0.01", "--t-end", "0.2", "--window", window,
        ]);
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(out.status.success(), "{err}");
        // The four-bar's default steps are square: the plan takes them one at a time.
        assert!(
            err.contains("21 steps (dt = 0.01 s, window 21 asked, taken one step at a time"),
            "{err}"
        );
    }
}

#[test]
fn argument_errors_are_one_line() {
    let line = bad_input(&["simulate", FOURBAR, "--dt", "-inf", "--t-end", "1"]);
    assert!(
        line.contains("time step must be positive, got -inf"),
        "{line}"
    );
    let line = bad_input(&[
        "simulate", FOURBAR, "--dt", "0.1", "--t-end", "1", "--bogus",
    ]);
    assert!(line.contains("--bogus"), "{line}");
    let line = bad_input(&["simulate", FOURBAR, "--dt", "abc", "--t-end", "1"]);
    assert!(line.contains("abc"), "{line}");
    let line = bad_input(&["simulate", FOURBAR]);
    assert!(line.contains("--dt"), "{line}");
}

#[test]
fn an_output_that_names_an_input_is_refused() {
    let dir = scratch("out-is-input");
    let scene = dir.join("fourbar.yaml");
    std::fs::copy(FOURBAR, &scene).unwrap();
    let before = text(&scene);
    let s = scene.to_str().unwrap();
    let line = bad_input(&["simulate", s, "--dt", "0.01", "--t-end", "0.1", "--out", s]);
    assert!(line.contains("refusing to overwrite"), "{line}");
    // The same file by another name.
    let other = format!("{}/./fourbar.yaml", dir.display());
    bad_input(&[
        "simulate", s, "--dt", "0.01", "--t-end", "0.1", "--out", &other,
    ]);
    let traj = "scenes/trajectories/fourbar-theta.csv";
    bad_input(&[
        "inverse",
        "scenes/fourbar-theta.yaml",
        "--trajectory",
        traj,
        "--out",
        traj,
    ]);
    assert_eq!(text(&scene), before);
    std::fs::remove_dir_all(&dir).ok();
}

/// A run that ends early (here at a torque that turns NaN at t > 0.3 s) and writes to
/// standard output ends it with a line that says so.
#[test]
fn a_run_that_ends_early_on_stdout_ends_with_an_incomplete_line() {
    let dir = scratch("incomplete-stdout");
    let scene = dir.join("nan.yaml");
    let mut yaml = text(Path::new("scenes/pendulum.yaml"));
    yaml += "  - {type: torque, coordinate: theta, value: \"sqrt(0.3-t)\"}\n";
    std::fs::write(&scene, yaml).unwrap();
    let out = mbfg(&[
        "simulate",
        scene.to_str().unwrap(),
        "--dt",
        "0.01",
        "--t-end",
        "0.5",
    ]);
    error_line(&out, 1);
    let csv = String::from_utf8_lossy(&out.stdout);
    let last = csv.lines().last().unwrap();
    assert!(last.starts_with("# incomplete: step "), "{last}");
    std::fs::remove_dir_all(&dir).ok();
}

/// A torque that turns NaN at t > 0.3 s: the step that meets it is named with the
/// effect; the run ends there, and --continue-on-failure does not make that a success.
#[test]
fn a_non_finite_effect_is_named_and_ends_the_run_whatever_the_flags() {
    let dir = scratch("nan-torque");
    let scene = dir.join("nan.yaml");
    let mut yaml = text(Path::new("scenes/pendulum.yaml"));
    yaml += "  - {type: torque, coordinate: theta, value: \"sqrt(0.3-t)\"}\n";
    std::fs::write(&scene, yaml).unwrap();
    let csv = dir.join("run.csv");
    for (coords, extra) in [("dc", None), ("ic", Some("--continue-on-failure"))] {
        let mut args = vec![
            "simulate",
            scene.to_str().unwrap(),
            "--coords",
            coords,
            "--dt",
            "0.01",
            "--t-end",
            "1",
            "--out",
            csv.to_str().unwrap(),
        ];
        args.extend(extra);
        let line = error_line(&mbfg(&args), 1);
        assert!(
            line.contains("step 31 (t = 0.31 s)") && line.contains("torque on theta = sqrt(0.3-t)"),
            "{line}"
        );
        assert!(!csv.exists());
        let partial = text(&dir.join("run.partial.csv"));
        assert_eq!(partial.lines().count(), 1 + 31);
        assert!(!partial.contains("NaN"));
    }
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn points_beyond_the_scene_extent_are_refused() {
    let dir = scratch("far");
    let scene = dir.join("far.yaml");
    let yaml = text(Path::new("scenes/pendulum.yaml"))
        .replace(
            "{name: A, x: 0, y: 0, fixed: true}",
            "{name: A, x: 1e308, y: 0, fixed: true}",
        )
        .replace("{name: P, x: 1, y: 0}", "{name: P, x: 1e308, y: 1e307}");
    std::fs::write(&scene, yaml).unwrap();
    let line = bad_input(&["check", scene.to_str().unwrap()]);
    assert!(
        line.contains("points[0].x") && line.contains("beyond"),
        "{line}"
    );
    std::fs::remove_dir_all(&dir).ok();
}

/// A 30 t pendulum is as regular as a 1 kg one: its accelerations do not depend on the
/// mass, and neither does the run.
#[test]
fn mass_scale_does_not_make_the_dynamics_singular() {
    let dir = scratch("heavy");
    let scene = dir.join("heavy.yaml");
    let yaml = text(Path::new("scenes/pendulum.yaml")).replace("mass: 1}", "mass: 3e7}");
    std::fs::write(&scene, yaml).unwrap();
    let s = scene.to_str().unwrap();
    let check = mbfg(&["check", s]);
    assert!(check.status.success());
    assert!(String::from_utf8_lossy(&check.stdout).contains("initial max |q̈| = 14.715"));
    for coords in ["dc", "ic"] {
        let out = mbfg(&[
            "simulate", s, "--coords", coords, "--dt", "0.001", "--t-end", "1",
        ]);
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
    }
    std::fs::remove_dir_all(&dir).ok();
}

/// The stiff spring (period 99 ms) stepped at 0.1 s: warned with its numbers, or
/// refused with --strict.
#[test]
fn a_step_too_coarse_for_the_stiffest_spring_is_not_silent() {
    let args = [
        "simulate",
        "scenes/hard/stiff-spring.yaml",
        "--dt",
        "0.1",
        "--t-end",
        "5",
    ];
    let out = mbfg(&args);
    assert!(out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("warning: dt = 0.1 s is too coarse for spring")
            && err.contains("period is 9.935e-2 s"),
        "{err}"
    );
    assert!(
        err.contains("warning: the energy of this conservative scene drifted"),
        "{err}"
    );
    let mut strict = args.to_vec();
    strict.push("--strict");
    let line = bad_input(&strict);
    assert!(line.contains("dt ≤ 1.58e-2 s resolves it"), "{line}");
    // At a tenth of the period: no warning.
    let out = mbfg(&[
        "simulate",
        "scenes/hard/stiff-spring.yaml",
        "--dt",
        "0.01",
        "--t-end",
        "1",
    ]);
    assert!(!String::from_utf8_lossy(&out.stderr).contains("warning"));
}

/// The explicit Euler rule on Andrews' squeezer (driven, so no energy drift to
/// watch): at 10 µs every step converges and the crank ends 0.21 rad ahead of
/// Hermite–Simpson's at 0.03 s; its energy balance against the motor's work is 1.7 %
/// off, and the run says so, or is refused with --strict. At 1 µs and with the
/// trapezoidal rule it is silent.
#[test]
fn an_explicit_euler_run_that_loses_its_energy_balance_is_not_silent() {
    let dir = scratch("euler");
    let csv = dir.join("run.csv");
    let run = |integrator: &str, dt: &str, strict: bool| {
        let mut args = vec![
            "simulate",
            "scenes/benchmarks/andrews-squeezer.yaml",
            "--integrator",
            integrator,
            "--dt",
            dt,
            "--t-end",
            "0.03",
            "--out",
            csv.to_str().unwrap(),
        ];
        if strict {
            args.push("--strict");
        }
        mbfg(&args)
    };
    let out = run("euler", "1e-5", false);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    assert!(
        err.contains("warning: the energy balance (integrator euler)"),
        "{err}"
    );
    let line = error_line(&run("euler", "1e-5", true), 1);
    assert!(line.contains("nothing was written (--strict)"), "{line}");
    for (integrator, dt) in [("euler", "1e-6"), ("trapezoidal", "1e-5")] {
        let out = run(integrator, dt, false);
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(
            out.status.success() && !err.contains("warning"),
            "{integrator} {dt}: {err}"
        );
    }
    std::fs::remove_dir_all(&dir).ok();
}

/// An inverse solve that fails writes nothing, kept or not; a prescription with more
/// or fewer coordinates than degrees of freedom is refused as bad input. (The default
/// start is the solution of a fully prescribed problem, so the batch converges in its
/// first iteration; the staged start still fails, in its first stage.)
#[test]
fn a_failed_inverse_solve_writes_nothing() {
    let dir = scratch("inverse");
    let csv = dir.join("q.csv");
    let base = [
        "inverse",
        "scenes/fourbar-theta.yaml",
        "--trajectory",
        "scenes/trajectories/fourbar-theta.csv",
        "--start",
        "staged",
        "--out",
        csv.to_str().unwrap(),
    ];
    let line = error_line(&mbfg(&base), 1);
    assert!(
        line.contains("staged start (stage 1) did not converge"),
        "{line}"
    );
    let mut keep = base.to_vec();
    keep.push("--keep-unconverged");
    error_line(&mbfg(&keep), 1);
    assert!(!csv.exists() && !dir.join("q.partial.csv").exists());
    let mut quick = base.to_vec();
    quick.splice(4..6, ["--max-iterations", "1"]);
    let out = mbfg(&quick);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(
        csv.exists(),
        "one iteration solves a fully prescribed problem"
    );
    let over = dir.join("over.csv");
    let rows: String = (0..20)
        .map(|k| format!("{},{},{}\n", k as f64 * 0.005, 6e-5 * k as f64, 1.0))
        .collect();
    std::fs::write(&over, format!("t,theta,P1.x\n{rows}")).unwrap();
    let line = bad_input(&[
        "inverse",
        "scenes/fourbar-theta.yaml",
        "--trajectory",
        over.to_str().unwrap(),
    ]);
    assert!(line.contains("over-prescribe"), "{line}");
    let under = dir.join("under.csv");
    let rows: String = (0..20)
        .map(|k| format!("{},{}\n", k as f64 * 0.005, -0.01 * k as f64))
        .collect();
    std::fs::write(&under, format!("t,theta1\n{rows}")).unwrap();
    let line = bad_input(&[
        "inverse",
        "scenes/double-pendulum.yaml",
        "--trajectory",
        under.to_str().unwrap(),
    ]);
    assert!(
        line.contains("one prescribed coordinate per degree of freedom"),
        "{line}"
    );
    std::fs::remove_dir_all(&dir).ok();
}

/// A long run in the background, its CSV to `csv`.
fn long_run(csv: &Path) -> std::process::Child {
    Command::new(env!("CARGO_BIN_EXE_mbfg"))
        .args([
            "simulate", FOURBAR, "--dt", "1e-4", "--t-end", "1000", "--out",
        ])
        .arg(csv)
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("run mbfg")
}

fn signal(child: &std::process::Child, name: &str) {
    let ok = Command::new("kill")
        .args([format!("-{name}"), child.id().to_string()])
        .status()
        .unwrap()
        .success();
    assert!(ok, "kill -{name}");
}

#[test]
fn ctrl_c_keeps_the_steps_solved_and_kill_leaves_the_old_file() {
    let dir = scratch("signals");
    let csv = dir.join("run.csv");
    std::fs::write(&csv, "old\n").unwrap();
    let child = long_run(&csv);
    std::thread::sleep(Duration::from_millis(700));
    signal(&child, "INT");
    let asked = Instant::now();
    let out = child.wait_with_output().unwrap();
    assert!(
        asked.elapsed() < Duration::from_secs(2),
        "{:?}",
        asked.elapsed()
    );
    let line = error_line(&out, 130);
    assert!(
        line.contains("interrupted after step") && line.contains("run.partial.csv"),
        "{line}"
    );
    assert_eq!(text(&csv), "old\n");
    let partial = text(&dir.join("run.partial.csv"));
    assert!(partial.lines().count() > 10, "{}", partial.lines().count());

    let child = long_run(&csv);
    std::thread::sleep(Duration::from_millis(500));
    signal(&child, "KILL");
    child.wait_with_output().unwrap();
    assert_eq!(text(&csv), "old\n");
    std::fs::remove_dir_all(&dir).ok();
}

/// Two runs writing the same file: each result is complete, so the file is one of
/// them, never a mix.
#[test]
fn concurrent_runs_to_one_file_leave_one_whole_result() {
    let dir = scratch("concurrent");
    let csv = dir.join("run.csv");
    let spawn = |t_end: &str| {
        Command::new(env!("CARGO_BIN_EXE_mbfg"))
            .args([
                "simulate", FOURBAR, "--dt", "1e-3", "--t-end", t_end, "--out",
            ])
            .arg(&csv)
            .current_dir(env!("CARGO_MANIFEST_DIR"))
            .stdout(Stdio::null())
            .spawn()
            .unwrap()
    };
    let (mut a, mut b) = (spawn("3"), spawn("2"));
    assert!(a.wait().unwrap().success() && b.wait().unwrap().success());
    let rows = text(&csv).lines().count() - 1;
    assert!(rows == 3001 || rows == 2001, "{rows} rows");
    let leftovers = std::fs::read_dir(&dir).unwrap().count();
    assert_eq!(leftovers, 1, "temporary files left behind");
    std::fs::remove_dir_all(&dir).ok();
}

/// A full disk (Linux's /dev/full) is named in the error; a device is written in
/// place, never replaced by a rename.
#[cfg(target_os = "linux")]
#[test]
fn a_full_device_is_named_and_left_a_device() {
    use std::os::unix::fs::FileTypeExt;
    let full = Path::new("/dev/full");
    if !full.exists() {
        return;
    }
    let out = mbfg(&[
        "simulate",
        FOURBAR,
        "--dt",
        "0.01",
        "--t-end",
        "0.1",
        "--out",
        "/dev/full",
    ]);
    let line = error_line(&out, 1);
    assert!(
        line.contains("cannot write /dev/full") && line.contains("No space left"),
        "{line}"
    );
    assert!(std::fs::metadata(full)
        .unwrap()
        .file_type()
        .is_char_device());
}

/// `check` never prints NaN or Inf as a result: a spring of 1e308 N/m stretched by
/// 99 m has an infinite energy, which is bad input.
#[test]
fn check_refuses_a_scene_whose_numbers_overflow() {
    let dir = scratch("overflow");
    let scene = dir.join("inf.yaml");
    let yaml = text(Path::new("scenes/spring-damper.yaml")).replace(
        "stiffness: 20, rest_length: 0.8",
        "stiffness: 1e308, rest_length: 100",
    );
    std::fs::write(&scene, yaml).unwrap();
    let line = bad_input(&["check", scene.to_str().unwrap()]);
    assert!(line.contains("potential energy is inf"), "{line}");
    std::fs::remove_dir_all(&dir).ok();
}

/// A trajectory whose header names no coordinate of the scene is refused at its
/// header, however many rows follow, and the message stays one short line.
#[test]
fn a_trajectory_header_is_checked_before_its_rows() {
    let dir = scratch("header");
    let csv = dir.join("q.csv");
    let name = "no_such_coordinate";
    let mut text = format!("t,{name}\n");
    for k in 0..200_000 {
        text += &format!("{},0\n", k as f64 * 1e-3);
    }
    std::fs::write(&csv, text).unwrap();
    let line = bad_input(&[
        "inverse",
        "scenes/fourbar-theta.yaml",
        "--trajectory",
        csv.to_str().unwrap(),
    ]);
    assert!(line.contains("unknown coordinate"), "{line}");
    std::fs::remove_dir_all(&dir).ok();
}

/// `--trace-solver` prints one line per solver iteration to standard error and
/// leaves the trajectory as it is.
#[test]
fn the_solver_trace_goes_to_stderr_and_changes_nothing() {
    let dir = scratch("trace");
    let (plain, traced) = (dir.join("plain.csv"), dir.join("traced.csv"));
    let run = |out: &Path, trace: bool| {
        let mut args = vec![
            "simulate",
            "scenes/fourbar.yaml",
            "--dt",
            "0.01",
            "--t-end",
            "0.05",
            "--out",
            out.to_str().unwrap(),
        ];
        if trace {
            args.push("--trace-solver");
        }
        mbfg(&args)
    };
    let quiet = run(&plain, false);
    let loud = run(&traced, true);
    assert!(quiet.status.success() && loud.status.success());
    let lines: Vec<String> = String::from_utf8_lossy(&loud.stderr)
        .lines()
        .filter(|l| l.starts_with("k0="))
        .map(String::from)
        .collect();
    // Every step after the first takes at least one iteration.
    assert!(lines.len() >= 5, "{lines:?}");
    assert!(
        lines.iter().any(|l| l.starts_with("k0=1 k1=2 it=1 ")),
        "{lines:?}"
    );
    assert!(!String::from_utf8_lossy(&quiet.stderr).contains("k0="));
    assert_eq!(
        std::fs::read(&plain).unwrap(),
        std::fs::read(&traced).unwrap()
    );
}

/// Three parallel cranks on one coupler (two redundant constraints) reach a flat
/// position where θ stops determining the rest: IC stops ahead of it in a window and in
/// a batch alike, and the hint names what passes it (DC), not a window or a dt.
#[test]
fn an_ill_posed_stop_in_a_batch_points_to_dc() {
    let dir = scratch("triple-crank");
    let scene = dir.join("triple-crank.yaml");
    std::fs::write(
        &scene,
        "name: triple-crank
parameters: {rc: 0.5, th0: pi/3}
points:
  - {name: A, x: 0, y: 0, fixed: true}
  - {name: B, x: 1, y: 0, fixed: true}
  - {name: C, x: 2, y: 0, fixed: true}
  - {name: P1, x: rc*cos(th0), y: rc*sin(th0)}
  - {name: P2, x: 1 + rc*cos(th0), y: rc*sin(th0)}
  - {name: P3, x: 2 + rc*cos(th0), y: rc*sin(th0)}
bodies:
  - {name: crank1, points: [A, P1], mass: 1}
  - {name: crank2, points: [B, P2], mass: 1}
  - {name: crank3, points: [C, P3], mass: 1}
  - {name: coupler, points: [P1, P2, P3], mass: 3, cog: [1, 0], inertia: 1}
coordinates:
  - {name: theta, type: angle, points: [A, P1]}
independent: [theta]
initial: {velocities: {theta: 2}}
effects:
  - {type: gravity, vector: [0, -9.81]}
",
    )
    .unwrap();
    let out = dir.join("run.csv");
    for mode in ["--batch", "--window=1"] {
        let run = mbfg(&[
            "simulate",
            scene.to_str().unwrap(),
            "--coords",
            "ic",
            mode,
            "--dt",
            "0.01",
            "--t-end",
            "1",
            "--out",
            out.to_str().unwrap(),
        ]);
        let line = error_line(&run, 1);
        assert!(line.contains("singular configuration"), "{mode}: {line}");
        assert!(
            line.ends_with("(--coords dc does not stop there)"),
            "{mode}: {line}"
        );
    }
}

/// A block on a spring dragged by a slow belt with Coulomb friction written as
/// sign(): at the first stick the implicit step has no solution (the friction's jump
/// reverses the motion that made it). The failure names the jumping effect and how to
/// smooth it.
#[test]
fn a_step_across_a_jumping_load_names_the_jump() {
    let dir = scratch("stick-slip");
    let scene = dir.join("stick-slip.yaml");
    let mut text = String::from(
        "name: stick-slip
parameters: {mu: 3, vb: 0.1}
points:
  - {name: A, x: 0, y: 0, fixed: true}
  - {name: G, x: 1, y: 0, fixed: true}
  - {name: S, x: 1, y: 0, mass: 1}
constraints:
  - {name: guide, type: fixed_slider, point: S, line: [A, G]}
coordinates:
  - {name: s, type: distance, point: S, along: [A, G]}
independent: [s]
effects:
  - {name: spring, type: spring_damper, points: [A, S], stiffness: 100, rest_length: 1}
",
    );
    let jumping =
        "  - {name: friction, type: force, point: S, value: [\"-mu*sign(vx(S) - vb)\", 0]}\n";
    let smooth =
        "  - {name: friction, type: force, point: S, value: [\"-mu*tanh((vx(S) - vb)/1e-3)\", 0]}\n";
    let out = dir.join("run.csv");
    let run_with = |scene: &Path, more: &[&str]| {
        let mut args = vec![
            "simulate",
            scene.to_str().unwrap(),
            "--dt",
            "0.001",
            "--t-end",
            "0.5",
            "--out",
            out.to_str().unwrap(),
        ];
        args.extend_from_slice(more);
        mbfg(&args)
    };
    let run = |scene: &Path| run_with(scene, &[]);
    std::fs::write(&scene, text.clone() + jumping).unwrap();
    // With fixed steps, and with error-controlled ones (whose steps shrink to the
    // smallest size there).
    for (more, failed) in [
        (&[][..], "did not converge"),
        (&["--rtol", "1e-6"][..], "no step from t = "),
    ] {
        let line = error_line(&run_with(&scene, more), 1);
        assert!(line.contains(failed), "{more:?}: {line}");
        assert!(
            line.ends_with(
                "(effect 'friction' jumps with sign(): smooth it, e.g. tanh(x/1e-3) for sign(x))"
            ),
            "{more:?}: {line}"
        );
    }
    // Smoothed, the same scene runs.
    text.push_str(smooth);
    std::fs::write(&scene, text).unwrap();
    let ok = run(&scene);
    assert!(
        ok.status.success(),
        "{}",
        String::from_utf8_lossy(&ok.stderr)
    );
}

/// A double pendulum tied to the ground by a 1e6 N/m spring, in IC at dt = 1 ms (ω·dt
/// about 1.7): the warning before the run names the spring, and where the run fails
/// (Hermite–Simpson's general solver) the failure says so again with the dt that
/// resolves it. The trapezoidal rule's steps, solved as square systems, hold their
/// equations: that run completes (it had failed at step 33 before), warned about
/// the spring and about its energy drift (32 % here; 0.6 % at dt = 0.1 ms, falling
/// like dt²), and `--strict` refuses it.
#[test]
fn a_failure_on_a_step_too_coarse_for_a_spring_names_it() {
    let dir = scratch("stiff-tie");
    let scene = dir.join("stiff-tie.yaml");
    std::fs::write(
        &scene,
        "name: stiff-tie
points:
  - {name: O, x: 0, y: 0, fixed: true}
  - {name: W, x: 1.5, y: -1, fixed: true}
  - {name: P1, x: 1, y: 0}
  - {name: P2, x: 2, y: 0}
bodies:
  - {name: l1, points: [O, P1], mass: 1}
  - {name: l2, points: [P1, P2], mass: 1}
coordinates:
  - {name: a1, type: angle, points: [O, P1]}
  - {name: a2, type: angle, points: [P1, P2]}
independent: [a1, a2]
effects:
  - {type: gravity, vector: [0, -9.81]}
  - {name: tie, type: spring_damper, points: [W, P2], stiffness: 1e6, rest_length: 0.99*auto}
",
    )
    .unwrap();
    let out = dir.join("run.csv");
    let run_with = |extra: &[&str]| {
        let mut args = vec![
            "simulate",
            scene.to_str().unwrap(),
            "--coords",
            "ic",
            "--dt",
            "0.001",
            "--t-end",
            "1",
            "--out",
            out.to_str().unwrap(),
        ];
        args.extend(extra);
        mbfg(&args)
    };
    let trapezoidal = run_with(&[]);
    let err = String::from_utf8_lossy(&trapezoidal.stderr);
    assert!(trapezoidal.status.success(), "{err}");
    assert!(
        err.contains("warning: dt = 0.001 s is too coarse for tie")
            && err.contains("warning: the energy of this conservative scene drifted"),
        "{err}"
    );
    let strict = run_with(&["--strict"]);
    let line = error_line(&strict, 2);
    assert!(line.contains("too coarse for tie"), "{line}");
    let run = run_with(&["--integrator", "hermite-simpson"]);
    let err = String::from_utf8_lossy(&run.stderr);
    assert!(
        err.contains("warning: dt = 0.001 s is too coarse for"),
        "{err}"
    );
    let line = error_line(&run, 1);
    assert!(line.contains("did not converge"), "{line}");
    assert!(line.contains("(dt is too coarse for"), "{line}");
    assert!(
        line.contains("'tie'") && line.ends_with("s resolves it)"),
        "{line}"
    );
}

/// A 1 m arm with a tail of eight 2 mm links at dt = 10 ms: the tail's links turn
/// far more than a radian a step. The run is refined (a body turns 0.12 rad a step at
/// 10 ms); its tangent run at 5 ms then failed at step 18 with a body turning fast,
/// was retried with the paper's integrator factors, which failed at step 1 (a slow
/// step, not one to refine), and the run ended there. A failure on a step too
/// coarse for the motion is now refined further first: the run completes, at the
/// finer step, with the default integrators.
#[test]
fn a_whip_of_millimetre_links_is_refined_not_retried_with_other_factors() {
    let dir = scratch("mm-tail");
    let scene = dir.join("mm-tail.yaml");
    let mut text = String::from(
        "name: mm-tail
points:
  - {name: O, x: 0, y: 0, fixed: true}
  - {name: A, x: 1, y: 0}
",
    );
    let mut bodies = String::from("  - {name: arm, points: [O, A], mass: 5}\n");
    for i in 1..=8 {
        let prev = if i == 1 {
            "A".to_string()
        } else {
            format!("Q{}", i - 1)
        };
        text += &format!(
            "  - {{name: Q{i}, x: {}, y: {}}}\n",
            1.0 + 0.002 * i as f64,
            -0.001 * i as f64
        );
        bodies += &format!("  - {{name: c{i}, points: [{prev}, Q{i}], mass: 0.001}}\n");
    }
    text += "bodies:\n";
    text += &bodies;
    text += "coordinates:
  - {name: phi, type: angle, points: [O, A]}
  - {name: psi1, type: angle, points: [A, Q1]}
effects:
  - {type: gravity, vector: [0, -9.81]}
";
    std::fs::write(&scene, text).unwrap();
    let out = dir.join("run.csv");
    let run = mbfg(&[
        "simulate",
        scene.to_str().unwrap(),
        "--dt",
        "0.01",
        "--t-end",
        "0.5",
        "--out",
        out.to_str().unwrap(),
    ]);
    let err = String::from_utf8_lossy(&run.stderr);
    assert!(run.status.success(), "{err}");
    let summary = String::from_utf8_lossy(&run.stdout);
    assert!(
        summary.contains("integrated at dt =") && !summary.contains("the paper's integrators"),
        "{summary}"
    );
    assert_eq!(
        std::fs::read_to_string(&out).unwrap().lines().count(),
        51 + 1,
        "a row per step on the grid asked for"
    );
}

/// `mbfg` run by a shell under `ulimit -v <kib>` (the process's address-space limit).
fn mbfg_under_ulimit(kib: u64, args: &[&str]) -> Output {
    let script = format!("ulimit -v {kib} && exec \"$0\" \"$@\"");
    Command::new("bash")
        .arg("-c")
        .arg(script)
        .arg(env!("CARGO_BIN_EXE_mbfg"))
        .args(args)
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .output()
        .expect("run bash")
}

#[test]
fn the_address_space_limit_is_the_memory_a_run_may_use() {
    // A held batch of 2·10⁵ full-integrator steps needs a few GB: under a 1 GB
    // address-space limit it is refused at once with the figure, not aborted by the
    // allocator (exit 134) halfway through.
    let args = [
        "simulate",
        FOURBAR,
        "--dc-integrators",
        "full",
        "--batch",
        "--dt",
        "0.001",
        "--t-end",
        "200",
    ];
    let started = Instant::now();
    let line = error_line(&mbfg_under_ulimit(1_000_000, &args), 2);
    assert!(
        line.contains("needs about") && line.contains("GB of memory"),
        "{line}"
    );
    assert!(line.contains("more than the 1.0 GB available"), "{line}");
    assert!(started.elapsed() < Duration::from_secs(10));
    // An ordinary run under the same limit goes through.
    let out = mbfg_under_ulimit(
        1_000_000,
        &["simulate", FOURBAR, "--dt", "0.01", "--t-end", "1"],
    );
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

#[test]
fn a_model_too_large_names_its_file_once() {
    let out = mbfg_in(&["check", FOURBAR], &[("MBFG_MEMORY_LIMIT", "1e3")]);
    let line = error_line(&out, 2);
    assert_eq!(line.matches(FOURBAR).count(), 1, "{line}");
}

#[test]
fn out_may_not_name_the_mechanism_file_a_scene_reads() {
    let dir = scratch("mechanism");
    std::fs::create_dir_all(dir.join("mbse")).unwrap();
    std::fs::copy("scenes/pick-and-place-mbse.yaml", dir.join("scene.yaml")).unwrap();
    std::fs::copy(
        "scenes/mbse/pick-and-place.yaml",
        dir.join("mbse/pick-and-place.yaml"),
    )
    .unwrap();
    let before = text(&dir.join("mbse/pick-and-place.yaml"));
    let out = Command::new(env!("CARGO_BIN_EXE_mbfg"))
        .args(["simulate", "scene.yaml", "--dt", "0.01", "--t-end", "0.1"])
        .args(["--out", "mbse/../mbse/pick-and-place.yaml"])
        .current_dir(&dir)
        .output()
        .unwrap();
    let line = error_line(&out, 2);
    assert!(line.contains("refusing to overwrite"), "{line}");
    assert_eq!(text(&dir.join("mbse/pick-and-place.yaml")), before);
}

fn mkfifo(path: &Path) {
    let made = Command::new("mkfifo").arg(path).status().expect("mkfifo");
    assert!(made.success());
}

#[test]
fn a_fifo_as_out_is_one_stream_and_a_signal_ends_a_wait_on_it() {
    let dir = scratch("fifo");
    let fifo = dir.join("rows.csv");
    mkfifo(&fifo);
    let args = ["simulate", FOURBAR, "--dt", "0.01", "--t-end", "1", "--out"];
    let reader = {
        let fifo = fifo.clone();
        std::thread::spawn(move || std::fs::read_to_string(fifo).unwrap())
    };
    let mut full = args.to_vec();
    full.push(fifo.to_str().unwrap());
    let out = mbfg(&full);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    // The one reader gets the header and every row, not an empty stream.
    assert_eq!(reader.join().unwrap().lines().count(), 102);

    // Nobody reads: SIGTERM ends the wait at once.
    let mut child = Command::new(env!("CARGO_BIN_EXE_mbfg"))
        .args(&full)
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    std::thread::sleep(Duration::from_millis(500));
    let killed = Command::new("kill")
        .args(["-TERM", &child.id().to_string()])
        .status()
        .unwrap();
    assert!(killed.success());
    let started = Instant::now();
    loop {
        if let Some(status) = child.try_wait().unwrap() {
            assert!(!status.success());
            break;
        }
        if started.elapsed() > Duration::from_secs(5) {
            child.kill().ok();
            panic!("mbfg ignored SIGTERM while waiting on a FIFO");
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

#[test]
fn temporary_files_of_killed_runs_are_removed_by_the_next() {
    let dir = scratch("stale");
    let target = dir.join("run.csv");
    // A process id above the kernel's largest (4194304) was never alive.
    let stale = dir.join(".run.csv.9999999.tmp");
    let other = dir.join(".other.csv.9999999.tmp");
    std::fs::write(&stale, "t\n").unwrap();
    std::fs::write(&other, "t\n").unwrap();
    let out = mbfg(&[
        "simulate",
        FOURBAR,
        "--dt",
        "0.01",
        "--t-end",
        "0.1",
        "--out",
        target.to_str().unwrap(),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(!stale.exists(), "the stale temporary file is still there");
    assert!(other.exists(), "another target's file was removed");
}

#[test]
fn a_reader_that_stops_reading_ends_the_run_quietly() {
    for args in [
        vec!["check", FOURBAR],
        vec!["simulate", FOURBAR, "--dt", "0.001", "--t-end", "20"],
    ] {
        let mut child = Command::new(env!("CARGO_BIN_EXE_mbfg"))
            .args(&args)
            .current_dir(env!("CARGO_MANIFEST_DIR"))
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        // `| head -c 10`: a few bytes read, then the pipe closed.
        let mut first = [0u8; 10];
        std::io::Read::read_exact(child.stdout.as_mut().unwrap(), &mut first).unwrap();
        drop(child.stdout.take());
        let out = child.wait_with_output().unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(0), "{args:?}: {err}");
        assert!(!err.contains("error"), "{args:?}: {err}");
    }
}

#[test]
fn an_unwritable_stderr_never_ends_in_a_panic() {
    let full = || {
        std::fs::OpenOptions::new()
            .write(true)
            .open("/dev/full")
            .unwrap()
    };
    for (args, code) in [
        (vec!["simulate", FOURBAR, "--dt", "-1", "--t-end", "1"], 2),
        (
            vec!["simulate", FOURBAR, "--dt", "0.01", "--t-end", "0.1"],
            0,
        ),
        (vec!["check", "no-such-scene.yaml"], 2),
        (vec!["simulate", "--no-such-option"], 2),
    ] {
        let out = Command::new(env!("CARGO_BIN_EXE_mbfg"))
            .args(&args)
            .current_dir(env!("CARGO_MANIFEST_DIR"))
            .stdout(Stdio::null())
            .stderr(full())
            .status()
            .unwrap();
        assert_eq!(out.code(), Some(code), "{args:?}");
    }
}

/// A scene file in `dir`, the four-bar with theta, with `from` replaced by `to`.
fn theta_scene(dir: &Path, name: &str, from: &str, to: &str) -> PathBuf {
    let text = text(Path::new("scenes/fourbar-theta.yaml"));
    assert!(text.contains(from), "{from}");
    let path = dir.join(name);
    std::fs::write(&path, text.replace(from, to)).unwrap();
    path
}

/// The `worst |Φ| …` or `max |Φ| = …` figure of a summary or check report.
fn phi_figure(report: &str, key: &str) -> f64 {
    let rest = &report[report
        .find(key)
        .unwrap_or_else(|| panic!("{key} in {report}"))
        + key.len()..];
    let number: String = rest
        .trim_start()
        .chars()
        .take_while(|c| !matches!(c, ',' | ' ' | ';'))
        .collect();
    number
        .parse()
        .unwrap_or_else(|_| panic!("{number:?} in {report}"))
}

#[test]
fn a_crank_placed_at_a_huge_angle_is_assembled_to_the_usual_tolerance() {
    // θ = 10⁸ rad: an angle is no length scale; the start's |Φ| is that of any other.
    let dir = scratch("huge-angle");
    let scene = theta_scene(
        &dir,
        "s.yaml",
        "positions: {theta: 0}",
        "positions: {theta: 1e8}",
    );
    let out = mbfg(&["check", scene.to_str().unwrap()]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let phi = phi_figure(&String::from_utf8_lossy(&out.stdout), "max |Φ| =");
    assert!(phi < 1e-9, "max |Φ| = {phi}");
    let out = mbfg(&[
        "simulate",
        scene.to_str().unwrap(),
        "--coords",
        "ic",
        "--dt",
        "0.01",
        "--t-end",
        "0.05",
        "--out",
        dir.join("o.csv").to_str().unwrap(),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    // Along the run θ itself carries 10⁸·ε ≈ 10⁻⁸ rad of rounding: |Φ| stays near that
    // floor (it was 0.93 when the start was accepted unassembled).
    let phi = phi_figure(&String::from_utf8_lossy(&out.stdout), "worst |Φ|");
    assert!(phi < 1e-6, "worst |Φ| = {phi}");
}

#[test]
fn a_start_that_cannot_assemble_names_the_constraints() {
    let dir = scratch("no-assembly");
    let scene = theta_scene(&dir, "s.yaml", "length: sqrt(13)", "length: 100");
    for args in [
        vec!["check"],
        vec!["simulate", "--dt", "0.01", "--t-end", "0.1"],
    ] {
        let mut args = args.clone();
        args.insert(1, scene.to_str().unwrap());
        let line = error_line(&mbfg(&args), 2);
        assert!(line.contains("rocker: distance(P2,B)"), "{line}");
    }
}

#[test]
fn a_load_with_a_pole_inside_a_step_warns_and_strict_refuses_it() {
    let dir = scratch("pole");
    let gravity = "  - {type: gravity, vector: [0, -9.81]}";
    for (name, value) in [
        ("inverse", "-30 + 0.01/(theta+1)"),
        ("tangent", "30 + tan(5*theta)"),
    ] {
        let scene = theta_scene(
            &dir,
            &format!("{name}.yaml"),
            gravity,
            &format!("{gravity}\n  - {{name: {name}, type: torque, coordinate: theta, value: \"{value}\"}}"),
        );
        let scene = scene.to_str().unwrap();
        let out = dir.join("o.csv");
        let out = out.to_str().unwrap();
        let mut warned = 0;
        for extra in [
            vec!["--coords", "dc"],
            vec!["--coords", "ic"],
            vec!["--integrator", "hermite-simpson"],
        ] {
            let mut args = vec![
                "simulate", scene, "--dt", "0.01", "--t-end", "1", "--out", out,
            ];
            args.extend(&extra);
            let run = mbfg(&args);
            let err = String::from_utf8_lossy(&run.stderr).into_owned();
            // The tangent's pole may stop a solve instead (an error, exit 1): never
            // a silent exit 0.
            if run.status.success() {
                assert!(
                    err.contains(&format!("warning: effect '{name}' changes from"))
                        && err.contains("t = 0."),
                    "{name} {extra:?}: {err}"
                );
                assert!(err.lines().all(|l| l.chars().count() <= 300), "{err}");
                warned += 1;
                args.push("--strict");
                let strict = mbfg(&args);
                let line = error_line(&strict, 1);
                assert!(line.contains("(--strict)"), "{line}");
            } else {
                assert_eq!(run.status.code(), Some(1), "{name} {extra:?}: {err}");
            }
        }
        assert!(warned >= 1, "{name}: no run warned");
    }
}

/// A torque that grows without bound in time (exp(1/(1.2 − t)) on the double
/// pendulum) ends the run where the motion outruns any step, in DC as in IC, with the
/// steps before it kept: the DC run stops on its own failed step, never made again
/// from t = 0 with the paper's integrator factors (which cost 16× the first run and
/// failed at the same place).
#[test]
fn a_load_that_grows_without_bound_in_time_ends_the_run_where_it_outruns_the_step() {
    let dir = scratch("time-pole");
    let scene = dir.join("pole.yaml");
    let text0 = text(Path::new("scenes/double-pendulum.yaml"));
    let effect =
        "effects:\n  - {name: pole, type: torque, coordinate: theta1, value: \"exp(1/(1.2-t))\"}\n";
    assert!(text0.contains("effects:\n"));
    std::fs::write(&scene, text0.replacen("effects:\n", effect, 1)).unwrap();
    let mut last_t = Vec::new();
    for coords in ["dc", "ic"] {
        let out = dir.join(format!("{coords}.csv"));
        let run = mbfg(&[
            "simulate",
            scene.to_str().unwrap(),
            "--coords",
            coords,
            "--dt",
            "0.01",
            "--t-end",
            "2",
            "--out",
            out.to_str().unwrap(),
        ]);
        let line = error_line(&run, 1);
        assert!(
            line.contains("did not converge") && line.contains("too coarse"),
            "{coords}: {line}"
        );
        let summary = String::from_utf8_lossy(&run.stdout);
        assert!(!summary.contains("paper's integrators"), "{summary}");
        let partial = text(&dir.join(format!("{coords}.partial.csv")));
        let t = common::last_t(&partial);
        assert!((1.1..1.2).contains(&t), "{coords}: last row at t = {t}");
        last_t.push(t);
    }
    assert!((last_t[0] - last_t[1]).abs() <= 0.05, "{last_t:?}");
}

#[test]
fn a_batch_estimate_beyond_the_memory_is_refused_and_names_the_window() {
    let dir = scratch("batch-memory");
    let scene = "scenes/identification/pendulum-friction-bad.yaml";
    let readings = common::measured(
        &dir,
        Path::new("scenes/identification/pendulum-friction.yaml"),
        "0.001",
        "1",
    );
    let out = dir.join("estimate.csv");
    let run = |how: &[&str], limit: &str| {
        let mut args = vec![
            "estimate",
            scene,
            "--measurements",
            readings.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ];
        args.extend(how);
        mbfg_in(&args, &[("MBFG_MEMORY_LIMIT", limit)])
    };
    // 401 steps of 11 unknowns: about 5.8 MB.
    let line = error_line(&run(&["--batch"], "2e6"), 2);
    assert!(
        line.contains("a batch estimate of 401 steps of 11 unknowns needs about")
            && line.contains("more than the 2.0 MB available")
            && line.contains("--window N"),
        "{line}"
    );
    assert!(!out.exists());
    // The window the message names runs in that memory; the batch in more.
    let window = run(&["--window", "20"], "2e6");
    assert!(window.status.success(), "{}", common::stderr(&window));
    let batch = run(&["--batch"], "1e8");
    assert!(batch.status.success(), "{}", common::stderr(&batch));
}
