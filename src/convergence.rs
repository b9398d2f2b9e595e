//! How a solve ended: why it stopped, after how many iterations, at what cost, and
//! (where an evaluation failed) why.

/// Why a solve stopped.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Termination {
    Converged,
    IterationLimit,
    Diverged,
}

impl std::fmt::Display for Termination {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Termination::Converged => "converged",
            Termination::IterationLimit => "iteration limit",
            Termination::Diverged => "diverged",
        })
    }
}

/// The outcome of one solve.
#[derive(Debug, Clone, PartialEq)]
pub struct SolveReport {
    /// Linear solves performed.
    pub iterations: usize,
    /// Factorizations performed: one per linear solve for the general solver; a
    /// square step's simplified iterations reuse one.
    pub factorizations: usize,
    pub termination: Termination,
    /// ½ Σ‖whitened residual‖² at the returned estimate (prior included; hard
    /// factors weighted by 1/[`HARD_SIGMA`](crate::solver::HARD_SIGMA)).
    pub cost: f64,
    /// Why the factors could not be evaluated where the solve ended, when that is
    /// what stopped it (the message of the evaluation's error).
    pub cause: Option<String>,
}

impl SolveReport {
    /// A solve that stopped after `iterations` at `cost`.
    pub fn new(termination: Termination, iterations: usize, cost: f64) -> SolveReport {
        SolveReport {
            iterations,
            factorizations: iterations,
            termination,
            cost,
            cause: None,
        }
    }
}

impl std::fmt::Display for SolveReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{}, cost {:.3e} after {} iterations",
            self.termination, self.cost, self.iterations
        )?;
        if let Some(cause) = &self.cause {
            write!(f, " ({cause})")?;
        }
        Ok(())
    }
}
