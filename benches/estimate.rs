//! Benchmarks of state estimation (`make bench`): the benchmark four-bar's bad model
//! (scenes/estimation/) corrected by its crank encoder read at 200 Hz for 10 s
//! (2001 readings, seed 1, from a 1 ms simulation of the true scene): the fixed-lag
//! estimator at windows 1, 20 and 50, and the batch estimate of the whole record.
//! Each iteration is the whole record; criterion's time divided by 2001 is the cost
//! per step. `online_steps/<N>` runs the online estimator (window 20) over N steps of
//! repeated readings: the time per step must not grow with N.

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion};
use mbfg::coordinates::Coordinates;
use mbfg::estimate::{estimate, run, EstimateOptions, Estimator, Record, Smoothing, Uncertainty};
use mbfg::forward::{simulate, ForwardOptions};
use mbfg::sensors::measure::measure;
use mbfg::smoother::Mode;
use mbfg::{Model, Scene};
use std::hint::black_box;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

fn model(name: &str) -> Arc<Model> {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("scenes/estimation")
        .join(name);
    Arc::new(Model::new(&Scene::load(path).unwrap()).unwrap())
}

/// The encoder's readings of the true four-bar over `t_end` at 200 Hz, as the bad
/// scene's record.
fn record(bad: &Model, t_end: f64) -> Record {
    let truth_model = model("fourbar.yaml");
    let options = ForwardOptions::new(Coordinates::Dependent, 0.005, t_end, Mode::FixedLag(1));
    let (truth, _) = simulate(truth_model.clone(), &options, &mut |_, _| {}).unwrap();
    let m = measure(&truth_model, &truth, 1, None).unwrap();
    let enc = m.column("enc").unwrap();
    let columns = vec!["t".to_string(), "enc".to_string()];
    let rows: Vec<(f64, Vec<f64>)> =
        m.t.iter()
            .zip(&enc)
            .map(|(&t, &y)| (t, vec![t, y]))
            .collect();
    Record::from_rows(bad, &columns, &rows, None).unwrap()
}

fn record_runs(c: &mut Criterion) {
    let bad = model("fourbar-bad.yaml");
    let record = record(&bad, 10.0);
    let mut group = c.benchmark_group("estimate_fourbar_10s_200hz");
    group
        .sample_size(10)
        .measurement_time(Duration::from_secs(20));
    for (label, smoothing) in [
        ("window_1", Smoothing::Window(1)),
        ("window_20", Smoothing::Window(20)),
        ("window_50", Smoothing::Window(50)),
        ("batch", Smoothing::Batch),
    ] {
        let options = EstimateOptions {
            smoothing,
            ..EstimateOptions::default()
        };
        group.bench_function(label, |b| {
            b.iter(|| {
                let mut last = 0.0;
                estimate(bad.clone(), &record, &options, &mut |e| {
                    last = e.x[0];
                    Ok(())
                })
                .unwrap();
                black_box(last)
            })
        });
    }
    group.finish();
}

fn online_steps(c: &mut Criterion) {
    let bad = model("fourbar-bad.yaml");
    let record = record(&bad, 80.0);
    let mut group = c.benchmark_group("online_steps");
    group
        .sample_size(10)
        .measurement_time(Duration::from_secs(20));
    for steps in [1_000usize, 16_000] {
        group.bench_with_input(BenchmarkId::from_parameter(steps), &steps, |b, &steps| {
            b.iter(|| {
                let eg = run::graph_with(
                    &bad,
                    EstimateOptions::default().motion(&bad),
                    &record,
                    &Uncertainty::of(&bad, record.dt),
                )
                .unwrap();
                let settings = EstimateOptions::default().settings;
                let mut est = Estimator::new(bad.clone(), eg, 20, settings, false).unwrap();
                for k in 0..steps {
                    let readings = &record.steps[k];
                    black_box(
                        est.update(run::reading_factors(&bad, readings).unwrap())
                            .unwrap(),
                    );
                }
            })
        });
    }
    group.finish();
}

criterion_group!(benches, record_runs, online_steps);
criterion_main!(benches);
