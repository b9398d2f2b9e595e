//! Per-step cost against the size of the mechanism (`cargo bench --bench scale`): the
//! N four-bar (IFToMM A02; N = 1 … 100 loops, 2N + 3 coordinates) and the n-link
//! pendulum (n = 2 … 256 links, 3n coordinates) of `scenes/scale/`, each in four
//! series: DC with N_w = 1, IC with N_w = 1, DC batch (the trapezoidal rule), and DC
//! with N_w = 1 under Hermite–Simpson (`dc_w1_hs`, beside `dc_w1` for the cost of its
//! step against the trapezoidal rule's); 100 steps of dt = 1 ms from the scene's start.
//!
//! The time criterion reports is **per step, set-up apart**: each iteration runs a
//! 101-step run and a one-step run and reports the difference divided by 100
//! (`iter_custom`): what the steps after the first cost, without the set-up a run pays
//! once (the square step's sparse analysis, the first step's factorization). With 20
//! steps the set-up of a 64-link pendulum outweighed them, and the machine's slow
//! spells made the difference 0 or less; a pair whose difference is not positive is
//! run again. A size whose run takes
//! more than [`BUDGET`] is skipped, with every larger size of the same series, and a line
//! on stderr says so: extrapolated from the smaller sizes' per-step times with their
//! last local slope (at least 1), since one step of the largest sizes takes minutes
//! with a dense solver; then where one step with the set-up, or one run, takes more.

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion};
use mbfg::forward::{simulate, Coordinates, ForwardOptions, Integrator};
use mbfg::smoother::Mode;
use mbfg::{Model, Scene};
use std::hint::black_box;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

const DT: f64 = 1e-3;
/// Steps per measured run.
const STEPS: usize = 100;
/// The most one measured run (STEPS steps) may take.
const BUDGET: Duration = Duration::from_secs(1);

const FOURBAR: [usize; 8] = [1, 2, 5, 10, 20, 40, 50, 100];
const PENDULUM: [usize; 8] = [2, 4, 8, 16, 32, 64, 128, 256];

fn load(path: PathBuf) -> Arc<Model> {
    Arc::new(Model::new(&Scene::load(path).unwrap()).unwrap())
}

/// The scene of one size: the N four-bar of 40 loops is the published benchmark's
/// (`scenes/benchmarks/`), every other size is in `scenes/scale/`.
fn scene(family: &str, size: usize) -> PathBuf {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("scenes");
    let dir = if family == "n-fourbar" && size == 40 {
        "benchmarks"
    } else {
        "scale"
    };
    root.join(dir).join(format!("{family}-{size}.yaml"))
}

struct Series {
    tag: &'static str,
    coords: Coordinates,
    mode: Mode,
    integrator: Integrator,
}

const SERIES: [Series; 4] = [
    Series {
        tag: "dc_w1",
        coords: Coordinates::Dependent,
        mode: Mode::FixedLag(1),
        integrator: Integrator::Trapezoidal,
    },
    Series {
        tag: "dc_w1_hs",
        coords: Coordinates::Dependent,
        mode: Mode::FixedLag(1),
        integrator: Integrator::HermiteSimpson,
    },
    Series {
        tag: "ic_w1",
        coords: Coordinates::Independent,
        mode: Mode::FixedLag(1),
        integrator: Integrator::Trapezoidal,
    },
    Series {
        tag: "dc_batch",
        coords: Coordinates::Dependent,
        mode: Mode::Batch,
        integrator: Integrator::Trapezoidal,
    },
];

/// Runs `steps` steps; its wall time. Panics if a step fails: a benchmark of a run
/// that stopped early would measure something else.
fn run(model: &Arc<Model>, series: &Series, steps: usize) -> Duration {
    let mut opts = ForwardOptions::new(series.coords, DT, steps as f64 * DT, series.mode);
    opts.integrator = series.integrator;
    let start = Instant::now();
    let (tr, s) = simulate(model.clone(), &opts, &mut |_, _| {}).unwrap();
    let elapsed = start.elapsed();
    assert!(s.failures.is_empty() && tr.len() == steps + 1);
    black_box(s.steps);
    elapsed
}

fn family(c: &mut Criterion, name: &str, sizes: &[usize]) {
    let mut group = c.benchmark_group(format!("{name}_us_per_step"));
    group
        .sample_size(10)
        .warm_up_time(Duration::from_millis(300))
        .measurement_time(Duration::from_secs(2));
    for series in &SERIES {
        let mut over_budget = None;
        // (coordinates, seconds a step) of the sizes measured, ascending.
        let mut measured: Vec<(f64, f64)> = Vec::new();
        for &size in sizes {
            if let Some(smaller) = over_budget {
                eprintln!(
                    "scale: skipping {name}-{size} {}: {name}-{smaller} already took more than {BUDGET:?} a run",
                    series.tag
                );
                continue;
            }
            let model = load(scene(name, size));
            let n = model.n() as f64;
            // Extrapolated with the series' last local slope (at least 1): a size over the
            // budget is not even probed, as one step of it can take minutes.
            if let Some(&(n1, t1)) = measured.last() {
                let (n0, t0) = measured[measured.len().saturating_sub(2)];
                let k = if n1 > n0 {
                    ((t1 / t0).ln() / (n1 / n0).ln()).max(1.0)
                } else {
                    1.0
                };
                let guess = t1 * (n / n1).powf(k) * STEPS as f64;
                if guess > BUDGET.as_secs_f64() {
                    eprintln!(
                        "scale: skipping {name}-{size} {}: one run of {STEPS} steps extrapolates to ≈ {guess:.1} s (slope {k:.1}; > {BUDGET:?})",
                        series.tag
                    );
                    over_budget = Some(size);
                    continue;
                }
            }
            // One step with the set-up, the better of two (the first run of a process
            // pays for more); a run over the budget is skipped after one try.
            let one = run(&model, series, 1).min(run(&model, series, 1));
            // (One step with the set-up: times STEPS it would overstate a run whose
            // set-up outweighs its steps, the 128-link pendulum's in IC.)
            if one > BUDGET {
                eprintln!(
                    "scale: skipping {name}-{size} {}: one step with the set-up took {one:.1?} (> {BUDGET:?})",
                    series.tag
                );
                over_budget = Some(size);
                continue;
            }
            // One whole run: the time a step for the extrapolation to the next size.
            let whole = run(&model, series, STEPS);
            if whole > BUDGET {
                eprintln!(
                    "scale: skipping {name}-{size} {}: one run of {STEPS} steps took {whole:.1?} (> {BUDGET:?})",
                    series.tag
                );
                over_budget = Some(size);
                continue;
            }
            measured.push((n, whole.as_secs_f64() / STEPS as f64));
            group.bench_with_input(BenchmarkId::new(series.tag, size), &size, |b, _| {
                b.iter_custom(|iters| {
                    let mut per_step = Duration::ZERO;
                    for _ in 0..iters {
                        let steps = (0..5)
                            .map(|_| {
                                run(&model, series, STEPS + 1)
                                    .saturating_sub(run(&model, series, 1))
                            })
                            .find(|steps| !steps.is_zero())
                            .expect("five runs of STEPS + 1 steps no slower than one step");
                        per_step += steps / STEPS as u32;
                    }
                    per_step
                })
            });
        }
    }
    group.finish();
}

fn nfourbar(c: &mut Criterion) {
    family(c, "n-fourbar", &FOURBAR);
}

fn pendulum(c: &mut Criterion) {
    family(c, "n-pendulum", &PENDULUM);
}

criterion_group!(benches, nfourbar, pendulum);
criterion_main!(benches);
