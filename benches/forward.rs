//! Benchmarks of forward dynamics (`make bench`): the paper's four-bar, 5 s at
//! dt = 1 ms, DC and IC, fixed-lag windows of 1, 2, 5, 10 steps and batch; one LM
//! iteration of a 10-step window; the dynamics factor with its Jacobians.

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion};
use mbfg::factors::Dynamics;
use mbfg::forward::{simulate, Coordinates, ForwardGraph, ForwardOptions};
use mbfg::graph::Factor;
use mbfg::smoother::Mode;
use mbfg::solver::{Settings, WindowSolver};
use mbfg::{Model, Scene};
use std::hint::black_box;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

fn load(name: &str) -> Arc<Model> {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("scenes")
        .join(name);
    Arc::new(Model::new(&Scene::load(path).unwrap()).unwrap())
}

fn scene_for(coords: Coordinates) -> &'static str {
    match coords {
        Coordinates::Dependent => "fourbar.yaml",
        Coordinates::Independent => "fourbar-theta.yaml",
    }
}

fn forward_runs(c: &mut Criterion) {
    let mut group = c.benchmark_group("fourbar_5s_dt1ms");
    group
        .sample_size(10)
        .measurement_time(Duration::from_secs(8));
    for coords in [Coordinates::Dependent, Coordinates::Independent] {
        let model = load(scene_for(coords));
        let tag = if coords == Coordinates::Dependent {
            "dc"
        } else {
            "ic"
        };
        for mode in [
            Mode::FixedLag(1),
            Mode::FixedLag(2),
            Mode::FixedLag(5),
            Mode::FixedLag(10),
            Mode::Batch,
        ] {
            let label = match mode {
                Mode::FixedLag(n) => format!("window{n}"),
                Mode::Batch => "batch".into(),
            };
            let opts = ForwardOptions::new(coords, 1e-3, 5.0, mode);
            group.bench_function(BenchmarkId::new(tag, label), |b| {
                b.iter(|| {
                    let (_, s) = simulate(model.clone(), &opts, &mut |_, _| {}).unwrap();
                    assert!(s.failures.is_empty());
                    black_box(s.steps)
                })
            });
        }
    }
    group.finish();
}

/// One Gauss-Newton iteration (linearize, factor, solve, trial) of a 10-step window
/// at t ≈ 1 s of the DC run.
fn one_iteration(c: &mut Criterion) {
    let model = load("fourbar.yaml");
    let opts = ForwardOptions::new(Coordinates::Dependent, 1e-3, 1.0, Mode::FixedLag(1));
    let (tr, _) = simulate(model.clone(), &opts, &mut |_, _| {}).unwrap();
    let fg = ForwardGraph::new(model.clone(), &opts).unwrap();
    let s = fg.graph.layout().size();
    let mut values = vec![0.0; tr.len() * s];
    fg.fill_from_trajectory(&model, &tr, &mut values);
    let settings = Settings {
        max_iterations: 1,
        ..Settings::default()
    };
    let mut solver = WindowSolver::new(&fg.graph, 10, settings).unwrap();
    let (k0, k1) = (tr.len() - 10, tr.len());
    // Perturb so the iteration has work to do.
    for v in &mut values[k0 * s..k1 * s] {
        *v *= 1.0 + 1e-6;
    }
    let start = values.clone();
    c.bench_function("lm_iteration_dc_window10", |b| {
        b.iter(|| {
            values.copy_from_slice(&start);
            black_box(solver.solve(&fg.graph, &mut values, k0, k1, None).unwrap())
        })
    });
}

/// f^d_dyn: residual and ∂/∂q, ∂/∂q̇, ∂/∂q̈ of the four-bar at a moving state.
fn dynamics_factor(c: &mut Criterion) {
    let model = load("fourbar.yaml");
    let opts = ForwardOptions::new(Coordinates::Dependent, 1e-3, 0.3, Mode::FixedLag(1));
    let (tr, _) = simulate(model.clone(), &opts, &mut |_, _| {}).unwrap();
    let k = tr.len() - 1;
    let n = model.n();
    let (q, dq) = (tr.q_at(k).to_vec(), tr.dq_at(k).to_vec());
    let ddq = tr.ddq[k * n..(k + 1) * n].to_vec();
    let factor = Dynamics::new(model.clone());
    let mut ws = mbfg::graph::Workspace::new(factor.scratch());
    let mut r = vec![0.0; factor.dim()];
    let mut jac: Vec<Vec<f64>> = vec![vec![0.0; n * n]; 3];
    let t = tr.t[k];
    c.bench_function("dynamics_factor_with_jacobians", |b| {
        b.iter(|| {
            factor
                .evaluate(t, &[&q, &dq, &ddq], &mut r, Some(&mut jac), &mut ws)
                .unwrap();
            black_box(r[0])
        })
    });
}

criterion_group!(benches, forward_runs, one_iteration, dynamics_factor);
criterion_main!(benches);
