//! Parameter identification by the three-simulation method: a true scene simulated,
//! its sensors read with seeded noise, and a model whose parameters are wrong
//! (`estimation: parameters:`) identified from the readings with the motion. The
//! thresholds are the issue's: each parameter within its tolerance of the truth, the
//! reported 1σ covering the truth in at least 9 of 10 seeds, the state RMSEs of the
//! estimation benchmark met at the same time; a parameter the readings do not
//! determine named with the reason; every refused use named.

use mbfg::coordinates::Coordinates;
use mbfg::estimate::{
    estimate, EstimateOptions, EstimateSummary, Estimates, ProcessSource, Record, Smoothing,
};
use mbfg::factors::Integrator;
use mbfg::forward::{simulate, ForwardOptions};
use mbfg::sensors::measure::measure;
use mbfg::smoother::Mode;
use mbfg::trajectory::Trajectory;
use mbfg::{Model, Scene};
use std::path::{Path, PathBuf};
use std::sync::Arc;

mod common;

fn path(name: &str) -> PathBuf {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    match name.strip_prefix("scenes/") {
        Some(rest) => root.join("scenes").join(rest),
        None => root.join("tests/data/identification").join(name),
    }
}

fn model(name: &str) -> Arc<Model> {
    Arc::new(Model::new(&Scene::load(path(name)).unwrap()).unwrap())
}

/// The true motion of `scene` over `t_end`: a 1 ms simulation sampled every 5 ms.
fn truth(scene: &str, t_end: f64) -> Trajectory {
    let m = model(scene);
    let options = ForwardOptions::new(Coordinates::Dependent, 0.001, t_end, Mode::FixedLag(1));
    let (fine, _) = simulate(m, &options, &mut |_, _| {}).unwrap();
    fine.every(5, 0.005)
}

/// The batch estimate of `bad` from the readings of its sensors made on `truth` by
/// the true scene `true_scene` (seed): an `input` sensor reads the true scene's
/// torques.
fn identify(
    bad: &str,
    true_scene: &str,
    truth: &Trajectory,
    seed: u64,
) -> (Estimates, EstimateSummary) {
    let m = model(bad);
    let record = record_of(&m, &model(true_scene), truth, seed);
    common::estimate_record(m, &record, Smoothing::Batch)
}

/// The readings of `bad`'s sensors made on `truth` by `true_model` (seed), as a
/// record of `bad`.
fn record_of(bad: &Model, true_model: &Model, truth: &Trajectory, seed: u64) -> Record {
    record_at(bad, true_model, truth, seed, None)
}

/// [`record_of`] for an estimate at step `dt` (default: the readings' period).
fn record_at(
    bad: &Model,
    true_model: &Model,
    truth: &Trajectory,
    seed: u64,
    dt: Option<f64>,
) -> Record {
    let readings = measure(true_model, truth, seed, None).unwrap();
    let wanted: Vec<String> = bad.sensors.iter().flat_map(|s| s.columns()).collect();
    let mut columns = vec!["t".to_string()];
    columns.extend(wanted.iter().cloned());
    let values: Vec<Vec<f64>> = wanted.iter().map(|c| readings.column(c).unwrap()).collect();
    let rows: Vec<(f64, Vec<f64>)> = (0..readings.t.len())
        .map(|i| {
            let mut row = vec![readings.t[i]];
            row.extend(values.iter().map(|v| v[i]));
            (readings.t[i], row)
        })
        .collect();
    Record::from_rows(bad, &columns, &rows, dt).unwrap()
}

fn rms_off(est: &Estimates, truth: &Trajectory, column: &str) -> f64 {
    let n = truth.names.len();
    let c = truth.names.iter().position(|x| x == "theta").unwrap();
    let v = est.column(column).unwrap();
    let t = match column.split(':').next().unwrap() {
        "q" => &truth.q,
        "dq" => &truth.dq,
        _ => &truth.ddq,
    };
    let s: f64 = v
        .iter()
        .enumerate()
        .map(|(k, x)| (x - t[k * n + c]).powi(2))
        .sum();
    (s / v.len() as f64).sqrt()
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Per seed: (|error| / truth, |error| / σ) of parameter `name`, and the θ RMSEs.
fn ten_seeds(
    (bad, true_scene): (&str, &str),
    truth: &Trajectory,
    name: &str,
    true_value: f64,
) -> Vec<[f64; 5]> {
    (1..=10)
        .map(|seed| {
            let (table, summary) = identify(bad, true_scene, truth, seed);
            let p = summary
                .identification
                .parameters
                .iter()
                .find(|p| p.name == name)
                .unwrap();
            assert!(
                p.undetermined.is_none(),
                "seed {seed}: {:?}",
                p.undetermined
            );
            let err = (p.estimate - true_value).abs();
            // The batch lowers the default process σ once the parameters carry the
            // model's error.
            assert!(
                matches!(
                    summary.process_source,
                    ProcessSource::Identified { from, .. } if summary.process_sigma < from
                ),
                "seed {seed}: process σ {} ({:?})",
                summary.process_sigma,
                summary.process_source
            );
            [
                err / true_value,
                err / p.sigma,
                rms_off(&table, truth, "q:theta"),
                rms_off(&table, truth, "dq:theta"),
                rms_off(&table, truth, "ddq:theta"),
            ]
        })
        .collect()
}

#[test]
fn gravity_is_identified_within_one_percent_with_honest_sigmas() {
    let scenes = ("fourbar-gravity.yaml", "scenes/estimation/fourbar.yaml");
    let truth = truth(scenes.1, 10.0);
    let runs = ten_seeds(scenes, &truth, "g", 10.0);
    for (k, r) in runs.iter().enumerate() {
        assert!(
            r[0] < 0.01,
            "seed {}: g off by {:.2} %",
            k + 1,
            100.0 * r[0]
        );
    }
    let covered = runs.iter().filter(|r| r[1] <= 1.0).count();
    assert!(covered >= 9, "1σ covers the truth in {covered} of 10 seeds");
    // The estimation benchmark's batch targets for the crank encoder, met at once.
    let col = |i: usize| median(runs.iter().map(|r| r[i]).collect());
    assert!(col(2) <= 2.8e-3, "z RMSE {:.2e}", col(2));
    assert!(col(3) <= 0.016, "ż RMSE {:.2e}", col(3));
    assert!(col(4) <= 0.20, "z̈ RMSE {:.2e}", col(4));
}

#[test]
fn the_crank_mass_is_identified_with_honest_sigmas() {
    // A 1° crank encoder over 10 s: at the default process σ the dynamics tie the
    // crank's mass to the motion only loosely (σ ≈ 1.7 %); the σ lowered after
    // identification ties it closer. The reported σ stays the default's, which the
    // readings do not reject. Hermite–Simpson, the default where parameters are
    // identified, leaves no bias of the 5 ms step.
    let scenes = ("fourbar-crank-mass.yaml", "fourbar-heavy-crank-true.yaml");
    let truth = truth(scenes.1, 10.0);
    let runs = ten_seeds(scenes, &truth, "m_crank", 2.2);
    let covered = runs.iter().filter(|r| r[1] <= 1.0).count();
    assert!(covered >= 9, "1σ covers the truth in {covered} of 10 seeds");
    assert!(runs.iter().all(|r| r[1] <= 3.0), "an error beyond 3σ");
    let relative_sigma = median(runs.iter().map(|r| r[0] / r[1]).collect());
    assert!(
        relative_sigma <= 0.02,
        "σ {:.2} % of the mass",
        100.0 * relative_sigma
    );
    let err = median(runs.iter().map(|r| r[0]).collect());
    let within = runs.iter().filter(|r| r[0] <= 0.01).count();
    eprintln!(
        "crank mass: median error {:.2} %, σ {:.2} %, within 1 % in {within} of 10 seeds \
         (errors {:?} %)",
        100.0 * err,
        100.0 * relative_sigma,
        runs.iter()
            .map(|r| (1e4 * r[0]).round() / 100.0)
            .collect::<Vec<_>>()
    );
    assert!(err <= 0.003, "median error {:.2} %", 100.0 * err);
    assert_eq!(within, 10, "within 1 % in {within} of 10 seeds");
}

#[test]
fn hermite_simpson_leaves_no_bias_of_the_step_in_a_parameter() {
    // With the model trusted (process σ 1e-3 at 5 ms, the same intensity at 2.5 ms),
    // the crank mass fitted to 10 s of a 1° encoder read every 5 ms, estimated at
    // steps of 5 and 2.5 ms from the same readings: the trapezoidal rule's estimate
    // moves with the step (its error at the step is a bias of the parameter),
    // Hermite–Simpson's hardly does.
    let scenes = ("fourbar-crank-mass.yaml", "fourbar-heavy-crank-true.yaml");
    let truth = truth(scenes.1, 10.0);
    let text = std::fs::read_to_string(path(scenes.0)).unwrap();
    let trusted = |dt: Option<f64>| {
        let sigma = 1e-3 * (0.005 / dt.unwrap_or(0.005)).sqrt();
        let text = text.replace(
            "estimation:\n",
            &format!("estimation:\n  process_sigma: {sigma}\n"),
        );
        assert!(text.contains("process_sigma"));
        Arc::new(Model::new(&Scene::from_str(&text, &path(scenes.0)).unwrap()).unwrap())
    };
    for seed in 1..=2 {
        let mass = |integrator, dt| {
            let m = trusted(dt);
            let record = record_at(&m, &model(scenes.1), &truth, seed, dt);
            let options = EstimateOptions {
                smoothing: Smoothing::Batch,
                integrator: Some(integrator),
                dt,
                ..EstimateOptions::default()
            };
            let (_, summary) = common::estimate_with(m, &record, &options);
            assert_eq!(summary.integrator, integrator);
            summary.identification.parameters[0].estimate
        };
        let moved = |integrator| (mass(integrator, None) - mass(integrator, Some(0.0025))) / 2.2;
        let (trapezoidal, simpson) = (
            moved(Integrator::Trapezoidal),
            moved(Integrator::HermiteSimpson),
        );
        eprintln!("seed {seed}: from 5 to 2.5 ms the mass moved {trapezoidal:e} (trapezoidal), {simpson:e} (Hermite–Simpson)");
        assert!(
            trapezoidal > 0.002,
            "seed {seed}: trapezoidal moved {trapezoidal:e}"
        );
        assert!(
            simpson.abs() < 0.1 * trapezoidal,
            "seed {seed}: Hermite–Simpson moved {simpson:e}"
        );
    }
}

/// Each of `truths` (name, true value) within 2 % of the truth and 3 of its σ's,
/// identified; the parameter's estimate.
fn assert_identified(
    summary: &EstimateSummary,
    truths: &[(&str, f64)],
    seed: u64,
) -> Vec<mbfg::estimate::ParameterEstimate> {
    truths
        .iter()
        .map(|&(name, value)| {
            let p = summary
                .identification
                .parameters
                .iter()
                .find(|p| p.name == name)
                .unwrap();
            let err = (p.estimate - value).abs();
            assert!(
                err < 0.02 * value && err < 3.0 * p.sigma,
                "seed {seed}: {name} = {} ± {}",
                p.estimate,
                p.sigma
            );
            assert!(
                p.undetermined.is_none(),
                "seed {seed}: {:?}",
                p.undetermined
            );
            p.clone()
        })
        .collect()
}

#[test]
fn a_spring_and_a_damper_are_identified_within_two_percent() {
    let truth = truth("scenes/spring-damper.yaml", 10.0);
    for seed in 1..=3 {
        let (_, summary) = identify(
            "spring-damper-kc.yaml",
            "spring-damper-kc.yaml",
            &truth,
            seed,
        );
        assert_identified(&summary, &[("k", 20.0), ("c", 0.5)], seed);
    }
}

#[test]
fn friction_written_in_a_torques_expression_is_identified() {
    // Viscous and smoothed Coulomb friction in a hinge, as one torque expression that
    // uses both parameters, identified from an encoder (1 mrad) from guesses half the
    // truth: within 2 % and 3σ on three seeds. The σ at the lowered process σ holds
    // the truth within 3 of it too, and is what the readings tell of b: an
    // output-error fit's σ is 1.53e-5 (with the parameters' copies linked at 1e-5 of
    // the prior's σ a step, their drift set it at 6.8e-5).
    let truth = truth("scenes/identification/pendulum-friction.yaml", 10.0);
    for seed in 1..=3 {
        let (table, summary) = identify(
            "scenes/identification/pendulum-friction-bad.yaml",
            "scenes/identification/pendulum-friction.yaml",
            &truth,
            seed,
        );
        let found = assert_identified(&summary, &[("b", 0.05), ("mu", 0.1)], seed);
        for (p, value) in found.iter().zip([0.05, 0.1]) {
            let low = p.sigma_lowered.expect("the process σ lowered");
            assert!(
                (p.estimate - value).abs() < 3.0 * low && low < 0.1 * p.sigma,
                "seed {seed}: {} = {} ± {low} at the lowered process σ",
                p.name,
                p.estimate
            );
        }
        let b = found[0].sigma_lowered.unwrap();
        assert!(
            b < 2.5e-5,
            "seed {seed}: σ of b {b} at the lowered process σ"
        );
        assert!(
            summary.undetermined.is_empty(),
            "{:?}",
            summary.undetermined
        );
        let z = rms_off(&table, &truth, "q:theta");
        assert!(z < 1e-3, "seed {seed}: θ RMSE {z}");
    }
}

#[test]
fn a_chaotic_double_pendulums_link_mass_is_identified() {
    // Released horizontal, the double pendulum is chaotic within seconds; its second
    // link's mass, guessed 30 % low, is identified from two 1 mrad encoders over 10 s,
    // with the motion, and no angle is named undetermined though the start is known
    // far better than the readings tell it.
    let truth = truth("scenes/identification/double-pendulum.yaml", 10.0);
    let (_, summary) = identify(
        "scenes/identification/double-pendulum-bad.yaml",
        "scenes/identification/double-pendulum.yaml",
        &truth,
        2,
    );
    let m2 = &assert_identified(&summary, &[("m2", 1.0)], 2)[0];
    let low = m2.sigma_lowered.expect("the process σ lowered");
    assert!(
        (m2.estimate - 1.0).abs() < 3.0 * low && (m2.estimate - 1.0).abs() < 1e-3,
        "m2 = {} ± {low}",
        m2.estimate
    );
    assert!(
        summary.undetermined.is_empty(),
        "{:?}",
        summary.undetermined
    );
}

#[test]
fn a_point_mass_is_identified() {
    let truth = truth("point-mass-true.yaml", 5.0);
    let (_, summary) = identify("point-mass.yaml", "point-mass-true.yaml", &truth, 1);
    let p = &summary.identification.parameters[0];
    assert!(p.undetermined.is_none(), "{:?}", p.undetermined);
    let err = (p.estimate - 1.0).abs();
    assert!(
        err < 0.02 && err < 3.0 * p.sigma,
        "{} ± {}",
        p.estimate,
        p.sigma
    );
}

#[test]
fn mass_and_inertia_in_a_pure_rotation_are_named_not_identified() {
    let truth = truth("pendulum-true.yaml", 5.0);
    let (_, summary) = identify(
        "pendulum-mass-inertia.yaml",
        "pendulum-true.yaml",
        &truth,
        1,
    );
    let id = &summary.identification;
    for (p, other) in id.parameters.iter().zip(["i_rod", "m"]) {
        let why = p.undetermined.as_deref().unwrap_or_else(|| {
            panic!(
                "{} = {} ± {} given as identified",
                p.name, p.estimate, p.sigma
            )
        });
        assert!(why.contains("combination") && why.contains(other), "{why}");
    }
    assert!(
        id.correlation[1].abs() > 0.99,
        "correlation {}",
        id.correlation[1]
    );
}

fn refusal(text: &str) -> String {
    let scene = Scene::from_str(text, Path::new("inline.yaml"));
    let err = match scene {
        Err(e) => e.to_string(),
        Ok(s) => match Model::new(&s) {
            Err(e) => e.to_string(),
            Ok(_) => panic!("accepted:\n{text}"),
        },
    };
    err
}

const BASE: &str = "
points:
  - {name: A, x: 0, y: 0, fixed: true}
  - {name: P, x: 1, y: 0}
  - {name: W, x: 1, y: -1, fixed: true}
bodies:
  - {name: rod, points: [A, P], mass: MASS}
effects:
  - {type: gravity, vector: [0, -G]}
  - {name: spring, type: spring_damper, points: [W, P], stiffness: 20, rest_length: REST}
  - {name: motor, type: torque, coordinate: theta, value: TORQUE}
coordinates:
  - {name: theta, type: angle, points: [A, P]}
sensors:
  - {name: enc, type: encoder, coordinate: theta, sigma: 0.001}
";

fn scene(params: &str, identified: &str, edits: &[(&str, &str)]) -> String {
    let mut body = BASE.to_string();
    for (k, v) in [
        ("MASS", "1"),
        ("G", "9.81"),
        ("REST", "0.8"),
        ("TORQUE", "0"),
    ] {
        let v = edits.iter().find(|(e, _)| *e == k).map_or(v, |(_, v)| *v);
        body = body.replace(k, v);
    }
    format!("parameters: {{{params}}}\n{body}estimation:\n  parameters: [{identified}]\n")
}

#[test]
fn every_use_an_estimate_cannot_vary_is_refused_by_name() {
    // (parameters, the identified one, edits of BASE, what the message says)
    type Case<'a> = (&'a str, &'a str, &'a [(&'a str, &'a str)], &'a str);
    let cases: [Case; 6] = [
        (
            "L: 0.8",
            "{name: L, sigma: 0.1}",
            &[("REST", "L")],
            "rest_length",
        ),
        (
            "a: 1, a2: 2*a",
            "{name: a, sigma: 0.1}",
            &[("TORQUE", "a2*t")],
            "write the identified parameter itself",
        ),
        (
            "m: 1",
            "{name: m, sigma: 0.1}",
            &[("MASS", "m^2")],
            "not linear",
        ),
        (
            "mass: 1",
            "{name: mas, sigma: 0.1}",
            &[("MASS", "mass")],
            "did you mean 'mass'",
        ),
        (
            "m: 1, u: 2",
            "{name: u, sigma: 0.1}",
            &[("MASS", "m")],
            "changes nothing",
        ),
        ("g: 9", "{name: g, sigma: 0}", &[("G", "g")], "positive"),
    ];
    for (params, identified, edits, expect) in cases {
        let text = scene(params, identified, edits);
        let err = refusal(&text);
        assert!(err.contains(expect), "{expect}: {err}");
    }
    // A motor's no-load speed is refused with the way to identify it: the motor
    // written as a torque.
    let text = scene("w: 30", "{name: w, sigma: 1}", &[("TORQUE", "0")]).replace(
        "{name: motor, type: torque, coordinate: theta, value: 0}",
        "{name: motor, type: dc_motor, coordinate: theta, stall_torque: 1, no_load_speed: w}",
    );
    assert!(text.contains("no_load_speed: w"));
    let err = refusal(&text);
    assert!(
        err.contains("no_load_speed") && err.contains("write the motor as a torque"),
        "{err}"
    );
    // A sensor's expression sees the estimate (a scale, an offset): a parameter only
    // it uses is accepted, and one computed from an identified parameter refused.
    let text = scene("a: 1, c: 1", "{name: a, sigma: 0.1}", &[("MASS", "c")]).replace(
        "sensors:\n",
        "sensors:\n  - {name: e2, type: expression, value: \"a*theta\", sigma: 0.1}\n",
    );
    let m = Model::new(&Scene::from_str(&text, Path::new("inline.yaml")).unwrap()).unwrap();
    assert_eq!(m.parameters.as_ref().unwrap().names, ["a"]);
    assert!(m.sensors.iter().any(|s| s.uses_parameters()));
    let text = scene("a: 1, a2: 2*a", "{name: a, sigma: 0.1}", &[("MASS", "a")]).replace(
        "sensors:\n",
        "sensors:\n  - {name: e2, type: expression, value: \"a2*theta\", sigma: 0.1}\n",
    );
    let err = refusal(&text);
    assert!(
        err.contains("write the identified parameter itself"),
        "{err}"
    );
    // The same scene with the parameter used where it may be is accepted.
    let ok = scene("a: 1", "{name: a, sigma: 0.1}", &[("TORQUE", "a*t")]);
    let m = Model::new(&Scene::from_str(&ok, Path::new("inline.yaml")).unwrap()).unwrap();
    assert_eq!(m.parameters.as_ref().unwrap().names, ["a"]);
    let ok = scene("g: 9", "{name: g, sigma: 1}", &[("G", "g")]);
    let m = Model::new(&Scene::from_str(&ok, Path::new("inline.yaml")).unwrap()).unwrap();
    assert_eq!(m.parameters.as_ref().unwrap().names, ["g"]);
}

#[test]
fn the_classical_experiment_identifies_an_arms_masses_and_inertias() {
    // Joint encoders (1 mrad) and joint torque readings (`input` sensors, 0.05 N·m)
    // of an arm driven by known torques; the model's torques unknown inputs read by
    // the sensors, the links' masses and inertias identified from priors 20-50 % off.
    let truth = truth("arm-true.yaml", 10.0);
    let (_, summary) = identify("arm-masses.yaml", "arm-true.yaml", &truth, 1);
    let exact = [
        ("m1", 2.0),
        ("m2", 1.0),
        ("i1", 2.0 / 12.0),
        ("i2", 0.64 / 12.0),
    ];
    for (name, value) in exact {
        let p = summary
            .identification
            .parameters
            .iter()
            .find(|p| p.name == name)
            .unwrap();
        assert!(p.undetermined.is_none(), "{name}: {:?}", p.undetermined);
        let err = (p.estimate - value).abs() / value;
        eprintln!(
            "{name} = {} ± {} (truth {value}): {:.2} %",
            p.estimate,
            p.sigma,
            100.0 * err
        );
        assert!(err < 0.02, "{name} off by {:.2} %", 100.0 * err);
    }
}

#[test]
fn an_input_sensor_reads_the_scenes_torques_and_needs_an_unknown_input_to_estimate() {
    let m = model("arm-true.yaml");
    let (q, dq) = (m.initial.q.as_slice(), m.initial.dq.as_slice());
    let torque1 = m.sensors.iter().position(|s| s.name == "torque1").unwrap();
    let mut out = [0.0];
    m.sensors[torque1]
        .value(&m, 0.5, q, dq, &vec![0.0; m.n()], &mut out)
        .unwrap();
    let expected = 12.0 * (1.3f64 * 0.5).sin() + 8.0 * (3.1f64 * 0.5).sin() + 5.0;
    assert!(
        (out[0] - expected).abs() < 1e-12,
        "{} against {expected}",
        out[0]
    );
    // The true scene, which declares no unknown input, cannot estimate from it.
    let truth = truth("arm-true.yaml", 0.1);
    let record = record_of(&m, &m, &truth, 1);
    let err = estimate(m, &record, &EstimateOptions::default(), &mut |_| Ok(())).unwrap_err();
    let msg = err.to_string();
    assert!(
        msg.contains("torque1") && msg.contains("estimation: inputs"),
        "{msg}"
    );
}

#[test]
fn a_start_far_from_the_first_reading_is_reached_along_the_mechanism() {
    // The friction pendulum's scene placed 2.6 rad from where the record starts (the
    // rod drawn at 3 rad, the truth released at 0.37), its start left to the default
    // priors: the first solve begins at the first reading, reached along the
    // mechanism, and the estimate is the one from a start placed right. From the
    // scene's start itself, step 0 ran out of iterations.
    let truth = truth("scenes/identification/pendulum-friction.yaml", 10.0);
    let text = std::fs::read_to_string(path("scenes/identification/pendulum-friction-bad.yaml"))
        .unwrap()
        .replace(
            "{name: P, x: 0.9320390859672263, y: 0.36235775447667357}",
            &format!("{{name: P, x: {}, y: {}}}", 3f64.cos(), 3f64.sin()),
        )
        .replace("  initial_sigma: {theta: 1e-6}\n", "")
        .replace("  initial_velocity_sigma: {theta: 1e-6}\n", "");
    assert!(text.contains(&format!("x: {}", 3f64.cos())));
    let file = std::env::temp_dir().join(format!("mbfg-far-start-{}.yaml", std::process::id()));
    std::fs::write(&file, text).unwrap();
    let far = Arc::new(Model::new(&Scene::load(&file).unwrap()).unwrap());
    std::fs::remove_file(&file).ok();
    let truth_model = model("scenes/identification/pendulum-friction.yaml");
    let record = record_of(&far, &truth_model, &truth, 1);
    for smoothing in [Smoothing::Batch, Smoothing::Window(10)] {
        let (table, summary) = common::estimate_record(far.clone(), &record, smoothing);
        let z = rms_off(&table, &truth, "q:theta");
        assert!(z < 1e-3, "{smoothing:?}: θ RMSE {z}");
        if smoothing == Smoothing::Batch {
            assert_identified(&summary, &[("b", 0.05), ("mu", 0.1)], 1);
        }
    }
}

#[test]
fn an_encoders_offset_and_a_gyroscopes_scale_are_identified() {
    // A damped pendulum read by an incremental encoder (the angle plus an unknown
    // offset, −0.4 rad) and a gyroscope 5 % high, both written as sensor expressions
    // of identified parameters: the offset, the scale and the damping together, with
    // the motion, from priors of 0, 0 and 0.02.
    let truth = truth("scenes/identification/sensor-calibration.yaml", 10.0);
    for seed in 1..=2 {
        let (table, summary) = identify(
            "scenes/identification/sensor-calibration-bad.yaml",
            "scenes/identification/sensor-calibration.yaml",
            &truth,
            seed,
        );
        assert_identified(&summary, &[("b", 0.05), ("gain", 0.05)], seed);
        let off = summary
            .identification
            .parameters
            .iter()
            .find(|p| p.name == "off")
            .unwrap();
        assert!(
            (off.estimate + 0.4).abs() < 1e-3 && (off.estimate + 0.4).abs() < 3.0 * off.sigma,
            "seed {seed}: off = {} ± {}",
            off.estimate,
            off.sigma
        );
        assert!(off.undetermined.is_none(), "{:?}", off.undetermined);
        let z = rms_off(&table, &truth, "q:theta");
        assert!(z < 1e-3, "seed {seed}: θ RMSE {z}");
    }
}

#[test]
fn a_dc_motors_stall_torque_and_no_load_speed_are_identified_as_a_torque() {
    // The crank-rocker spun up from rest by a DC motor (stall torque 60 N·m, no-load
    // speed 30 rad/s), read by a crank encoder for 5 s; the motor written as the
    // torque ts*(1 - rate(theta)/w0), both identified from guesses of 40 and 20.
    let truth = truth("dc-motor-true.yaml", 5.0);
    let (_, summary) = identify("dc-motor.yaml", "dc-motor-true.yaml", &truth, 1);
    assert_identified(&summary, &[("ts", 60.0), ("w0", 30.0)], 1);
}
