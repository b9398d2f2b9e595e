//! Inverse dynamics by the factor graph against the classical solution computed with
//! the exact derivatives of the prescribed motion.

use mbfg::inverse::{self, InverseOptions, Prescription};
use mbfg::io::Table;
use mbfg::{Model, Scene};
use std::path::PathBuf;
use std::sync::Arc;

fn load(name: &str) -> Arc<Model> {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("scenes")
        .join(name);
    Arc::new(Model::new(&Scene::load(path).unwrap()).unwrap())
}

/// θ(t) = 1.2(1 − cos 2t) and its derivatives.
fn crank(t: f64) -> (f64, f64, f64) {
    (
        1.2 * (1.0 - (2.0 * t).cos()),
        2.4 * (2.0 * t).sin(),
        4.8 * (2.0 * t).cos(),
    )
}

fn table(name: &str, dt: f64, t_end: f64, f: impl Fn(f64) -> f64) -> Table {
    let rows = (t_end / dt).round() as usize + 1;
    let mut values = Vec::with_capacity(2 * rows);
    for k in 0..rows {
        let t = k as f64 * dt;
        values.extend([t, f(t)]);
    }
    Table {
        columns: vec!["t".into(), name.into()],
        values,
        rows,
    }
}

fn rms(a: &[f64]) -> f64 {
    (a.iter().map(|v| v * v).sum::<f64>() / a.len() as f64).sqrt()
}

#[test]
fn fourbar_crank_torque_matches_the_classical_solution() {
    let model = load("fourbar-theta.yaml");
    let theta = model.names.iter().position(|c| c == "theta").unwrap();
    let (dt, t_end) = (5e-3, 10.0);
    let tab = table("theta", dt, t_end, |t| crank(t).0);
    let p = Prescription::from_table(&model, &tab, "test").unwrap();
    let sol = inverse::solve(model.clone(), &p, &InverseOptions::default()).unwrap();
    let n = model.n();
    let exact = inverse::classical(&model, &[theta], &sol.trajectory.t, |t| {
        let (a, b, c) = crank(t);
        (vec![a], vec![b], vec![c])
    })
    .unwrap();
    let torque: Vec<f64> = (0..p.steps).map(|k| sol.forces[k * n + theta]).collect();
    let truth: Vec<f64> = (0..p.steps).map(|k| exact.forces[k * n + theta]).collect();
    let err: Vec<f64> = torque.iter().zip(&truth).map(|(a, b)| a - b).collect();
    let peak = truth.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    let rmse = rms(&err);
    eprintln!(
        "four-bar inverse: torque RMSE {rmse:.3e} N·m (peak {peak:.2} N·m), tracking {:.2e} rad, |Φ| {:.1e}, {} iterations, {:?}",
        sol.summary.worst_tracking, sol.summary.worst_phi, sol.summary.report.iterations, sol.summary.wall_time
    );
    assert!(peak > 30.0, "peak torque {peak}");
    assert!(rmse <= 5e-3, "torque RMSE {rmse:.3e} N·m");
    assert!(sol.summary.worst_tracking <= 1e-6);
    assert!(sol.summary.worst_phi <= 1e-9);
    // Nothing acts on the other coordinates.
    for k in 0..p.steps {
        for i in (0..n).filter(|&i| i != theta) {
            assert_eq!(sol.forces[k * n + i], 0.0);
        }
    }
}
