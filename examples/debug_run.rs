use mbfg::forward::{simulate, Coordinates, ForwardOptions};
use mbfg::smoother::Mode;
use mbfg::{Model, Scene};
use std::sync::Arc;
fn main() {
    let a: Vec<String> = std::env::args().collect();
    let scene = Scene::load(&a[1]).unwrap();
    let model = Arc::new(Model::new(&scene).unwrap());
    let coords = if a[2] == "ic" {
        Coordinates::Independent
    } else {
        Coordinates::Dependent
    };
    let w: usize = a[3].parse().unwrap();
    let t_end: f64 = a[4].parse().unwrap();
    let mut opts = ForwardOptions::new(
        coords,
        1e-3,
        t_end,
        if w == 0 {
            Mode::Batch
        } else {
            Mode::FixedLag(w)
        },
    );
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
    let (_tr, s) = simulate(model, &opts, &mut |_, _| {}).unwrap();
    println!("{s:?}");
}
