//! One run of a benchmark case, for profilers (`valgrind --tool=callgrind`):
//! `cargo run --release --example profile -- CASE`, CASE one of `dc1`, `dc10`,
//! `dcbatch`, `ic1`, `ic10`, `icbatch`, `inv4bar`, `invrobot` (inverse, DC), `inv4bar-ic`,
//! `invrobot-ic`.
use mbfg::forward::{simulate, Coordinates, ForwardOptions};
use mbfg::inverse::{self, InverseOptions, Prescription};
use mbfg::smoother::Mode;
use mbfg::{Model, Scene};
use std::sync::Arc;

fn load(name: &str) -> Arc<Model> {
    Arc::new(Model::new(&Scene::load(format!("scenes/{name}")).unwrap()).unwrap())
}

fn main() {
    let case = std::env::args().nth(1).unwrap_or_else(|| "dc1".into());
    let forward = |coords, scene: &str, mode| {
        let opts = ForwardOptions::new(coords, 1e-3, 5.0, mode);
        let (_, s) = simulate(load(scene), &opts, &mut |_, _| {}).unwrap();
        println!(
            "{case}: {:?}, mean iterations {:.3}, max {}, failures {}",
            s.wall_time,
            s.mean_iterations,
            s.max_iterations,
            s.failures.len()
        );
    };
    let inverse = |scene: &str, file: &str, coordinates| {
        let model = load(scene);
        let table =
            mbfg::io::read_table(std::path::Path::new(&format!("scenes/trajectories/{file}")))
                .unwrap();
        let p = Prescription::from_table(&model, &table, file).unwrap();
        let options = InverseOptions {
            coordinates,
            ..InverseOptions::default()
        };
        let sol = inverse::solve(model, &p, &options).unwrap();
        println!(
            "{case}: {:?} {:?}",
            sol.summary.wall_time, sol.summary.report
        );
    };
    let (dc, ic) = (Coordinates::Dependent, Coordinates::Independent);
    match case.as_str() {
        "dc1" => forward(dc, "fourbar.yaml", Mode::FixedLag(1)),
        "dc10" => forward(dc, "fourbar.yaml", Mode::FixedLag(10)),
        "dcbatch" => forward(dc, "fourbar.yaml", Mode::Batch),
        "ic1" => forward(ic, "fourbar-theta.yaml", Mode::FixedLag(1)),
        "ic10" => forward(ic, "fourbar-theta.yaml", Mode::FixedLag(10)),
        "icbatch" => forward(ic, "fourbar-theta.yaml", Mode::Batch),
        "inv4bar" => inverse("fourbar-theta.yaml", "fourbar-theta.csv", dc),
        "invrobot" => inverse("pick-and-place.yaml", "pick-and-place.csv", dc),
        "inv4bar-ic" => inverse("fourbar-theta.yaml", "fourbar-theta.csv", ic),
        "invrobot-ic" => inverse("pick-and-place.yaml", "pick-and-place.csv", ic),
        other => panic!("unknown case {other}"),
    }
}
