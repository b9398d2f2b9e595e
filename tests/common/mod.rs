//! Helpers shared by the integration tests.
#![allow(dead_code)]

use std::path::{Path, PathBuf};

/// A four-bar with a declared crank angle, gravity and one sensor of every kind (a
/// gyroscope and an accelerometer on a body whose first point is fixed too).
pub const SENSOR_SCENE: &str = "
points:
  - {name: A, x: 0, y: 0, fixed: true}
  - {name: P1, x: 1, y: 0}
  - {name: P2, x: 1, y: 2}
  - {name: B, x: 4, y: 0, fixed: true}
bodies:
  - {name: crank, points: [A, P1], mass: 1}
  - {name: coupler, points: [P1, P2], mass: 2}
  - {name: rocker, points: [B, P2], mass: 4, length: sqrt(13)}
coordinates:
  - {name: theta, type: angle, points: [A, P1]}
independent: [theta]
initial:
  velocities: {theta: 2}
effects:
  - {type: gravity, vector: [0.5, -9.81]}
sensors:
  - {name: enc, type: encoder, coordinate: theta, sigma: 0.0174533, resolution: 4096, rate: 200}
  - {name: gyro, type: gyroscope, body: coupler, sigma: 9.84e-4}
  - {name: gyro0, type: gyroscope, body: crank, sigma: 1e-3}
  - {name: acc, type: accelerometer, body: coupler, point: P2, sigma: 0.056}
  - {name: acc0, type: accelerometer, body: rocker, point: B, sigma: 0.056}
  - {name: cam, type: marker, point: P2, sigma: 0.001, rate: 50}
  - {name: gap, type: expression, value: \"x(P2) - x(P1)^2 + rate(theta)*omega(rocker) + sin(angle(coupler)) + t*vy(P2)\", sigma: 0.01}
estimation:
  process_sigma: 0.5
  initial_sigma: {theta: 0.3}
  initial_velocity_sigma: {theta: 1}
  inputs:
    - {coordinate: theta, sigma_rate: 20}
";

/// A scene of the suite by file name.
pub fn scene_path(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("scenes")
        .join(name)
}

/// A small deterministic generator (no dependency for a few random numbers).
pub struct Rng(pub u64);

impl Rng {
    /// Uniform in [−1, 1).
    pub fn uniform(&mut self) -> f64 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((self.0 >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0
    }

    /// n values uniform in [−scale, scale).
    pub fn values(&mut self, n: usize, scale: f64) -> Vec<f64> {
        (0..n).map(|_| scale * self.uniform()).collect()
    }
}

/// Runs the `mbfg` binary in the crate's directory with extra environment variables.
pub fn mbfg_env(args: &[&str], env: &[(&str, &str)]) -> std::process::Output {
    let mut c = std::process::Command::new(env!("CARGO_BIN_EXE_mbfg"));
    c.args(args).current_dir(env!("CARGO_MANIFEST_DIR"));
    for (k, v) in env {
        c.env(k, v);
    }
    c.output().expect("run mbfg")
}

/// Runs the `mbfg` binary in the crate's directory.
pub fn mbfg(args: &[&str]) -> std::process::Output {
    mbfg_env(args, &[])
}

/// A fresh, empty directory for one test's files.
pub fn scratch(group: &str, name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("mbfg-{group}-{}-{name}", std::process::id()));
    std::fs::remove_dir_all(&dir).ok();
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// A process's standard error as text.
pub fn stderr(out: &std::process::Output) -> String {
    String::from_utf8_lossy(&out.stderr).into_owned()
}

/// A failing call: the exit code, and exactly one line `error: …` on stderr.
pub fn one_error_line(out: &std::process::Output, code: i32) -> String {
    let err = stderr(out);
    assert_eq!(out.status.code(), Some(code), "stderr: {err}");
    let text = err.strip_suffix('\n').unwrap_or(&err);
    assert!(!text.contains('\n'), "one line expected, got:\n{err}");
    assert!(text.starts_with("error: "), "{text}");
    text.to_string()
}

/// RMSE over the free points' x, y of `run` against `references/<reference>/`, at
/// the reference's samples that the run has.
pub fn reference_rmse(
    model: &mbfg::Model,
    run: &mbfg::forward::Trajectory,
    reference: &str,
) -> f64 {
    use mbfg::model::PointSlot;
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("references")
        .join(reference)
        .join("reference.csv.gz");
    let truth = mbfg::io::read_table(&path).unwrap_or_else(|e| panic!("{e}"));
    let t_ref = truth.column("t").unwrap();
    let step = t_ref[1] - t_ref[0];
    let cols: Vec<usize> = model
        .points
        .iter()
        .filter_map(|p| match p {
            PointSlot::Free(i) => Some(*i),
            PointSlot::Fixed(_) => None,
        })
        .flat_map(|i| [i, i + 1])
        .collect();
    let reference_cols: Vec<Vec<f64>> = cols
        .iter()
        .map(|&c| truth.column(&format!("q:{}", model.names[c])).unwrap())
        .collect();
    let (mut sum, mut count) = (0.0, 0usize);
    for (k, &t) in run.t.iter().enumerate() {
        let j = (t / step).round() as usize;
        if j >= t_ref.len() || (t_ref[j] - t).abs() > 1e-9 {
            continue;
        }
        for (c, col) in cols.iter().zip(&reference_cols) {
            let d = run.q_at(k)[*c] - col[j];
            sum += d * d;
            count += 1;
        }
    }
    assert!(count > 0, "no common samples with {}", path.display());
    (sum / count as f64).sqrt()
}

/// `mbfg simulate SCENE --dt 0.001 --t-end T --out OUT` and `extra`; must succeed.
pub fn simulate(scene: &str, t_end: &str, out: &Path, extra: &[&str]) -> std::process::Output {
    let mut args = vec![
        "simulate",
        scene,
        "--dt",
        "0.001",
        "--t-end",
        t_end,
        "--out",
        out.to_str().unwrap(),
    ];
    args.extend(extra);
    let run = mbfg(&args);
    assert!(run.status.success(), "{}", stderr(&run));
    run
}

/// The time of a trajectory CSV's last row (its first column).
pub fn last_t(csv: &str) -> f64 {
    let row = csv.lines().last().expect("an empty CSV");
    let t = row.split(',').next().unwrap_or("");
    t.parse()
        .unwrap_or_else(|e| panic!("last row {row:?}: t {t:?}: {e}"))
}

/// The estimate of the model `m` from `record` with `smoothing` at the defaults
/// otherwise: its final steps and its summary.
pub fn estimate_record(
    m: std::sync::Arc<mbfg::Model>,
    record: &mbfg::estimate::Record,
    smoothing: mbfg::estimate::Smoothing,
) -> (mbfg::estimate::Estimates, mbfg::estimate::EstimateSummary) {
    let options = mbfg::estimate::EstimateOptions {
        smoothing,
        ..mbfg::estimate::EstimateOptions::default()
    };
    estimate_with(m, record, &options)
}

/// The estimate of the model `m` from `record` with `options`: its final steps and
/// its summary.
pub fn estimate_with(
    m: std::sync::Arc<mbfg::Model>,
    record: &mbfg::estimate::Record,
    options: &mbfg::estimate::EstimateOptions,
) -> (mbfg::estimate::Estimates, mbfg::estimate::EstimateSummary) {
    let mut table = mbfg::estimate::Estimates::for_model(&m);
    let summary = mbfg::estimate::estimate(m, record, options, &mut |e| {
        table.push(e);
        Ok(())
    })
    .unwrap();
    (table, summary)
}

/// `mbfg simulate` of `scene` over 2 s (`--dt`, sampled every 5 ms) and `mbfg measure`
/// of its sensors (`seed`): the readings' file in `dir`.
pub fn measured(dir: &Path, scene: &Path, dt: &str, seed: &str) -> PathBuf {
    let truth = dir.join("truth.csv");
    let out = mbfg(&[
        "simulate",
        scene.to_str().unwrap(),
        "--dt",
        dt,
        "--t-end",
        "2",
        "--sample-dt",
        "0.005",
        "--out",
        truth.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    let all = dir.join("all.csv");
    let out = mbfg(&[
        "measure",
        scene.to_str().unwrap(),
        "--trajectory",
        truth.to_str().unwrap(),
        "--seed",
        seed,
        "--out",
        all.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    all
}
