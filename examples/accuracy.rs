//! Four-bar accuracy and timing against the minimal-coordinate reference:
//! `cargo run --release --example accuracy -- [dt] [windows...]`.
use mbfg::forward::{simulate, Coordinates, ForwardOptions};
use mbfg::smoother::Mode;
use mbfg::{reference, Model, Scene};
use std::sync::Arc;

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let dt: f64 = args.get(1).map(|s| s.parse().unwrap()).unwrap_or(1e-3);
    let scene = Scene::load(&std::env::var("SCENE").unwrap_or("scenes/fourbar-theta.yaml".into())).unwrap();
    let model = Arc::new(Model::new(&scene).unwrap());
    let ref_model = Model::new(&Scene::load("scenes/fourbar-theta.yaml").unwrap()).unwrap();
    let t_end: f64 = std::env::var("TEND")
        .map(|s| s.parse().unwrap())
        .unwrap_or(5.0);
    let t0 = std::time::Instant::now();
    let truth = reference::minimal_coordinates_rk4(
        &ref_model,
        &ref_model.independent,
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
    if let Ok(grid) = std::env::var("GRID") {
        // GRID="tiq,tiv,dyn;..." sweeps DC noise models at N_w = 1.
        for triple in grid.split(';') {
            let v: Vec<f64> = triple.split(',').map(|x| x.parse().unwrap()).collect();
            let coords = if std::env::var("IC").is_ok() { Coordinates::Independent } else { Coordinates::Dependent };
            let mut opts = ForwardOptions::new(coords, dt, t_end, Mode::FixedLag(1));
            opts.noise.integrator_position = v[0];
            opts.noise.integrator_velocity = v[1];
            opts.noise.dynamics = v[2];
            if let Some(e) = v.get(3) { opts.noise.equality = *e; }
            if let Some(e) = v.get(4) { opts.noise.initial_q = *e; }
            opts.continue_on_failure = true;
            let (tr, s) = simulate(model.clone(), &opts, &mut |_, _| {}).unwrap();
            let rmse = reference::rmse_points(&tr, &truth, &pts);
            for f in s.failures.iter().take(3) {
                println!("  failure at step {} t={:.3}: {:?}", f.step, f.t, f.report);
            }
            println!("{triple}: rmse {rmse:.3e} iters {:.2} failures {}", s.mean_iterations, s.failures.len());
        }
        return;
    }
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
            opts.continue_on_failure = true;
            if std::env::var("ONLY")
                .map(|o| o != format!("{coords:?}{mode:?}"))
                .unwrap_or(false)
            {
                continue;
            }
            let (tr, s) = simulate(model.clone(), &opts, &mut |_, _| {}).unwrap();
            for f in s.failures.iter().take(5) {
                println!("  failure at step {} t={:.3}: {:?}", f.step, f.t, f.report);
            }
            if std::env::var("TRACE").is_ok() {
                let mut phi = vec![0.0; model.m()];
                for k in (0..tr.len()).step_by(50) {
                    model.phi_into(tr.q_at(k), &mut phi);
                    let p = phi.iter().fold(0.0f64, |a, b| a.max(b.abs()));
                    let e: f64 = (0..4).map(|c| (tr.q_at(k)[c] - truth.q_at(k)[c]).abs()).fold(0.0, f64::max);
                    println!("  t={:.3} |phi|={p:.2e} err={e:.2e} q={:?}", tr.t[k], &tr.q_at(k)[..4]);
                }
            }
            let rmse = reference::rmse_points(&tr, &truth, &pts);
            println!("{coords:?} {mode:?}: rmse {rmse:.3e}  time {:?}  iters {:.2}/{}  |Φ| {:.1e} |Φq q̇| {:.1e} drift {:.2e} failures {}",
                s.wall_time, s.mean_iterations, s.max_iterations, s.worst_phi, s.worst_velocity_constraint, s.energy_drift.unwrap_or(0.0), s.failures.len());
        }
    }
}
