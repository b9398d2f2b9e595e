//! One step of a dependent-coordinate run with tangent integrators, or of an
//! independent-coordinate run, solved as the square system it is, with a sparse
//! Jacobian: per-step cost that grows with the number of bodies, not with its cube.
//!
//! With tangent integrators a DC step has as many equations as unknowns and they
//! hold exactly (see [`crate::factors::tangent`]): Φ(q) = 0, Φ_q q̇ = 0, f_dyn = 0, and the
//! projected integrators P(q) e = 0. Each projection is dense (P couples every
//! coordinate of a chain), but P e = 0 says e lies in the row space of Φ_q, that is
//! e = Φ_qᵀμ for a multiplier μ; and f_dyn = 0 is the augmented system with its
//! multiplier λ. So the step is also the root of
//!
//! ```text
//!   Φ(q) = 0                       Φ_q q̈ + q̇ᵀΦ_qq q̇ = 0
//!   Φ_q q̇ = 0                      M q̈ + Φ_qᵀλ − Q(q, q̇, t) = 0
//!   e_q(q, q̇) − Φ_qᵀμ₁ = 0         e_v(q̇, q̈) − Φ_qᵀμ₂ = 0
//! ```
//!
//! (active constraints only; e_q, e_v the trapezoidal or Euler residuals of the
//! positions and velocities), whose Jacobian has a few nonzeros per row: Newton's
//! method with faer's sparse LU, its symbolic analysis done once per mechanism.
//!
//! With Hermite–Simpson the integrators are its collocation rules, and the step also
//! holds the dynamics at its middle: q̈_m and λ_m as unknowns, the augmented system at
//! the Hermite interpolants q_m, q̇_m as equations (`stage.rs`).
//!
//! An IC step is the same system with the integrators on the independent
//! coordinates z only and no μ: q follows from z through Φ(q) = 0, and f^i_dyn = 0
//! is the augmented system's q̈ on z. Its equations are as many as its unknowns
//! where the constraints have full rank (m + f = n); the weak f_eq between
//! consecutive q, which the general solver also weighs, is left out (at its default
//! σ its weight is 1e-16 of the integrators').
//!
//! Near a rank loss of Φ_q (a singular configuration) the system keeps its plain
//! augmented dynamics: on the physical branch its solution is smooth, with
//! multipliers that grow like 1/σ. Its Newton iteration converges there to a
//! residual at the rounding of its terms, where the updates (that rounding
//! amplified by the Jacobian's condition, which grows like 1/σ²) stop shrinking;
//! such a residual ends the iteration ([`ROUNDING_RESIDUAL`]). A step that would
//! end within [`passage::near`] of the rank loss is stepped over ([`Passage`]), as
//! is a Hermite–Simpson IC step near one whose solution the arithmetic does not
//! resolve to the step tolerance ([`SquareStep::resolved`]): how close that is
//! differs from one mechanism to the next. A Hermite–Simpson DC step
//! damps its projections there instead ([`System::row_damping`]): the rounding of Φ
//! otherwise reaches its motion through the nested projections amplified like 1/σ⁴.
//! Where Newton does not converge within a few iterations away from a rank loss,
//! the step goes back to the general solver, whose dynamics regularize the
//! augmented system near a rank loss instead (see
//! [`crate::dynamics::DynamicsKernel`]).

mod factors;
mod passage;
mod regularity;
mod stage;
mod system;

use super::options::Integrator;
use super::plan::Plan;
use crate::coordinates::Coordinates;
use crate::dynamics::{self, DynamicsKernel};
use crate::linalg::sparse::Pattern;
use crate::model::Model;
use factors::Factors;
use nalgebra::DVector;
use passage::{Passage, Passed};
pub(super) use regularity::{GramWork, Regularity, Remeasure};
use stage::Stage;
use std::sync::Arc;
use system::{Sink, System};

/// Iterations after which a step goes back to the general solver: from a step's
/// prediction Newton converges in two to four, the simplified iteration (factors
/// of an earlier Jacobian) in five to eight.
const MAX_ITERATIONS: usize = 24;

/// Where the simplified iteration stops: an estimated error below this fraction of
/// the step tolerance (a converged Newton iteration's error is about the square of
/// its last update).
const SETTLED: f64 = 1e-6;

/// A contraction from which updates below the step tolerance count as the
/// rounding of the residual: they no longer shrink.
const ROUNDING_FLOOR: f64 = 0.5;

/// The largest rounding (a fraction of the step tolerance) later steps settle at.
const ROUNDING_KEPT: f64 = 1e-2;

/// The largest residual, relative to 1 + max |xᵢ| over every unknown, that counts
/// as the rounding of the equations' terms (their products of multipliers of 1e2–1e4
/// with gradients round at about 1e-16 of that).
const ROUNDING_RESIDUAL: f64 = 1e-14;

/// κ of a Hermite–Simpson step's damped projections ([`System::row_damping`]): a
/// constraint is enforced exactly along the directions of Φ_q whose normalized
/// singular value exceeds about √κ = 0.1. Closer to a rank loss its rounding
/// would otherwise be amplified like 1/σ⁴ into the motion (an energy error of
/// 5e-11 J a step at σ = 3e-3 on one loop of the N four-bar, against 1e-14 J
/// damped). A trapezoidal step drifts from the constraints like h³, enough to
/// carry a loop onto its other branch where they are not enforced: its
/// projections stay exact.
const PROJECTION_DAMPING: f64 = 1e-2;

/// The distance to a rank loss (at a step's start) below which its projections
/// are damped, √κ (for a mechanism whose rows are well conditioned at its initial
/// configuration: [`SquareStep::scaled_to_its_initial_configuration`]): farther,
/// where damping would leave a fraction of the constraints' drift, they are exact.
const DAMPED_BELOW: f64 = 0.1;

/// A residual this small relative to 1 + max |xᵢ| is the rounding of the
/// equations' terms, amplified at most a thousandfold: an update above the step
/// tolerance taken from it moves the iterate along a direction the arithmetic
/// does not resolve.
const NEAR_ROUNDING: f64 = 1e3 * ROUNDING_RESIDUAL;

/// A step's guess is measured for its distance to a rank loss where the last
/// step's, carried on, comes within this many times [`passage::near`].
const LOOKOUT: f64 = 10.0;

/// Fresh factorizations after which a step goes back to the general solver.
const MAX_FACTORIZATIONS: usize = 8;

/// The largest contraction accepted from an iteration with factors of an earlier
/// Jacobian: then the error left after an update below the tolerance is below the
/// tolerance too. Slower, the iterate is linearized and factored afresh. The
/// contraction is the mean over the last two updates where there are two: the
/// error of a stiff mechanism's fast modes often alternates (an update shrinking
/// by 0.01, the next by 0.4), and one update alone would refactor an iteration
/// that converges fast.
const MAX_CONTRACTION: f64 = 0.25;

/// What bounds a step's Newton iteration.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepLimits {
    /// At most this many linear solves.
    pub max_iterations: usize,
    /// Converged once a step moves every variable by at most this times (1 + |x|).
    pub step_tolerance: f64,
}

/// What the square step took to solve a step.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct StepWork {
    /// Linear solves.
    pub iterations: usize,
    /// Factorizations (a linear solve may reuse an earlier one).
    pub factorizations: usize,
}

/// One iteration of the square step, as a solve's observer sees it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepIteration {
    /// 1-based iteration of this step.
    pub iteration: usize,
    /// Half the squared norm of the residual the update was solved from.
    pub cost: f64,
    /// max |δᵢ| / (1 + |xᵢ|) over the step's variables.
    pub update: f64,
    /// Whether the Jacobian was factored afresh for this update (else an earlier
    /// one's factors were used: a chord update).
    pub fresh: bool,
    /// Whether the iteration stopped here, converged.
    pub settled: bool,
}

/// The scratch of one step's Newton iteration.
struct Work {
    x: Vec<f64>,
    residual: Vec<f64>,
    values: Vec<f64>,
    q_force: Vec<f64>,
    kq: Vec<f64>,
    kv: Vec<f64>,
    /// Hermite–Simpson's stage: q_m and q̇_m, Q there and its Jacobians (empty
    /// for a two-point rule).
    stage_state: Vec<f64>,
    stage_force: Vec<f64>,
    stage_kq: Vec<f64>,
    stage_kv: Vec<f64>,
    factors: Factors,
    /// The factors and values of the other pattern ([`Equations::pattern`]),
    /// swapped with `factors` and `values` as a step's projections are damped
    /// or not (`active_damped`: which ones those hold).
    other: Option<(Factors, Vec<f64>)>,
    active_damped: bool,
    gram: GramWork,
    /// The multipliers of the last step solved: the next step's first guess.
    multipliers: Vec<f64>,
    /// The step's damping of its projections, per active row
    /// ([`System::row_damping`]; empty where they are exact).
    damping: Vec<f64>,
    /// Whether the step being solved damps its projections: a damped system's
    /// step within [`DAMPED_BELOW`] of a rank loss (or at an unmeasured distance)
    /// that [`SquareStep::solve`] takes as it lands.
    near_rank_loss: bool,
    /// The iterate before an update that may be undone.
    saved: Vec<f64>,
    /// Whether `factors` hold the LU of a Jacobian of this system (of an earlier
    /// iterate, maybe of an earlier step), which the next iterations may reuse.
    factored: bool,
    /// The size of the updates where the last step that reached the residual's
    /// rounding stopped shrinking (0 before any did): no iteration gets below it.
    rounding: f64,
    /// Whether the last iteration took an update above the step tolerance from a
    /// residual at [`NEAR_ROUNDING`]: its solution is not resolved to the tolerance.
    unresolved: bool,
}

/// The square system of a DC step with tangent integrators or of an IC step, with
/// its sparsity analysed once.
pub struct SquareStep {
    equations: Equations,
    work: Work,
    /// The longer steps a step next to a rank loss of Φ_q is interpolated from.
    passage: Passage,
    /// The steps' distance to a rank loss as last measured, and when it is
    /// measured again (the default: unknown, to be measured at the next guess).
    recent: Remeasure,
    /// q at the end of the last step solved (NaN after a failure): `recent`
    /// describes the steps before only where the next starts there.
    ended: Vec<f64>,
    /// The guess of the step being solved (q, q̇, q̈), kept to start again from.
    guess: Vec<f64>,
    /// Whether the last step solved was interpolated from a longer step over a
    /// rank loss.
    passed: bool,
    /// Whether a step next to a rank loss stands only where it is resolved to the
    /// step tolerance ([`SquareStep::resolved`]).
    checks_resolution: bool,
    /// Whether a step near a rank loss damps its projections, where its system
    /// can ([`System::damped`]).
    damps: bool,
    /// The distance to a rank loss below which its projections are damped.
    damped_below: f64,
}

/// The step system with its Jacobian's pattern and the regularity test: what the
/// iteration reads, apart from its scratch ([`Work`]).
#[derive(Clone)]
struct Equations {
    system: System,
    /// The Jacobian's pattern with exact projections, and where the system can
    /// damp them, with their damping's entries (analysed apart: those entries
    /// change the LU's ordering and fill, by a third on the 40 loops).
    jacobian: Pattern,
    damped_jacobian: Option<Pattern>,
    regularity: Regularity,
}

impl Equations {
    /// The Jacobian's pattern, with damped projections or exact ones.
    fn pattern(&self, damped: bool) -> &Pattern {
        match (damped, &self.damped_jacobian) {
            (true, Some(pattern)) => pattern,
            _ => &self.jacobian,
        }
    }
}

impl SquareStep {
    /// The step system of a DC graph of `model` with tangent integrators of
    /// `integrator` at `dt`; `None` where the integrator has no square step
    /// ([`Integrator::has_square_step`]) or its sparse analysis fails (the general
    /// solver then takes every step).
    pub fn dependent(model: Arc<Model>, integrator: Integrator, dt: f64) -> Option<SquareStep> {
        let integrated = (0..model.n()).collect();
        SquareStep::new(model, integrator, dt, integrated, true)
    }

    /// The step system of an IC graph of `model` (integrators of `integrator` on
    /// the independent coordinates `independent`) at `dt`; `None` where the integrator has no
    /// square step, the system is not square (redundant constraints) or its sparse
    /// analysis fails.
    pub fn independent(
        model: Arc<Model>,
        integrator: Integrator,
        dt: f64,
        independent: &[usize],
    ) -> Option<SquareStep> {
        if model.active.len() != model.m() {
            return None;
        }
        let integrated = independent.to_vec();
        SquareStep::new(model, integrator, dt, integrated, false)
    }

    fn new(
        model: Arc<Model>,
        integrator: Integrator,
        dt: f64,
        integrated: Vec<usize>,
        projected: bool,
    ) -> Option<SquareStep> {
        if !integrator.has_square_step() {
            return None;
        }
        let n = model.n();
        let mut force_entries = Vec::new();
        for force in &model.forces {
            match force.jacobian_pattern(&model) {
                Some((rows, cols)) => {
                    for &r in &rows {
                        force_entries.extend(cols.iter().map(|&c| (r, c)));
                    }
                }
                None => force_entries.extend((0..n).flat_map(|r| (0..n).map(move |c| (r, c)))),
            }
        }
        force_entries.sort_unstable();
        force_entries.dedup();
        let mass = model.mass_entries();
        let system = System {
            model,
            integrator,
            dt,
            mass,
            force_entries,
            integrated,
            projected,
            projection_damping: match integrator {
                Integrator::HermiteSimpson => PROJECTION_DAMPING,
                _ => 0.0,
            },
        };
        let size = system.size();
        if system.equations() != size {
            return None;
        }
        // The Jacobian's pattern from one structural pass of its assembly.
        let mut emitted = Vec::new();
        let x = vec![0.0; size];
        let dense = if system.force_entries.is_empty() {
            0
        } else {
            n * n
        };
        let (kq, kv) = (vec![0.0; dense], vec![0.0; dense]);
        let stage_state = vec![0.0; 2 * n];
        let stage = match system.staged() {
            true => Stage {
                state: &stage_state,
                force: &x[..n],
                kq: &kq,
                kv: &kv,
            },
            false => Stage::NONE,
        };
        system.assemble(
            &x,
            (&kq, &kv),
            &stage,
            &[],
            &mut Sink::Pattern(&mut emitted),
        );
        let jacobian = Pattern::new(size, &emitted);
        let factors = Factors::new(&jacobian)?;
        let damped_jacobian = match system.damped() {
            true => {
                let mut emitted = Vec::new();
                let damping = vec![0.0; system.model.active.len()];
                let sink = &mut Sink::Pattern(&mut emitted);
                system.assemble(&x, (&kq, &kv), &stage, &damping, sink);
                Some(Pattern::new(size, &emitted))
            }
            false => None,
        };
        let damped_factors = match &damped_jacobian {
            Some(pattern) => Some(Factors::new(pattern)?),
            None => None,
        };
        let regularity = Regularity::new(&system.model);
        let equations = Equations {
            system,
            jacobian,
            damped_jacobian,
            regularity,
        };
        let work = Work::new(&equations, (factors, damped_factors))?;
        Some(SquareStep::of(equations, work).scaled_to_its_initial_configuration())
    }

    /// The square step of `equations` with its scratch, before any step: its
    /// steps near a rank loss checked for their resolution and damped where the
    /// system can be.
    fn of(equations: Equations, work: Work) -> SquareStep {
        let n = equations.system.model.n();
        SquareStep {
            equations,
            work,
            passage: Passage::default(),
            recent: Remeasure::default(),
            ended: vec![f64::NAN; n],
            guess: vec![0.0; 3 * n],
            passed: false,
            checks_resolution: true,
            damps: true,
            damped_below: DAMPED_BELOW,
        }
    }

    /// This square step with its damped zone ([`DAMPED_BELOW`]) scaled to the
    /// mechanism's distance to a rank loss at its initial configuration, where
    /// that is below 1: a mechanism whose rows are ill-conditioned by its scales
    /// alone (Andrews' squeezer: s = 6.8e-3 all along) is no nearer a rank loss
    /// for it, and its projections stay exact.
    fn scaled_to_its_initial_configuration(mut self) -> SquareStep {
        let model = self.equations.system.model.clone();
        let initial = self.distance(model.initial.q.as_slice());
        self.damped_below = DAMPED_BELOW * initial.min(1.0);
        self
    }

    /// This square step set to steps of `dt` (its factors and its multipliers
    /// taken afresh).
    fn set_dt(&mut self, dt: f64) {
        if self.equations.system.dt != dt {
            self.equations.system.dt = dt;
            self.work.factored = false;
            self.work.multipliers.fill(0.0);
            self.work.rounding = 0.0;
        }
    }

    /// The same step system at another time step, with this one's sparse analysis
    /// (a failed step's substeps).
    pub fn at_dt(&self, dt: f64) -> Option<SquareStep> {
        let mut equations = self.equations.clone();
        equations.system.dt = dt;
        // (The factors held are of either pattern: each is remade from its own.)
        let (exact, damped) = match self.work.active_damped {
            false => (&self.work.factors, self.work.other.as_ref().map(|o| &o.0)),
            true => (&self.work.other.as_ref()?.0, Some(&self.work.factors)),
        };
        let factors = (exact.like(), damped.map(Factors::like));
        let work = Work::new(&equations, factors)?;
        Some(SquareStep {
            checks_resolution: self.checks_resolution,
            damps: self.damps,
            damped_below: self.damped_below,
            ..SquareStep::of(equations, work)
        })
    }

    /// This square step for an error-controlled run: its steps next to a rank loss
    /// are not checked for their resolution, as the run's error estimate rejects a
    /// step whose error the rounding sets, and a smaller step lands elsewhere. Its
    /// damped steps ([`SquareStep::damped`]) are the run's to keep at the size
    /// that reached the zone: damped projections leave a lost rank to the
    /// integrators, which holds over the few steps of one size that cross the
    /// zone, not over the thousands of shrinking steps the estimates there, which
    /// read q̈'s lost component, would ask for (40 loops at rtol 1e-10 drifted by
    /// 0.4 to 8 J over 5 s).
    pub(super) fn error_controlled(mut self) -> SquareStep {
        self.checks_resolution = false;
        self
    }
}

/// The square step of `plan`'s graph for `model` (in IC, on the independent
/// coordinates `independent`), where the plan has one (and its
/// integrator too: [`Integrator::has_square_step`]) and its sparse analysis
/// succeeds.
pub(super) fn for_plan(
    model: &Arc<Model>,
    plan: &Plan,
    independent: &[usize],
) -> Option<SquareStep> {
    if !plan.square_step {
        return None;
    }
    let (integrator, dt) = (plan.integrator, plan.dt);
    match plan.coordinates {
        Coordinates::Dependent => SquareStep::dependent(model.clone(), integrator, dt),
        Coordinates::Independent => {
            SquareStep::independent(model.clone(), integrator, dt, independent)
        }
    }
}

impl Work {
    /// Scratch for `system`'s iteration, unfactored, its multipliers at 0; `None`
    /// where G's analysis fails.
    fn new(equations: &Equations, (factors, damped): (Factors, Option<Factors>)) -> Option<Work> {
        let system = &equations.system;
        let n = system.model.n();
        let size = system.size();
        let dense = if system.force_entries.is_empty() {
            0
        } else {
            n * n
        };
        let (stage_state, stage_force, stage_dense) = match system.staged() {
            true => (2 * n, n, dense),
            false => (0, 0, 0),
        };
        Some(Work {
            x: vec![0.0; size],
            residual: vec![0.0; size],
            values: vec![0.0; equations.jacobian.row_idx.len()],
            q_force: vec![0.0; n],
            kq: vec![0.0; dense],
            kv: vec![0.0; dense],
            stage_state: vec![0.0; stage_state],
            stage_force: vec![0.0; stage_force],
            stage_kq: vec![0.0; stage_dense],
            stage_kv: vec![0.0; stage_dense],
            factors,
            other: damped.map(|f| (f, vec![0.0; equations.pattern(true).row_idx.len()])),
            active_damped: false,
            factored: false,
            rounding: 0.0,
            unresolved: false,
            saved: vec![0.0; size],
            damping: Vec::new(),
            near_rank_loss: false,
            gram: equations.regularity.work(&system.model)?,
            multipliers: vec![0.0; size - 3 * n],
        })
    }
}

impl Equations {
    /// What a step's equations take from the step before and hold over its
    /// iteration: the damping of its projections at q₀ (a damped step's Jacobian
    /// then factored afresh).
    fn prepare(&self, before: &[f64], work: &mut Work) {
        work.damping.clear();
        if self.system.damped() && work.near_rank_loss {
            let n = self.system.model.n();
            let model = &*self.system.model;
            let norms = self
                .regularity
                .row_norms(model, &before[..n], &mut work.gram);
            self.system.row_damping(norms, &mut work.damping);
        }
        let damped = !work.damping.is_empty();
        // A damped step factors its own Jacobian: next to a rank loss the Jacobian
        // changes fast from one step to the next, and an iteration on an earlier
        // one's factors ends where its updates stop shrinking, short of the
        // solution along the lost rank (error-controlled runs on 40 loops lost
        // 2e-9 J at such steps).
        if damped {
            work.factored = false;
        }
        if damped != work.active_damped {
            if let Some((factors, values)) = work.other.as_mut() {
                std::mem::swap(&mut work.factors, factors);
                std::mem::swap(&mut work.values, values);
                work.active_damped = damped;
                work.factored = false;
            }
        }
    }

    /// The residual of the step system at `work.x` in `work.residual`; `None`
    /// where an effect cannot be evaluated or it is not finite.
    fn residual(&self, t: f64, before: &[f64], work: &mut Work) -> Option<()> {
        let system = &self.system;
        let model = &*system.model;
        let n = model.n();
        let (q, v) = (&work.x[..n], &work.x[n..2 * n]);
        work.q_force.fill(0.0);
        for force in &model.forces {
            force.add_to(model, q, v, t, &mut work.q_force).ok()?;
        }
        if system.staged() {
            system.stage_state(&work.x, before, &mut work.stage_state);
            let (qm, vm) = work.stage_state.split_at(n);
            work.stage_force.fill(0.0);
            for force in &model.forces {
                force
                    .add_to(model, qm, vm, system.stage_time(t), &mut work.stage_force)
                    .ok()?;
            }
        }
        let stage = Stage {
            state: &work.stage_state,
            force: &work.stage_force,
            kq: &work.stage_kq,
            kv: &work.stage_kv,
        };
        let forces = (&work.q_force[..], &stage);
        system.residual(&work.x, before, forces, &work.damping, &mut work.residual);
        work.residual.iter().all(|v| v.is_finite()).then_some(())
    }

    /// The residual (`work.residual`) and the Jacobian's values (`work.values`) of
    /// the step system at `work.x`, and the Jacobian's LU (`work.factors`); `None`
    /// where an effect cannot be evaluated, either is not finite or the LU fails.
    fn linearize(&self, t: f64, before: &[f64], work: &mut Work) -> Option<()> {
        let system = &self.system;
        let model = &*system.model;
        let n = model.n();
        work.factored = false;
        self.residual(t, before, work)?;
        let (q, v) = (&work.x[..n], &work.x[n..2 * n]);
        if !system.force_entries.is_empty() {
            for force in &model.forces {
                force
                    .add_jacobians(model, (q, v, t), &mut work.kq, &mut work.kv)
                    .ok()?;
            }
            if system.staged() {
                let (qm, vm) = work.stage_state.split_at(n);
                for force in &model.forces {
                    force
                        .add_jacobians(
                            model,
                            (qm, vm, system.stage_time(t)),
                            &mut work.stage_kq,
                            &mut work.stage_kv,
                        )
                        .ok()?;
                }
            }
        }
        work.values.fill(0.0);
        let stage = Stage {
            state: &work.stage_state,
            force: &work.stage_force,
            kq: &work.stage_kq,
            kv: &work.stage_kv,
        };
        system.assemble(
            &work.x,
            (&work.kq, &work.kv),
            &stage,
            &work.damping,
            &mut Sink::Values {
                slots: &self.pattern(work.active_damped).slots,
                values: &mut work.values,
                next: 0,
            },
        );
        for &(r, c) in &system.force_entries {
            work.kq[r * n + c] = 0.0;
            work.kv[r * n + c] = 0.0;
            if system.staged() {
                work.stage_kq[r * n + c] = 0.0;
                work.stage_kv[r * n + c] = 0.0;
            }
        }
        if !work.values.iter().all(|v| v.is_finite()) {
            return None;
        }
        let pattern = self.pattern(work.active_damped);
        work.factors.factor(pattern, &work.values)?;
        work.factored = true;
        Some(())
    }

    /// Newton's method on the step system from the guess in `block`; the
    /// iterations taken when it converged. Simplified where it may be: the LU of
    /// an earlier Jacobian (of this step or of one before) is used as long as the
    /// updates shrink by [`MAX_CONTRACTION`] or faster (a step's Jacobian changes
    /// little from the one before it); the first update that does not is discarded
    /// and the iterate factored afresh.
    fn newton(
        &self,
        t: f64,
        before: &[f64],
        block: &mut [f64],
        limits: StepLimits,
        work: &mut Work,
        mut watch: Option<&mut dyn FnMut(&StepIteration)>,
    ) -> Option<StepWork> {
        let system = &self.system;
        let model = &*system.model;
        let n = model.n();
        self.prepare(before, work);
        work.x[..3 * n].copy_from_slice(&block[..3 * n]);
        work.x[3 * n..].copy_from_slice(&work.multipliers);
        // The sizes of the last two updates taken with the factors now held.
        let (mut last, mut before_last) = (f64::INFINITY, f64::INFINITY);
        let mut factorizations = 0;
        // Whether the last update was taken with an earlier step's factors and
        // nothing to judge them by: undone (from `work.saved`) if the next one shows
        // they do not carry the iteration.
        let mut blind = false;
        for iteration in 1..=limits.max_iterations.min(MAX_ITERATIONS) {
            let fresh = !work.factored;
            if fresh {
                factorizations += 1;
                if factorizations > MAX_FACTORIZATIONS {
                    return None;
                }
                self.linearize(t, before, work)?;
            } else {
                self.residual(t, before, work)?;
            }
            let cost = match watch {
                Some(_) => 0.5 * work.residual.iter().map(|r| r * r).sum::<f64>(),
                None => 0.0,
            };
            let residual_size = max_abs(&work.residual);
            let scale = 1.0 + max_abs(&work.x);
            work.factors.solve_in_place(&mut work.residual);
            if !work.residual.iter().all(|d| d.is_finite()) {
                return None;
            }
            let update = relative_update(&work.x[..3 * n], &work.residual);
            // The contraction θ over the last update and, where there are two, over
            // the last two (their geometric mean). The error left after this update:
            // about its square after a Newton update; after a simplified one,
            // θ/(1 − θ) of it at the last update's θ (an alternating iteration's
            // next update may shrink 50 times less, well inside SETTLED's margin).
            // Updates that stop shrinking below the tolerance are the residual's
            // rounding, as far as any iteration gets; an error estimated below the
            // rounding an earlier step reached is settled too (a large mechanism's
            // rounding can lie above SETTLED's target). (None: no update taken with
            // these factors yet.)
            let contraction = (!fresh && last.is_finite()).then(|| {
                let one = update / last;
                let two = if before_last.is_finite() {
                    (update / before_last).sqrt()
                } else {
                    one
                };
                (one, two)
            });
            let settled = match contraction {
                _ if fresh => update <= limits.step_tolerance,
                None => false,
                Some((c, _)) => {
                    let floor = c >= ROUNDING_FLOOR && update <= limits.step_tolerance;
                    // (Remembered only well below the tolerance, where it cannot
                    // be a slow iteration.)
                    if floor && update <= ROUNDING_KEPT * limits.step_tolerance {
                        work.rounding = update;
                    }
                    let target = (SETTLED * limits.step_tolerance).max(work.rounding);
                    c < 1.0 && c / (1.0 - c) * update <= target || floor
                }
            };
            if let Some(watch) = watch.as_mut() {
                watch(&StepIteration {
                    iteration,
                    cost,
                    update,
                    fresh,
                    settled,
                });
            }
            if update > limits.step_tolerance && residual_size <= NEAR_ROUNDING * scale {
                work.unresolved = true;
            }
            // A residual at the rounding of the equations' terms: x solves them as far
            // as the arithmetic tells (near a rank loss of Φ_q the updates from here
            // are that rounding amplified by the Jacobian's condition, and never shrink).
            // (x is the iterate the residual was taken at: the update is not applied yet.)
            if !settled
                && update > limits.step_tolerance
                && residual_size <= ROUNDING_RESIDUAL * scale
            {
                return self.finish(model, block, iteration, factorizations, work);
            }
            // Below the tolerance the updates approach the residual's rounding and
            // their contraction is noise: a fresh factorization buys nothing the
            // iteration does not reach anyway.
            if !settled
                && update > limits.step_tolerance
                && contraction.is_some_and(|(one, two)| one >= 1.0 || two > MAX_CONTRACTION)
            {
                // The earlier Jacobian no longer carries the iteration.
                work.factored = false;
                if blind {
                    work.x.copy_from_slice(&work.saved);
                    blind = false;
                }
                continue;
            }
            blind = !fresh && contraction.is_none();
            if blind {
                work.saved.copy_from_slice(&work.x);
            }
            (before_last, last) = if fresh {
                (f64::INFINITY, update)
            } else {
                (last, update)
            };
            for (xi, di) in work.x.iter_mut().zip(&work.residual) {
                *xi -= di;
            }
            if settled {
                return self.finish(model, block, iteration, factorizations, work);
            }
        }
        None
    }

    /// Whether the solution in `work.x` is resolved to the step tolerance: its
    /// iteration never moved it along a direction the arithmetic does not resolve,
    /// and a fresh Newton update from it, the residual's rounding amplified by the
    /// Jacobian's condition, stays below the tolerance.
    fn resolved(&self, t: f64, before: &[f64], limits: StepLimits, work: &mut Work) -> bool {
        if work.unresolved || self.linearize(t, before, work).is_none() {
            return false;
        }
        work.factors.solve_in_place(&mut work.residual);
        let n = self.system.model.n();
        relative_update(&work.x[..3 * n], &work.residual) <= limits.step_tolerance
    }

    /// The step's solution `work.x` into `block`.
    fn finish(
        &self,
        model: &Model,
        block: &mut [f64],
        iterations: usize,
        factorizations: usize,
        work: &mut Work,
    ) -> Option<StepWork> {
        let n = model.n();
        block[..3 * n].copy_from_slice(&work.x[..3 * n]);
        self.system.fill_independent(block);
        work.multipliers.copy_from_slice(&work.x[3 * n..]);
        Some(StepWork {
            iterations,
            factorizations,
        })
    }
}

/// The size of an update `d` of the state `x` (q, q̇, q̈; `d` may go on past
/// it): max |dᵢ| / (1 + |xᵢ|).
fn relative_update(x: &[f64], d: &[f64]) -> f64 {
    x.iter()
        .zip(d)
        .map(|(xi, di)| di.abs() / (1.0 + xi.abs()))
        .fold(0.0, f64::max)
}

/// max |vᵢ| (0 for an empty slice; a NaN passed over, as `f64::max` does), over
/// four lanes: the maximum does not depend on the order, and four independent
/// chains of comparisons run faster than one.
fn max_abs(v: &[f64]) -> f64 {
    let pick = |m: f64, x: f64| if x.abs() > m { x.abs() } else { m };
    let mut lanes = [0.0f64; 4];
    let mut chunks = v.chunks_exact(4);
    for chunk in &mut chunks {
        for (m, x) in lanes.iter_mut().zip(chunk) {
            *m = pick(*m, *x);
        }
    }
    let tail = chunks.remainder().iter().fold(0.0, |m, x| pick(m, *x));
    lanes.iter().fold(tail, |m, x| pick(m, *x))
}

impl SquareStep {
    /// Step 0 holds q and q̇ at the model's initial state (in `block`), and f_dyn
    /// asks q̈ of the augmented system there, which is regular where the steps are
    /// taken from here: its solution, once the configuration passes the same test;
    /// `None` where it declines (the general solver then takes it).
    pub fn solve_first(&mut self, t: f64, block: &mut [f64]) -> Option<StepWork> {
        let model = &*self.equations.system.model;
        let n = model.n();
        if !self
            .equations
            .regularity
            .regular(model, &block[..n], &mut self.work.gram)
        {
            return None;
        }
        let q = DVector::from_column_slice(&block[..n]);
        let dq = DVector::from_column_slice(&block[n..2 * n]);
        let ddq = dynamics::accelerations_guess(model, &q, &dq, t).ok()?;
        if !ddq.iter().all(|v| v.is_finite()) {
            return None;
        }
        block[2 * n..3 * n].copy_from_slice(ddq.as_slice());
        self.equations.system.fill_independent(block);
        Some(StepWork {
            iterations: 1,
            factorizations: 1,
        })
    }

    /// Solves step `block` (guess in, solution out) at time `t`, given the step
    /// before (`before`); the work taken, or `None` where it declines or does not
    /// converge (`block` is then unspecified). `watch` sees every iteration. A
    /// step whose guess or solution lies within [`passage::near`] of a rank loss
    /// of Φ_q, or that fails near one, is interpolated from a longer step that
    /// clears it ([`Passage`]); far from any rank loss the solution's distance is
    /// measured as [`Remeasure`] says, not every step.
    pub fn solve(
        &mut self,
        t: f64,
        before: &[f64],
        block: &mut [f64],
        limits: StepLimits,
        watch: Option<&mut dyn FnMut(&StepIteration)>,
    ) -> Option<StepWork> {
        let n = self.equations.system.model.n();
        if self.may_damp() && before[..n] != self.ended[..] {
            // Another solver took the step before (a rescue): the distance last
            // measured, which decides whether this step is damped, is not this
            // run's.
            self.recent = Remeasure::default();
        }
        let solved = self.solve_from(t, before, block, limits, watch);
        match solved {
            Some(_) => self.ended.copy_from_slice(&block[..n]),
            None => self.ended.fill(f64::NAN),
        }
        solved
    }

    /// [`SquareStep::solve`] from the distances to a rank loss in `recent`.
    fn solve_from(
        &mut self,
        t: f64,
        before: &[f64],
        block: &mut [f64],
        limits: StepLimits,
        watch: Option<&mut dyn FnMut(&StepIteration)>,
    ) -> Option<StepWork> {
        let n = self.equations.system.model.n();
        self.passed = false;
        if let Passed::Taken(work) = self.passage.resume(t, before, block, n) {
            self.equations.system.fill_independent(block);
            self.passed = true;
            return Some(work);
        }
        let damped = self.may_damp();
        self.work.near_rank_loss = damped && self.starts_near(before);
        // The guess's distance to a rank loss only where the last steps' s, carried
        // on at twice its last change, may come near one within this step.
        let (last, change) = self.recent.last();
        let zone = passage::near(&self.equations.system, damped);
        let near = last - 2.0 * change.abs() < LOOKOUT * zone;
        let from_guess = match near {
            true => self.distance(&block[..n]),
            false => f64::INFINITY,
        };
        if from_guess >= zone {
            self.guess.copy_from_slice(&block[..3 * n]);
            match self.solve_plain_watched(t, before, block, limits, watch) {
                Some(work) => {
                    // Far from a rank loss the last measure stands for this one.
                    if self.recent.standing().is_some() {
                        return Some(work);
                    }
                    let s = self.clearance(before, block);
                    self.recent.measured(s);
                    // Resolution is checked near a rank loss and where steps are fine
                    // enough that several span the zone: where one step crosses it, the
                    // step's own error outweighs the rounding a landing is solved to,
                    // and a longer step over errs more (20 loops at 25 ms: 1.5e-3 m
                    // became 9.2e-2 m).
                    let coarse = change.abs() >= Remeasure::FAR;
                    let regular = s >= DynamicsKernel::REGULAR_ABOVE || coarse;
                    if s >= zone && (regular || self.resolved(t, before, limits)) {
                        return Some(work);
                    }
                    block[..3 * n].copy_from_slice(&self.guess);
                }
                None if from_guess >= DynamicsKernel::REGULAR_ABOVE => {
                    self.recent = Remeasure::default();
                    return None;
                }
                None => {}
            }
        }
        self.recent = Remeasure::default();
        let mut passage = std::mem::take(&mut self.passage);
        let solved = passage.start(self, t, before, block, limits);
        self.passage = passage;
        if solved.is_some() {
            self.equations.system.fill_independent(block);
            self.passed = true;
        }
        solved
    }

    /// Whether this square step damps its projections near a rank loss: its
    /// system can, and its run lets it.
    fn may_damp(&self) -> bool {
        self.damps && self.equations.system.damped()
    }

    /// Whether a step from `before` starts within `damped_below` of a rank loss:
    /// from the last measure where it is far, else measured there (unmeasured
    /// counts as near).
    fn starts_near(&mut self, before: &[f64]) -> bool {
        let n = self.equations.system.model.n();
        let start = match (self.recent.least() < self.damped_below, self.recent.fresh()) {
            (false, _) => f64::INFINITY,
            (true, Some(s)) => s,
            (true, None) => {
                let s = self.distance(&before[..n]);
                self.recent.measured(s);
                s
            }
        };
        start < self.damped_below
    }

    /// Whether the last step solved started near a rank loss where its
    /// projections are damped: solved damped, or interpolated from a longer step
    /// over the rank loss, damped too.
    pub fn damped(&self) -> bool {
        self.work.near_rank_loss
    }

    /// Whether the last step solved was interpolated from a longer step over a
    /// rank loss ([`Passage`]).
    pub fn passed(&self) -> bool {
        self.passed
    }

    /// Whether a longer step over a rank loss is under way: the next steps of this
    /// size, each from the one before, are its interpolants and then its end.
    pub fn passing(&self) -> bool {
        self.passage.under_way()
    }

    /// [`SquareStep::solve`] without the passage: Newton's method on this step.
    fn solve_plain(
        &mut self,
        t: f64,
        before: &[f64],
        block: &mut [f64],
        limits: StepLimits,
    ) -> Option<StepWork> {
        self.solve_plain_watched(t, before, block, limits, None)
    }

    fn solve_plain_watched(
        &mut self,
        t: f64,
        before: &[f64],
        block: &mut [f64],
        limits: StepLimits,
        watch: Option<&mut dyn FnMut(&StepIteration)>,
    ) -> Option<StepWork> {
        let work = &mut self.work;
        work.unresolved = false;
        let solved = self.equations.newton(t, before, block, limits, work, watch);
        if solved.is_none() {
            // The next step starts its multipliers and its Jacobian afresh.
            work.multipliers.fill(0.0);
            work.factored = false;
            work.rounding = 0.0;
        }
        solved
    }

    /// Whether the step just solved (at `t`, from `before`) is resolved to the
    /// step tolerance ([`Equations::resolved`]). Near a rank loss the step system's
    /// condition grows like the inverse square of the distance, at a rate that
    /// differs from one mechanism to the next: this measures it where the distance
    /// alone cannot tell. Only Hermite–Simpson's steps are held to it: they err so
    /// little that an unresolved landing sets their error at a passage, where a
    /// trapezoidal step over errs more than the landing it avoids.
    fn resolved(&mut self, t: f64, before: &[f64], limits: StepLimits) -> bool {
        let system = &self.equations.system;
        !(self.checks_resolution && system.staged() && !system.damped())
            || self.equations.resolved(t, before, limits, &mut self.work)
    }

    /// The distance to a rank loss of Φ_q of a step solved (`state`: q, q̇, q̈)
    /// from `before`: at its end, and with Hermite–Simpson at its stage too, whose
    /// dynamics hold there (the configuration can pass a rank loss between two
    /// ends clear of it, and the stage land next to it).
    fn clearance(&mut self, before: &[f64], state: &[f64]) -> f64 {
        let n = self.equations.system.model.n();
        let end = self.distance(&state[..n]);
        if !self.equations.system.staged() {
            return end;
        }
        let system = &self.equations.system;
        let mut stage = std::mem::take(&mut self.work.stage_state);
        system.stage_state(state, before, &mut stage);
        let middle = self.distance(&stage[..n]);
        self.work.stage_state = stage;
        end.min(middle)
    }

    /// The distance to a rank loss of Φ_q at q of the rows nearest one,
    /// (max (G⁻¹)ᵢᵢ)^(−1/2): a step's accuracy near a rank loss is that of the loop
    /// that loses it, however many lose it at once.
    fn distance(&mut self, q: &[f64]) -> f64 {
        let model = &*self.equations.system.model;
        self.equations
            .regularity
            .nearest_rank_loss(model, q, &mut self.work.gram)
    }
}

#[cfg(test)]
mod tests;
