//! Forward dynamics as factor graphs (paper, sections 4.1, 4.2 and 5): the graph in
//! dependent coordinates (DC) and in independent coordinates (IC), and a simulation
//! run over a horizon by the fixed-lag smoother or in batch.
//!
//! `options` holds what a run is asked, `graph` the factor graph, `run` and
//! `segment` the run over the horizon, `failure` and `summary` what it reports.

mod exact_step;
mod failure;
mod graph;
mod options;
mod run;
mod segment;
mod summary;

pub use crate::coordinates::Coordinates;
pub use crate::kinematics::{Determinacy, SingularConfiguration};
pub use crate::trajectory::{round_time, Trajectory};
pub use failure::StepFailure;
pub use graph::ForwardGraph;
pub use options::{DcIntegrators, ForwardOptions, Integrator, NoiseModels};
pub use run::{simulate, simulate_interruptible, simulate_streaming, StepSink};
pub use segment::AUTO_BATCH_ITERATIONS;
pub use summary::{Refinement, Reselection, RunSummary};
