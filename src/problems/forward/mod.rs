//! Forward dynamics as factor graphs (paper, sections 4.1, 4.2 and 5): the graph in
//! dependent coordinates (DC) and in independent coordinates (IC), and a simulation
//! run over a horizon by the fixed-lag smoother or in batch.
//!
//! `options` holds what a run is asked and `plan` what the run decides from it
//! once: the schedule that runs, the solver of a step, the rescues in their order.
//! `graph` is the factor graph; `run` makes the run over the horizon (again at a
//! finer step or with other integrator factors where the plan's rescues say so) in
//! `segment`s, whose steps `steps` takes one at a time (through `stepwise`, with
//! `square_step` where it can) or `windows` hands to the general smoother, each
//! step judged by `judge` (failures, the IC watch) and rescued by `substeps`;
//! `failure` and `summary` are what it reports, `balance` the energy balance its
//! summary carries. A run with a tolerance sizes its steps by `error_control`
//! instead, in `adaptive`, and `run_check` checks its rows against the tolerance,
//! making it again at a tighter one where they miss it.

mod adaptive;
mod balance;
pub mod energy_checks;
mod error_control;
mod failure;
mod graph;
mod judge;
mod options;
mod plan;
mod run;
mod run_check;
mod segment;
mod square_step;
mod start;
mod steps;
mod stepwise;
mod substeps;
mod summary;
mod windows;

pub use crate::coordinates::Coordinates;
pub use crate::kinematics::{Determinacy, SingularConfiguration};
pub use crate::trajectory::{round_time, Trajectory};
pub use adaptive::NO_STEP_CONVERGED;
pub use balance::BalanceOff;
pub use error_control::Tolerance;
pub use failure::StepFailure;
pub use graph::ForwardGraph;
pub use options::{DcIntegrators, ForwardOptions, Integrator, NoiseModels, Observers};
pub use plan::{Memory, Plan, Rescue, Schedule};
pub use run::{simulate, simulate_interruptible, simulate_streaming, StepSink};
pub use run_check::ToleranceScope;
pub use start::Start;
pub use summary::{
    ErrorControl, LoadJump, Passages, Refinement, Reselection, RunCheck, RunSummary,
};
