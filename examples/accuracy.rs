//! Four-bar accuracy and timing against the minimal-coordinate reference:
//! `cargo run --release --example accuracy -- [dt] [windows...]`.
use mbfg::forward::{simulate, Coordinates, ForwardOptions};
use mbfg::smoother::Mode;
use mbfg::{reference, Model, Scene};
use std::sync::Arc;

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let dt: f64 = args.get(1).map(|s| s.parse().unwrap()).unwrap_or(1e-3);
    let scene = Scene::load("scenes/fourbar-theta.yaml").unwrap();
    let model = Arc::new(Model::new(&scene).unwrap());
    let t_end: f64 = std::env::var("TEND")
        .map(|s| s.parse().unwrap())
        .unwrap_or(5.0);
    let t0 = std::time::Instant::now();
    let truth = reference::minimal_coordinates_rk4(
        &model,
        &model.independent,
        dt,
        t_end,
        dt.min(1e-4) / 2.0,
    )
    .unwrap();
    eprintln!("reference: {:?}", t0.elapsed());
    let pts: Vec<usize> = (0..4).collect();
    let modes: Vec<Mode> = vec![
        Mode::FixedLag(1),
        Mode::FixedLag(2),
        Mode::FixedLag(5),
        Mode::FixedLag(10),
        Mode::Batch,
    ];
    for coords in [Coordinates::Dependent, Coordinates::Independent] {
        for mode in &modes {
            let mut opts = ForwardOptions::new(coords, dt, t_end, *mode);
            let env = |k: &str, d: f64| {
                std::env::var(k)
                    .ok()
                    .map(|v| v.parse().unwrap())
                    .unwrap_or(d)
            };
            opts.noise.integrator_position = env("TIQ", opts.noise.integrator_position);
            opts.noise.integrator_velocity = env("TIV", opts.noise.integrator_velocity);
            opts.noise.dynamics = env("DYN", opts.noise.dynamics);
            opts.noise.hard = env("HARD", opts.noise.hard);
            opts.continue_on_failure = true;
            if std::env::var("ONLY")
                .map(|o| o != format!("{coords:?}{mode:?}"))
                .unwrap_or(false)
            {
                continue;
            }
            let (tr, s) = simulate(model.clone(), &opts, &mut |_, _| {}).unwrap();
            let rmse = reference::rmse_points(&tr, &truth, &pts);
            println!("{coords:?} {mode:?}: rmse {rmse:.3e}  time {:?}  iters {:.2}/{}  |Φ| {:.1e} |Φq q̇| {:.1e} drift {:.2e} failures {}",
                s.wall_time, s.mean_iterations, s.max_iterations, s.worst_phi, s.worst_velocity_constraint, s.energy_drift.unwrap_or(0.0), s.failures.len());
        }
    }
}
