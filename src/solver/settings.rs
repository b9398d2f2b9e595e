//! The solver's settings: method, stopping rules and their thresholds, what the
//! past leaves to a fixed-lag window, and the report of one solve.

use super::*;

/// The nonlinear least-squares method.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Method {
    GaussNewton,
    LevenbergMarquardt,
}

/// Stopping rules. A solve stops when an undamped step satisfies
/// |δᵢ| ≤ `step_tolerance`·(1 + |xᵢ|) for every component, or restores the hard
/// factors within that tolerance and either is predicted to lower the cost by less
/// than [`Thresholds::flat_decrease`] of itself or fails to lower it while below
/// [`Thresholds::stall`] relative or predicting less than that fraction of it, or
/// when a damped step below the tolerance fails to lower the cost (converged: the
/// cost's round-off is reached), after `max_iterations` linear solves (iteration
/// limit), or when the cost is not finite or LM's damping exceeds
/// [`Thresholds::max_damping`] without progress (diverged).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Settings {
    pub method: Method,
    pub max_iterations: usize,
    pub step_tolerance: f64,
    /// LM's damping when a step first fails, relative to the diagonal of the normal
    /// equations (solves start undamped).
    pub initial_damping: f64,
    /// The fixed-lag smoother keeps each marginal prior on the tangent space of the
    /// hard equations of the step it informs ([`WindowSolver::project_prior`]): for
    /// graphs whose soft factors conflict with their hard ones (dependent coordinates).
    pub tangent_priors: bool,
    /// What the step leaving a fixed-lag window leaves to the steps after it.
    pub past: Past,
    /// Whether a solve whose Gauss-Newton steps converge linearly (or fail) goes on
    /// with the exact reduced Hessian ([`WindowSolver::exact_hessian`]). That helps a
    /// least-squares compromise with a residual (the paper's DC graph), whose
    /// Gauss-Newton matrix misses second-order terms; a graph with one equation per
    /// unknown has a zero residual, Gauss-Newton is Newton's method there, and the
    /// finite-difference Hessian only adds its error (the six-bar press in IC at
    /// 0.1 ms crawled from t = 0.021 s with it, and reaches 0.116 s without).
    pub second_order: bool,
    /// Corrections onto the hard equations after a step, each the least-norm step
    /// of the step's C from the residuals left, until they are below 10⁻¹⁰: one
    /// undoes the O(|δ|²) violation of a short step; a step of a few tenths of a
    /// unit along curved constraints (an estimate pulled toward a reading far from
    /// its guess) needs several.
    pub corrections: usize,
    /// Smallest 1/cond(H) (as the Cholesky factor's pivots bound it) at which a
    /// one-block window's Gauss-Newton step still comes from the normal equations;
    /// below it the step is the least-squares solution of J itself, whose condition
    /// is the square root of H's: a light crank against a stiff spring in
    /// independent coordinates makes J's 1e8 into H's 1e16, where the Cholesky step
    /// has no correct digit and the six-bar press's window solves wander for dozens
    /// of iterations.
    pub normal_equations_limit: f64,
    /// Whether a one-block window's solve, after an undamped Gauss-Newton step that
    /// lowered the cost, first tries the chord step (the last linearization's H and
    /// Jacobians with the residuals at the new point) and stops when it is below the
    /// tolerance, instead of linearizing again to find out. Only where no marginal
    /// prior is made from that linearization: a solve with the step before held,
    /// and every solve of a conditioned past (independent coordinates). Off: every
    /// convergence is decided on a fresh linearization.
    pub chord_test: bool,
    /// A fixed-lag window's step whose values moved less than this since its last
    /// linearization (each unknown relative to 1 + its size there) keeps that
    /// linearization in the window's next solves: its factors enter through their
    /// linear model, and only the newest steps and those that moved are evaluated
    /// again (iSAM2's fluid relinearization). `None`: every step of the window is
    /// linearized again for every solve. Windows of at least 3 steps, outside the
    /// batch, in a solve's first two iterations; for Gauss–Newton matrices
    /// (not with `second_order`).
    pub relinearize_beyond: Option<f64>,
    /// Whether a solve ends right after an undamped Gauss–Newton step that kept the
    /// hard equations and was to gain less than [`Thresholds::flat_decrease`] of the
    /// cost, without linearizing at its end: the convergence test passes there
    /// whatever the trial's cost, so that linearization would only report it. The
    /// point is corrected onto the hard equations; H and g stay those of the point
    /// before the step (an estimate's covariances come from them). Off: every
    /// solve ends on a linearization of its answer.
    pub end_on_flat_step: bool,
    /// Whether a step's size is measured against the largest entry of the variable
    /// it moves (a step's q̈, its forces) rather than against each entry: where one
    /// linear solve gives the whole vector (an inverse step's q̈ and Q from the
    /// augmented system), its small entries carry the round-off of its large ones.
    pub step_per_variable: bool,
    /// The iteration's finer thresholds.
    pub thresholds: Thresholds,
    /// Prints every iteration to standard error ([`Trace`]).
    pub trace: bool,
}

/// The thresholds inside the iteration, each named for what it decides. The
/// defaults are the values every test and report of the project runs with.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Thresholds {
    /// LM's damping of a direction is at least this times its damping scale (so a
    /// direction with no curvature is still damped).
    pub damping_floor: f64,
    /// Damping at which LM gives up (diverged).
    pub max_damping: f64,
    /// Damping below this is switched off after an accepted step.
    pub negligible_damping: f64,
    /// Ratio of actual to predicted decrease above which the next step is undamped.
    pub good_ratio: f64,
    /// An undamped step longer than this fraction of the one before, twice in a row,
    /// is linear convergence: the solve turns to the exact Hessian.
    pub slow_rate: f64,
    /// A predicted decrease below this fraction of the cost (with the hard equations
    /// restored) is convergence.
    pub flat_decrease: f64,
    /// A step that fails to lower the cost while it is below this (relative), or
    /// predicts less than this fraction of the cost, is convergence: the comparison
    /// only sees the residuals' round-off.
    pub stall: f64,
    /// Relative step of the exact Hessian's central differences.
    pub difference_step: f64,
    /// Halvings tried after an undamped step overshoots (1/2 … 1/2ⁿ).
    pub backtrack_halvings: usize,
    /// Singular values of a one-block window's reduced Jacobian below this fraction
    /// of the largest are taken as 0 by the least-squares step (round-off in J); so
    /// are those below max(rows, columns)·ε of it, the round-off of the SVD itself.
    pub least_squares_cutoff: f64,
}

impl Default for Thresholds {
    fn default() -> Self {
        Thresholds {
            damping_floor: 1e-12,
            max_damping: 1e16,
            negligible_damping: 1e-12,
            good_ratio: 0.75,
            slow_rate: 0.25,
            flat_decrease: 1e-12,
            stall: 1e-6,
            difference_step: 1e-6,
            backtrack_halvings: 8,
            least_squares_cutoff: 1e-14,
        }
    }
}

/// What marginalization leaves of the step that leaves a fixed-lag window.
///
/// The integrators are soft, so a marginal prior treats the phase of the motion as an
/// integrated random walk: its information along the motion falls like k⁻³ over a
/// run, while the second-order terms of f_dyn's residual grow with the speed (ω²).
/// Once they exceed it, the one direction the solve must find is the one the cost
/// barely sees: Gauss-Newton and even Newton converge linearly at rates near 1, and
/// the window solves stall (a motor-driven slider-crank at 13 rad/s after 2.6 s).
/// Conditioning on the leaving step, held at its estimate, keeps the integrators'
/// full information on the next step at every step of a run.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Past {
    /// The Schur complement: the exact Gaussian marginal of the linearized system
    /// (the paper's fixed-lag smoother).
    Marginalized,
    /// The factors joining the leaving step to the next, with the leaving step held
    /// at its estimate (a conditional density: H₁₁ and g₁ without the Schur term).
    Conditioned,
    /// Marginalized while the window solves converge; from the first that does not,
    /// that window is solved again after a conditioned prior, and so is every later
    /// one, as after a marginal that cannot be formed ([`crate::smoother::fixed_lag`]). Where the marginal prior works it keeps
    /// its smoothing (dependent coordinates: 1.6× lower RMSE on the chaotic double
    /// pendulum at 1 ms; identical in independent coordinates, whose graph
    /// is square).
    Adaptive,
}

impl Default for Settings {
    fn default() -> Self {
        Settings {
            method: Method::LevenbergMarquardt,
            max_iterations: 50,
            step_tolerance: 1e-8,
            initial_damping: 1e-4,
            tangent_priors: false,
            past: Past::Marginalized,
            second_order: true,
            corrections: 1,
            normal_equations_limit: 1e-10,
            chord_test: true,
            end_on_flat_step: false,
            relinearize_beyond: None,
            step_per_variable: false,
            thresholds: Thresholds::default(),
            trace: false,
        }
    }
}

impl Settings {
    /// Refuses settings that make no sense.
    pub fn validate(&self) -> Result<()> {
        if self.max_iterations == 0 {
            return Err(Error::InvalidArgument(
                "max_iterations must be at least 1".into(),
            ));
        }
        if !(self.step_tolerance > 0.0 && self.step_tolerance < 1.0) {
            return Err(Error::InvalidArgument(format!(
                "step_tolerance must be in (0, 1), got {}",
                self.step_tolerance
            )));
        }
        if let Some(b) = self.relinearize_beyond {
            if !(b > 0.0 && b < 1.0) {
                return Err(Error::InvalidArgument(format!(
                    "relinearize_beyond must be in (0, 1), got {b}"
                )));
            }
            if self.second_order {
                return Err(Error::InvalidArgument(
                    "relinearize_beyond keeps Gauss–Newton Jacobians, which the exact \
                     Hessian of second_order does not use: set one of them"
                        .into(),
                ));
            }
        }
        if !(self.initial_damping >= 0.0 && self.initial_damping.is_finite()) {
            return Err(Error::InvalidArgument(format!(
                "initial_damping must be ≥ 0, got {}",
                self.initial_damping
            )));
        }
        Ok(())
    }
}
