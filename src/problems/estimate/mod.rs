//! State estimation: the motion of a mechanism from its model and noisy sensor
//! readings, by the fixed-lag smoother (online, [`Estimator`]) or a batch solve of
//! the whole record, with the marginal covariance of every estimate and the
//! normalized innovations that show whether it is honest.

pub mod consistency;
pub mod determination;
pub mod graph;
pub mod identification;
pub mod online;
pub mod options;
pub mod process_noise;
pub mod record;
pub mod run;
pub mod start;
pub mod table;

pub use consistency::Nis;
pub use determination::{Determination, Undetermined};
pub use graph::EstimationGraph;
pub use identification::{Identification, ParameterEstimate};
pub use online::{Estimator, StepEstimate, Update};
pub use options::{EstimateOptions, Smoothing, Uncertainty, RELINEARIZE_BEYOND};
pub use process_noise::ProcessSource;
pub use record::{Record, StepReading};
pub use run::{estimate, estimate_with_progress, finer_step_advice, EstimateSummary};
pub use table::Estimates;
