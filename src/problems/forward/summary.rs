//! What a run reports beside its trajectory ([`RunSummary`]): iterations, the worst
//! constraint violations, the energy drift, the failures, and where the run was
//! refined ([`Refinement`]) or switched coordinates ([`Reselection`]).

use super::failure::StepFailure;
use super::plan::Plan;
use crate::convergence::SolveReport;
use crate::error::{Error, Result};
use crate::model::Model;
use std::time::Duration;

/// What a run reports beside its trajectory.
#[derive(Debug, Clone, PartialEq)]
pub struct RunSummary {
    pub steps: usize,
    pub wall_time: Duration,
    /// What the run decided and ran: its schedule, integrator factors and settings
    /// (of the attempt whose trajectory this is).
    pub plan: Plan,
    /// Steps the square step took, and steps of a stepwise run the general solver
    /// took (near a rank loss of Φ_q, or where the square step did not converge).
    pub square_steps: usize,
    pub general_steps: usize,
    /// Mean and max Newton or Levenberg–Marquardt iterations (linear solves) per
    /// solve: per step for a stepwise run or the smoother, of the whole horizon for
    /// a batch.
    pub mean_iterations: f64,
    pub max_iterations: usize,
    /// Mean factorizations per window solve: as many as the linear solves for the
    /// general solver, fewer for square steps (which reuse one while it carries).
    pub mean_factorizations: f64,
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
    /// With [`DcIntegrators::Auto`](super::options::DcIntegrators::Auto): the failure with tangent integrator factors
    /// after which this run was made again with the paper's.
    pub full_after: Option<StepFailure>,
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

/// Linear solves per window solve, as running totals (a long run keeps no list).
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct Iterations {
    total: usize,
    factorizations: usize,
    count: usize,
    max: usize,
}

impl Iterations {
    pub(super) fn push(&mut self, report: &SolveReport) {
        self.total += report.iterations;
        self.factorizations += report.factorizations;
        self.count += 1;
        self.max = self.max.max(report.iterations);
    }

    pub(super) fn extend(&mut self, other: Iterations) {
        self.total += other.total;
        self.factorizations += other.factorizations;
        self.count += other.count;
        self.max = self.max.max(other.max);
    }
}

/// The summary's measures of a trajectory, accumulated step by step as the steps
/// become final (so that a long run holds none of them).
pub(super) struct Stats {
    /// Per constraint: Φ, then Φ_q q̇.
    rows: Vec<f64>,
    /// The nonzeros of M (row, column, value): the kinetic energy in time linear in
    /// a chain's length, as Φ_q q̇ over each constraint's own coordinates.
    mass: Vec<(usize, usize, f64)>,
    worst_phi: f64,
    worst_vel: f64,
    conservative: bool,
    e0: Option<f64>,
    drift: f64,
    peak_kinetic: f64,
    steps: usize,
}

impl Stats {
    pub(super) fn new(model: &Model) -> Self {
        Stats {
            rows: vec![0.0; model.m()],
            mass: model.mass_entries(),
            worst_phi: 0.0,
            worst_vel: 0.0,
            conservative: model.scene.is_conservative(),
            e0: None,
            drift: 0.0,
            peak_kinetic: 0.0,
            steps: 0,
        }
    }

    /// Adds step `steps()`'s state, which must be finite.
    pub(super) fn add(&mut self, model: &Model, q: &[f64], dq: &[f64]) -> Result<()> {
        if !q.iter().chain(dq).all(|v| v.is_finite()) {
            return Err(Error::singular(format!(
                "non-finite state at step {}",
                self.steps
            )));
        }
        model.phi_into(q, &mut self.rows);
        self.worst_phi = self.rows.iter().fold(self.worst_phi, |w, v| w.max(v.abs()));
        model.constraint_rates_into(q, dq, &mut self.rows);
        self.worst_vel = self.rows.iter().fold(self.worst_vel, |w, v| w.max(v.abs()));
        let kinetic = 0.5
            * self
                .mass
                .iter()
                .map(|&(i, j, m)| dq[i] * m * dq[j])
                .sum::<f64>();
        self.peak_kinetic = self.peak_kinetic.max(kinetic);
        if self.conservative {
            let qv = nalgebra::DVector::from_column_slice(q);
            let e = kinetic + model.potential_energy(&qv);
            let e0 = *self.e0.get_or_insert(e);
            self.drift = self.drift.max((e - e0).abs());
        }
        self.steps += 1;
        Ok(())
    }

    /// The summary of the steps added.
    pub(super) fn finish(
        self,
        wall_time: Duration,
        iterations: Iterations,
        failures: Vec<StepFailure>,
        plan: Plan,
    ) -> RunSummary {
        RunSummary {
            plan,
            square_steps: 0,
            general_steps: 0,
            steps: self.steps,
            wall_time,
            mean_iterations: iterations.total as f64 / iterations.count.max(1) as f64,
            mean_factorizations: iterations.factorizations as f64 / iterations.count.max(1) as f64,
            max_iterations: iterations.max,
            worst_phi: self.worst_phi,
            worst_velocity_constraint: self.worst_vel,
            energy_drift: self.conservative.then_some(self.drift),
            peak_kinetic_energy: self.peak_kinetic,
            failures,
            conditioned_from: None,
            reselections: Vec::new(),
            interrupted: None,
            full_after: None,
            refinement: None,
        }
    }
}
