//! Writes `reports/inverse.md` (run by `make report`): the suite's inverse-dynamics
//! problems solved by the factor graphs (DC and IC) against the classical solution
//! with the exact derivatives of each prescription. The forward pages come from the
//! Python harness (`harness/report.py`), which compares with the committed references.

use mbfg::forward::Coordinates;
use mbfg::inverse::{self, InverseOptions, Prescription};
use mbfg::motions;
use mbfg::{Model, Scene};
use std::fmt::Write as _;
use std::sync::Arc;
use std::time::Instant;

fn load(path: &str) -> Arc<Model> {
    Arc::new(Model::new(&Scene::load(path).expect("scene")).expect("model"))
}

fn inverse_table(out: &mut String) {
    writeln!(
        out,
        "# Inverse dynamics\n\nThe suite's prescriptions (`scenes/trajectories/`), solved in batch from the kinematic start, \
         against the classical solution with the exact derivatives of the prescription \
         (position, velocity, acceleration problems, then the augmented system).\n\n\
         | problem | coords | force RMSE | peak | RMSE / peak | worst tracking | iterations | time |\n|---|---|---|---|---|---|---|---|"
    )
    .unwrap();
    type Motion = fn(f64) -> (Vec<f64>, Vec<f64>, Vec<f64>);
    let crank: Motion = |t| motions::split([motions::fourbar_crank(t)]);
    let robot: Motion = |t| motions::split(motions::robot_cycle(t));
    let pendulum: Motion = |t| motions::split(motions::double_pendulum(t));
    for (name, scene, file, motion) in [
        (
            "four-bar crank",
            "fourbar-theta",
            "fourbar-theta.csv",
            crank,
        ),
        (
            "pick-and-place motors",
            "pick-and-place",
            "pick-and-place.csv",
            robot,
        ),
        (
            "double pendulum joints",
            "double-pendulum",
            "double-pendulum.csv",
            pendulum,
        ),
    ] {
        let model = load(&format!("scenes/{scene}.yaml"));
        let table =
            mbfg::io::read_table(std::path::Path::new(&format!("scenes/trajectories/{file}")))
                .expect("trajectory");
        let p = Prescription::from_table(&model, &table, file).expect("prescription");
        for coords in [Coordinates::Dependent, Coordinates::Independent] {
            eprintln!("  inverse {name} {coords:?}");
            let opts = InverseOptions {
                coordinates: coords,
                ..InverseOptions::default()
            };
            let start = Instant::now();
            let sol = inverse::solve(model.clone(), &p, &opts).expect("inverse");
            let time = start.elapsed();
            let exact = inverse::classical(&model, &p.indices, &sol.trajectory.t, motion)
                .expect("classical");
            let n = model.n();
            for &i in &p.indices {
                let err: f64 = (0..p.steps)
                    .map(|k| (sol.forces[k * n + i] - exact.forces[k * n + i]).powi(2))
                    .sum::<f64>()
                    / p.steps as f64;
                let peak = (0..p.steps).fold(0.0f64, |m, k| m.max(exact.forces[k * n + i].abs()));
                writeln!(
                    out,
                    "| {name}: Q:{} | {} | {:.3e} | {peak:.2} | {:.2e} | {:.0e} | {} | {:.0} ms |",
                    model.names[i],
                    if coords == Coordinates::Dependent {
                        "DC"
                    } else {
                        "IC"
                    },
                    err.sqrt(),
                    err.sqrt() / peak,
                    sol.summary.worst_tracking,
                    sol.summary.report.iterations,
                    time.as_secs_f64() * 1e3
                )
                .unwrap();
            }
        }
    }
    out.push_str("\nTargets (inverse-dynamics issue): four-bar ≤ 5e-3 N·m RMSE; robot ≤ 1e-3 of peak; double pendulum ≤ 1e-4 of peak (there checked in `tests/inverse.rs` against closed-form Lagrange equations as well).\n");
}

fn main() {
    std::fs::create_dir_all("reports").expect("reports/");
    let mut page = String::new();
    inverse_table(&mut page);
    std::fs::write("reports/inverse.md", page).expect("write reports/inverse.md");
    eprintln!("wrote reports/inverse.md");
}
