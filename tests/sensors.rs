//! Sensors: the scene's `sensors:` and `estimation:` sections, each sensor's
//! measurement function against known values, its closed-form Jacobians against
//! central finite differences at generic (not assembled) states, quantization, and
//! the seeded noise of `measure`.

use mbfg::sensors::{measure::measure, Sensor, SensorKind};
use mbfg::{Model, Scene};
use std::path::Path;
mod common;
use common::Rng;

use common::SENSOR_SCENE as SCENE;

fn model_of(text: &str) -> mbfg::Result<Model> {
    Model::new(&Scene::from_str(text, Path::new("sensors.yaml"))?)
}

fn model() -> Model {
    model_of(SCENE).unwrap()
}

fn scene_error(text: &str) -> String {
    match Scene::from_str(text, Path::new("bad.yaml")) {
        Ok(_) => panic!("accepted:\n{text}"),
        Err(e) => e.to_string(),
    }
}

/// SCENE with its `sensors:` replaced by `sensors` (one entry per line).
fn with_sensors(sensors: &str) -> String {
    let head = SCENE.split("sensors:").next().unwrap();
    format!("{head}sensors:\n{sensors}\n")
}

#[test]
fn the_scene_declares_sensors_and_estimation() {
    let m = model();
    let names: Vec<&str> = m.sensors.iter().map(|s| s.name.as_str()).collect();
    assert_eq!(names, ["enc", "gyro", "gyro0", "acc", "acc0", "cam", "gap"]);
    let theta = m.index_of("theta").unwrap();
    assert!(matches!(m.sensors[0].kind, SensorKind::Encoder { coordinate } if coordinate == theta));
    assert_eq!(m.sensors[0].resolution, Some(4096));
    assert_eq!(m.sensors[0].rate, Some(200.0));
    assert_eq!(m.sensors[1].rate, None);
    assert_eq!(m.sensors[3].columns(), ["acc.x", "acc.y"]);
    assert_eq!(m.sensors[0].columns(), ["enc"]);
    assert_eq!(m.sensors[3].reads(), [true, false, true]);
    assert_eq!(m.sensors[1].reads(), [true, true, false]);
    assert_eq!(m.sensors[6].reads(), [true, true, false]);
    assert_eq!(m.estimation.process_sigma, Some(0.5));
    assert_eq!(m.estimation.initial_sigma, [(theta, 0.3)]);
    assert_eq!(m.estimation.initial_velocity_sigma, [(theta, 1.0)]);
    assert_eq!(m.estimation.inputs, [(theta, 20.0)]);
    assert_eq!(m.sensor_index("cam"), Some(5));
}

#[test]
fn a_scene_without_sensors_has_none() {
    let scene = Scene::load(common::scene_path("fourbar-theta.yaml")).unwrap();
    assert!(scene.sensors.is_empty());
    assert_eq!(scene.estimation, Default::default());
    let m = Model::new(&scene).unwrap();
    assert!(m.sensors.is_empty());
    assert_eq!(m.estimation, Default::default());
}

#[test]
fn bad_sensors_are_refused_with_one_line() {
    let cases: &[(&str, &str)] = &[
        ("  - {name: s, type: lidar, sigma: 1}", "sensors[0].type: unknown sensor type 'lidar'"),
        ("  - {name: s, type: encoder, coordinate: theta, sigma: 1, gain: 2}", "sensors[0].gain: unknown key 'gain'"),
        ("  - {name: s, type: encoder, coordinate: phi, sigma: 1}", "sensors[0].coordinate: unknown coordinate 'phi'"),
        ("  - {name: s, type: encoder, coordinate: theta, sigma: 0}", "sensors[0].sigma: must be positive"),
        ("  - {name: s, type: encoder, coordinate: theta, sigma: -1}", "sensors[0].sigma: must be positive"),
        ("  - {name: s, type: encoder, coordinate: theta}", "sensors[0].sigma: missing required key"),
        ("  - {name: s, type: encoder, coordinate: theta, sigma: 1, rate: 0}", "sensors[0].rate: must be positive"),
        ("  - {name: s, type: encoder, coordinate: theta, sigma: 1, resolution: 10.5}", "sensors[0].resolution: must be a whole number"),
        ("  - {name: s, type: encoder, coordinate: P1.x, sigma: 1, resolution: 10}", "coordinate 'P1.x' is not an angle"),
        ("  - {name: s, type: gyroscope, body: arm, sigma: 1}", "sensors[0].body: unknown body 'arm'"),
        ("  - {name: s, type: accelerometer, body: crank, point: P2, sigma: 1}", "point 'P2' is not on body 'crank'"),
        ("  - {name: s, type: marker, point: A, sigma: 1}", "sensor 's': point 'A' is fixed; it observes nothing of the motion"),
        ("  - {name: s, type: marker, point: Q, sigma: 1}", "unknown point 'Q'"),
        ("  - {name: s, type: expression, value: 2*t, sigma: 1}", "does not depend on the state"),
        ("  - {name: s, type: expression, value: x(Q), sigma: 1}", "no point named 'Q'"),
        ("  - {name: t, type: encoder, coordinate: theta, sigma: 1}", "sensors[0].name: duplicate name 't'"),
        ("  - {name: s, type: marker, point: P1, sigma: 1}\n  - {name: s, type: marker, point: P2, sigma: 1}", "sensors[1].name: duplicate name 's'"),
        ("  - {type: marker, point: P1, sigma: 1}", "sensors[0].name: missing required key"),
    ];
    for (sensors, expect) in cases {
        let e = scene_error(&with_sensors(sensors));
        assert!(e.contains(expect), "{sensors}: {e}");
        assert!(e.starts_with("bad.yaml:"), "{e}");
        assert!(!e.contains('\n'), "{e}");
    }
}

#[test]
fn a_sensor_on_a_fixed_body_is_refused() {
    // A body of only fixed points is refused by itself; this one's free point is held
    // by the two fixed ones.
    let text = SCENE
        .replace(
            "  - {name: B, x: 4, y: 0, fixed: true}\n",
            "  - {name: B, x: 4, y: 0, fixed: true}\n  - {name: G, x: 5, y: 0, fixed: true}\n  - {name: C, x: 5, y: 1}\n",
        )
        .replace(
            "bodies:\n",
            "bodies:\n  - {name: ground, points: [B, G, C], mass: 1, cog: [0.5, 0], inertia: 1}\n",
        );
    let head = text.split("sensors:").next().unwrap();
    let e = scene_error(&format!(
        "{head}sensors:\n  - {{name: g, type: gyroscope, body: ground, sigma: 1}}\n"
    ));
    assert!(
        e.contains("sensors[0].body: sensor 'g': body 'ground' is fixed; it observes nothing of the motion"),
        "{e}"
    );
}

#[test]
fn bad_estimation_is_refused() {
    let head = SCENE.split("estimation:").next().unwrap();
    let cases: &[(&str, &str)] = &[
        ("  process_sigma: 0", "estimation.process_sigma: must be positive"),
        ("  initial_sigma: {phi: 1}", "unknown coordinate 'phi'"),
        ("  initial_sigma: {A.x: 1}", "point 'A' is fixed"),
        ("  initial_velocity_sigma: {theta: -1}", "estimation.initial_velocity_sigma.theta: must be positive"),
        ("  inputs:\n    - {coordinate: theta, sigma_rate: 0}", "estimation.inputs[0].sigma_rate: must be positive"),
        ("  inputs:\n    - {coordinate: theta}", "estimation.inputs[0].sigma_rate: missing required key"),
        ("  inputs:\n    - {coordinate: theta, sigma_rate: 1}\n    - {coordinate: theta, sigma_rate: 2}", "duplicate input on 'theta'"),
        ("  noise: 1", "estimation.noise: unknown key"),
    ];
    for (est, expect) in cases {
        let e = scene_error(&format!("{head}estimation:\n{est}\n"));
        assert!(e.contains(expect), "{est}: {e}");
    }
}

/// A generic state: q near the assembled one but off the constraints, random rates.
fn state(m: &Model, rng: &mut Rng) -> [Vec<f64>; 3] {
    let n = m.n();
    let q = m
        .initial
        .q
        .iter()
        .map(|v| v + 0.2 * rng.uniform())
        .collect();
    [q, rng.values(n, 1.5), rng.values(n, 3.0)]
}

/// Largest |closed form − central differences| / max(1, |J|max) over the three
/// blocks of `sensor` at x.
fn jacobian_error(m: &Model, sensor: &Sensor, t: f64, x: &[Vec<f64>; 3]) -> f64 {
    let (n, dim) = (m.n(), sensor.dim());
    let mut h = vec![f64::NAN; dim];
    let mut blocks = [
        vec![f64::NAN; dim * n],
        vec![f64::NAN; dim * n],
        vec![f64::NAN; dim * n],
    ];
    {
        let [jq, jdq, jddq] = &mut blocks;
        sensor
            .jacobians(m, t, &x[0], &x[1], &x[2], &mut h, jq, jdq, jddq)
            .unwrap();
    }
    let mut plain = vec![0.0; dim];
    sensor.value(m, t, &x[0], &x[1], &x[2], &mut plain).unwrap();
    assert_eq!(h, plain, "{}: value differs with Jacobians", sensor.name);
    let reads = sensor.reads();
    let mut worst = 0.0f64;
    for (k, block) in blocks.iter().enumerate() {
        assert!(
            block.iter().all(|v| v.is_finite()),
            "{}: block {k} not written",
            sensor.name
        );
        if !reads[k] {
            assert!(
                block.iter().all(|&v| v == 0.0),
                "{}: reads() denies block {k}",
                sensor.name
            );
        }
        let scale = block.iter().fold(1.0f64, |a, v| a.max(v.abs()));
        for j in 0..n {
            let step = 1e-6 * x[k][j].abs().max(1.0);
            let (mut up, mut dn) = (x.clone(), x.clone());
            up[k][j] += step;
            dn[k][j] -= step;
            let (mut hu, mut hd) = (vec![0.0; dim], vec![0.0; dim]);
            sensor.value(m, t, &up[0], &up[1], &up[2], &mut hu).unwrap();
            sensor.value(m, t, &dn[0], &dn[1], &dn[2], &mut hd).unwrap();
            for i in 0..dim {
                let fd = (hu[i] - hd[i]) / (up[k][j] - dn[k][j]);
                worst = worst.max((block[i * n + j] - fd).abs() / scale);
            }
        }
    }
    worst
}

#[test]
fn every_sensor_jacobian_matches_finite_differences() {
    let m = model();
    let mut rng = Rng(11);
    for _ in 0..5 {
        let x = state(&m, &mut rng);
        for sensor in &m.sensors {
            let err = jacobian_error(&m, sensor, 0.7, &x);
            assert!(err < 1e-7, "{}: relative error {err:e}", sensor.name);
        }
    }
}

#[test]
fn readings_have_their_meaning() {
    let m = model();
    let n = m.n();
    let s = |name: &str| &m.sensors[m.sensor_index(name).unwrap()];
    let read = |name: &str, q: &[f64], dq: &[f64], ddq: &[f64]| {
        let sensor = s(name);
        let mut out = vec![0.0; sensor.dim()];
        sensor.value(&m, 0.0, q, dq, ddq, &mut out).unwrap();
        out
    };
    // The crank at angle a turning at w: P1 = (cos a, sin a).
    let (a, w) = (0.3f64, 2.0);
    let mut q = m.initial.q.as_slice().to_vec();
    let mut dq = vec![0.0; n];
    let mut ddq = vec![0.0; n];
    let p1 = m.index_of("P1.x").unwrap();
    let theta = m.index_of("theta").unwrap();
    q[p1] = a.cos();
    q[p1 + 1] = a.sin();
    q[theta] = a;
    dq[p1] = -w * a.sin();
    dq[p1 + 1] = w * a.cos();
    dq[theta] = w;
    assert_eq!(read("enc", &q, &dq, &ddq), [a]);
    assert!((read("gyro0", &q, &dq, &ddq)[0] - w).abs() < 1e-14);
    // At rest, an accelerometer reads −g in its body's frame: the rocker points
    // from B to P2.
    let p2 = m.index_of("P2.x").unwrap();
    let d = [q[p2] - 4.0, q[p2 + 1]];
    let l = d[0].hypot(d[1]);
    let (ex, ey) = ([d[0] / l, d[1] / l], [-d[1] / l, d[0] / l]);
    let g = [0.5, -9.81];
    let acc0 = read("acc0", &q, &vec![0.0; n], &ddq);
    assert!(
        (acc0[0] + ex[0] * g[0] + ex[1] * g[1]).abs() < 1e-12,
        "{acc0:?}"
    );
    assert!(
        (acc0[1] + ey[0] * g[0] + ey[1] * g[1]).abs() < 1e-12,
        "{acc0:?}"
    );
    // A point accelerating at g is in free fall: it reads nothing.
    ddq[p2] = g[0];
    ddq[p2 + 1] = g[1];
    let acc = read("acc", &q, &dq, &ddq);
    assert!(acc.iter().all(|v| v.abs() < 1e-12), "{acc:?}");
    assert_eq!(read("cam", &q, &dq, &ddq), [q[p2], q[p2 + 1]]);
}

#[test]
fn a_reading_that_cannot_be_formed_is_an_error_not_nan() {
    let m = model();
    let n = m.n();
    let gyro = &m.sensors[m.sensor_index("gyro").unwrap()];
    // P2 on P1: the coupler has no direction.
    let mut q = m.initial.q.as_slice().to_vec();
    let p1 = m.index_of("P1.x").unwrap();
    let p2 = m.index_of("P2.x").unwrap();
    q[p2] = q[p1];
    q[p2 + 1] = q[p1 + 1];
    let mut out = [0.0];
    let e = gyro
        .value(&m, 0.0, &q, &vec![0.0; n], &vec![0.0; n], &mut out)
        .unwrap_err()
        .to_string();
    assert!(e.contains("sensor 'gyro'") && e.contains("coincide"), "{e}");
    // A state of the wrong size.
    let e = gyro.value(&m, 0.0, &q[1..], &q, &q, &mut out).unwrap_err();
    assert!(e.to_string().contains("sensor 'gyro'"), "{e}");
}

#[test]
fn quantization_and_effective_sigma() {
    let m = model();
    let enc = &m.sensors[0];
    let quantum = std::f64::consts::TAU / 4096.0;
    assert_eq!(enc.quantize(0.0), 0.0);
    assert_eq!(enc.quantize(0.4 * quantum), 0.0);
    assert_eq!(enc.quantize(0.6 * quantum), quantum);
    assert_eq!(enc.quantize(-2.6 * quantum), -3.0 * quantum);
    let expect = (0.0174533f64.powi(2) + quantum * quantum / 12.0).sqrt();
    assert!((enc.effective_sigma() - expect).abs() < 1e-15);
    let gyro = &m.sensors[1];
    assert_eq!(gyro.quantize(0.123456789), 0.123456789);
    assert_eq!(gyro.effective_sigma(), 9.84e-4);
}

/// A trajectory of the model: a state of every row from a smooth motion (not a
/// solution; the readings only need states).
fn trajectory(m: &Model, rows: usize, dt: f64) -> mbfg::trajectory::Trajectory {
    let n = m.n();
    let mut tr = mbfg::trajectory::Trajectory {
        names: m.names.clone(),
        t: Vec::new(),
        q: Vec::new(),
        dq: Vec::new(),
        ddq: Vec::new(),
    };
    for k in 0..rows {
        let t = k as f64 * dt;
        tr.t.push(t);
        for i in 0..n {
            let w = 1.0 + i as f64;
            tr.q.push(m.initial.q[i] + 0.1 * (w * t).sin());
            tr.dq.push(0.1 * w * (w * t).cos());
            tr.ddq.push(-0.1 * w * w * (w * t).sin());
        }
    }
    tr
}

#[test]
fn measure_adds_seeded_noise_of_sigma_at_each_rate() {
    let m = model();
    let tr = trajectory(&m, 2001, 0.001);
    let a = measure(&m, &tr, 5, None).unwrap();
    let b = measure(&m, &tr, 5, None).unwrap();
    let c = measure(&m, &tr, 6, None).unwrap();
    assert_eq!(
        a.values.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
        b.values.iter().map(|v| v.to_bits()).collect::<Vec<_>>()
    );
    assert_ne!(a.column("gyro"), c.column("gyro"));
    assert_eq!(a.t.len(), 2001);
    // 200 Hz: every fifth row; 50 Hz: every twentieth.
    let enc = a.column("enc").unwrap();
    let cam = a.column("cam.y").unwrap();
    assert_eq!(enc.iter().filter(|v| !v.is_nan()).count(), 401);
    assert_eq!(cam.iter().filter(|v| !v.is_nan()).count(), 101);
    assert!(enc[5].is_finite() && enc[4].is_nan() && cam[20].is_finite() && cam[10].is_nan());
    let quantum = std::f64::consts::TAU / 4096.0;
    for v in enc.iter().filter(|v| !v.is_nan()) {
        let k = v / quantum;
        assert!(
            (k - k.round()).abs() < 1e-9,
            "{v} is not a multiple of the quantum"
        );
    }
    // The noise of the gyroscope: mean 0 and σ within a few standard errors.
    let gyro = m.sensor_index("gyro").unwrap();
    let n = m.n();
    let mut h = [0.0];
    let residuals: Vec<f64> = a
        .column("gyro")
        .unwrap()
        .iter()
        .enumerate()
        .map(|(k, v)| {
            let s = |x: &[f64]| x[k * n..(k + 1) * n].to_vec();
            m.sensors[gyro]
                .value(&m, tr.t[k], &s(&tr.q), &s(&tr.dq), &s(&tr.ddq), &mut h)
                .unwrap();
            v - h[0]
        })
        .collect();
    let count = residuals.len() as f64;
    let mean = residuals.iter().sum::<f64>() / count;
    let sd = (residuals.iter().map(|r| (r - mean).powi(2)).sum::<f64>() / count).sqrt();
    let sigma = 9.84e-4;
    assert!(mean.abs() < 4.0 * sigma / count.sqrt(), "mean {mean:e}");
    assert!((sd / sigma - 1.0).abs() < 0.06, "sd {sd:e}");
    // A rate off the trajectory's grid.
    let e = measure(&m, &tr, 5, Some(300.0)).unwrap_err().to_string();
    assert!(e.contains("sensor 'gyro' reads at 300 Hz"), "{e}");
}

#[test]
fn measurements_round_trip_through_csv() {
    use mbfg::sensors::measure::Measurements;
    let m = model();
    let tr = trajectory(&m, 41, 0.005);
    let a = measure(&m, &tr, 9, Some(100.0)).unwrap();
    let dir = common::scratch("sensors", "roundtrip");
    let path = dir.join("m.csv");
    a.write_csv(std::fs::File::create(&path).unwrap()).unwrap();
    let b = Measurements::read(&path, Some(&m)).unwrap();
    assert_eq!(a.columns, b.columns);
    assert_eq!(a.t, b.t);
    let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    // NaN reads back as the same NaN.
    assert_eq!(bits(&a.values), bits(&b.values));
    assert!(a.values.iter().any(|v| v.is_nan()));
    // A column no sensor has.
    std::fs::write(&path, "t,enc,lidar\n0,1,2\n").unwrap();
    let e = Measurements::read(&path, Some(&m)).unwrap_err().to_string();
    assert!(e.contains("column `lidar` is not a reading"), "{e}");
    std::fs::remove_dir_all(&dir).ok();
}
