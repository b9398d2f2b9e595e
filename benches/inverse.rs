//! Benchmarks of inverse dynamics (`make bench`): the suite's prescriptions for the
//! four-bar (10 s, 2001 samples) and the pick-and-place robot (5 s, 1001 samples),
//! each solved in batch from the kinematic start, in dependent coordinates (the
//! targets) and in independent ones (`_ic`).

use criterion::{criterion_group, criterion_main, Criterion};
use mbfg::forward::Coordinates;
use mbfg::inverse::{self, InverseOptions, Prescription};
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
    for (label, scene, file, coordinates) in [
        (
            "fourbar_10s_dt5ms",
            "fourbar-theta.yaml",
            "fourbar-theta.csv",
            Coordinates::Dependent,
        ),
        (
            "robot_5s_dt5ms",
            "pick-and-place.yaml",
            "pick-and-place.csv",
            Coordinates::Dependent,
        ),
        (
            "fourbar_10s_dt5ms_ic",
            "fourbar-theta.yaml",
            "fourbar-theta.csv",
            Coordinates::Independent,
        ),
        (
            "robot_5s_dt5ms_ic",
            "pick-and-place.yaml",
            "pick-and-place.csv",
            Coordinates::Independent,
        ),
    ] {
        let (model, p) = problem(scene, file);
        let options = InverseOptions {
            coordinates,
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
