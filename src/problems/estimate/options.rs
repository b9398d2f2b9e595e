//! What an estimation run is asked to do ([`EstimateOptions`]) and the model's
//! uncertainty it weighs the readings against ([`Uncertainty`]).

use crate::coordinates::Coordinates;
use crate::error::{Error, Result};
use crate::factors::Integrator;
use crate::solver::Settings;

/// How the record is solved.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Smoothing {
    /// The fixed-lag smoother over the N newest steps: a step's estimate is final
    /// when it leaves the window.
    Window(usize),
    /// The whole record at once (started from a fixed-lag pass).
    Batch,
}

/// The solver's settings for an estimate: a step toward a reading far from the
/// guess moves along curved constraints (several corrections back onto them), and
/// the solve stops after a Gauss–Newton step that was to gain less than 10⁻³ of
/// the window's cost (about half its number of residuals): what is left after
/// it is far below one unit of χ², a change of the estimate well inside its σ,
/// not the round-off a simulation's step is solved to.
pub fn estimation_settings() -> Settings {
    let mut s = Settings {
        corrections: 20,
        // The first steps of a record may start far from the readings along a
        // direction they barely determine (the velocity from a rough start), where
        // the solve crawls before it converges.
        max_iterations: 200,
        end_on_flat_step: true,
        // Levenberg–Marquardt on the Gauss–Newton matrix throughout: where the
        // readings barely determine a direction (a start the gyroscope cannot yet
        // tell from an unknown torque), the exact Hessian is not positive definite
        // and its damped steps crawl along the valley the Gauss–Newton steps cross.
        second_order: false,
        // A window's older steps keep their Jacobians until they move by 1 % (see
        // `RELINEARIZE_BEYOND`).
        relinearize_beyond: Some(RELINEARIZE_BEYOND),
        ..Settings::default()
    };
    s.thresholds.flat_decrease = 1e-3;
    s
}

/// How far (relative) a fixed-lag window's step moves before its Jacobians are
/// made again ([`Settings::relinearize_beyond`]). On the benchmark four-bar with a
/// window of 50 steps, 1 % differentiates about a third of the window's factors
/// per solve, and the estimate moves by under 0.2 of its σ at any step (a median
/// of 10⁻⁶ of it); at 2 % and beyond, the stale Jacobians cost more Gauss–Newton
/// iterations than they save.
pub const RELINEARIZE_BEYOND: f64 = 0.01;

/// The window an estimate uses when none is asked.
pub const DEFAULT_WINDOW: usize = 20;

/// The window of the fixed-lag pass that starts a batch estimate, while it holds the
/// start of the record.
pub const BATCH_START_WINDOW: usize = DEFAULT_WINDOW;
/// The window of that pass once the readings have caught up with the start: a
/// filter, as its estimates only start the batch's solve (which converges to the
/// same optimum from a filter's path as from a 5-step window's, at half the cost).
pub const BATCH_PASS_WINDOW: usize = 1;

/// An estimation run's settings.
#[derive(Debug, Clone, PartialEq)]
pub struct EstimateOptions {
    pub coordinates: Coordinates,
    pub smoothing: Smoothing,
    /// The step; `None`: the readings' period.
    pub dt: Option<f64>,
    /// The rule between consecutive steps: the trapezoidal rule, or Hermite–Simpson
    /// (fourth order). `None`: [`default_integrator`].
    pub integrator: Option<Integrator>,
    pub settings: Settings,
}

impl Default for EstimateOptions {
    fn default() -> Self {
        EstimateOptions {
            coordinates: Coordinates::Dependent,
            smoothing: Smoothing::Window(DEFAULT_WINDOW),
            dt: None,
            integrator: None,
            settings: estimation_settings(),
        }
    }
}

impl EstimateOptions {
    /// The coordinates and the integrator the graph of `model`'s estimate is written
    /// in.
    pub fn motion(&self, model: &crate::model::Model) -> (Coordinates, Integrator) {
        let integrator = self.integrator.unwrap_or_else(|| default_integrator(model));
        (self.coordinates, integrator)
    }

    pub fn validate(&self) -> Result<()> {
        if let Smoothing::Window(0) = self.smoothing {
            return Err(Error::InvalidArgument(
                "the window must hold at least 1 step".into(),
            ));
        }
        if let Some(dt) = self.dt {
            if !(dt > 0.0 && dt.is_finite()) {
                return Err(Error::InvalidArgument(format!(
                    "dt must be positive and finite, got {dt}"
                )));
            }
        }
        self.settings.validate()
    }
}

/// σ of the dynamics factor when the scene gives no `process_sigma`, in the
/// coordinates' acceleration units (m/s², rad/s²), at a step of
/// [`DEFAULT_PROCESS_STEP`]: a model believed to about a third of gravity's effect.
/// The summary's NIS says whether it suits the record.
pub const DEFAULT_PROCESS_SIGMA: f64 = 3.0;
/// The step the default σ's are given for. At a step dt they are scaled by
/// √(this / dt): the process noise is a white-noise intensity, whose average over a
/// step has that σ, so that reading the same motion faster does not make the
/// estimate trust the model more (at 5 kHz the unscaled default left the truth
/// within ±2σ at 71 % of the steps of a four-bar's record, 87 % scaled).
pub const DEFAULT_PROCESS_STEP: f64 = 0.005;
/// σ of the dynamics factor when the scene declares unknown inputs or identified
/// parameters and no `process_sigma` (at [`DEFAULT_PROCESS_STEP`]): the inputs and the
/// parameters carry the model's error, the process noise only what they cannot (a
/// tenth of [`DEFAULT_PROCESS_SIGMA`]); with the default's σ the process noise would
/// explain much of what the inputs should.
pub const DEFAULT_PROCESS_SIGMA_WITH_INPUTS: f64 = 0.3;
/// σ of the prior on an initial position the scene does not name (m or rad): a start
/// known only roughly.
pub const DEFAULT_INITIAL_SIGMA: f64 = 1.0;
/// σ of the prior on an initial velocity the scene does not name (m/s or rad/s).
pub const DEFAULT_INITIAL_VELOCITY_SIGMA: f64 = 1.0;
/// σ of the prior on an unknown input's initial value (N or N·m): free.
pub const INPUT_INITIAL_SIGMA: f64 = 30.0;
/// The integrators hold the motion model to this fraction of one step's process
/// noise: the process noise, not the integration rule, is what lets the estimate
/// leave the model.
pub const INTEGRATOR_FRACTION: f64 = 1.0;
/// How many times tighter than the loosest prior on the start the integrators may
/// be held ([`Uncertainty::integrators`]): the information matrix then spans 10¹²,
/// whose factorization keeps about three digits of the weakest direction.
pub const RESOLVED_SPREAD: f64 = 1e6;

/// The integrator of an estimate that names none: Hermite–Simpson where the scene
/// identifies parameters, the trapezoidal rule otherwise. A parameter is fitted to a
/// whole record, so the trapezoidal rule's error at the step enters it as a bias that
/// more readings do not shrink (+0.5 % on a four-bar's crank mass at 5 ms, from a
/// record 10 s long); a state's estimate is dominated by the readings' noise, at half
/// the cost a step.
pub fn default_integrator(model: &crate::model::Model) -> Integrator {
    if model.parameters.is_some() {
        Integrator::HermiteSimpson
    } else {
        Integrator::Trapezoidal
    }
}

/// Whether the scene declares unknown inputs or identified parameters: they carry the
/// model's error, and the process noise only what they cannot.
pub fn carries_its_error(model: &crate::model::Model) -> bool {
    !model.estimation.inputs.is_empty() || model.parameters.is_some()
}

/// The model's uncertainty, resolved against a model: every σ the graph weighs.
#[derive(Debug, Clone, PartialEq)]
pub struct Uncertainty {
    /// σ of f_dyn (per coordinate of q̈).
    pub process: f64,
    /// σ of the prior on each q₀ and q̇₀ entry.
    pub initial_q: Vec<f64>,
    pub initial_dq: Vec<f64>,
    /// The unknown inputs: (coordinate of q, σ of their rate, per √s).
    pub inputs: Vec<(usize, f64)>,
    /// σ of the prior of each identified parameter, in `Model::parameters` order.
    pub parameters: Vec<f64>,
}

impl Uncertainty {
    /// The scene's `estimation:` section over the defaults, for a step `dt` (the
    /// default process σ's scaled to it: [`DEFAULT_PROCESS_STEP`]).
    pub fn of(model: &crate::model::Model, dt: f64) -> Self {
        let spec = &model.estimation;
        let mut u = Uncertainty::defaults(model.n());
        // (A record's step read from its times is the default's to rounding.)
        let at_step = if (dt / DEFAULT_PROCESS_STEP - 1.0).abs() < 1e-9 {
            1.0
        } else {
            (DEFAULT_PROCESS_STEP / dt).sqrt()
        };
        u.process = match (spec.process_sigma, carries_its_error(model)) {
            (Some(p), _) => p,
            (None, false) => DEFAULT_PROCESS_SIGMA * at_step,
            (None, true) => DEFAULT_PROCESS_SIGMA_WITH_INPUTS * at_step,
        };
        for &(i, s) in &spec.initial_sigma {
            u.initial_q[i] = s;
        }
        for &(i, s) in &spec.initial_velocity_sigma {
            u.initial_dq[i] = s;
        }
        u.inputs = spec.inputs.clone();
        u.parameters = model
            .scene
            .estimation
            .parameters
            .iter()
            .map(|(_, s)| *s)
            .collect();
        u
    }

    /// The defaults for a model of `n` coordinates.
    pub fn defaults(n: usize) -> Self {
        Uncertainty {
            process: DEFAULT_PROCESS_SIGMA,
            initial_q: vec![DEFAULT_INITIAL_SIGMA; n],
            initial_dq: vec![DEFAULT_INITIAL_VELOCITY_SIGMA; n],
            inputs: Vec::new(),
            parameters: Vec::new(),
        }
    }

    /// σ of the position and velocity integrators at step `dt`: one step's share of
    /// the process noise, ½σΔt² and σΔt, but never more than [`RESOLVED_SPREAD`]
    /// times tighter than the loosest prior on the start's positions or velocities.
    /// Tighter, the information matrix would hold entries of 1/σ² of the integrators
    /// beside the prior's 1/σ², and lose the directions only the prior and the
    /// readings determine to round-off (a small process σ, or readings at kilohertz
    /// rates); at the floor, a step's positions may leave the integrated motion by a
    /// millionth of the prior's σ, far below what any reading resolves.
    pub fn integrators(&self, dt: f64) -> [f64; 2] {
        let v = INTEGRATOR_FRACTION * self.process * dt;
        let loosest = |s: &[f64]| s.iter().fold(0.0f64, |a, &b| a.max(b)) / RESOLVED_SPREAD;
        [
            (0.5 * v * dt).max(loosest(&self.initial_q)),
            v.max(loosest(&self.initial_dq)),
        ]
    }
}
