//! `mbfg simulate` and `mbfg inverse` outputs beyond the plain CSV: gzip by the
//! name's `.gz`, `--sample-dt` decimation, and the optional `--columns` (bodies,
//! energy) after the standard ones.

use mbfg::io::{read_table, Table};
use std::path::{Path, PathBuf};

mod common;
use common::{mbfg, one_error_line, stderr};

/// A fresh directory of this test's own.
fn scratch(name: &str) -> PathBuf {
    common::scratch("outputs", name)
}

/// `mbfg simulate SCENE --dt 0.001 --t-end T --out OUT` and `extra`; must succeed.
fn simulate(scene: &str, t_end: &str, out: &Path, extra: &[&str]) -> Table {
    common::simulate(scene, t_end, out, extra);
    read_table(out).unwrap()
}

fn max_abs(v: &[f64]) -> f64 {
    v.iter().fold(0.0, |a, b| a.max(b.abs()))
}

const STANDARD: [&str; 10] = [
    "t",
    "q:P.x",
    "q:P.y",
    "q:theta",
    "dq:P.x",
    "dq:P.y",
    "dq:theta",
    "ddq:P.x",
    "ddq:P.y",
    "ddq:theta",
];

#[test]
fn gzip_output_holds_the_same_table_as_plain() {
    let dir = scratch("gz");
    let plain = simulate("scenes/fourbar.yaml", "0.2", &dir.join("run.csv"), &[]);
    let gz_path = dir.join("run.csv.gz");
    let gz = simulate("scenes/fourbar.yaml", "0.2", &gz_path, &[]);
    let bytes = std::fs::read(&gz_path).unwrap();
    std::fs::remove_dir_all(&dir).ok();
    assert_eq!(&bytes[..2], &[0x1f, 0x8b], "not a gzip stream");
    assert_eq!(plain.rows, 201);
    assert_eq!(gz, plain);
}

#[test]
fn sample_dt_keeps_every_kth_row_and_the_last() {
    let dir = scratch("sample");
    let full = simulate("scenes/pendulum.yaml", "0.1", &dir.join("full.csv"), &[]);
    let sampled = simulate(
        "scenes/pendulum.yaml",
        "0.1",
        &dir.join("sampled.csv"),
        &["--sample-dt", "0.03"],
    );
    // A stride of one step is the full output.
    let same = simulate(
        "scenes/pendulum.yaml",
        "0.1",
        &dir.join("same.csv"),
        &["--sample-dt", "0.001"],
    );
    std::fs::remove_dir_all(&dir).ok();
    assert_eq!(same, full);
    assert_eq!(sampled.columns, full.columns);
    let t = sampled.column("t").unwrap();
    let expected = [0.0, 0.03, 0.06, 0.09, 0.1];
    assert_eq!(t.len(), expected.len(), "{t:?}");
    for (a, b) in t.iter().zip(expected) {
        assert!((a - b).abs() < 1e-12, "{t:?}");
    }
    // The kept rows are the full run's rows, unchanged (the solve is the same).
    let w = full.columns.len();
    for (i, k) in [0, 30, 60, 90, 100].into_iter().enumerate() {
        assert_eq!(
            sampled.values[i * w..(i + 1) * w],
            full.values[k * w..(k + 1) * w]
        );
    }
}

#[test]
fn a_sample_dt_that_is_not_a_whole_number_of_steps_is_bad_input() {
    for bad in ["0.0015", "0.0005", "0", "-0.01", "nan"] {
        let out = mbfg(&[
            "simulate",
            "scenes/pendulum.yaml",
            "--dt",
            "0.001",
            "--t-end",
            "0.01",
            "--sample-dt",
            bad,
        ]);
        let line = one_error_line(&out, 2);
        assert!(
            line.contains("--sample-dt") && line.contains("integer multiple"),
            "{line}"
        );
        assert!(out.stdout.is_empty(), "nothing is run or written");
    }
}

#[test]
fn an_unknown_column_group_is_bad_input_naming_the_valid_ones() {
    let out = mbfg(&[
        "simulate",
        "scenes/pendulum.yaml",
        "--dt",
        "0.001",
        "--t-end",
        "0.01",
        "--columns",
        "bodies,power",
    ]);
    let line = one_error_line(&out, 2);
    assert!(
        line.contains("`power`") && line.contains("bodies, energy"),
        "{line}"
    );
}

#[test]
fn pendulum_columns_follow_the_standard_ones_and_energy_balances() {
    let dir = scratch("pendulum");
    let table = simulate(
        "scenes/pendulum.yaml",
        "2",
        &dir.join("run.csv"),
        &["--columns", "energy,bodies", "--sample-dt", "0.01"],
    );
    let plain = simulate("scenes/pendulum.yaml", "0.01", &dir.join("plain.csv"), &[]);
    std::fs::remove_dir_all(&dir).ok();
    // Without --columns the contract is unchanged.
    assert_eq!(plain.columns, STANDARD);
    let mut expected: Vec<&str> = STANDARD.to_vec();
    expected.extend([
        "angle:rod",
        "x:rod",
        "y:rod",
        "vx:rod",
        "vy:rod",
        "kinetic",
        "potential",
        "energy_balance",
    ]);
    assert_eq!(table.columns, expected);
    assert_eq!(table.rows, 201);
    let peak = max_abs(&table.column("kinetic").unwrap());
    let balance = max_abs(&table.column("energy_balance").unwrap());
    assert!(peak > 1.0 && balance <= 1e-3 * peak, "{balance} vs {peak}");
    let (angle, theta) = (
        table.column("angle:rod").unwrap(),
        table.column("q:theta").unwrap(),
    );
    // The rod swings through −π, where atan2 jumps: the angle stays continuous.
    assert!(theta.iter().any(|&v| v < -3.0));
    for (a, b) in angle.iter().zip(&theta) {
        assert!((a - b).abs() < 1e-9, "{a} vs {b}");
    }
}

#[test]
fn spring_damper_balance_closes_with_the_damper_work() {
    let dir = scratch("damper");
    let table = simulate(
        "scenes/spring-damper.yaml",
        "3",
        &dir.join("run.csv.gz"),
        &["--columns", "energy"],
    );
    std::fs::remove_dir_all(&dir).ok();
    assert_eq!(
        table.columns[STANDARD.len()..],
        ["kinetic", "potential", "work:spring", "energy_balance"]
    );
    let kinetic = table.column("kinetic").unwrap();
    let potential = table.column("potential").unwrap();
    let work = table.column("work:spring").unwrap();
    let peak = max_abs(&kinetic);
    let balance = max_abs(&table.column("energy_balance").unwrap());
    let drift: Vec<f64> = kinetic
        .iter()
        .zip(&potential)
        .map(|(k, v)| k + v - kinetic[0] - potential[0])
        .collect();
    assert!(balance <= 1e-3 * peak, "{balance} vs {peak}");
    assert!(max_abs(&drift) > 1e-2 * peak, "the damper takes energy out");
    assert!(*work.last().unwrap() < 0.0);
}

#[test]
fn a_partial_gzip_result_is_named_partial_csv_gz_and_sampled() {
    let dir = scratch("partial");
    let scene = dir.join("nan.yaml");
    let mut yaml = std::fs::read_to_string("scenes/pendulum.yaml").unwrap();
    yaml += "  - {type: torque, coordinate: theta, value: \"sqrt(0.3-t)\"}\n";
    std::fs::write(&scene, yaml).unwrap();
    let out = dir.join("run.csv.gz");
    let run = mbfg(&[
        "simulate",
        scene.to_str().unwrap(),
        "--dt",
        "0.01",
        "--t-end",
        "1",
        "--sample-dt",
        "0.1",
        "--columns",
        "energy",
        "--out",
        out.to_str().unwrap(),
    ]);
    let line = one_error_line(&run, 1);
    let partial = dir.join("run.partial.csv.gz");
    assert!(line.contains("run.partial.csv.gz"), "{line}");
    assert!(!out.exists());
    let table = read_table(&partial).unwrap();
    std::fs::remove_dir_all(&dir).ok();
    // Steps 0..=30 were kept: rows at 0, 0.1, 0.2, 0.3.
    let t = table.column("t").unwrap();
    assert_eq!(t.len(), 4, "{t:?}");
    assert!((t[3] - 0.3).abs() < 1e-12, "{t:?}");
    assert!(
        table.column("work:torque1").is_some(),
        "{:?}",
        table.columns
    );
}

#[test]
fn inverse_writes_gzip_samples_and_closes_the_balance_with_the_drive_work() {
    let dir = scratch("inverse");
    let prescription = dir.join("theta.csv");
    // theta(t) = −t²: a pendulum driven down from horizontal.
    let mut text = String::from("t,theta\n");
    for k in 0..=200 {
        let t = k as f64 * 0.005;
        text += &format!("{t},{}\n", -t * t);
    }
    std::fs::write(&prescription, text).unwrap();
    let out = dir.join("inv.csv.gz");
    let run = mbfg(&[
        "inverse",
        "scenes/pendulum.yaml",
        "--trajectory",
        prescription.to_str().unwrap(),
        "--sample-dt",
        "0.05",
        "--columns",
        "energy",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(run.status.success(), "{}", stderr(&run));
    let table = read_table(&out).unwrap();
    std::fs::remove_dir_all(&dir).ok();
    assert_eq!(table.rows, 21);
    let n = table.columns.len();
    assert_eq!(table.columns[n - 2..], ["work:Q", "energy_balance"]);
    assert!(table.columns.contains(&"Q:theta".to_string()));
    let peak = max_abs(&table.column("kinetic").unwrap());
    let balance = max_abs(&table.column("energy_balance").unwrap());
    assert!(balance <= 1e-3 * peak, "{balance} vs {peak}");
}

/// `--columns joints`: the forces on the bodies at a pin balance (the four-bar's pins
/// carry no mass and no load), and the ground's reactions hold the mechanism up.
#[test]
fn joint_force_columns_balance_at_the_pins() {
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_mbfg"))
        .args([
            "simulate",
            "scenes/fourbar.yaml",
            "--dt",
            "0.001",
            "--t-end",
            "0.5",
            "--columns",
            "joints",
        ])
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .output()
        .unwrap();
    assert!(out.status.success());
    let text = String::from_utf8_lossy(&out.stdout);
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    let col = |name: &str| {
        header
            .iter()
            .position(|h| *h == name)
            .unwrap_or_else(|| panic!("{name}"))
    };
    let (a, b) = (col("F:crank@P1.x"), col("F:coupler@P1.x"));
    let (c, d) = (col("F:coupler@P2.y"), col("F:rocker@P2.y"));
    let mut rows = 0;
    for line in lines {
        let v: Vec<f64> = line.split(',').map(|x| x.parse().unwrap()).collect();
        assert!(
            (v[a] + v[b]).abs() <= 1e-6 * v[a].abs().max(1.0),
            "P1: {} {}",
            v[a],
            v[b]
        );
        assert!(
            (v[c] + v[d]).abs() <= 1e-6 * v[c].abs().max(1.0),
            "P2: {} {}",
            v[c],
            v[d]
        );
        rows += 1;
    }
    assert_eq!(rows, 501);
}

/// `--columns constraints`: one `R:<name>` per scene constraint. The slider-crank's
/// guide holds the 0.5 kg block up against gravity and the rod: with the rod's force on
/// the block (`joints`), m_S a_S = m_S g + R n − F:rod@S along the guide's normal
/// n = (0, 1). A redundant constraint carries nothing.
#[test]
fn constraint_force_columns_hold_the_block_on_its_guide() {
    let dir = scratch("constraints");
    let table = simulate(
        "scenes/slider-crank.yaml",
        "0.5",
        &dir.join("slider-crank.csv"),
        &["--columns", "joints,constraints"],
    );
    assert_eq!(table.columns.last().map(String::as_str), Some("R:guide"));
    let col = |name: &str| table.column(name).unwrap_or_else(|| panic!("{name}"));
    let (r, ay, fy) = (col("R:guide"), col("ddq:S.y"), col("F:rod@S.y"));
    let largest = max_abs(&r);
    assert!(largest > 1.0, "{largest}");
    for k in 0..r.len() {
        let normal = 0.5 * (ay[k] + 9.81) + fy[k];
        assert!(
            (r[k] - normal).abs() <= 1e-6 * largest,
            "{k}: {} {normal}",
            r[k]
        );
    }
    let table = simulate(
        "scenes/hard/redundant-fourbar.yaml",
        "0.1",
        &dir.join("redundant.csv"),
        &["--columns", "constraints"],
    );
    assert!(col_all_zero(&table, "R:coupler-again"));
}

fn col_all_zero(table: &Table, name: &str) -> bool {
    table.column(name).unwrap().iter().all(|v| *v == 0.0)
}

#[test]
fn a_refined_runs_columns_integrate_over_every_step_it_took() {
    // At dt = 10 ms the link turns over a radian a step: the run is integrated at a
    // finer step and writes the 10 ms rows. The work columns integrate over the
    // finer steps; integrated over the rows they were off by 23 % of the energy.
    let dir = scratch("refined");
    let scene = format!(
        "{}/tests/data/fast-link-refined.yaml",
        env!("CARGO_MANIFEST_DIR")
    );
    let run = |out: &Path, extra: &[&str]| {
        let mut args = vec![
            "simulate", &scene, "--coords", "ic", "--dt", "0.01", "--t-end", "0.3", "--out",
        ];
        args.push(out.to_str().unwrap());
        args.extend(extra);
        let run = mbfg(&args);
        assert!(run.status.success(), "{}", stderr(&run));
        String::from_utf8_lossy(&run.stdout).to_string()
    };
    let summary = run(&dir.join("plain.csv"), &[]);
    assert!(summary.contains("integrated at dt"), "{summary}");
    run(&dir.join("columns.csv"), &["--columns", "energy,bodies"]);
    let plain = read_table(&dir.join("plain.csv")).unwrap();
    let table = read_table(&dir.join("columns.csv")).unwrap();
    std::fs::remove_dir_all(&dir).ok();
    // The rows are the same, on the 10 ms grid.
    assert_eq!(table.rows, 31);
    for name in &plain.columns {
        assert_eq!(plain.column(name), table.column(name), "{name}");
    }
    let peak = max_abs(&table.column("kinetic").unwrap());
    let balance = max_abs(&table.column("energy_balance").unwrap());
    assert!(balance < 0.01 * peak, "{balance} vs {peak}");
    let (theta, angle) = (
        table.column("q:theta").unwrap(),
        table.column("angle:link1").unwrap(),
    );
    for (a, b) in theta.iter().zip(&angle) {
        assert!((a - b).abs() < 1e-9, "{a} vs {b}");
    }
}
