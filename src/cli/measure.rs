//! `mbfg measure`: simulated sensor readings of a known trajectory — each sensor's
//! reading at its rate, with seeded noise and quantization — written as CSV.

use super::failure::{plain, Failure};
use super::output::Output;
use super::{load, print_summary};
use std::path::PathBuf;

/// The arguments of `mbfg measure`.
#[derive(clap::Args)]
pub struct MeasureArgs {
    /// Scene file (YAML) with a `sensors:` section.
    scene: PathBuf,
    /// The true motion: a trajectory CSV as `mbfg simulate` writes it (t, q:<c>,
    /// dq:<c>, ddq:<c>; gzip-compressed when it ends in `.gz`).
    #[arg(long, value_name = "FILE.csv")]
    trajectory: PathBuf,
    /// Seed of the noise: the same seed gives the same readings.
    #[arg(long, value_name = "N")]
    seed: u64,
    /// Readings per second of the sensors without a `rate` of their own (default:
    /// one at every row of the trajectory).
    #[arg(long, value_name = "HZ")]
    rate: Option<f64>,
    /// Output CSV (`t`, then one column per reading entry; gzip-compressed when it
    /// ends in `.gz`); the summary then goes to standard output.
    #[arg(long, value_name = "FILE.csv")]
    out: Option<PathBuf>,
}

pub fn run(args: MeasureArgs) -> Result<(), Failure> {
    let MeasureArgs {
        scene,
        trajectory,
        seed,
        rate,
        out,
    } = args;
    let (_, model) = load(&scene)?;
    if model.sensors.is_empty() {
        return Err(Failure::Input(format!(
            "scene {} has no sensors: declare them in a `sensors:` section (docs/scene-format.md)",
            scene.display()
        )));
    }
    if let Some(r) = rate {
        if !(r > 0.0 && r.is_finite()) {
            return Err(Failure::Input(format!(
                "--rate must be a positive number of readings per second, got {r}"
            )));
        }
    }
    let output = Output::open(
        out.as_deref(),
        &super::inputs(&scene, &model, &[&trajectory]),
    )?;
    // Only the columns the sensors read must be there (positions always).
    let mut needed = [true, false, false];
    for s in &model.sensors {
        for (n, r) in needed.iter_mut().zip(s.reads()) {
            *n |= r;
        }
    }
    let truth = mbfg::io::read_trajectory(&trajectory, &model.names, needed).map_err(plain)?;
    let readings = mbfg::sensors::measure::measure(&model, &truth, seed, rate)
        .map_err(|e| Failure::Input(format!("{}: {}", trajectory.display(), plain(e))))?;
    let count = readings.values.iter().filter(|v| !v.is_nan()).count();
    let to_file = output.to_file();
    output
        .commit_with(&|w| readings.write_csv(w))
        .map_err(Failure::Run)?;
    print_summary(
        to_file,
        &format!(
            "{count} readings of {} sensor{} at {} times (seed {seed})",
            model.sensors.len(),
            if model.sensors.len() == 1 { "" } else { "s" },
            readings.t.len()
        ),
    );
    Ok(())
}
