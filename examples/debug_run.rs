use mbfg::forward::{simulate, Coordinates, ForwardOptions};
use mbfg::smoother::Mode;
use mbfg::{Model, Scene};
use std::sync::Arc;
fn main() {
    let a: Vec<String> = std::env::args().collect();
    let scene = Scene::load(&a[1]).unwrap();
    let model = Arc::new(Model::new(&scene).unwrap());
    let coords = if a[2] == "ic" { Coordinates::Independent } else { Coordinates::Dependent };
    let w: usize = a[3].parse().unwrap();
    let t_end: f64 = a[4].parse().unwrap();
    let opts = ForwardOptions::new(coords, 1e-3, t_end, if w == 0 { Mode::Batch } else { Mode::FixedLag(w) });
    let (_tr, s) = simulate(model, &opts, &mut |_, _| {}).unwrap();
    println!("{s:?}");
}
