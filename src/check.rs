//! `mbfg check`: what a scene assembles to, in a few lines a person can read.

use crate::dynamics;
use crate::model::Model;
use crate::scene::Scene;
use std::fmt;

/// The summary `mbfg check` prints.
#[derive(Debug, Clone)]
pub struct CheckReport {
    pub file: String,
    pub n: usize,
    pub m: usize,
    pub rank: usize,
    pub dof: usize,
    pub coordinates: Vec<String>,
    pub independent: Vec<String>,
    pub redundant: Vec<String>,
    pub bodies: usize,
    pub effects: Vec<String>,
    /// max |Φ| at the assembled initial state.
    pub initial_residual: f64,
    pub kinetic_energy: f64,
    pub potential_energy: f64,
    /// max |q̈| at the initial state, or why it could not be computed.
    pub initial_acceleration: Result<f64, String>,
    /// What the reader ignored (`note: …`) and what looks unintended (`warning: …`).
    pub remarks: Vec<String>,
}

impl CheckReport {
    pub fn new(scene: &Scene, model: &Model) -> CheckReport {
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
            initial_residual: model.phi(&init.q).amax(),
            kinetic_energy: model.kinetic_energy(&init.dq),
            potential_energy: model.potential_energy(&init.q),
            remarks: scene
                .notes
                .iter()
                .map(|n| format!("note: {n}"))
                .chain(
                    [
                        crate::plausibility::placement_warning(model),
                        crate::plausibility::idle_warning(model),
                        crate::plausibility::inertia_warning(model),
                    ]
                    .into_iter()
                    .flatten()
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
