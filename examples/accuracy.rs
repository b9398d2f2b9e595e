//! The paper's four-bar (5 s from rest under gravity) against a minimal-coordinate
//! RK4 reference: RMSE, wall time, iterations and constraint residuals for DC (scene
//! `fourbar`) and IC (scene `fourbar-theta`) over N_w ∈ {1, 2, 5, 10} and batch.
//!
//! `cargo run --release --features testing --example accuracy -- [dt]`; environment:
//! `TEND` (default 5), `ONLY` (e.g. `DependentFixedLag(1)`),
//! `GRID="σ_iq,σ_iv,σ_dyn[,σ_eq[,σ_q0]];..."` sweeps noise models at N_w = 1 (or
//! `WINDOW=n|batch`), DC or, with `IC=1`, IC.
use mbfg::forward::{simulate, Coordinates, ForwardOptions};
use mbfg::smoother::Mode;
use mbfg::{reference, Model, Scene};
use std::sync::Arc;

fn load(path: &str) -> Arc<Model> {
    Arc::new(Model::new(&Scene::load(path).expect("scene")).expect("model"))
}

fn main() {
    let dt: f64 = std::env::args()
        .nth(1)
        .map(|s| s.parse().expect("dt"))
        .unwrap_or(1e-3);
    let t_end: f64 = std::env::var("TEND")
        .map(|s| s.parse().expect("TEND"))
        .unwrap_or(5.0);
    let dc = load("scenes/fourbar.yaml");
    let ic = load("scenes/fourbar-theta.yaml");
    let t0 = std::time::Instant::now();
    let truth =
        reference::minimal_coordinates_rk4(&ic, &ic.independent, dt, t_end, dt.min(1e-4) / 2.0)
            .expect("reference");
    eprintln!("reference: {:?}", t0.elapsed());
    // x₁, y₁, x₂, y₂ come first in both scenes.
    let points: Vec<usize> = (0..4).collect();
    let run = |coords: Coordinates, mode: Mode, tweak: &dyn Fn(&mut ForwardOptions)| {
        let model = if coords == Coordinates::Dependent {
            dc.clone()
        } else {
            ic.clone()
        };
        let mut opts = ForwardOptions::new(coords, dt, t_end, mode);
        opts.continue_on_failure = true;
        tweak(&mut opts);
        let (tr, s) = simulate(model, &opts, &mut |_, _| {}).expect("simulate");
        for f in s.failures.iter().take(3) {
            println!(
                "  not converged: step {} (t = {:.3}): {:?}",
                f.step, f.t, f.report
            );
        }
        (reference::rmse_points(&tr, &truth, &points), s)
    };
    if let Ok(grid) = std::env::var("GRID") {
        let coords = if std::env::var("IC").is_ok() {
            Coordinates::Independent
        } else {
            Coordinates::Dependent
        };
        for spec in grid.split(';') {
            let v: Vec<f64> = spec.split(',').map(|x| x.parse().expect("σ")).collect();
            let mode = match std::env::var("WINDOW").ok().as_deref() {
                None => Mode::FixedLag(1),
                Some("batch") => Mode::Batch,
                Some(n) => Mode::FixedLag(n.parse().expect("WINDOW")),
            };
            let (rmse, s) = run(coords, mode, &|o| {
                o.noise.integrator_position = v[0];
                o.noise.integrator_velocity = v[1];
                o.noise.dynamics = v[2];
                if let Some(&e) = v.get(3) {
                    o.noise.equality = e;
                }
                if let Some(&e) = v.get(4) {
                    o.noise.initial_q = e;
                }
            });
            println!(
                "{spec}: rmse {rmse:.3e}  iterations {:.2}  failures {}",
                s.mean_iterations,
                s.failures.len()
            );
        }
        return;
    }
    let only = std::env::var("ONLY").ok();
    for coords in [Coordinates::Dependent, Coordinates::Independent] {
        for mode in [
            Mode::FixedLag(1),
            Mode::FixedLag(2),
            Mode::FixedLag(5),
            Mode::FixedLag(10),
            Mode::Batch,
        ] {
            if only
                .as_ref()
                .is_some_and(|o| *o != format!("{coords:?}{mode:?}"))
            {
                continue;
            }
            // REPEAT=n: the median wall time of n runs (the machine is shared).
            let repeat: usize = std::env::var("REPEAT")
                .map(|v| v.parse().expect("REPEAT"))
                .unwrap_or(1);
            let mut runs: Vec<(f64, mbfg::forward::RunSummary)> = (0..repeat.max(1))
                .map(|_| run(coords, mode, &|_| {}))
                .collect();
            runs.sort_by_key(|r| r.1.wall_time);
            let (rmse, s) = runs.swap_remove(runs.len() / 2);
            println!(
                "{coords:?} {mode:?}: rmse {rmse:.3e}  time {:?}  iterations {:.2}/{}  |Φ| {:.1e}  |Φq q̇| {:.1e}  drift {:.2e}  failures {}",
                s.wall_time,
                s.mean_iterations,
                s.max_iterations,
                s.worst_phi,
                s.worst_velocity_constraint,
                s.energy_drift.unwrap_or(0.0),
                s.failures.len()
            );
        }
    }
}
