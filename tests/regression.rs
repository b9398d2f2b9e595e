//! RMSE regression thresholds against the committed references.
//!
//! `tests/data/rmse-bounds.csv` lists scene × coordinates × window × dt with an RMSE
//! bound in metres over the x, y of every moving point: the value measured when the
//! row was added, with a small margin. A run above its bound fails; tightening a bound
//! is how an improvement is locked in (`python -m harness.regression` measures every
//! row and rewrites the file with fresh values and the margin).

use mbfg::forward::{simulate, Coordinates, ForwardOptions};
use mbfg::io::read_table;
use mbfg::model::PointSlot;
use mbfg::smoother::Mode;
use mbfg::{Model, Scene};
use std::path::PathBuf;
use std::sync::Arc;

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

struct Row {
    line: String,
    scene: String,
    reference: String,
    coords: Coordinates,
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
            Row {
                line: l.to_string(),
                scene: f[0].into(),
                reference: f[1].into(),
                coords: match f[2] {
                    "dc" => Coordinates::Dependent,
                    "ic" => Coordinates::Independent,
                    other => panic!("rmse-bounds.csv: coords '{other}'"),
                },
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

/// RMSE over the free points' x, y at the reference's samples that the run has.
fn rmse(model: &Model, run: &mbfg::forward::Trajectory, reference: &str) -> f64 {
    let path = root()
        .join("references")
        .join(reference)
        .join("reference.csv.gz");
    let truth = read_table(&path).unwrap_or_else(|e| panic!("{e}"));
    let t_ref = truth.column("t").unwrap();
    let step = t_ref[1] - t_ref[0];
    let cols: Vec<usize> = model
        .points
        .iter()
        .filter_map(|p| match p {
            PointSlot::Free(i) => Some(*i),
            PointSlot::Fixed(_) => None,
        })
        .flat_map(|i| [i, i + 1])
        .collect();
    let reference_cols: Vec<Vec<f64>> = cols
        .iter()
        .map(|&c| truth.column(&format!("q:{}", model.names[c])).unwrap())
        .collect();
    let (mut sum, mut count) = (0.0, 0usize);
    for (k, &t) in run.t.iter().enumerate() {
        let j = (t / step).round() as usize;
        if j >= t_ref.len() || (t_ref[j] - t).abs() > 1e-9 {
            continue;
        }
        for (c, col) in cols.iter().zip(&reference_cols) {
            let d = run.q_at(k)[*c] - col[j];
            sum += d * d;
            count += 1;
        }
    }
    assert!(count > 0, "no common samples with {}", path.display());
    (sum / count as f64).sqrt()
}

#[test]
fn rmse_stays_within_the_checked_in_bounds() {
    let rows = bounds();
    assert!(!rows.is_empty());
    let mut failures = Vec::new();
    for row in &rows {
        let scene = Scene::load(root().join("scenes").join(format!("{}.yaml", row.scene))).unwrap();
        let model = Arc::new(Model::new(&scene).unwrap());
        let options = ForwardOptions::new(row.coords, row.dt, row.t_end, row.mode);
        let (run, summary) = simulate(model.clone(), &options, &mut |_, _| {}).unwrap();
        let measured = if summary.failures.is_empty() {
            rmse(&model, &run, &row.reference)
        } else {
            f64::INFINITY
        };
        println!("{:<60} measured {measured:.4e}", row.line);
        if measured > row.bound {
            failures.push(format!(
                "{}: measured {measured:.4e} > bound {:.4e}",
                row.line, row.bound
            ));
        }
    }
    assert!(
        failures.is_empty(),
        "RMSE above its bound:\n{}",
        failures.join("\n")
    );
}
