//! `mbfg check`: parse and assemble a scene, and print what it holds.

use super::failure::Failure;
use super::load;
use mbfg::check::CheckReport;
use std::path::PathBuf;

/// The arguments of `mbfg check`.
#[derive(clap::Args)]
pub struct CheckArgs {
    /// Scene or MBSE mechanism file (YAML).
    scene: PathBuf,
}

/// `mbfg check`: prints the report, or refuses a scene whose initial state is out of
/// range.
pub fn run(args: CheckArgs) -> Result<(), Failure> {
    let CheckArgs { scene } = args;
    let (scene, model) = load(&scene)?;
    let report = CheckReport::new(&scene, &model);
    let numbers = [
        ("max |Φ|", report.initial_residual),
        ("kinetic energy", report.kinetic_energy),
        ("potential energy", report.potential_energy),
    ];
    if let Some((what, v)) = numbers.iter().find(|(_, v)| !v.is_finite()) {
        return Err(Failure::Input(format!(
            "{}: the initial state's {what} is {v}: a value in the scene is out of range",
            scene.file
        )));
    }
    println!("{report}");
    Ok(())
}
