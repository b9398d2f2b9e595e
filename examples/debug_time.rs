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
    let mut opts = ForwardOptions::new(Coordinates::Dependent, dt, t_end, Mode::FixedLag(1));
    opts.continue_on_failure = true;
    let (tr, _s) = simulate(model.clone(), &opts, &mut |_, _| {}).unwrap();
    let n = tr.n();
    let stride: usize = std::env::var("STRIDE")
        .map(|s| s.parse().unwrap())
        .unwrap_or(50);
    let from: usize = std::env::var("FROM")
        .map(|s| s.parse().unwrap())
        .unwrap_or(0);
    for k in (from..tr.len()).step_by(stride) {
        let e: f64 = (0..4)
            .map(|c| (tr.q[k * n + c] - truth.q[k * n + c]).abs())
            .fold(0.0, f64::max);
        let acc: f64 = (0..4)
            .map(|c| truth.ddq[k * n + c].abs())
            .fold(0.0, f64::max);
        println!(
            "t={:.3} err {:.2e} theta {:.3} dtheta {:.2} max|ddq| {:.1}  q {:?}",
            tr.t[k],
            e,
            truth.q[k * n + 4],
            truth.dq[k * n + 4],
            acc,
            &truth.q[k * n..k * n + 4]
                .iter()
                .map(|v| (v * 1000.0).round() / 1000.0)
                .collect::<Vec<_>>()
        );
    }
}
