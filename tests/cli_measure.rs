//! `mbfg measure` end to end: seeded noise (reproducible, of the declared σ), each
//! sensor at its rate (empty cells between), quantized encoders, and bad input (exit
//! 2, one line naming what is wrong).

mod common;
use common::{mbfg, one_error_line, scratch, stderr};
use std::path::{Path, PathBuf};

const SENSORS: &str = "
sensors:
  - {name: enc, type: encoder, coordinate: theta, sigma: 0.0174533, resolution: 4096, rate: 200}
  - {name: raw, type: encoder, coordinate: theta, sigma: 0.01}
  - {name: gyro, type: gyroscope, body: coupler, sigma: 9.84e-4}
  - {name: acc, type: accelerometer, body: coupler, point: P1, sigma: 0.056}
  - {name: cam, type: marker, point: P2, sigma: 0.001, rate: 50}
  - {name: gap, type: expression, value: \"x(P2) - x(P1)\", sigma: 0.01}
";

/// The four-bar with an angle coordinate and `sensors`, in `dir`.
fn scene(dir: &Path, sensors: &str) -> PathBuf {
    let base = std::fs::read_to_string(common::scene_path("fourbar-theta.yaml")).unwrap();
    let path = dir.join("scene.yaml");
    std::fs::write(&path, format!("{base}{sensors}")).unwrap();
    path
}

/// A simulated truth of `t_end` s at dt = 1 ms.
fn truth(dir: &Path, scene: &Path, t_end: &str) -> PathBuf {
    let path = dir.join("truth.csv");
    let out = mbfg(&[
        "simulate",
        scene.to_str().unwrap(),
        "--dt",
        "0.001",
        "--t-end",
        t_end,
        "--out",
        path.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    path
}

struct Csv {
    header: Vec<String>,
    /// None for an empty cell.
    rows: Vec<Vec<Option<f64>>>,
}

impl Csv {
    fn read(path: &Path) -> Csv {
        let text = std::fs::read_to_string(path).unwrap();
        let mut lines = text.lines();
        let header = lines.next().unwrap().split(',').map(String::from).collect();
        let rows = lines
            .map(|l| {
                l.split(',')
                    .map(|v| (!v.is_empty()).then(|| v.parse().unwrap()))
                    .collect()
            })
            .collect();
        Csv { header, rows }
    }

    fn column(&self, name: &str) -> Vec<Option<f64>> {
        let j = self.header.iter().position(|c| c == name).unwrap();
        self.rows.iter().map(|r| r[j]).collect()
    }
}

fn measure(scene: &Path, truth: &Path, out: &Path, extra: &[&str]) -> std::process::Output {
    let mut args = vec![
        "measure",
        scene.to_str().unwrap(),
        "--trajectory",
        truth.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ];
    args.extend(extra);
    mbfg(&args)
}

#[test]
fn readings_are_seeded_noisy_quantized_and_at_their_rates() {
    let dir = scratch("measure", "readings");
    let scene = scene(&dir, SENSORS);
    let truth = truth(&dir, &scene, "2");
    let (a, b, c) = (dir.join("a.csv"), dir.join("b.csv"), dir.join("c.csv"));
    for (path, seed) in [(&a, "7"), (&b, "7"), (&c, "8")] {
        let out = measure(&scene, &truth, path, &["--seed", seed]);
        assert!(out.status.success(), "{}", stderr(&out));
        let summary = String::from_utf8_lossy(&out.stdout);
        assert!(
            summary.contains("readings of 6 sensors at 2001 times (seed"),
            "{summary}"
        );
    }
    let bytes = |p: &Path| std::fs::read(p).unwrap();
    assert_eq!(
        bytes(&a),
        bytes(&b),
        "the same seed gave different readings"
    );
    assert_ne!(
        bytes(&a),
        bytes(&c),
        "different seeds gave the same readings"
    );

    let m = Csv::read(&a);
    assert_eq!(
        m.header,
        ["t", "enc", "raw", "gyro", "acc.x", "acc.y", "cam.x", "cam.y", "gap"]
    );
    assert_eq!(m.rows.len(), 2001);
    // 200 Hz and 50 Hz on a 1 kHz trajectory: every fifth and every twentieth row.
    let enc = m.column("enc");
    let cam = m.column("cam.x");
    for (k, (e, c)) in enc.iter().zip(&cam).enumerate() {
        assert_eq!(e.is_some(), k % 5 == 0, "enc at row {k}");
        assert_eq!(c.is_some(), k % 20 == 0, "cam at row {k}");
    }
    let quantum = std::f64::consts::TAU / 4096.0;
    for v in enc.iter().flatten() {
        let k = v / quantum;
        assert!(
            (k - k.round()).abs() < 1e-6,
            "{v} is not a multiple of 2π/4096"
        );
    }
    // The noise of `raw` against the true theta: mean 0, σ = 0.01.
    let t = Csv::read(&truth);
    let theta = t.column("q:theta");
    let r: Vec<f64> = m
        .column("raw")
        .iter()
        .zip(&theta)
        .map(|(v, th)| v.unwrap() - th.unwrap())
        .collect();
    let n = r.len() as f64;
    let mean = r.iter().sum::<f64>() / n;
    let sd = (r.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n).sqrt();
    assert!(mean.abs() < 4.0 * 0.01 / n.sqrt(), "mean {mean:e}");
    assert!((sd / 0.01 - 1.0).abs() < 0.07, "sd {sd:e}");
    // The quantized encoder: its error is the noise and the rounding together.
    let e: Vec<f64> = enc
        .iter()
        .zip(&theta)
        .filter_map(|(v, th)| Some(v.as_ref()? - th.unwrap()))
        .collect();
    let sd_e = (e.iter().map(|x| x * x).sum::<f64>() / e.len() as f64).sqrt();
    let expect = (0.0174533f64.powi(2) + quantum * quantum / 12.0).sqrt();
    assert!((sd_e / expect - 1.0).abs() < 0.15, "{sd_e:e} vs {expect:e}");

    // --rate sets the sensors without their own: 100 Hz, every tenth row.
    let d = dir.join("d.csv");
    let out = measure(&scene, &truth, &d, &["--seed", "7", "--rate", "100"]);
    assert!(out.status.success(), "{}", stderr(&out));
    let m = Csv::read(&d);
    // Rows where some sensor reads: 200 Hz (enc) is the finest.
    assert_eq!(m.rows.len(), 401);
    let gyro = m.column("gyro");
    for (k, g) in gyro.iter().enumerate() {
        assert_eq!(g.is_some(), k % 2 == 0, "gyro at row {k}");
    }
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn bad_input_is_one_line() {
    let dir = scratch("measure", "errors");
    let scene_path = scene(&dir, SENSORS);
    let truth = truth(&dir, &scene_path, "0.05");
    let out_csv = dir.join("m.csv");
    let s = scene_path.to_str().unwrap();
    let tr = truth.to_str().unwrap();

    // A rate whose times are not rows of the trajectory.
    let e = one_error_line(
        &measure(
            &scene_path,
            &truth,
            &out_csv,
            &["--seed", "1", "--rate", "300"],
        ),
        2,
    );
    assert!(
        e.contains("sensor 'raw' reads at 300 Hz") && e.contains("is not a time of the trajectory"),
        "{e}"
    );
    let e = one_error_line(
        &measure(
            &scene_path,
            &truth,
            &out_csv,
            &["--seed", "1", "--rate", "-5"],
        ),
        2,
    );
    assert!(e.contains("--rate must be a positive number"), "{e}");
    assert!(!out_csv.exists(), "a failed run left its output");

    // A missing column.
    let text = std::fs::read_to_string(&truth).unwrap();
    let header: Vec<&str> = text.lines().next().unwrap().split(',').collect();
    let drop = header.iter().position(|c| *c == "ddq:P1.y").unwrap();
    let cut: String = text
        .lines()
        .map(|l| {
            let mut f: Vec<&str> = l.split(',').collect();
            f.remove(drop);
            f.join(",") + "\n"
        })
        .collect();
    let cut_path = dir.join("cut.csv");
    std::fs::write(&cut_path, cut).unwrap();
    let e = one_error_line(
        &measure(&scene_path, &cut_path, &out_csv, &["--seed", "1"]),
        2,
    );
    assert!(e.contains("no column `ddq:P1.y`"), "{e}");
    // ... which a scene whose sensors read no accelerations does not need.
    let pos = scene(
        &dir,
        "\nsensors:\n  - {name: cam, type: marker, point: P2, sigma: 0.001}\n",
    );
    let out = measure(&pos, &cut_path, &out_csv, &["--seed", "1"]);
    assert!(out.status.success(), "{}", stderr(&out));

    // A scene without sensors.
    let e = one_error_line(
        &mbfg(&[
            "measure",
            "scenes/fourbar-theta.yaml",
            "--trajectory",
            tr,
            "--seed",
            "1",
        ]),
        2,
    );
    assert!(
        e.contains("scene scenes/fourbar-theta.yaml has no sensors: "),
        "{e}"
    );

    // Scene errors: an unknown sensor type, a sensor on a fixed point.
    let bad = scene(&dir, "\nsensors:\n  - {name: s, type: sonar, sigma: 1}\n");
    let e = one_error_line(
        &mbfg(&[
            "measure",
            bad.to_str().unwrap(),
            "--trajectory",
            tr,
            "--seed",
            "1",
        ]),
        2,
    );
    assert!(
        e.contains("sensors[0].type: unknown sensor type 'sonar'"),
        "{e}"
    );
    let fixed = scene(
        &dir,
        "\nsensors:\n  - {name: m, type: marker, point: B, sigma: 1}\n",
    );
    let e = one_error_line(
        &mbfg(&[
            "measure",
            fixed.to_str().unwrap(),
            "--trajectory",
            tr,
            "--seed",
            "1",
        ]),
        2,
    );
    assert!(
        e.contains("sensor 'm': point 'B' is fixed; it observes nothing of the motion"),
        "{e}"
    );

    // A missing --seed is clap's one line.
    let e = one_error_line(&mbfg(&["measure", s, "--trajectory", tr]), 2);
    assert!(e.contains("--seed"), "{e}");
    std::fs::remove_dir_all(&dir).ok();
}
