//! The plan of a forward run ([`Plan`]): every decision the options leave to the
//! run, made once from the model and the options, as data. Which integrator
//! factors, which schedule really runs (a square graph's window or batch is taken
//! one step at a time), which solver takes a step, which prior a step leaves, what
//! the run holds in memory, and the rescues in the order they are tried. The run
//! carries the plan out; the summary, the CLI and Python print it.

use super::options::{DcIntegrators, ForwardOptions, Integrator};
use crate::coordinates::Coordinates;
use crate::error::Result;
use crate::model::Model;
use crate::smoother::{self, Mode};
use crate::solver::{Past, Settings};
use std::fmt;

/// How the steps of a run are solved.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Schedule {
    /// One step at a time, each given the step before, held fixed: the square
    /// step where it can, else the general solver's conditional solve. Every
    /// window and the batch of a square graph have this solution.
    Stepwise,
    /// The fixed-lag smoother over the N_w newest steps, through the general solver.
    FixedLag(usize),
    /// All steps at once through the general solver, from a one-step start.
    Batch,
}

impl fmt::Display for Schedule {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Schedule::Stepwise => write!(f, "one step at a time"),
            Schedule::FixedLag(n) => write!(f, "window {n}"),
            Schedule::Batch => write!(f, "batch"),
        }
    }
}

/// What a run does where a step, a segment or the run fails, in the order the
/// run tries them (a plan lists those that apply, [`Plan::rescues`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Rescue {
    /// A step the square step declines (near a rank loss of Φ_q) or does not
    /// converge on goes to the general solver, whose Levenberg–Marquardt
    /// iteration has its own fallbacks (exact Hessian, least-squares step).
    GeneralSolver,
    /// A window that fails after a marginal prior is solved again after a
    /// conditioned one, and every later prior is conditioned.
    ConditionedPast,
    /// A failed step is solved again from the end of 2, 8 or 64 substeps.
    Substeps,
    /// In IC, where the coordinates in use stop determining the others while
    /// Φ_q keeps its rank, the run goes on with a better set.
    Reselection,
    /// A run that fails, or converges, over a step too coarse for the motion is
    /// made again at dt / K, every K-th state kept.
    Refinement,
    /// A DC step the tangent integrator factors fail from every substep guess is
    /// taken by the paper's, that step only (never the whole run again: measured
    /// over the test suites and the robustness matrix, a run made again with them
    /// from t = 0 never got further).
    PaperIntegrators,
}

impl Rescue {
    /// Every rescue, in the order a run tries them: a step's before a segment's
    /// before the run's.
    pub const LADDER: [Rescue; 6] = [
        Rescue::GeneralSolver,
        Rescue::ConditionedPast,
        Rescue::Substeps,
        Rescue::Reselection,
        Rescue::Refinement,
        Rescue::PaperIntegrators,
    ];
}

/// Bytes a run holds at its peak, roughly.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Memory {
    /// Handing its steps out as they become final
    /// ([`simulate_streaming`](super::simulate_streaming)).
    pub streamed: f64,
    /// Returning its trajectory ([`simulate`](super::simulate)).
    pub held: f64,
}

/// Every decision of a forward run, made once ([`Plan::new`]).
#[derive(Debug, Clone, PartialEq)]
pub struct Plan {
    pub coordinates: Coordinates,
    pub integrator: Integrator,
    /// In DC, the integrator factors: [`DcIntegrators::Tangent`] or
    /// [`DcIntegrators::Full`] (`Auto` resolved); `None` in IC.
    pub dc_integrators: Option<DcIntegrators>,
    pub dt: f64,
    /// Steps, t = 0 included.
    pub steps: usize,
    /// The schedule asked for.
    pub asked: Mode,
    /// The schedule that runs.
    pub schedule: Schedule,
    /// Whether the square step takes the steps it can ([`Schedule::Stepwise`] only).
    pub square_step: bool,
    /// The settings of the solves, as the schedule runs them.
    pub settings: Settings,
    pub memory: Memory,
    /// The rescues this run may try, in the order it tries them.
    pub rescues: Vec<Rescue>,
}

/// Steps a stepwise run holds: the two its predictions read, and room to hand the
/// final ones out together, now and then, not one by one between the solves.
pub(super) const STEPWISE_BUFFER: usize = 4096;

impl Plan {
    /// The plan of a run of `model` with `options`, once they are valid.
    pub fn new(model: &Model, options: &ForwardOptions) -> Result<Plan> {
        options.validate_options(model)?;
        let plan = Plan::decide(model, options);
        crate::limits::ensure_fits(
            &format!("a run of {} steps of {} coordinates", plan.steps, model.n()),
            plan.memory.streamed,
        )?;
        Ok(plan)
    }

    fn decide(model: &Model, options: &ForwardOptions) -> Plan {
        let dc_integrators = match (options.coordinates, options.dc_integrators) {
            (Coordinates::Independent, _) => None,
            (_, DcIntegrators::Full) => Some(DcIntegrators::Full),
            (_, DcIntegrators::Tangent | DcIntegrators::Auto) => Some(DcIntegrators::Tangent),
        };
        let square = dc_integrators != Some(DcIntegrators::Full);
        // The square step has the integrators' equations, and needs as many
        // constraints as rows of Φ_q in IC (no redundant ones). Hermite–Simpson's is
        // taken in DC only: in IC, where nothing projects the stage's interpolated
        // state, a step too coarse for the motion can converge to a root off it
        // that the general solver does not reach, and the run then stops instead of
        // being refined.
        let square_step = square
            && options.square_steps
            && options.integrator.has_square_step()
            && options.settings.past != Past::Marginalized
            && match options.coordinates {
                Coordinates::Dependent => true,
                Coordinates::Independent => {
                    model.active.len() == model.m()
                        && options.integrator != Integrator::HermiteSimpson
                }
            };
        let steps = options.steps();
        let schedule = match options.mode {
            _ if square_step => Schedule::Stepwise,
            Mode::FixedLag(n) => Schedule::FixedLag(n.min(steps.max(1))),
            Mode::Batch => Schedule::Batch,
        };
        let settings = Settings {
            // The DC graph's integrators conflict with its constraints.
            tangent_priors: options.coordinates == Coordinates::Dependent,
            // A square graph's steps each hold all their equations: a marginal prior
            // adds nothing to the next step's solution but its linearization about the
            // step's prediction, whose error grows in a stiff transient; the exact
            // conditional is the step's own solution, and the batch's.
            past: match options.settings.past {
                Past::Adaptive if square => Past::Conditioned,
                past => past,
            },
            // One equation per unknown: Gauss–Newton is Newton's method.
            second_order: options.settings.second_order && !square,
            ..options.settings
        };
        let mut rescues = Vec::new();
        for rescue in Rescue::LADDER {
            let applies = match rescue {
                Rescue::GeneralSolver => square_step,
                Rescue::ConditionedPast => {
                    !square_step && settings.past == Past::Adaptive && schedule != Schedule::Batch
                }
                Rescue::Substeps => schedule != Schedule::Batch,
                Rescue::Reselection => options.coordinates == Coordinates::Independent,
                Rescue::Refinement => options.refine,
                // Hermite–Simpson's tangent factors are its own; the paper has none.
                Rescue::PaperIntegrators => {
                    options.dc_integrators == DcIntegrators::Auto
                        && options.coordinates == Coordinates::Dependent
                        && options.integrator != Integrator::HermiteSimpson
                }
            };
            if applies {
                rescues.push(rescue);
            }
        }
        let mut plan = Plan {
            coordinates: options.coordinates,
            integrator: options.integrator,
            dc_integrators,
            dt: options.dt,
            steps,
            asked: options.mode,
            schedule,
            square_step,
            settings,
            memory: Memory {
                streamed: 0.0,
                held: 0.0,
            },
            rescues,
        };
        plan.memory = plan.memory_estimate(model);
        plan
    }

    /// Whether every step has as many equations as unknowns, all of which hold at
    /// the solution (IC, and DC with tangent integrators).
    pub fn square(&self) -> bool {
        self.dc_integrators != Some(DcIntegrators::Full)
    }

    /// Whether DC integrator factors are projected on the tangent space.
    pub fn tangent_dc(&self) -> bool {
        self.dc_integrators == Some(DcIntegrators::Tangent)
    }

    /// Whether the run may try `rescue`.
    pub fn tries(&self, rescue: Rescue) -> bool {
        self.rescues.contains(&rescue)
    }

    /// The variables the solve keeps (a stepwise run's few steps, the fixed-lag
    /// smoother's buffer of a few thousand, every step for a batch), the linear
    /// systems it solves, and with the trajectory returned, its every step.
    fn memory_estimate(&self, model: &Model) -> Memory {
        let n = model.n() as f64;
        let s = 3.0 * (n + model.independent.len() as f64);
        let steps = self.steps as f64;
        let per_step_system = 8.0 * s * (3.0 * s + 2.0 * model.m() as f64) * 4.0;
        let (held, solved) = match self.schedule {
            Schedule::Stepwise => ((STEPWISE_BUFFER as f64).min(steps), 2.0f64.min(steps)),
            Schedule::FixedLag(w) => (
                (smoother::stream_capacity(w) as f64).min(steps),
                (w as f64).min(steps) + 1.0,
            ),
            Schedule::Batch => (steps, steps),
        };
        let streamed = 8.0 * held * s * 2.0 + per_step_system * solved;
        Memory {
            streamed,
            held: streamed + 8.0 * steps * 3.0 * n * 2.0,
        }
    }

    /// What runs, in words: the schedule, and the one asked where it differs.
    pub fn describe(&self) -> String {
        let asked = match self.asked {
            Mode::FixedLag(n) => Schedule::FixedLag(n),
            Mode::Batch => Schedule::Batch,
        };
        match self.schedule {
            Schedule::Stepwise if asked == Schedule::FixedLag(1) => "window 1, square steps".into(),
            // Each step holds all its equations: every window, and the batch, has
            // the solution of one step at a time.
            Schedule::Stepwise => format!("{asked} asked, taken one step at a time, square steps"),
            other => other.to_string(),
        }
    }
}

/// What the options ask of the memory and of the model, judged by their plan.
impl ForwardOptions {
    /// Bytes a run of `model` with these options holds at its peak, roughly, when it
    /// returns its trajectory ([`simulate`](super::simulate)); see [`Plan::memory`].
    pub fn memory_estimate(&self, model: &Model) -> Result<f64> {
        Ok(Plan::new(model, self)?.memory.held)
    }

    /// Refuses a run whose estimate does not fit the memory available: with its
    /// trajectory `held`, or streamed (which [`validate`](Self::validate) checks).
    pub fn check_memory(&self, model: &Model, held: bool) -> Result<()> {
        let plan = Plan::new(model, self)?;
        let bytes = if held {
            plan.memory.held
        } else {
            plan.memory.streamed
        };
        crate::limits::ensure_fits(
            &format!("a run of {} steps of {} coordinates", plan.steps, model.n()),
            bytes,
        )
    }

    /// Refuses options that make no sense, or a run that does not fit the memory
    /// available (streamed), with the reason.
    pub fn validate(&self, model: &Model) -> Result<()> {
        Plan::new(model, self).map(drop)
    }
}
