//! The uncertainty of a window's estimate: the marginal covariance of each step,
//! from the normal equations at the estimate (the inverse of the Gauss–Newton
//! Hessian, its diagonal blocks only).

use super::structure::{Scope, Span};
use super::{LinearPrior, WindowSolver};
use crate::error::{Error, Result};
use crate::graph::ChainGraph;

/// Which steps of a window a covariance call gives.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Marginals {
    /// Every step's.
    Every,
    /// The window's first and last steps' (a fixed-lag estimator's final and newest
    /// estimates); the others are left empty.
    Ends,
}

impl WindowSolver {
    /// The marginal covariance of every step k0..k1 (`window`) of the estimate in `values`, with
    /// `prior` on step k0: the factors are linearized at `values`, H is factored
    /// undamped, and H⁻¹'s diagonal block of each step (in its reduced unknowns y,
    /// δx = p + N y) is mapped to the step's variables, Σ_x = N Σ_y Nᵀ: the hard
    /// equations hold exactly, so the covariance lies in their null space.
    /// `out[b]` is row-major s × s for step k0 + b (empty for a step `marginals`
    /// leaves out).
    ///
    /// [`WindowSolver::covariances_after_solve`] reads the last solve's
    /// linearization instead, when the solve has just ended on this window.
    pub fn covariances(
        &mut self,
        graph: &ChainGraph,
        values: &[f64],
        window: std::ops::Range<usize>,
        prior: Option<&LinearPrior>,
        marginals: Marginals,
        out: &mut Vec<Vec<f64>>,
    ) -> Result<()> {
        let (k0, k1) = (window.start, window.end);
        if k1 <= k0 || k1 - k0 > self.normal.h.capacity() {
            return Err(Error::InvalidArgument(format!(
                "window {k0}..{k1} is empty or larger than the solver's capacity {}",
                self.normal.h.capacity()
            )));
        }
        let span = Span {
            k0,
            k1,
            prior,
            scope: Scope::Window { held: false },
        };
        self.evaluate(graph, values, span, true)?;
        self.covariances_of_linearization(graph, k0, marginals, out)
    }

    /// [`WindowSolver::covariances`] from the linearization the last solve of the
    /// window k0..k1 ended on (at its estimate, or at the point of its last step, a
    /// step below the solve's tolerance away): one linearization of the window
    /// fewer. Only right directly after a converged `solve` of that window.
    pub fn covariances_after_solve(
        &mut self,
        graph: &ChainGraph,
        k0: usize,
        k1: usize,
        marginals: Marginals,
        out: &mut Vec<Vec<f64>>,
    ) -> Result<()> {
        if self.normal.h.blocks() != k1 - k0 {
            return Err(Error::InvalidArgument(format!(
                "the last solve was not of the window {k0}..{k1}"
            )));
        }
        self.covariances_of_linearization(graph, k0, marginals, out)
    }

    fn covariances_of_linearization(
        &mut self,
        graph: &ChainGraph,
        k0: usize,
        marginals: Marginals,
        out: &mut Vec<Vec<f64>>,
    ) -> Result<()> {
        let factored = self.normal.undamped_factor == Some(self.lin.generation);
        if !factored {
            self.normal
                .chol
                .factor(&self.normal.h, &[])
                .map_err(|(block, _)| Error::Singular {
                    what: "the estimate's information matrix is not positive definite: \
                       the readings and the model leave a direction of the motion \
                       undetermined"
                        .into(),
                    step: Some(self.structure.run_step(k0 + block)),
                    t: Some(crate::trajectory::round_time(self.time(graph, k0 + block))),
                })?;
        }
        // Σ_y of the blocks asked, in `out` (its buffers reused from call to call), then
        // each mapped in place: Σ_x = N Σ_y Nᵀ, with Σ_y, N and NΣ_y in `scratch`.
        match marginals {
            Marginals::Every => self.normal.chol.inverse_diagonal_blocks(out),
            Marginals::Ends => self.normal.chol.inverse_end_blocks(out),
        }
        let s = self.s;
        let last = out.len().saturating_sub(1);
        for (b, cov) in out.iter_mut().enumerate() {
            if marginals == Marginals::Ends && b != 0 && b != last {
                cov.clear();
                continue;
            }
            let red = &self.lin.hard[b].reduction;
            let d = red.dim;
            let (sigma_y, rest) = self.scratch.split_at_mut(s * s);
            let (basis, rest) = rest.split_at_mut(s * s);
            let ns = &mut rest[..s * d];
            sigma_y[..d * d].copy_from_slice(&cov[..d * d]);
            red.basis_into(basis);
            ns.fill(0.0);
            for i in 0..s {
                for l in 0..d {
                    let a = basis[i * d + l];
                    if a != 0.0 {
                        for j in 0..d {
                            ns[i * d + j] += a * sigma_y[l * d + j];
                        }
                    }
                }
            }
            cov.clear();
            cov.resize(s * s, 0.0);
            for i in 0..s {
                for j in 0..=i {
                    let v: f64 = (0..d).map(|l| ns[i * d + l] * basis[j * d + l]).sum();
                    cov[i * s + j] = v;
                    cov[j * s + i] = v;
                }
            }
        }
        Ok(())
    }
}
