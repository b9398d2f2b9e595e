//! `mbfg simulate --until EXPR`: the run ends with the step after the expression
//! crosses zero, the summary names the time of the zero located within that step, and
//! a name that is not a state quantity is refused with the closest valid one.

mod common;

use common::{mbfg, one_error_line, scratch, stderr};

fn rows(path: &std::path::Path) -> (Vec<String>, Vec<Vec<f64>>) {
    let text = std::fs::read_to_string(path).unwrap();
    let mut lines = text.lines();
    let header = lines
        .next()
        .unwrap()
        .split(',')
        .map(str::to_string)
        .collect();
    let rows = lines
        .map(|l| l.split(',').map(|v| v.parse().unwrap()).collect())
        .collect();
    (header, rows)
}

#[test]
fn a_run_ends_where_the_expression_crosses_zero() {
    let dir = scratch("until", "theta");
    let out = dir.join("run.csv");
    let run = mbfg(&[
        "simulate",
        "examples/tutorial/swinging-bar.yaml",
        "--dt",
        "0.001",
        "--t-end",
        "5",
        "--until",
        "theta - 0.2",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(run.status.success(), "{}", stderr(&run));
    let summary = String::from_utf8_lossy(&run.stdout).into_owned();
    let at: f64 = summary
        .split("stopped by --until 'theta - 0.2' at t = ")
        .nth(1)
        .and_then(|r| r.split(' ').next())
        .unwrap_or_else(|| panic!("{summary}"))
        .parse()
        .unwrap();
    let (header, rows) = rows(&out);
    assert!(
        summary.starts_with(&format!("{} steps", rows.len())),
        "{summary}"
    );
    let col = |name: &str| header.iter().position(|h| h == name).unwrap();
    let (t, q, v) = (col("t"), col("q:theta"), col("dq:theta"));
    let (a, b) = (&rows[rows.len() - 2], &rows[rows.len() - 1]);
    // The zero lies in the last step, and only there: theta - 0.2 changes sign across it.
    assert!(a[t] < at && at <= b[t], "{} < {at} <= {}", a[t], b[t]);
    assert!(a[q] < 0.2 && b[q] >= 0.2, "{} {}", a[q], b[q]);
    assert!(rows[..rows.len() - 1].iter().all(|r| r[q] < 0.2));
    // At the located time, the cubic Hermite interpolant of theta is 0.2.
    let h = b[t] - a[t];
    let s = (at - a[t]) / h;
    let theta = (2.0 * s.powi(3) - 3.0 * s * s + 1.0) * a[q]
        + (s.powi(3) - 2.0 * s * s + s) * h * a[v]
        + (-2.0 * s.powi(3) + 3.0 * s * s) * b[q]
        + (s.powi(3) - s * s) * h * b[v];
    assert!((theta - 0.2).abs() < 1e-9, "theta({at}) = {theta}");
    // The same stop where the rows are held (optional columns need the whole run).
    let held = dir.join("held.csv");
    let run = mbfg(&[
        "simulate",
        "examples/tutorial/swinging-bar.yaml",
        "--dt",
        "0.001",
        "--t-end",
        "5",
        "--until",
        "theta - 0.2",
        "--columns",
        "energy",
        "--out",
        held.to_str().unwrap(),
    ]);
    assert!(run.status.success(), "{}", stderr(&run));
    assert_eq!(self::rows(&held).1.len(), rows.len());
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn a_condition_that_never_crosses_runs_to_the_end() {
    let run = mbfg(&[
        "simulate",
        "scenes/pendulum.yaml",
        "--dt",
        "0.01",
        "--t-end",
        "0.5",
        "--until",
        "t - 10",
    ]);
    assert!(run.status.success(), "{}", stderr(&run));
    assert!(!stderr(&run).contains("stopped by"), "{}", stderr(&run));
    let csv = String::from_utf8_lossy(&run.stdout);
    assert_eq!(csv.lines().count(), 1 + 51);
}

#[test]
fn a_name_that_is_not_a_state_quantity_is_refused_with_the_closest() {
    let run = mbfg(&[
        "simulate",
        "examples/tutorial/swinging-bar.yaml",
        "--dt",
        "0.01",
        "--t-end",
        "1",
        "--until",
        "thetta + 1",
    ]);
    let line = one_error_line(&run, 2);
    assert!(
        line.contains("'thetta' is not a state quantity; did you mean 'theta'?"),
        "{line}"
    );
}
