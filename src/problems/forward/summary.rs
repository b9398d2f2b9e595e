//! What a run reports beside its trajectory ([`RunSummary`]): iterations, the worst
//! constraint violations, the energy drift, the failures, and where the run was
//! refined ([`Refinement`]) or switched coordinates ([`Reselection`]).

use super::balance::{Balance, BalanceOff};
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
    /// Steps of a stepwise DC run that the paper's integrator factors took, for
    /// that step only, where the tangent ones failed from every guess.
    pub paper_steps: usize,
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
    /// How far a scene with non-conservative effects is off its energy balance
    /// (None for a conservative scene, or where an effect could not be evaluated).
    pub energy_balance: Option<BalanceOff>,
    /// The first step over which an expression load jumped (a pole or a
    /// discontinuity passed over), see [`LoadJump`].
    pub load_jump: Option<LoadJump>,
    /// The passages through singular configurations (rank losses of Φ_q).
    pub passages: Passages,
    pub failures: Vec<StepFailure>,
    /// With [`Past::Adaptive`](crate::solver::Past::Adaptive), the step from which the smoother conditioned on its
    /// past: its window solve had not converged after a marginal prior.
    pub conditioned_from: Option<(usize, f64)>,
    /// In independent coordinates, where the run switched to another set.
    pub reselections: Vec<Reselection>,
    /// Set (to the last step kept) when the caller interrupted the run.
    pub interrupted: Option<usize>,
    /// With [`ForwardOptions::refine`](super::options::ForwardOptions::refine): the finer step this run was integrated at.
    pub refinement: Option<Refinement>,
    /// With [`ForwardOptions::tolerance`](super::options::ForwardOptions::tolerance):
    /// the tolerance and the steps the error control took.
    pub error_control: Option<ErrorControl>,
}

/// What the error control of a run with a tolerance did: the steps it took (each
/// solved once more for each rejection or failed solve before it) and their sizes.
#[derive(Debug, Clone, PartialEq)]
pub struct ErrorControl {
    pub tolerance: super::error_control::Tolerance,
    /// Steps kept.
    pub accepted: usize,
    /// Steps solved and taken again smaller: their estimated error was too large.
    pub rejected: usize,
    /// Steps whose solve failed and were taken again smaller.
    pub failed_solves: usize,
    /// The smallest and largest step kept (s).
    pub smallest: f64,
    pub largest: f64,
    /// Steps kept at the smallest size though their estimated error exceeded the
    /// tolerance: there the estimate is the noise of the solves' accelerations, not
    /// the step's error.
    pub at_floor: usize,
    /// Steps kept unestimated where they damped their projections near a rank
    /// loss (Hermite–Simpson, DC), at the size that reached it.
    pub damped: usize,
    /// With the tolerance on the run's rows
    /// ([`ToleranceScope::Run`](super::ToleranceScope::Run)): what its check found.
    /// The counts above are the last run's, whose rows were written.
    pub check: Option<RunCheck>,
}

/// The check of a run's rows against its tolerance: the runs made and the rows'
/// estimated error.
#[derive(Debug, Clone, PartialEq)]
pub struct RunCheck {
    /// The step rtol of each run made, in order (the first the tolerance asked; a
    /// tighter one for each run made again): the last one's rows were written. The
    /// check run, at a coarser step tolerance, is not listed.
    pub step_rtols: Vec<f64>,
    /// The rows' estimated error, in units of the tolerance (the weighted RMS of q
    /// and q̇ as the steps', the largest over the rows); `None` where not checked.
    pub estimated: Option<f64>,
    /// Why the rows were not checked.
    pub unchecked: Option<String>,
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

/// A step across which a load's change disagrees with its slopes at both ends (by
/// more than half of their scale): a pole (`0.01/(theta+1)`, `tan(5*theta)`) or a
/// discontinuity (`sign(…)`, a step in t) lies inside the step, which the integrator
/// stepped over as if the load were smooth.
#[derive(Debug, Clone, PartialEq)]
pub struct LoadJump {
    /// The effect's name.
    pub effect: String,
    /// The step's end time, and the load's value at its start and end.
    pub t: f64,
    pub from: f64,
    pub to: f64,
}

impl LoadJump {
    /// The warning `mbfg simulate` prints.
    pub fn message(&self) -> String {
        format!(
            "effect '{}' changes from {:.3e} to {:.3e} over the step ending at t = {} s, against its slopes at both ends: a pole or a discontinuity inside the step was stepped over; a smaller dt, or a load without it",
            self.effect,
            self.from,
            self.to,
            time(self.t)
        )
    }
}

/// The run's passages through singular configurations: steps where the distance
/// to a rank loss of Φ_q, s = (tr G⁻¹)^(−1/2) (G the Gram matrix of Φ_q's
/// normalized rows), has a minimum that is below [`Passages::BELOW`] or closer to
/// 0 than its change over the steps either side (a rank loss passed between two
/// steps). There the mechanism gains degrees of freedom, may leave its branch, and
/// a step is hardest to solve: the summary says how many there were and what they
/// did to the velocity constraints and the energy.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Passages {
    pub count: usize,
    /// The first one's time.
    pub first: Option<f64>,
    /// max |Φ_q q̇| over the steps either side of a passage.
    pub worst_velocity_constraint: f64,
    /// The largest change of the energy across a passage (from the step before its
    /// minimum to the step after) of a conservative scene, and its time.
    pub energy_jump: Option<(f64, f64)>,
}

impl Passages {
    /// A minimum of s below this is a passage (the dynamics kernel's
    /// [`REGULAR_ABOVE`](crate::dynamics::DynamicsKernel::REGULAR_ABOVE)).
    pub const BELOW: f64 = 1e-3;
    /// An energy jump across a passage above this fraction of the largest kinetic
    /// energy is warned of: the passage changed the motion, not only the integrator's
    /// error (the trapezoidal rule moves the N four-bar's energy by 1e-9 of it across
    /// a passage at 1 ms).
    pub const ENERGY_JUMP_TOLERANCE: f64 = 1e-4;
}

/// The passages' measure of each step as it is added: s, |Φ_q q̇| and the energy
/// of the last three steps.
struct PassageWatch {
    regularity: super::square_step::Regularity,
    gram: super::square_step::GramWork,
    /// (s, max |Φ_q q̇|, energy) of the last three steps, oldest first.
    last: Vec<(f64, f64, Option<f64>)>,
    /// When s is measured.
    remeasure: super::square_step::Remeasure,
}

impl PassageWatch {
    fn new(model: &Model) -> Option<PassageWatch> {
        if model.active.is_empty() {
            return None;
        }
        let regularity = super::square_step::Regularity::new(model);
        let gram = regularity.work(model)?;
        Some(PassageWatch {
            regularity,
            gram,
            last: Vec::with_capacity(3),
            remeasure: Default::default(),
        })
    }

    /// Adds a step (its configuration q at time t, its max |Φ_q q̇| and energy);
    /// a passage at the step before is added to `passages`.
    fn add(
        &mut self,
        model: &Model,
        (t_before, q): (f64, &[f64]),
        velocity: f64,
        energy: Option<f64>,
        passages: &mut Passages,
    ) {
        let s = match self.remeasure.standing() {
            Some(s) => s,
            None => {
                let s = self
                    .regularity
                    .distance_to_rank_loss(model, q, &mut self.gram);
                self.remeasure.measured(s);
                s
            }
        };
        if self.last.len() == 3 {
            self.last.remove(0);
        }
        self.last.push((s, velocity, energy));
        let [a, b, c] = match self.last.as_slice() {
            [a, b, c] => [*a, *b, *c],
            _ => return,
        };
        let minimum = b.0 <= a.0 && b.0 < c.0;
        let change = 0.5 * ((b.0 - a.0).abs() + (c.0 - b.0).abs());
        if !(minimum && (b.0 < Passages::BELOW || b.0 < change)) {
            return;
        }
        passages.count += 1;
        passages.first.get_or_insert(t_before);
        passages.worst_velocity_constraint = passages
            .worst_velocity_constraint
            .max(a.1)
            .max(b.1)
            .max(c.1);
        if let (Some(ea), Some(ec)) = (a.2, c.2) {
            let jump = (ec - ea).abs();
            if passages.energy_jump.is_none_or(|(j, _)| jump > j) {
                passages.energy_jump = Some((jump, t_before));
            }
        }
    }
}

/// A time as the messages write it: six decimals at most, trailing zeros dropped.
fn time(t: f64) -> String {
    let s = format!("{t:.6}");
    s.trim_end_matches('0').trim_end_matches('.').to_string()
}

/// The expression loads of a model, watched for jumps across steps.
struct Watched {
    /// (effect name, force, component count).
    loads: Vec<(String, crate::model::forces::Force)>,
    /// Scratch: a state between steps.
    q: Vec<f64>,
    dq: Vec<f64>,
    /// The largest |value| seen, per load and component.
    scale: Vec<f64>,
    /// Each load's value at the end of the step watched last, and its change over
    /// that step.
    ends: Vec<Option<[f64; 2]>>,
    changes: Vec<Option<[f64; 2]>>,
}

/// The fraction of a step at which the slopes at its ends are taken.
const SLOPE_FRACTION: f64 = 1e-4;

impl Watched {
    fn new(model: &Model) -> Option<Self> {
        use crate::model::forces::Force;
        let loads: Vec<(String, Force)> = model
            .forces
            .iter()
            .zip(&model.scene.effects)
            .filter(|(f, _)| matches!(f, Force::Torque { .. } | Force::PointForce { .. }))
            .map(|(f, e)| (crate::derived::effect_name(e).to_string(), f.clone()))
            .collect();
        (!loads.is_empty()).then(|| Watched {
            scale: vec![0.0; 2 * loads.len()],
            ends: vec![None; loads.len()],
            changes: vec![None; loads.len()],
            loads,
            q: vec![0.0; model.n()],
            dq: vec![0.0; model.n()],
        })
    }

    /// The components of load `l` at the point `s` ∈ [0, 1] of the step from `a` to `b`.
    fn at(
        &mut self,
        model: &Model,
        l: usize,
        (t0, q0, dq0): (f64, &[f64], &[f64]),
        (t1, q1, dq1): (f64, &[f64], &[f64]),
        s: f64,
    ) -> Option<[f64; 2]> {
        use crate::model::forces::Force;
        for i in 0..q0.len() {
            self.q[i] = q0[i] + s * (q1[i] - q0[i]);
            self.dq[i] = dq0[i] + s * (dq1[i] - dq0[i]);
        }
        let t = t0 + s * (t1 - t0);
        match &self.loads[l].1 {
            Force::Torque { value, .. } => {
                Some([value.value(model, &self.q, &self.dq, t).ok()?, 0.0])
            }
            Force::PointForce { value, .. } => Some([
                value[0].value(model, &self.q, &self.dq, t).ok()?,
                value[1].value(model, &self.q, &self.dq, t).ok()?,
            ]),
            _ => None,
        }
    }

    /// The first load that jumps over the step from `a` to `b`.
    fn jump(
        &mut self,
        model: &Model,
        a: (f64, &[f64], &[f64]),
        b: (f64, &[f64], &[f64]),
        first: bool,
    ) -> Option<LoadJump> {
        for l in 0..self.loads.len() {
            // The value at the step's start is the one at the last step's end.
            let v0 = match self.ends[l].take() {
                Some(v) => Some(v),
                None => self.at(model, l, a, b, 0.0),
            };
            let v1 = self.at(model, l, a, b, 1.0);
            self.ends[l] = v1;
            let before = self.changes[l].take();
            if let (Some(v0), Some(v1)) = (v0, v1) {
                let change = [v1[0] - v0[0], v1[1] - v0[1]];
                self.changes[l] = Some(change);
                // A change within a quarter of the last step's is the smooth load's
                // (a pole or a jump changes the load unlike the step before, and the
                // watch ends at the first): the slopes are not taken.
                let smooth = |c: usize, before: [f64; 2]| {
                    let scale = self.scale[2 * l + c].max(v0[c].abs());
                    (change[c] - before[c]).abs()
                        <= 0.25 * (change[c].abs() + before[c].abs()) + 1e-9 * (1.0 + scale)
                };
                if let (false, Some(before)) = (first, before) {
                    if smooth(0, before) && smooth(1, before) {
                        for c in 0..2 {
                            let scale = &mut self.scale[2 * l + c];
                            *scale = scale.max(v0[c].abs());
                        }
                        continue;
                    }
                }
            }
            let (Some(v0), Some(v1), Some(near0), Some(near1)) = (
                v0,
                v1,
                self.at(model, l, a, b, SLOPE_FRACTION),
                self.at(model, l, a, b, 1.0 - SLOPE_FRACTION),
            ) else {
                continue;
            };
            for c in 0..2 {
                let scale = &mut self.scale[2 * l + c];
                *scale = scale.max(v0[c].abs());
                let change = v1[c] - v0[c];
                // The change the slopes at the ends predict (at the start of the first
                // step only the end's: a load may start with an infinite slope, √t).
                let slope1 = (v1[c] - near1[c]) / SLOPE_FRACTION;
                let predicted = match first {
                    true => slope1,
                    false => 0.5 * ((near0[c] - v0[c]) / SLOPE_FRACTION + slope1),
                };
                let miss = (change - predicted).abs();
                if miss > 0.5 * (change.abs() + predicted.abs())
                    && miss > 1e-6 * (1.0 + *scale)
                    && miss > 1e3 * f64::EPSILON * (v0[c].abs() + v1[c].abs()) / SLOPE_FRACTION
                {
                    return Some(LoadJump {
                        effect: self.loads[l].0.clone(),
                        t: b.0,
                        from: v0[c],
                        to: v1[c],
                    });
                }
            }
        }
        None
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
    watched: Option<Watched>,
    load_jump: Option<LoadJump>,
    passage_watch: Option<PassageWatch>,
    passages: Passages,
    balance: Option<Balance>,
    /// The time of the step added last, and its kinetic energy.
    t_before: f64,
    kinetic_last: f64,
}

impl Stats {
    pub(super) fn new(model: &Model, integrator: super::Integrator) -> Self {
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
            watched: Watched::new(model),
            load_jump: None,
            passage_watch: PassageWatch::new(model),
            passages: Passages::default(),
            balance: Balance::new(model, integrator),
            t_before: 0.0,
            kinetic_last: 0.0,
        }
    }

    /// Looks for a load that jumps over the step from `before` to (t, q, q̇), until
    /// one does.
    pub(super) fn watch(
        &mut self,
        model: &Model,
        before: (f64, &[f64], &[f64]),
        t: f64,
        q: &[f64],
        dq: &[f64],
    ) {
        if self.load_jump.is_some() {
            return;
        }
        // Called after `add` of the step's end: the first step ends at state 1.
        let first = self.steps == 2;
        if let Some(w) = self.watched.as_mut() {
            self.load_jump = w.jump(model, before, (t, q, dq), first);
        }
    }

    /// Adds step `steps()`'s state at time t, which must be finite.
    pub(super) fn add(&mut self, model: &Model, t: f64, q: &[f64], dq: &[f64]) -> Result<()> {
        if !q.iter().chain(dq).all(|v| v.is_finite()) {
            return Err(Error::singular(format!(
                "non-finite state at step {}",
                self.steps
            )));
        }
        model.phi_into(q, &mut self.rows);
        self.worst_phi = self.rows.iter().fold(self.worst_phi, |w, v| w.max(v.abs()));
        model.constraint_rates_into(q, dq, &mut self.rows);
        let velocity = self.rows.iter().fold(0.0f64, |w, v| w.max(v.abs()));
        self.worst_vel = self.worst_vel.max(velocity);
        let kinetic = 0.5
            * self
                .mass
                .iter()
                .map(|&(i, j, m)| dq[i] * m * dq[j])
                .sum::<f64>();
        self.peak_kinetic = self.peak_kinetic.max(kinetic);
        let energy = self.conservative.then(|| {
            let qv = nalgebra::DVector::from_column_slice(q);
            kinetic + model.potential_energy(&qv)
        });
        if let Some(e) = energy {
            let e0 = *self.e0.get_or_insert(e);
            self.drift = self.drift.max((e - e0).abs());
        }
        if let Some(watch) = self.passage_watch.as_mut() {
            watch.add(
                model,
                (self.t_before, q),
                velocity,
                energy,
                &mut self.passages,
            );
        }
        if let (0, Some(balance)) = (self.steps, self.balance.as_mut()) {
            balance.start(model, t, q, dq, kinetic);
        }
        self.t_before = t;
        self.kinetic_last = kinetic;
        self.steps += 1;
        Ok(())
    }

    /// Carries the energy balance over the step from `before` (its time and q, q̇,
    /// q̈) to `now` at time t, after `add` of `now`.
    pub(super) fn balance(&mut self, model: &Model, before: (f64, &[f64]), t: f64, now: &[f64]) {
        if let Some(balance) = self.balance.as_mut() {
            balance.step(model, before, (t, now), self.kinetic_last);
        }
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
            paper_steps: 0,
            steps: self.steps,
            wall_time,
            mean_iterations: iterations.total as f64 / iterations.count.max(1) as f64,
            mean_factorizations: iterations.factorizations as f64 / iterations.count.max(1) as f64,
            max_iterations: iterations.max,
            worst_phi: self.worst_phi,
            worst_velocity_constraint: self.worst_vel,
            energy_drift: self.conservative.then_some(self.drift),
            peak_kinetic_energy: self.peak_kinetic,
            energy_balance: self.balance.as_ref().and_then(Balance::finish),
            load_jump: self.load_jump,
            passages: self.passages,
            failures,
            conditioned_from: None,
            reselections: Vec::new(),
            interrupted: None,
            refinement: None,
            error_control: None,
        }
    }
}
