//! The normal equations in the reduced unknowns of a window: H y = −g, block
//! tridiagonal, with Levenberg-Marquardt's damping, the Cholesky factor of the
//! damped H and the step y it gives. The linearization fills H and g; the iteration
//! damps, factors and solves them; the chord test and marginalization read them.

use crate::linalg::banded::{BandedCholesky, BlockTridiagonal};
use crate::linalg::dense::Summation;

/// H, g, their step and what making it takes, for windows of up to `capacity` steps
/// of `s` unknowns.
pub(super) struct NormalEquations {
    pub(super) h: BlockTridiagonal,
    pub(super) chol: BandedCholesky,
    pub(super) g: Vec<f64>,
    /// The step y of the last solve (`solve`), or one made from the rows.
    pub(super) delta: Vec<f64>,
    /// The diagonal added to H before it is factored.
    pub(super) damping: Vec<f64>,
    /// H y (`predicted_decrease`), or the gradient's change along a chord step.
    pub(super) hd: Vec<f64>,
    /// The linearization whose undamped Gauss–Newton H `chol` holds the factor of,
    /// if it does (so that covariances need not factor it again).
    pub(super) undamped_factor: Option<u64>,
}

impl NormalEquations {
    pub(super) fn new(capacity: usize, s: usize) -> Self {
        let n = capacity * s;
        NormalEquations {
            h: BlockTridiagonal::new(capacity, s),
            chol: BandedCholesky::new(capacity, s),
            g: vec![0.0; n],
            delta: vec![0.0; n],
            damping: vec![0.0; n],
            hd: vec![0.0; n],
            undamped_factor: None,
        }
    }

    /// How H's products and the factorization and its solves sum.
    pub(super) fn set_summation(&mut self, summation: Summation) {
        self.h.set_summation(summation);
        self.chol.set_summation(summation);
    }

    /// The step y = −H⁻¹g of the first `n` unknowns into `delta`, with the factor
    /// in `chol`.
    pub(super) fn solve(&mut self, n: usize) {
        for i in 0..n {
            self.delta[i] = -self.g[i];
        }
        self.chol.solve(&mut self.delta[..n]);
    }

    /// The decrease the linear model predicts for the soft factors along the reduced
    /// step y in `delta` (its first `n` unknowns): −gᵀy − ½yᵀHy.
    pub(super) fn predicted_decrease(&mut self, n: usize) -> f64 {
        self.h.multiply(&self.delta[..n], &mut self.hd[..n]);
        (0..n)
            .map(|i| -self.g[i] * self.delta[i] - 0.5 * self.delta[i] * self.hd[i])
            .sum()
    }
}
