//! The factors of the paper's section 6, each with closed-form Jacobians.
//!
//! Generic: [`Prior`] (f_prior), [`Equality`] (f_eq), [`Euler`] (f_ei),
//! [`Trapezoidal`] (f_ti). Dependent coordinates: [`PositionConstraints`] (f^d_pc),
//! [`VelocityConstraints`] (f^d_vc), [`Dynamics`] (f^d_dyn). Independent coordinates:
//! [`IndependentPosition`] (f^i_pc), [`IndependentVelocity`] (f^i_vc),
//! [`IndependentAcceleration`] (f^i_ac), [`IndependentDynamics`] (f^i_dyn).
//!
//! The dynamics factors need ∂q̈/∂q and ∂q̈/∂q̇, which the paper took numerically. We
//! differentiate the augmented system [M Φ_qᵀ; Φ_q 0][q̈; λ] = [Q; c] instead: with
//! its LU factors already at hand for q̈, each Jacobian column costs one more pair of
//! triangular solves, against a full re-factorization per column (two per column for
//! central differences) for a numerical Jacobian — exact and several times cheaper.

//!
//! One file per family: `priors`, `integrators`, `constraints`, `dynamics` (on the
//! [`DynamicsKernel`] of [`crate::dynamics`]), `independent` and `prescribed`.

mod constraints;
mod dynamics;
mod independent;
mod integrators;
mod prescribed;
mod priors;

pub use crate::dynamics::DynamicsKernel;
pub use constraints::{PositionConstraints, VelocityConstraints};
pub use dynamics::Dynamics;
pub use independent::{
    IndependentAcceleration, IndependentDynamics, IndependentPosition, IndependentVelocity,
};
pub use integrators::{Equality, Euler, Trapezoidal};
pub use prescribed::PrescribedMotion;
pub use priors::{ComponentPrior, Prior};

/// The `keys` and `noise` methods every factor here answers from its own fields.
macro_rules! key_and_noise_accessors {
    () => {
        fn keys(&self) -> &[Key] {
            &self.keys
        }
        fn noise(&self) -> &Noise {
            &self.noise
        }
    };
}
pub(crate) use key_and_noise_accessors;

/// Writes `scale`·I into a row-major d × d block.
pub(crate) fn identity(block: &mut [f64], d: usize, scale: f64) {
    block.fill(0.0);
    for i in 0..d {
        block[i * d + i] = scale;
    }
}

/// y = A x for a row-major rows × cols A.
fn mat_vec(a: &[f64], rows: usize, cols: usize, x: &[f64], y: &mut [f64]) {
    for i in 0..rows {
        y[i] = (0..cols).map(|j| a[i * cols + j] * x[j]).sum();
    }
}
