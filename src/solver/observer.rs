//! Watching a solve: one record per iteration, handed to an [`Observer`] installed
//! on the solver ([`WindowSolver::observe`]). [`Trace`] prints them.

/// What one iteration of a window solve did.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Iteration {
    /// The window's steps k0..k1.
    pub k0: usize,
    pub k1: usize,
    /// 1-based iteration of this solve.
    pub iteration: usize,
    /// Whether the step came from the exact (Newton) model.
    pub newton: bool,
    /// The cost before the step, and at the trial point (None when it was not
    /// evaluated: a converged step, or one whose evaluation failed).
    pub cost: f64,
    pub trial: Option<f64>,
    /// LM's damping (0: a Gauss-Newton step).
    pub damping: f64,
    /// The decrease the linear model predicted.
    pub predicted: f64,
    /// max |δᵢ| / (1 + |xᵢ|).
    pub largest_step: f64,
    /// Whether the step was below the tolerance, and whether it kept the hard
    /// equations.
    pub small: bool,
    pub restored: bool,
    /// Whether the step was a chord step (the last linearization's model with the
    /// residuals at the new point; see `Settings::chord_test`).
    pub chord: bool,
}

/// Receives every iteration of every solve.
pub trait Observer: Send {
    fn iteration(&mut self, it: &Iteration);
}

/// Prints each iteration to standard error, one line each.
#[derive(Debug, Default)]
pub struct Trace;

impl Observer for Trace {
    fn iteration(&mut self, it: &Iteration) {
        eprintln!(
            "k0={} k1={} it={} newton={} cost={:.6e} trial={} mu={:.1e} pred={:.3e} |d|={:.2e} small={} restored={}{}",
            it.k0,
            it.k1,
            it.iteration,
            it.newton,
            it.cost,
            it.trial.map_or("-".into(), |c| format!("{c:.6e}")),
            it.damping,
            it.predicted,
            it.largest_step,
            it.small,
            it.restored,
            if it.chord { " chord" } else { "" }
        );
    }
}
