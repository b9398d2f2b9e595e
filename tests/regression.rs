//! RMSE regression thresholds against the committed references.
//!
//! `tests/data/rmse-bounds.csv` lists scene × coordinates × window × dt with an RMSE
//! bound in metres over the x, y of every moving point: the value measured when the
//! row was added, with a small margin. A run above its bound fails; tightening a bound
//! is how an improvement is locked in (`python -m harness.regression` measures every
//! row and rewrites the file with fresh values and the margin). Lines starting with
//! `#` are comments (the harness notes there the rows whose run failed).
//!
//! The coordinates column is `dc` or `ic`, at the defaults, optionally followed by
//! variants, each after a `-`:
//! - `full`: DC with the paper's integrator factors ([`DcIntegrators::Full`]);
//! - `general`: every step through the general solver
//!   ([`ForwardOptions::square_steps`] off), where the default takes a step as a
//!   sparse square system, so that the windows and the batch really run theirs;
//! - `hs`: the Hermite–Simpson integrator ([`Integrator::HermiteSimpson`]).

mod common;

use common::reference_rmse;
use mbfg::forward::{simulate, Coordinates, DcIntegrators, ForwardOptions, Integrator};
use mbfg::smoother::Mode;
use mbfg::{Model, Scene};
use std::path::PathBuf;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Instant;

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

struct Row {
    line: String,
    scene: String,
    reference: String,
    coords: Coordinates,
    integrators: DcIntegrators,
    integrator: Integrator,
    square_steps: bool,
    mode: Mode,
    dt: f64,
    t_end: f64,
    bound: f64,
}

fn bounds() -> Vec<Row> {
    let text = std::fs::read_to_string(root().join("tests/data/rmse-bounds.csv")).unwrap();
    text.lines()
        .skip(1)
        .filter(|l| !l.trim().is_empty() && !l.starts_with('#'))
        .map(|l| {
            let f: Vec<&str> = l.split(',').map(str::trim).collect();
            assert_eq!(f.len(), 7, "rmse-bounds.csv: {l}");
            let mut parts = f[2].split('-');
            let coords = match parts.next() {
                Some("dc") => Coordinates::Dependent,
                Some("ic") => Coordinates::Independent,
                _ => panic!("rmse-bounds.csv: coords '{}'", f[2]),
            };
            let (mut integrators, mut integrator, mut square_steps) =
                (DcIntegrators::Auto, Integrator::Trapezoidal, true);
            for variant in parts {
                match variant {
                    "full" if coords == Coordinates::Dependent => integrators = DcIntegrators::Full,
                    "general" => square_steps = false,
                    "hs" => integrator = Integrator::HermiteSimpson,
                    _ => panic!("rmse-bounds.csv: coords '{}'", f[2]),
                }
            }
            Row {
                line: l.to_string(),
                scene: f[0].into(),
                reference: f[1].into(),
                coords,
                integrators,
                integrator,
                square_steps,
                mode: match f[3] {
                    "batch" => Mode::Batch,
                    n => Mode::FixedLag(n.parse().unwrap()),
                },
                dt: f[4].parse().unwrap(),
                t_end: f[5].parse().unwrap(),
                bound: f[6].parse().unwrap(),
            }
        })
        .collect()
}

/// A row's printed line, and its failure if above its bound.
type Measured = (String, Option<String>);

/// Row `row` run: its printed line, and its failure if above its bound.
fn measure(row: &Row) -> Measured {
    let scene = Scene::load(root().join("scenes").join(format!("{}.yaml", row.scene))).unwrap();
    let model = Arc::new(Model::new(&scene).unwrap());
    let mut options = ForwardOptions::new(row.coords, row.dt, row.t_end, row.mode);
    options.dc_integrators = row.integrators;
    options.integrator = row.integrator;
    options.square_steps = row.square_steps;
    let start = Instant::now();
    let (run, summary) = simulate(model.clone(), &options, &mut |_, _| {}).unwrap();
    let seconds = start.elapsed().as_secs_f64();
    let measured = if summary.failures.is_empty() {
        reference_rmse(&model, &run, &row.reference)
    } else {
        f64::INFINITY
    };
    let line = format!("{:<64} measured {measured:.4e} ({seconds:.2} s)", row.line);
    let failure = (measured > row.bound).then(|| {
        format!(
            "{}: measured {measured:.4e} > bound {:.4e}",
            row.line, row.bound
        )
    });
    (line, failure)
}

#[test]
fn rmse_stays_within_the_checked_in_bounds() {
    let rows = bounds();
    assert!(!rows.is_empty());
    // The rows on every core (they are independent runs), reported in file order.
    let next = AtomicUsize::new(0);
    let results: Mutex<Vec<Option<Measured>>> = Mutex::new(vec![None; rows.len()]);
    let workers = std::thread::available_parallelism().map_or(1, |n| n.get());
    std::thread::scope(|scope| {
        for _ in 0..workers {
            scope.spawn(|| loop {
                let i = next.fetch_add(1, Ordering::Relaxed);
                let Some(row) = rows.get(i) else { break };
                let result = measure(row);
                results.lock().unwrap()[i] = Some(result);
            });
        }
    });
    let mut failures = Vec::new();
    for (line, failure) in results.into_inner().unwrap().into_iter().flatten() {
        println!("{line}");
        failures.extend(failure);
    }
    assert!(
        failures.is_empty(),
        "RMSE above its bound:\n{}",
        failures.join("\n")
    );
}
