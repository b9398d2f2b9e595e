//! What a forward run is asked: the coordinates, the step and horizon, the solve's
//! mode, the integrator and its factors, the noise models ([`ForwardOptions`]).

use crate::coordinates::Coordinates;
use crate::error::{Error, Result};
use crate::model::Model;
use crate::smoother::Mode;
use crate::solver::Observer;
use crate::solver::{Past, Settings};
use std::sync::Arc;

pub use crate::factors::Integrator;

/// What the integrator factors ask of a step in dependent coordinates.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DcIntegrators {
    /// [`DcIntegrators::Tangent`]; a step that fails with them from every substep
    /// guess is taken by the paper's [`DcIntegrators::Full`], that step only
    /// ([`RunSummary::paper_steps`](super::summary::RunSummary::paper_steps)).
    Auto,
    /// Only along the directions the constraints leave free (see [`crate::factors::tangent`]):
    /// one soft equation per unknown, all of them satisfied, so that every window
    /// length and the batch have the solution of N_w = 1.
    Tangent,
    /// On all n coordinates, as in the paper: 2m more equations than unknowns per
    /// step, solved as a least-squares compromise weighted by the σ's.
    Full,
}

/// Standard deviations of the soft factors. Constraint factors (f_pc, f_vc, f^i_ac)
/// and the priors on the initial state are hard: the solver satisfies them exactly
/// (see [`crate::solver`]), so they have no σ.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NoiseModels {
    /// σ of the integrator of velocities into positions.
    pub integrator_position: f64,
    /// σ of the integrator of accelerations into velocities.
    pub integrator_velocity: f64,
    /// σ of f_dyn.
    pub dynamics: f64,
    /// σ of the weak f_eq between consecutive q (IC only).
    pub equality: f64,
    /// σ of the approximate prior on q₀ (IC), on its dependent entries.
    pub initial_q: f64,
}

impl NoiseModels {
    /// The paper's Table 2, which lists covariances: σ = √(10⁻²) for the integrators,
    /// √(10⁻⁴) for f_dyn, √(10²) for f_eq, √1 for the dependent entries of q₀.
    pub fn paper() -> Self {
        NoiseModels {
            integrator_position: 0.1,
            integrator_velocity: 0.1,
            dynamics: 0.01,
            equality: 10.0,
            initial_q: 1.0,
        }
    }

    fn validate(&self) -> Result<()> {
        for (name, v) in [
            ("integrator_position", self.integrator_position),
            ("integrator_velocity", self.integrator_velocity),
            ("dynamics", self.dynamics),
            ("equality", self.equality),
            ("initial_q", self.initial_q),
        ] {
            if !(v > 0.0 && v.is_finite()) {
                return Err(Error::InvalidArgument(format!(
                    "noise σ {name} must be positive, got {v}"
                )));
            }
        }
        Ok(())
    }
}

impl Default for NoiseModels {
    /// The defaults that give the best accuracy (see `docs/accuracy.md`): the paper's
    /// values but for f_eq, which pulls every q_k towards q_{k−1} and so brakes the
    /// motion, so it is all but switched off here (σ = 1e6). The branch is kept by the
    /// Newton iteration on the hard constraints, which starts every step from the
    /// previous one.
    fn default() -> Self {
        NoiseModels {
            integrator_position: 0.01,
            integrator_velocity: 0.01,
            dynamics: 0.1,
            equality: 1e6,
            ..NoiseModels::paper()
        }
    }
}

/// Everything a forward run needs besides the model.
#[derive(Debug, Clone, PartialEq)]
pub struct ForwardOptions {
    pub coordinates: Coordinates,
    pub dt: f64,
    pub t_end: f64,
    pub mode: Mode,
    pub integrator: Integrator,
    /// The integrator factors of dependent coordinates (IC is unaffected).
    pub dc_integrators: DcIntegrators,
    pub noise: NoiseModels,
    pub settings: Settings,
    /// Go on after a step whose solve did not converge (it is still reported).
    pub continue_on_failure: bool,
    /// Where a step fails because it is too coarse for the motion (a body turns more
    /// than [`StepFailure::LARGE_TURN`](super::failure::StepFailure::LARGE_TURN) a step), integrate the run again at a step
    /// `dt / factor` and keep every `factor`-th state, so that the output stays on the
    /// grid asked for ([`RunSummary::refinement`](super::summary::RunSummary::refinement) says so).
    pub refine: bool,
    /// Take each step of an IC run, or of a DC run with tangent integrators, with
    /// the trapezoidal rule or Euler as the sparse square system it is (the square
    /// step), where it can (away from singular configurations, and in IC without
    /// redundant constraints); `false` sends every step through the general solver
    /// with the window or batch asked, for comparison. The solution is the same to
    /// the step tolerance.
    pub square_steps: bool,
    /// Makes an observer of every iteration for each solver of the run's steps
    /// (the square step's, the general solver's windows and batch; not a rescue's
    /// substeps): how a program or a test watches the solves without parsing
    /// `--trace-solver`'s lines.
    pub observer: Option<Observers>,
    /// Steps sized by the accuracy asked, instead of a fixed step: each step's size
    /// chosen from its estimated local error, the rows still written at t = k·`dt`
    /// (interpolated between the steps taken). One step at a time only (N_w = 1).
    pub tolerance: Option<super::error_control::Tolerance>,
    /// What the tolerance bounds: the rows written (checked, and the run made again
    /// at a tighter step tolerance where they miss it), or each step's error only.
    pub tolerance_scope: super::run_check::ToleranceScope,
}

/// A maker of [`Observer`]s, one per solver a run makes.
#[derive(Clone)]
pub struct Observers(pub Arc<dyn Fn() -> Box<dyn Observer> + Send + Sync>);

impl Observers {
    pub fn new(make: impl Fn() -> Box<dyn Observer> + Send + Sync + 'static) -> Self {
        Observers(Arc::new(make))
    }

    pub(super) fn make(&self) -> Box<dyn Observer> {
        (self.0)()
    }
}

impl std::fmt::Debug for Observers {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Observers")
    }
}

impl PartialEq for Observers {
    fn eq(&self, other: &Self) -> bool {
        Arc::ptr_eq(&self.0, &other.0)
    }
}

impl ForwardOptions {
    pub fn new(coordinates: Coordinates, dt: f64, t_end: f64, mode: Mode) -> Self {
        ForwardOptions {
            coordinates,
            dt,
            t_end,
            mode,
            integrator: Integrator::Trapezoidal,
            dc_integrators: DcIntegrators::Auto,
            noise: NoiseModels::default(),
            // Marginal priors while they carry the solves, then conditioned (see [`Past`]).
            settings: Settings {
                past: Past::Adaptive,
                ..Settings::default()
            },
            continue_on_failure: false,
            refine: true,
            square_steps: true,
            observer: None,
            tolerance: None,
            tolerance_scope: Default::default(),
        }
    }

    /// Number of steps including t = 0: t_k = k·dt for k = 0..=round(t_end/dt)
    /// (for options that [`validate`](Self::validate) accepts).
    pub fn steps(&self) -> usize {
        crate::limits::step_count(self.dt, self.t_end).unwrap_or(0)
    }

    /// Refuses options that make no sense, with the reason.
    pub(super) fn validate_options(&self, model: &Model) -> Result<()> {
        let bad = |m: String| Err(Error::InvalidArgument(m));
        if !(self.dt > 0.0 && self.dt.is_finite()) {
            return bad(format!(
                "the time step must be positive, got {}",
                crate::io::number(self.dt)
            ));
        }
        if !(self.t_end.is_finite() && self.t_end >= self.dt) {
            return bad(format!(
                "the end time must be at least one step (dt = {} s), got {}",
                crate::io::number(self.dt),
                crate::io::number(self.t_end)
            ));
        }
        crate::limits::step_count(self.dt, self.t_end)?;
        if let Mode::FixedLag(0) = self.mode {
            return bad("the window must hold at least 1 step".into());
        }
        if self.coordinates == Coordinates::Independent {
            if model.independent.is_empty() {
                return bad(format!(
                    "{}: independent coordinates (--coords ic) need `independent: [...]` in the scene",
                    model.scene.file
                ));
            }
            if model.independent.len() != model.dof() {
                return bad(format!(
                    "{}: {} independent coordinate(s) declared for {} degrees of freedom",
                    model.scene.file,
                    model.independent.len(),
                    model.dof()
                ));
            }
        }
        if self.tolerance.is_some() {
            self.validate_tolerance()?;
        }
        self.noise.validate()?;
        self.settings.validate()
    }

    /// Refuses a tolerance with options its error-controlled steps do not take.
    fn validate_tolerance(&self) -> Result<()> {
        let bad = |m: &str| Err(Error::InvalidArgument(format!("rtol: {m}")));
        if self.mode != Mode::FixedLag(1) {
            return bad("error-controlled steps are taken one at a time: a window or a batch is not taken with a tolerance");
        }
        if self.coordinates == Coordinates::Dependent && self.dc_integrators == DcIntegrators::Full
        {
            return bad("error-controlled steps hold every step's equations exactly: not with the paper's integrator factors (dc integrators full)");
        }
        if self.settings.past == Past::Marginalized {
            return bad("error-controlled steps are each solved given the step before: not with a marginalized past");
        }
        Ok(())
    }
}
