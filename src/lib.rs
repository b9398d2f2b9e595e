//! mbfg: planar multibody dynamics as factor graphs.
//!
//! A [`scene::Scene`] (read from YAML) is assembled into an immutable
//! [`model::Model`]: coordinates q, constraints Φ(q), mass matrix M and the
//! generalized forces of the scene's effects. [`kinematics`] and [`dynamics`] give the
//! classical solutions (position, velocity and acceleration problems; q̈ from the KKT
//! system and z̈ by the R-matrix method) on which the factor graphs build.

// `!(x > 0.0)` is written on purpose: it also rejects NaN.
#![allow(clippy::neg_cmp_op_on_partial_ord)]
// Index loops mirror the math of the small dense kernels.
#![allow(clippy::needless_range_loop)]

pub mod convergence;
pub mod coordinates;
pub mod derived;
pub mod dynamics;
pub mod error;
pub mod expr;
pub mod factors;
pub mod graph;
pub mod io;
pub mod kinematics;
pub mod limits;
pub mod linalg;
pub mod model;
#[cfg(feature = "testing")]
pub mod motions;
pub mod problems;
#[cfg(feature = "python")]
mod python;
pub mod reactions;
#[cfg(feature = "testing")]
pub mod reference;
pub mod rng;
#[cfg(feature = "testing")]
pub mod scenario;
pub mod scene;
pub mod sensors;
pub mod smoother;
pub mod solver;
pub mod stop;
pub mod trajectory;

// The problems keep their paths at the crate's root: `mbfg::forward`, `mbfg::inverse`.
pub use problems::{estimate, forward, inverse};

pub use error::{Error, Result, SceneError};
pub use model::forces::ExternalLoad;
pub use model::Model;
pub use scene::Scene;

#[cfg(test)]
mod send_sync {
    fn assert_send_sync<T: Send + Sync>() {}

    #[test]
    fn model_and_scene_are_send_and_sync() {
        assert_send_sync::<crate::Model>();
        assert_send_sync::<crate::Scene>();
    }
}
