//! What a run reports beside its trajectory ([`RunSummary`]): iterations, the worst
//! constraint violations, the energy drift, the failures, and where the run was
//! refined ([`Refinement`]) or switched coordinates ([`Reselection`]).

use super::failure::StepFailure;
use crate::error::{Error, Result};
use crate::model::Model;
use crate::trajectory::Trajectory;
use std::time::Duration;

/// What a run reports beside its trajectory.
#[derive(Debug, Clone, PartialEq)]
pub struct RunSummary {
    pub steps: usize,
    pub wall_time: Duration,
    /// Mean and max linear solves per window solve (per step for the smoother).
    pub mean_iterations: f64,
    pub max_iterations: usize,
    /// max |Φ| and max |Φ_q q̇| over the trajectory.
    pub worst_phi: f64,
    pub worst_velocity_constraint: f64,
    /// max |E(t) − E(0)| when the scene is conservative.
    pub energy_drift: Option<f64>,
    /// The largest kinetic energy along the trajectory: the scale of the drift.
    pub peak_kinetic_energy: f64,
    pub failures: Vec<StepFailure>,
    /// With [`Past::Adaptive`](crate::solver::Past::Adaptive), the step from which the smoother conditioned on its
    /// past: its window solve had not converged after a marginal prior.
    pub conditioned_from: Option<(usize, f64)>,
    /// In independent coordinates, where the run switched to another set.
    pub reselections: Vec<Reselection>,
    /// Set (to the last step kept) when the caller interrupted the run.
    pub interrupted: Option<usize>,
    /// With [`DcIntegrators::Auto`](super::options::DcIntegrators::Auto): the failure with the paper's integrator factors
    /// after which this run was made again with tangent ones.
    pub tangent_after: Option<StepFailure>,
    /// With [`ForwardOptions::refine`](super::options::ForwardOptions::refine): the finer step this run was integrated at.
    pub refinement: Option<Refinement>,
}

/// A run integrated at a finer step than asked for, because a step at the coarser one
/// failed while a body turned more than [`StepFailure::LARGE_TURN`] per step. The
/// trajectory keeps every `factor`-th state: the grid asked for. Steps named in the
/// summary's failures and counts are steps of the finer grid.
#[derive(Debug, Clone, PartialEq)]
pub struct Refinement {
    /// Internal steps per step asked for.
    pub factor: usize,
    /// The internal step, dt / factor.
    pub dt: f64,
    /// The failure at the step asked for (or at the previous refinement).
    pub after: StepFailure,
}

impl Refinement {
    /// The most internal steps per step asked for: beyond it the motion is not what
    /// makes the steps fail, or the run would be too long to be what the user meant.
    pub const MAX_FACTOR: usize = 1024;
    /// The turn per internal step the factor aims at: half of
    /// [`StepFailure::LARGE_TURN`], for motions that speed up after the step measured.
    pub const TARGET_TURN: f64 = 0.25;
    /// A failed step over which no body turns this much (rad) is not refined: its
    /// failure has another cause than the step's size against the motion.
    pub const MIN_TURN: f64 = 0.05;
}

/// A switch of the independent coordinates during a run: at `step` the coordinates in
/// use were approaching a configuration where they stop determining the others,
/// while Φ_q kept its rank.
#[derive(Debug, Clone, PartialEq)]
pub struct Reselection {
    pub step: usize,
    pub t: f64,
    pub from: Vec<String>,
    pub to: Vec<String>,
}

pub(super) fn summarize(
    model: &Model,
    tr: &Trajectory,
    wall_time: Duration,
    iterations: &[usize],
    failures: Vec<StepFailure>,
) -> Result<RunSummary> {
    let (n, m) = (model.n(), model.m());
    let mut phi = vec![0.0; m];
    let mut jac = vec![0.0; m * n];
    let (mut worst_phi, mut worst_vel) = (0.0f64, 0.0f64);
    let conservative = model.scene.is_conservative();
    let mut e0 = None;
    let mut drift = 0.0f64;
    let mut peak_kinetic = 0.0f64;
    for k in 0..tr.len() {
        let (q, dq) = (tr.q_at(k), tr.dq_at(k));
        if !q.iter().chain(dq).all(|v| v.is_finite()) {
            return Err(Error::singular(format!("non-finite state at step {k}")));
        }
        model.phi_into(q, &mut phi);
        model.jacobian_into(q, &mut jac);
        worst_phi = phi.iter().fold(worst_phi, |w, v| w.max(v.abs()));
        for r in 0..m {
            let v: f64 = (0..n).map(|j| jac[r * n + j] * dq[j]).sum();
            worst_vel = worst_vel.max(v.abs());
        }
        let dv = nalgebra::DVector::from_column_slice(dq);
        let kinetic = model.kinetic_energy(&dv);
        peak_kinetic = peak_kinetic.max(kinetic);
        if conservative {
            let qv = nalgebra::DVector::from_column_slice(q);
            let e = kinetic + model.potential_energy(&qv);
            let e0 = *e0.get_or_insert(e);
            drift = drift.max((e - e0).abs());
        }
    }
    let total: usize = iterations.iter().sum();
    Ok(RunSummary {
        steps: tr.len(),
        wall_time,
        mean_iterations: total as f64 / iterations.len().max(1) as f64,
        max_iterations: iterations.iter().copied().max().unwrap_or(0),
        worst_phi,
        worst_velocity_constraint: worst_vel,
        energy_drift: conservative.then_some(drift),
        peak_kinetic_energy: peak_kinetic,
        failures,
        conditioned_from: None,
        reselections: Vec::new(),
        interrupted: None,
        tangent_after: None,
        refinement: None,
    })
}
