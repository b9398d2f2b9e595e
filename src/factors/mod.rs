//! The factors of the paper's section 6, each with closed-form Jacobians.
//!
//! Generic: [`Prior`] (f_prior), [`Equality`] (f_eq), [`Euler`] (f_ei),
//! [`Trapezoidal`] (f_ti), the [`Integrator`] that picks its factors. Dependent coordinates: [`PositionConstraints`] (f^d_pc),
//! [`VelocityConstraints`] (f^d_vc), [`Dynamics`] (f^d_dyn). Independent coordinates:
//! [`IndependentPosition`] (f^i_pc), [`IndependentVelocity`] (f^i_vc),
//! [`IndependentAcceleration`] (f^i_ac), [`IndependentDynamics`] (f^i_dyn). Sensors:
//! [`Reading`] (f_sensor).
//!
//! The dynamics factors need ∂q̈/∂q and ∂q̈/∂q̇, which the paper took numerically. We
//! differentiate the augmented system [M Φ_qᵀ; Φ_q 0][q̈; λ] = [Q; c] instead: with
//! its LU factors already at hand for q̈, each Jacobian column costs one more pair of
//! triangular solves, against a full re-factorization per column (two per column for
//! central differences) for a numerical Jacobian — exact and several times cheaper.
//!
//! One file per family: `priors`, `integrator` (the [`Integrator`] and its two-point
//! factors), [`collocation`] (Hermite–Simpson), [`tangent`] (integrator factors
//! projected on the constraints' tangent space), `constraints`, `dynamics` (on the
//! [`DynamicsKernel`] of [`crate::dynamics`]), `independent` and `prescribed`;
//! what they share (the key accessor, the identity block) in `shared`.

pub mod collocation;
mod constraints;
mod dynamics;
mod independent;
mod integrator;
mod parametric;
mod prescribed;
mod priors;
mod reading;
mod shared;
pub mod tangent;

pub use crate::dynamics::{DynamicsKernel, KernelScratch};
pub use collocation::{HermitePosition, SimpsonVelocity, SimpsonVelocityThrough};
pub use constraints::{PositionConstraints, VelocityConstraints};
pub use dynamics::{Dynamics, ALONG_FROM};
pub use independent::{
    IndependentAcceleration, IndependentDynamics, IndependentPosition, IndependentVelocity,
};
pub use integrator::{Equality, Euler, Form, Integrator, Partials, Trapezoidal, TwoPoint};
pub use parametric::ParametricDynamics;
pub use prescribed::PrescribedMotion;
pub use priors::{ComponentPrior, Prior};
pub use reading::{InputReading, Reading};
pub(crate) use shared::{identity, key_accessor};
pub use tangent::Projected;
