//! `mbfg check`: parse and assemble a scene, and print what it assembles to in a few
//! lines a person can read.

use super::failure::Failure;
use super::load;
use mbfg::dynamics;
use mbfg::model::Model;
use mbfg::scene::Scene;
use std::fmt;
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
    super::say(&report.to_string());
    Ok(())
}

/// The summary `mbfg check` prints.
#[derive(Debug, Clone)]
struct CheckReport {
    file: String,
    n: usize,
    m: usize,
    rank: usize,
    dof: usize,
    coordinates: Vec<String>,
    independent: Vec<String>,
    redundant: Vec<String>,
    bodies: usize,
    effects: Vec<String>,
    sensors: Vec<String>,
    /// max |Φ| at the assembled initial state.
    initial_residual: f64,
    kinetic_energy: f64,
    potential_energy: f64,
    /// max |q̈| at the initial state, or why it could not be computed.
    initial_acceleration: Result<f64, String>,
    /// What the reader ignored (`note: …`) and what looks unintended (`warning: …`).
    remarks: Vec<String>,
}

impl CheckReport {
    fn new(scene: &Scene, model: &Model) -> CheckReport {
        let init = &model.initial;
        CheckReport {
            file: scene.file.clone(),
            n: model.n(),
            m: model.m(),
            rank: model.active.len(),
            dof: model.dof(),
            coordinates: model.names.clone(),
            independent: scene.independent.clone(),
            redundant: model
                .redundant
                .iter()
                .map(|&k| model.constraints[k].name.clone())
                .collect(),
            bodies: scene.bodies.len(),
            effects: scene.effects.iter().map(|e| e.describe(scene)).collect(),
            sensors: model.sensors.iter().map(|s| s.describe(model)).collect(),
            initial_residual: model.phi(&init.q).amax(),
            kinetic_energy: model.kinetic_energy(&init.dq),
            potential_energy: model.potential_energy(&init.q),
            remarks: scene
                .notes
                .iter()
                .map(|n| format!("note: {n}"))
                .chain(
                    [
                        mbfg::model::plausibility::placement_warning(model),
                        mbfg::model::plausibility::idle_warning(model),
                        mbfg::model::plausibility::locked_warning(model),
                        mbfg::model::plausibility::inertia_warning(model),
                    ]
                    .into_iter()
                    .flatten()
                    .chain(mbfg::model::plausibility::units_warnings(model))
                    .map(|w| format!("warning: {w}")),
                )
                .collect(),
            initial_acceleration: dynamics::lagrange(model, &init.q, &init.dq, 0.0)
                .map_err(|e| e.to_string())
                .and_then(|s| {
                    let a = s.ddq.amax();
                    if s.ddq.iter().all(|v| v.is_finite()) {
                        Ok(a)
                    } else {
                        Err("not finite: a value in the scene is out of range".into())
                    }
                }),
        }
    }
}

impl fmt::Display for CheckReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(f, "scene: {}", self.file)?;
        writeln!(
            f,
            "n = {} coordinates: {}",
            self.n,
            self.coordinates.join(", ")
        )?;
        writeln!(
            f,
            "m = {} constraints (rank {}), {} {}",
            self.m,
            self.rank,
            self.bodies,
            if self.bodies == 1 { "body" } else { "bodies" }
        )?;
        if !self.redundant.is_empty() {
            writeln!(f, "redundant constraints: {}", self.redundant.join("; "))?;
        }
        writeln!(f, "degrees of freedom: {}", self.dof)?;
        if self.independent.is_empty() {
            writeln!(f, "independent coordinates: none declared")?;
        } else {
            writeln!(
                f,
                "independent coordinates: {}",
                self.independent.join(", ")
            )?;
        }
        if self.effects.is_empty() {
            writeln!(f, "effects: none")?;
        } else {
            writeln!(f, "effects:")?;
            for e in &self.effects {
                writeln!(f, "  {e}")?;
            }
        }
        // Only a scene with sensors says so: the others' report is as it was.
        if !self.sensors.is_empty() {
            writeln!(f, "sensors:")?;
            for s in &self.sensors {
                writeln!(f, "  {s}")?;
            }
        }
        writeln!(
            f,
            "initial state: max |Φ| = {:.2e}, kinetic energy {} J, potential energy {} J",
            self.initial_residual,
            readable(self.kinetic_energy),
            readable(self.potential_energy)
        )?;
        match &self.initial_acceleration {
            Ok(a) => write!(f, "initial max |q̈| = {}", readable(*a))?,
            Err(e) => write!(f, "initial accelerations: {e}")?,
        }
        for r in &self.remarks {
            write!(f, "\n{r}")?;
        }
        Ok(())
    }
}

/// Six decimals where that reads well, scientific notation beyond (1e300 J would
/// otherwise print 300 digits).
fn readable(v: f64) -> String {
    if v == 0.0 || (1e-3..1e9).contains(&v.abs()) {
        format!("{v:.6}")
    } else {
        format!("{v:.6e}")
    }
}
