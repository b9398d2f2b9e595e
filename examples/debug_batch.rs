use mbfg::forward::{simulate, Coordinates, ForwardOptions};
use mbfg::smoother::Mode;
use mbfg::{reference, Model, Scene};
use std::sync::Arc;
fn main() {
    let a: Vec<String> = std::env::args().collect();
    let t_end: f64 = a[1].parse().unwrap();
    let scene = Scene::load("scenes/fourbar-theta.yaml").unwrap();
    let model = Arc::new(Model::new(&scene).unwrap());
    let dt = 1e-3;
    let truth =
        reference::minimal_coordinates_rk4(&model, &model.independent, dt, t_end, 5e-5).unwrap();
    for mode in [Mode::FixedLag(1), Mode::FixedLag(3), Mode::Batch] {
        let mut opts = ForwardOptions::new(Coordinates::Dependent, dt, t_end, mode);
        opts.continue_on_failure = true;
        let (tr, s) = simulate(model.clone(), &opts, &mut |_, _| {}).unwrap();
        let n = tr.n();
        let mut line = String::new();
        for k in [tr.len() / 4, tr.len() / 2, tr.len() - 1] {
            let e: f64 = (0..4)
                .map(|c| (tr.q[k * n + c] - truth.q[k * n + c]).abs())
                .fold(0.0, f64::max);
            line += &format!(" t={:.3}: {:.2e}", tr.t[k], e);
        }
        println!(
            "{mode:?}: rmse {:.3e}{line} fails {} iters {:.2}",
            reference::rmse_points(&tr, &truth, &[0, 1, 2, 3]),
            s.failures.len(),
            s.mean_iterations
        );
    }
}
