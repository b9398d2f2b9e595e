//! Benchmarks of inverse dynamics (`make bench`): the suite's prescriptions for the
//! four-bar (10 s, 2001 samples) and the pick-and-place robot (5 s, 1001 samples),
//! each solved in batch from the kinematic start, in dependent coordinates (the
//! targets) and in independent ones (`_ic`); and the four-bar's motion as measured
//! data (`_8digits`, `_noisy`) with `sample_sigma` auto: smoothing and σ's included.

use criterion::{criterion_group, criterion_main, Criterion};
use mbfg::forward::Coordinates;
use mbfg::inverse::{self, InverseOptions, Prescription, SampleSigma};
use mbfg::{Model, Scene};
use std::hint::black_box;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

fn problem(scene: &str, trajectory: &str) -> (Arc<Model>, Prescription) {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let model =
        Arc::new(Model::new(&Scene::load(root.join("scenes").join(scene)).unwrap()).unwrap());
    let path = root.join("scenes/trajectories").join(trajectory);
    let table = mbfg::io::read_table(&path).unwrap();
    let p = Prescription::from_table(&model, &table, trajectory).unwrap();
    (model, p)
}

fn inverse_runs(c: &mut Criterion) {
    let mut group = c.benchmark_group("inverse");
    group
        .sample_size(10)
        .measurement_time(Duration::from_secs(10));
    for (label, scene, file, coordinates, sample_sigma) in [
        (
            "fourbar_10s_dt5ms",
            "fourbar-theta.yaml",
            "fourbar-theta.csv",
            Coordinates::Dependent,
            None,
        ),
        (
            "robot_5s_dt5ms",
            "pick-and-place.yaml",
            "pick-and-place.csv",
            Coordinates::Dependent,
            None,
        ),
        (
            "fourbar_10s_dt5ms_ic",
            "fourbar-theta.yaml",
            "fourbar-theta.csv",
            Coordinates::Independent,
            None,
        ),
        (
            "robot_5s_dt5ms_ic",
            "pick-and-place.yaml",
            "pick-and-place.csv",
            Coordinates::Independent,
            None,
        ),
        (
            "fourbar_10s_dt5ms_8digits",
            "fourbar-theta.yaml",
            "fourbar-theta-8digits.csv",
            Coordinates::Dependent,
            Some(SampleSigma::FromData),
        ),
        (
            "fourbar_10s_dt5ms_noisy",
            "fourbar-theta.yaml",
            "fourbar-theta-noisy.csv",
            Coordinates::Dependent,
            Some(SampleSigma::FromData),
        ),
    ] {
        let (model, p) = problem(scene, file);
        let options = InverseOptions {
            coordinates,
            sample_sigma,
            ..InverseOptions::default()
        };
        group.bench_function(label, |b| {
            b.iter(|| {
                black_box(
                    inverse::solve(model.clone(), &p, &options)
                        .unwrap()
                        .summary
                        .steps,
                )
            })
        });
    }
    group.finish();
}

criterion_group!(benches, inverse_runs);
criterion_main!(benches);
