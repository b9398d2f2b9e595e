//! Forward dynamics as factor graphs (paper, sections 4.1, 4.2 and 5): the graph in
//! dependent coordinates (DC) and in independent coordinates (IC), and a simulation
//! run over a horizon by the fixed-lag smoother or in batch.

use crate::dynamics;
use crate::error::{Error, Result};
use crate::factors::*;
use crate::graph::{ChainGraph, Factor, Layout, Noise, VarKind};
use crate::linalg::dense;

use crate::collocation;
use crate::model::{Model, PointSlot, State};
use crate::smoother::{self, Mode, Next};
use crate::solver::{Past, Settings, SolveReport, Termination};
use crate::tangent::{Projected, Rule};
use nalgebra::DVector;
use std::ops::ControlFlow;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// The coordinates the graph integrates.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Coordinates {
    /// Dependent (natural) coordinates q.
    Dependent,
    /// Independent coordinates z ⊂ q, with q recovered by the position problem.
    Independent,
}

/// The integrator factor between consecutive steps.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Integrator {
    Trapezoidal,
    Euler,
    /// Hermite–Simpson collocation, fourth order ([`crate::collocation`]).
    HermiteSimpson,
}

/// What the integrator factors ask of a step in dependent coordinates.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DcIntegrators {
    /// The paper's ([`DcIntegrators::Full`]); a run in which a solve fails with them
    /// (not at an ill-posed configuration, not interrupted; a batch solve: within
    /// [`AUTO_BATCH_ITERATIONS`]) is run again with [`DcIntegrators::Tangent`], and
    /// [`RunSummary::tangent_after`] says so.
    Auto,
    /// Only along the directions the constraints leave free (see [`crate::tangent`]):
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
    /// motion; at σ = 10 it costs the IC four-bar four orders of magnitude of
    /// accuracy (RMSE 3.7e-2 m, the paper's 1.7e-2 m, against 2.6e-6 m). The branch
    /// is kept by the Newton iteration on the hard constraints, which starts every
    /// step from the previous one.
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
    /// than [`StepFailure::LARGE_TURN`] a step), integrate the run again at a step
    /// `dt / factor` and keep every `factor`-th state, so that the output stays on the
    /// grid asked for ([`RunSummary::refinement`] says so).
    pub refine: bool,
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
        }
    }

    /// Whether the graph has one soft equation per unknown (IC, and DC with tangent
    /// integrators): its residual is zero at the solution, where Gauss-Newton is
    /// Newton's method ([`Settings::second_order`] is then of no use).
    pub fn is_square(&self) -> bool {
        self.coordinates == Coordinates::Independent || self.tangent_dc()
    }

    /// Whether the integrator factors of dependent coordinates are projected on the
    /// tangent space: asked for, or Hermite–Simpson under `auto` (its full factors'
    /// least-squares compromise costs windows two orders of accuracy, and a retry
    /// would gain nothing).
    pub fn tangent_dc(&self) -> bool {
        self.dc_integrators == DcIntegrators::Tangent
            || (self.dc_integrators == DcIntegrators::Auto
                && self.integrator == Integrator::HermiteSimpson)
    }

    /// Whether a DC run whose full integrator factors fail is made again with
    /// tangent ones ([`DcIntegrators::Auto`] with the trapezoidal rule or Euler).
    fn retries_tangent(&self) -> bool {
        self.coordinates == Coordinates::Dependent
            && self.dc_integrators == DcIntegrators::Auto
            && !self.tangent_dc()
    }

    /// Number of steps including t = 0: t_k = k·dt for k = 0..=round(t_end/dt)
    /// (for options that [`validate`](Self::validate) accepts).
    pub fn steps(&self) -> usize {
        crate::limits::step_count(self.dt, self.t_end).unwrap_or(0)
    }

    /// Bytes a run of `model` with these options holds at its peak, roughly: the
    /// variables of every step and the trajectory built from them, the window's
    /// linear system, and for a batch solve the system of the whole horizon.
    pub fn memory_estimate(&self, model: &Model) -> f64 {
        let n = model.n() as f64;
        let s = 3.0 * (n + model.independent.len() as f64);
        let steps = self.steps() as f64;
        let per_step_system = 8.0 * s * (3.0 * s + 2.0 * model.m() as f64) * 4.0;
        let solved = match self.mode {
            Mode::FixedLag(w) => (w as f64).min(steps) + 1.0,
            Mode::Batch => steps,
        };
        8.0 * steps * (s + 3.0 * n) * 2.0 + per_step_system * solved
    }

    /// Refuses options that make no sense, with the reason.
    pub fn validate(&self, model: &Model) -> Result<()> {
        let bad = |m: String| Err(Error::InvalidArgument(m));
        if !(self.dt > 0.0 && self.dt.is_finite()) {
            return bad(format!("the time step must be positive, got {}", self.dt));
        }
        if !(self.t_end.is_finite() && self.t_end >= self.dt) {
            return bad(format!(
                "the end time must be at least one step (dt = {}), got {}",
                self.dt, self.t_end
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
        self.noise.validate()?;
        self.settings.validate()?;
        crate::limits::ensure_fits(
            &format!(
                "a run of {} steps of {} coordinates",
                self.steps(),
                model.n()
            ),
            self.memory_estimate(model),
        )
    }
}

/// The graph of a forward problem, with its layout.
pub struct ForwardGraph {
    pub graph: ChainGraph,
    pub coordinates: Coordinates,
    n: usize,
    f: usize,
}

impl ForwardGraph {
    /// Builds the DC or IC graph for `model` (initial priors from its initial state).
    pub fn new(model: Arc<Model>, options: &ForwardOptions) -> Result<Self> {
        options.validate(&model)?;
        let (n, f) = (model.n(), model.independent.len());
        let nm = options.noise;
        let dt = options.dt;
        let init = &model.initial;
        let hard = Noise::Hard;
        let integrate = |x: VarKind, dx: VarKind, dim: usize, sigma: f64| -> Box<dyn Factor> {
            match options.integrator {
                Integrator::Trapezoidal | Integrator::HermiteSimpson => {
                    Box::new(Trapezoidal::new(x, dx, dim, dt, Noise::Isotropic(sigma)))
                }
                Integrator::Euler => Box::new(Euler::new(x, dx, dim, dt, Noise::Isotropic(sigma))),
            }
        };
        let dc_integrate = |x: VarKind, dx: VarKind, sigma: f64| -> Box<dyn Factor> {
            let rule = match options.integrator {
                Integrator::Trapezoidal | Integrator::HermiteSimpson => Rule::Trapezoidal,
                Integrator::Euler => Rule::Euler,
            };
            match options.dc_integrators {
                DcIntegrators::Tangent => Box::new(Projected::integrator(
                    model.clone(),
                    x,
                    dx,
                    rule,
                    dt,
                    Noise::Isotropic(sigma),
                )),
                DcIntegrators::Full | DcIntegrators::Auto => integrate(x, dx, n, sigma),
            }
        };
        // The position and velocity integrators of each coordinate set.
        let hermite = (options.integrator == Integrator::HermiteSimpson).then_some(|independent| {
            let sigma = [nm.integrator_position, nm.integrator_velocity];
            collocation::factors(&model, independent, dt, sigma)
        });
        let dc_integrators = || -> [Box<dyn Factor>; 2] {
            match &hermite {
                Some(factors) if options.tangent_dc() => factors(false)
                    .map(|f| Box::new(Projected::new(model.clone(), f)) as Box<dyn Factor>),
                Some(factors) => factors(false),
                None => [
                    dc_integrate(VarKind::Q, VarKind::Dq, nm.integrator_position),
                    dc_integrate(VarKind::Dq, VarKind::Ddq, nm.integrator_velocity),
                ],
            }
        };
        let ic_integrators = || -> [Box<dyn Factor>; 2] {
            match &hermite {
                Some(factors) => factors(true),
                None => [
                    integrate(VarKind::Z, VarKind::Dz, f, nm.integrator_position),
                    integrate(VarKind::Dz, VarKind::Ddz, f, nm.integrator_velocity),
                ],
            }
        };
        let graph = match options.coordinates {
            Coordinates::Dependent => ChainGraph {
                layout: Layout::new(&[(VarKind::Q, n), (VarKind::Dq, n), (VarKind::Ddq, n)]),
                dt,
                t0: 0.0,
                step_factors: [
                    Box::new(PositionConstraints::new(model.clone(), hard.clone()))
                        as Box<dyn Factor>,
                    Box::new(VelocityConstraints::new(model.clone(), hard.clone())),
                    Box::new(Dynamics::new(model.clone(), Noise::Isotropic(nm.dynamics))),
                ]
                .into_iter()
                .chain(dc_integrators())
                .collect(),
                initial_factors: vec![
                    Box::new(Prior::new(
                        VarKind::Q,
                        init.q.as_slice().to_vec(),
                        hard.clone(),
                    )),
                    Box::new(Prior::new(
                        VarKind::Dq,
                        init.dq.as_slice().to_vec(),
                        hard.clone(),
                    )),
                ],
            },
            Coordinates::Independent => {
                let z0: Vec<f64> = model.independent.iter().map(|&i| init.q[i]).collect();
                let dz0: Vec<f64> = model.independent.iter().map(|&i| init.dq[i]).collect();
                // Table 2: covariance 1 on the dependent entries, 10⁻³ on those in z.
                let mut sig = vec![nm.initial_q; n];
                for &i in &model.independent {
                    sig[i] = 1e-3f64.sqrt() * nm.initial_q;
                }
                ChainGraph {
                    layout: Layout::new(&[
                        (VarKind::Q, n),
                        (VarKind::Dq, n),
                        (VarKind::Ddq, n),
                        (VarKind::Z, f),
                        (VarKind::Dz, f),
                        (VarKind::Ddz, f),
                    ]),
                    dt,
                    t0: 0.0,
                    step_factors: [
                        Box::new(IndependentPosition::new(model.clone(), hard.clone()))
                            as Box<dyn Factor>,
                        Box::new(IndependentVelocity::new(model.clone(), hard.clone())),
                        Box::new(IndependentAcceleration::new(model.clone(), hard.clone())),
                        Box::new(IndependentDynamics::new(
                            model.clone(),
                            Noise::Isotropic(nm.dynamics),
                        )),
                    ]
                    .into_iter()
                    .chain(ic_integrators())
                    .chain([
                        Box::new(Equality::new(VarKind::Q, n, Noise::Isotropic(nm.equality)))
                            as Box<dyn Factor>,
                    ])
                    .collect(),
                    initial_factors: vec![
                        Box::new(Prior::new(VarKind::Z, z0, hard.clone())),
                        Box::new(Prior::new(VarKind::Dz, dz0, hard.clone())),
                        Box::new(Prior::new(
                            VarKind::Q,
                            init.q.as_slice().to_vec(),
                            Noise::Diagonal(sig),
                        )),
                    ],
                }
            }
        };
        Ok(ForwardGraph {
            graph,
            coordinates: options.coordinates,
            n,
            f,
        })
    }

    /// The initial guess of step 0: the model's initial state and its accelerations.
    fn initial_block(&self, model: &Model) -> Result<Vec<f64>> {
        let init = &model.initial;
        let ddq = dynamics::lagrange(model, &init.q, &init.dq, self.graph.t0)?.ddq;
        let mut block = Vec::with_capacity(self.graph.layout.size());
        block.extend_from_slice(init.q.as_slice());
        block.extend_from_slice(init.dq.as_slice());
        block.extend_from_slice(ddq.as_slice());
        if self.coordinates == Coordinates::Independent {
            for v in [&init.q, &init.dq, &ddq] {
                block.extend(model.independent.iter().map(|&i| v[i]));
            }
        }
        Ok(block)
    }

    /// Guess of step k from the steps before by a Taylor step,
    /// x + Δt ẋ + Δt²/2 ẍ + Δt³/6 j, ẋ + Δt ẍ + Δt²/2 j, ẍ + Δt j, with the jerk j
    /// from the last two accelerations (0 at step 1). A cubic guess lands the first
    /// Newton step within the tolerance more often than a quadratic one.
    fn predict(&self, values: &mut [f64], k: usize) {
        let s = self.graph.layout.size();
        let dt = self.graph.dt;
        let (prev, next) = values.split_at_mut(k * s);
        let older = (k >= 2).then(|| &prev[(k - 2) * s..(k - 1) * s]);
        let prev = &prev[(k - 1) * s..];
        let next = &mut next[..s];
        let triples: &[(usize, usize)] = if self.coordinates == Coordinates::Independent {
            &[(0, self.n), (3 * self.n, self.f)]
        } else {
            &[(0, self.n)]
        };
        for &(off, d) in triples {
            for i in 0..d {
                let (x, v, a) = (prev[off + i], prev[off + d + i], prev[off + 2 * d + i]);
                let j = older.map_or(0.0, |o| (a - o[off + 2 * d + i]) / dt);
                next[off + i] = x + dt * v + 0.5 * dt * dt * a + dt * dt * dt / 6.0 * j;
                next[off + d + i] = v + dt * a + 0.5 * dt * dt * j;
                next[off + 2 * d + i] = a + dt * j;
            }
        }
    }
}

/// A simulated motion: for each time, q, q̇ and q̈ in model order.
#[derive(Debug, Clone, PartialEq)]
pub struct Trajectory {
    pub names: Vec<String>,
    pub t: Vec<f64>,
    /// Row-major samples × n.
    pub q: Vec<f64>,
    pub dq: Vec<f64>,
    pub ddq: Vec<f64>,
}

impl Trajectory {
    pub fn len(&self) -> usize {
        self.t.len()
    }

    pub fn is_empty(&self) -> bool {
        self.t.is_empty()
    }

    pub fn n(&self) -> usize {
        self.names.len()
    }

    /// Every `stride`-th sample (0, stride, 2·stride, …), on the grid t_j = j·dt.
    pub fn every(&self, stride: usize, dt: f64) -> Trajectory {
        let n = self.n();
        let rows: Vec<usize> = (0..self.len()).step_by(stride.max(1)).collect();
        let pick = |v: &[f64]| {
            rows.iter()
                .flat_map(|&r| &v[r * n..(r + 1) * n])
                .copied()
                .collect()
        };
        Trajectory {
            names: self.names.clone(),
            t: (0..rows.len()).map(|j| j as f64 * dt).collect(),
            q: pick(&self.q),
            dq: pick(&self.dq),
            ddq: pick(&self.ddq),
        }
    }

    /// Keeps the first `len` samples.
    pub fn truncate(&mut self, len: usize) {
        let n = self.n();
        self.t.truncate(len);
        for v in [&mut self.q, &mut self.dq, &mut self.ddq] {
            v.truncate(len * n);
        }
    }

    /// Appends `other` but its first sample (the state this one ends with).
    fn append_after_first(&mut self, other: &Trajectory) {
        let n = self.n();
        self.t.extend_from_slice(other.t.get(1..).unwrap_or(&[]));
        for (v, o) in [
            (&mut self.q, &other.q),
            (&mut self.dq, &other.dq),
            (&mut self.ddq, &other.ddq),
        ] {
            v.extend_from_slice(o.get(n..).unwrap_or(&[]));
        }
    }

    pub fn q_at(&self, k: usize) -> &[f64] {
        &self.q[k * self.n()..(k + 1) * self.n()]
    }

    pub fn dq_at(&self, k: usize) -> &[f64] {
        &self.dq[k * self.n()..(k + 1) * self.n()]
    }
}

/// A step at which the run failed: its solve did not converge, or (independent
/// coordinates) the motion approached a configuration where they stop determining
/// the other coordinates.
#[derive(Debug, Clone, PartialEq)]
pub struct StepFailure {
    pub step: usize,
    pub t: f64,
    pub report: SolveReport,
    /// σ_r/σ₁ of Φ_q at the step's configuration, scaled by the coordinates' scales and
    /// row-normalized, r the constraints' rank at the start: near 0 where the
    /// mechanism approaches a singular configuration.
    pub constraint_conditioning: f64,
    /// Set when the run stopped because the independent coordinates approach a
    /// configuration where they do not determine the others (the step's own solve
    /// converged; `report` is its report).
    pub singular: Option<SingularConfiguration>,
    /// Set when the step failed in the one-step run that starts a batch solve.
    pub warm_start: bool,
    /// Set when the batch solve of the whole horizon failed (`step` is its last).
    pub batch: bool,
    /// Where the cost went non-finite: the effect that cannot be evaluated there.
    pub cause: Option<String>,
    /// The body that turns fastest over this step, from the velocities and
    /// accelerations of the step before: its name and its turn per step (rad). The
    /// message names it when the turn is more than [`StepFailure::LARGE_TURN`].
    pub fast_body: Option<(String, f64)>,
}

/// A configuration ahead where the independent coordinates z stop determining the
/// other coordinates' velocities: Φ_q restricted to the dependent coordinates
/// (square, m_active × (n − f)) loses a rank, so the matrix R of q̇ = R ż does not
/// exist there and the graph in independent coordinates is ill-posed. Found from its
/// distance to rank loss s ([`Determinacy`]) falling below
/// [`Determinacy::STOP_BELOW`].
#[derive(Debug, Clone, PartialEq)]
pub struct SingularConfiguration {
    /// Where s extrapolates to 0, linearly from this step and the one before (this
    /// step's time where s was not falling).
    pub t_singular: f64,
    /// s at the step where the run stopped.
    pub distance: f64,
    /// The rank the dependent block keeps there (singular values of its normalized
    /// rows above 10 s) and its full rank (the number of dependent coordinates).
    pub rank: usize,
    pub full_rank: usize,
    pub independent: Vec<String>,
    pub dependent: Vec<String>,
}

impl StepFailure {
    /// A turn per step (rad) beyond which a failure names the fastest body: the
    /// integrators relate positions by straight chords, and past about one radian a
    /// step the implicit equations of a coarse step stop having a nearby solution.
    pub const LARGE_TURN: f64 = 0.5;

    /// The run's time step: t_k = k·Δt for every step of a run.
    pub fn dt(&self) -> f64 {
        self.t / self.step.max(1) as f64
    }

    /// The reason for the failure, naming the step and the time (not what was
    /// written).
    pub fn message(&self) -> String {
        let t = round_time(self.t);
        match &self.singular {
            Some(c) => format!(
                "singular configuration at t ≈ {:.6} s (extrapolated): independent coordinates \
                 [{}] stop determining [{}] (rank {} < {}); stopped at step {} (t = {t} s), \
                 distance to rank loss {:.1e}",
                c.t_singular,
                c.independent.join(", "),
                crate::expr::abbreviated(&c.dependent),
                c.rank,
                c.full_rank,
                self.step,
                c.distance
            ),
            None => {
                let singular = if self.constraint_conditioning < 1e-2 {
                    format!(
                        "; Φ_q is close to losing rank there (σ_r/σ₁ = {:.1e}): a singular \
                         configuration",
                        self.constraint_conditioning
                    )
                } else {
                    String::new()
                };
                let stage = if self.warm_start {
                    "in the one-step run that starts the batch solve, "
                } else {
                    ""
                };
                if self.batch && self.cause.is_none() {
                    return format!(
                        "the batch solve of {} steps (t = 0 to {t} s) did not converge: {}, cost \
                         {:.3e} after {} iterations{singular}",
                        self.step + 1,
                        self.report.termination,
                        self.report.cost,
                        self.report.iterations
                    );
                }
                if let Some(cause) = &self.cause {
                    return format!(
                        "{stage}step {} (t = {t} s) cannot be solved: {cause}",
                        self.step
                    );
                }
                let turn = match &self.fast_body {
                    Some((body, per_step)) if *per_step > Self::LARGE_TURN => format!(
                        "; body {body} turns about {per_step:.2} rad over the step: the step is \
                         too coarse for the motion (dt below {:.2e} s keeps it under {} rad)",
                        self.dt() * Self::LARGE_TURN / per_step,
                        Self::LARGE_TURN
                    ),
                    _ => String::new(),
                };
                format!(
                    "{stage}step {} (t = {t} s) did not converge: {}, cost {:.3e} after {} \
                     iterations{singular}{turn}",
                    self.step, self.report.termination, self.report.cost, self.report.iterations
                )
            }
        }
    }
}

/// A time for messages: t₀ + k·Δt carries round-off (1.2690000000000001).
pub fn round_time(t: f64) -> f64 {
    (t * 1e9).round() / 1e9
}

/// How well the independent coordinates determine the others at q, without
/// allocating: the distance to rank loss s = (tr G⁻¹)^(−1/2) of Φ_q restricted to
/// the dependent coordinates, G = D̂D̂ᵀ with D̂ its active rows normalized.
/// √(λ_min(G)/m) ≤ s ≤ √λ_min(G): s is the smallest singular value of D̂ to within a
/// factor √m, and 0 where a rank is lost.
pub struct Determinacy {
    dependent: Vec<usize>,
    jac: Vec<f64>,
    column_norms: Vec<f64>,
    rows: Vec<f64>,
    chol: Vec<f64>,
    linv: Vec<f64>,
}

impl Determinacy {
    /// Where the coordinates in use determine the others less well than this and
    /// worse from step to step (or will at the next step, extrapolated), a run in
    /// independent coordinates looks for a better set. The pick-and-place robot's
    /// motor angles start just above it and head for s = 0 at t ≈ 0.33 s, while
    /// Φ_q's smallest row-normalized singular value only dips from 2.5e-2 to 4.6e-3
    /// at 0.4 s and recovers: the run switches three times and passes.
    pub const SEARCH_BELOW: f64 = 5e-3;

    /// A run switches to the best set where it determines the others this many times
    /// better than the set in use (so that it does not switch back at once).
    pub const SWITCH_GAIN: f64 = 1.5;

    /// A solve in independent coordinates that fails while s, falling, extrapolates
    /// to 0 within this many steps, and no set of coordinates does materially better
    /// ([`Determinacy::SWITCH_GAIN`]), is reported as the singular configuration
    /// ahead: the N four-bar under gravity fails 13 steps (1 ms) before its flat
    /// point, at s = 0.034, above [`Determinacy::STOP_BELOW`]. A failure where s is
    /// already below [`Determinacy::SEARCH_BELOW`] is attributed whatever the number
    /// of steps: at fine steps (the parallelogram at 0.01 ms fails 140 steps, 1.4 ms,
    /// before its flat point, at s = 4.2e-3) steps are no measure of the distance.
    pub const ATTRIBUTE_WITHIN: f64 = 20.0;

    /// ... and only where s is below this: a violent transient at a coarse step
    /// (a six-bar press whose crank reaches 350 rad/s within 20 ms, at 1 ms) makes s
    /// fall fast from 0.08 in a mechanism that has no singular configuration, and the
    /// extrapolation alone would name one.
    pub const ATTRIBUTE_BELOW: f64 = 0.05;

    /// A run in independent coordinates stops where even the best set's s falls
    /// below this: Φ_q itself is about to lose a rank, and no choice of coordinates
    /// helps. Approaching the parallelogram's flat configuration the solves in
    /// independent coordinates fail a step or two before the flat point; the run
    /// stops 0.6 ms (at 3 rad/s, Δt = 1 ms) ahead of it with its steps sound, and
    /// at coarse steps (5–20 ms), where s falls past the threshold in one step, where
    /// its linear extrapolation crosses 0 within the next step.
    pub const STOP_BELOW: f64 = 2.5e-3;

    pub fn new(model: &Model) -> Self {
        let dependent: Vec<usize> = (0..model.n())
            .filter(|i| !model.independent.contains(i))
            .collect();
        let ma = model.active.len();
        let mut det = Determinacy {
            jac: vec![0.0; model.m() * model.n()],
            column_norms: vec![1.0; model.n()],
            rows: vec![0.0; ma * dependent.len()],
            chol: vec![0.0; ma * ma],
            linv: vec![0.0; ma * ma],
            dependent,
        };
        det.set_column_scales(model, model.initial.q.as_slice());
        det
    }

    /// s at q: 0 where the dependent block has lost a rank (or is not square).
    pub fn distance(&mut self, model: &Model, q: &[f64]) -> f64 {
        self.jacobian(model, q);
        let dependent = std::mem::take(&mut self.dependent);
        let s = self.distance_over(model, &dependent);
        self.dependent = dependent;
        s
    }

    /// The set of independent coordinates that determines the others best at q, and
    /// its distance to rank loss s: over every set where there are at most 2000,
    /// else by swaps of one coordinate from the current set while s improves. Where
    /// even the best s is small, Φ_q itself is close to losing a rank.
    pub fn best(&mut self, model: &Model, q: &[f64]) -> (f64, Vec<usize>) {
        let (n, f) = (model.n(), model.independent.len());
        self.jacobian(model, q);
        let mut best = (
            self.distance_over(model, &complement(n, &model.independent)),
            model.independent.clone(),
        );
        let consider = |det: &mut Determinacy, set: &[usize], best: &mut (f64, Vec<usize>)| {
            let s = det.distance_over(model, &complement(n, set));
            if s > best.0 {
                *best = (s, set.to_vec());
            }
        };
        if binomial(n, f) <= 2000 {
            let mut set: Vec<usize> = (0..f).collect();
            loop {
                consider(self, &set, &mut best);
                // The next f-subset of 0..n in lexicographic order.
                let Some(i) = (0..f).rev().find(|&i| set[i] < n - f + i) else {
                    break;
                };
                set[i] += 1;
                for j in i + 1..f {
                    set[j] = set[j - 1] + 1;
                }
            }
        } else {
            loop {
                let before = best.0;
                let current = best.1.clone();
                for i in 0..f {
                    for c in (0..n).filter(|c| !current.contains(c)) {
                        let mut set = current.clone();
                        set[i] = c;
                        set.sort_unstable();
                        consider(self, &set, &mut best);
                    }
                }
                if best.0 <= before {
                    break;
                }
            }
        }
        best
    }

    fn jacobian(&mut self, model: &Model, q: &[f64]) {
        model.jacobian_into(q, &mut self.jac);
    }

    /// The norms of Φ_q's columns over the active rows at q (1 for a column without
    /// entries): the coordinates' scales, taken once at the initial configuration so
    /// that a column that shrinks towards a singular configuration is not rescaled.
    ///
    /// A point's x and y columns are scaled by no less than the root mean square of
    /// the two: a point placed level with its neighbour has an x column as small as
    /// that link (2·length from its distance equation alone) and a y column of 1 (its
    /// angle equation's), and scaling them apart made a 1 cm link that turned by
    /// 0.2 rad read as a rank loss three times closer than it was.
    fn set_column_scales(&mut self, model: &Model, q: &[f64]) {
        self.jacobian(model, q);
        let n = model.n();
        let squares: Vec<f64> = (0..n)
            .map(|c| {
                model
                    .active
                    .iter()
                    .map(|&k| self.jac[k * n + c].powi(2))
                    .sum()
            })
            .collect();
        let mut scale = squares.clone();
        for slot in &model.points {
            if let PointSlot::Free(x) = *slot {
                let both = 0.5 * (squares[x] + squares[x + 1]);
                scale[x] = squares[x].max(both);
                scale[x + 1] = squares[x + 1].max(both);
            }
        }
        for (norm, sq) in self.column_norms.iter_mut().zip(scale) {
            *norm = if sq > 0.0 { sq.sqrt() } else { 1.0 };
        }
    }

    /// s of Φ_q (in `self.jac`) restricted to the columns `dependent`.
    fn distance_over(&mut self, model: &Model, dependent: &[usize]) -> f64 {
        let (n, ma, d) = (model.n(), model.active.len(), dependent.len());
        if ma != d {
            return 0.0;
        }
        if ma == 0 {
            return f64::INFINITY;
        }
        for (r, &k) in model.active.iter().enumerate() {
            let row = &mut self.rows[r * d..(r + 1) * d];
            for (o, &c) in row.iter_mut().zip(dependent) {
                *o = self.jac[k * n + c];
            }
            // Columns scaled by the coordinates' scales (mixed units and sizes: a
            // 7 mm crank's angle column is 100× smaller than its points'), rows by
            // their whole scaled row: an equation whose dependent part vanishes (a
            // point on a crank at the top of its circle, with its y independent) no
            // longer determines them, whatever the size of that part.
            for (o, &c) in row.iter_mut().zip(dependent) {
                *o /= self.column_norms[c];
            }
            let norm = (0..n)
                .map(|c| (self.jac[k * n + c] / self.column_norms[c]).powi(2))
                .sum::<f64>()
                .sqrt();
            if !(norm > 0.0) {
                return 0.0;
            }
            row.iter_mut().for_each(|v| *v /= norm);
        }
        let (rows, g) = (&self.rows, &mut self.chol);
        for i in 0..ma {
            for j in 0..=i {
                g[i * ma + j] = (0..d).map(|c| rows[i * d + c] * rows[j * d + c]).sum();
            }
        }
        if dense::cholesky(g, ma).is_err() {
            return 0.0;
        }
        // tr G⁻¹ = ‖L⁻¹‖_F², L⁻¹ (lower triangular) column by column.
        let linv = &mut self.linv;
        let mut trace = 0.0;
        for j in 0..ma {
            for i in j..ma {
                let mut v = if i == j { 1.0 } else { 0.0 };
                for k in j..i {
                    v -= g[i * ma + k] * linv[k * ma + j];
                }
                v /= g[i * ma + i];
                linv[i * ma + j] = v;
                trace += v * v;
            }
        }
        trace.recip().sqrt()
    }

    /// The report of a run stopped at q (time t, distance s) with the step before
    /// at q0 (t0, s0): where s extrapolates to 0, and the rank kept there.
    ///
    /// The rank is what is left where the scaled dependent block's singular values,
    /// each extrapolated linearly from q0 and q to that time, have not fallen to a
    /// tenth of their value at q: a chain of N loops loses N ranks together at its
    /// flat configuration, whose singular values fall at different rates, and a
    /// count of those already small at the stop saw 5 of 40. Where s is not falling
    /// (no time to extrapolate to), those below 10 s at q are counted as lost.
    fn singular_configuration(
        &mut self,
        model: &Model,
        q0: &[f64],
        q: &[f64],
        (t0, s0): (f64, f64),
        (t, s): (f64, f64),
    ) -> SingularConfiguration {
        let t_singular = if s0 > s {
            t + s * (t - t0) / (s0 - s)
        } else {
            t
        };
        let d = self.dependent.len();
        let singular_values = |det: &mut Self, at: &[f64]| -> Option<Vec<f64>> {
            det.distance(model, at);
            let rows = nalgebra::DMatrix::from_row_slice(model.active.len(), d, &det.rows);
            // nalgebra's SVD does not return on a non-finite matrix.
            rows.iter().all(|v| v.is_finite()).then(|| {
                let mut sv: Vec<f64> = rows.singular_values().iter().copied().collect();
                sv.sort_by(|a, b| b.total_cmp(a));
                sv
            })
        };
        let before = singular_values(self, q0);
        let now = singular_values(self, q);
        let rank = match (before, now) {
            (Some(before), Some(now)) if t_singular > t && t > t0 => {
                let ahead = (t_singular - t) / (t - t0);
                let lost = now
                    .iter()
                    .zip(&before)
                    .filter(|(&v, &v0)| v + (v - v0) * ahead <= 0.1 * v)
                    .count();
                d - lost.max(1)
            }
            (_, Some(now)) => now.iter().filter(|&&v| v > 10.0 * s).count(),
            _ => 0,
        };
        let names = |idx: &mut dyn Iterator<Item = usize>| -> Vec<String> {
            idx.map(|i| model.names[i].clone()).collect()
        };
        SingularConfiguration {
            t_singular,
            distance: s,
            rank,
            full_rank: d,
            independent: names(&mut model.independent.iter().copied()),
            dependent: names(&mut self.dependent.iter().copied()),
        }
    }
}

/// The first step whose state is not finite (a solve that "converged" on an
/// overflowing force), as a failure naming the cause; an error when it is the
/// initial state.
fn first_non_finite(model: &Model, tr: &Trajectory) -> Result<Option<StepFailure>> {
    let n = tr.n();
    let finite = |k: usize| {
        tr.q_at(k)
            .iter()
            .chain(tr.dq_at(k))
            .chain(&tr.ddq[k * n..(k + 1) * n])
            .all(|v| v.is_finite())
    };
    let Some(k) = (0..tr.len()).find(|&k| !finite(k)) else {
        return Ok(None);
    };
    let (q, dq) = if k > 0 {
        (tr.q_at(k - 1), tr.dq_at(k - 1))
    } else {
        (tr.q_at(0), tr.dq_at(0))
    };
    let cause = model.effect_fault(q, dq, tr.t[k]).unwrap_or_else(|| {
        "the state is not finite: the forces or the accelerations overflow".into()
    });
    if k == 0 {
        return Err(Error::Singular(format!(
            "{}: the initial state cannot be used: {cause}",
            model.scene.file
        )));
    }
    Ok(Some(StepFailure {
        step: k,
        t: tr.t[k],
        report: SolveReport {
            iterations: 0,
            termination: Termination::Diverged,
            cost: f64::INFINITY,
        },
        constraint_conditioning: 1.0,
        singular: None,
        warm_start: false,
        batch: false,
        cause: Some(cause),
        fast_body: None,
    }))
}

/// The coordinates of 0..n not in `set`.
fn complement(n: usize, set: &[usize]) -> Vec<usize> {
    (0..n).filter(|i| !set.contains(i)).collect()
}

/// n choose k, saturating.
fn binomial(n: usize, k: usize) -> usize {
    (0..k.min(n)).fold(1usize, |acc, i| acc.saturating_mul(n - i) / (i + 1))
}

/// σ_r/σ₁ of Φ_q(q), r = the number of independent constraints at the start, scale-free:
/// its active rows, columns scaled by their norms at the initial configuration (the
/// coordinates' scales: mm-size links and angles in radians weigh alike), each row
/// then normalized. Raw, a well-conditioned mechanism with a 7 mm crank reads 1e-4.
fn constraint_conditioning(model: &Model, q: &[f64]) -> f64 {
    let r = model.active.len();
    if r == 0 {
        return 1.0;
    }
    let active = |q: &[f64]| {
        let jac = model.jacobian(&nalgebra::DVector::from_column_slice(q));
        nalgebra::DMatrix::from_fn(r, model.n(), |i, c| jac[(model.active[i], c)])
    };
    let initial = active(model.initial.q.as_slice());
    let mut a = active(q);
    for (c, scale) in initial.column_iter().map(|col| col.norm()).enumerate() {
        if scale > 0.0 {
            a.column_mut(c).unscale_mut(scale);
        }
    }
    for mut row in a.row_iter_mut() {
        let norm = row.norm();
        if norm > 0.0 {
            row.unscale_mut(norm);
        }
    }
    if !a.iter().all(|v| v.is_finite()) {
        // Not a configuration (nalgebra's SVD would not return on it).
        return 0.0;
    }
    let mut sv: Vec<f64> = a.singular_values().iter().copied().collect();
    sv.sort_by(|a, b| b.total_cmp(a));
    if sv[0] > 0.0 {
        sv.get(r - 1).copied().unwrap_or(0.0) / sv[0]
    } else {
        0.0
    }
}

/// What a run reports beside its trajectory.
#[derive(Debug, Clone, PartialEq)]
pub struct RunSummary {
    pub steps: usize,
    pub wall_time: Duration,
    /// Mean and max linear solves per window solve (per step for the smoother).
    pub mean_iterations: f64,
    pub max_iterations: usize,
    /// max |Φ| and max |Φ_q q̇| over the trajectory.
    pub worst_phi: f64,
    pub worst_velocity_constraint: f64,
    /// max |E(t) − E(0)| when the scene is conservative.
    pub energy_drift: Option<f64>,
    /// The largest kinetic energy along the trajectory: the scale of the drift.
    pub peak_kinetic_energy: f64,
    pub failures: Vec<StepFailure>,
    /// With [`Past::Adaptive`], the step from which the smoother conditioned on its
    /// past: its window solve had not converged after a marginal prior.
    pub conditioned_from: Option<(usize, f64)>,
    /// In independent coordinates, where the run switched to another set.
    pub reselections: Vec<Reselection>,
    /// Set (to the last step kept) when the caller interrupted the run.
    pub interrupted: Option<usize>,
    /// With [`DcIntegrators::Auto`]: the failure with the paper's integrator factors
    /// after which this run was made again with tangent ones.
    pub tangent_after: Option<StepFailure>,
    /// With [`ForwardOptions::refine`]: the finer step this run was integrated at.
    pub refinement: Option<Refinement>,
}

/// A run integrated at a finer step than asked for, because a step at the coarser one
/// failed while a body turned more than [`StepFailure::LARGE_TURN`] per step. The
/// trajectory keeps every `factor`-th state: the grid asked for. Steps named in the
/// summary's failures and counts are steps of the finer grid.
#[derive(Debug, Clone, PartialEq)]
pub struct Refinement {
    /// Internal steps per step asked for.
    pub factor: usize,
    /// The internal step, dt / factor.
    pub dt: f64,
    /// The failure at the step asked for (or at the previous refinement).
    pub after: StepFailure,
}

impl Refinement {
    /// The most internal steps per step asked for: beyond it the motion is not what
    /// makes the steps fail, or the run would be too long to be what the user meant.
    pub const MAX_FACTOR: usize = 1024;
    /// The turn per internal step the factor aims at: half of
    /// [`StepFailure::LARGE_TURN`], for motions that speed up after the step measured.
    pub const TARGET_TURN: f64 = 0.25;
    /// A failed step over which no body turns this much (rad) is not refined: its
    /// failure has another cause than the step's size against the motion.
    pub const MIN_TURN: f64 = 0.05;
}

/// A switch of the independent coordinates during a run: at `step` the coordinates in
/// use were approaching a configuration where they stop determining the others,
/// while Φ_q kept its rank.
#[derive(Debug, Clone, PartialEq)]
pub struct Reselection {
    pub step: usize,
    pub t: f64,
    pub from: Vec<String>,
    pub to: Vec<String>,
}

/// Simulates the model's motion. `progress(done, total)` is called after each step.
pub fn simulate(
    model: Arc<Model>,
    options: &ForwardOptions,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<(Trajectory, RunSummary)> {
    simulate_interruptible(model, options, &mut |done, total| {
        progress(done, total);
        ControlFlow::Continue(())
    })
}

/// [`simulate`], where `progress` returning `Break` after a step ends the run there
/// (a user's Ctrl-C): the steps solved so far are returned, and
/// [`RunSummary::interrupted`] names the last one. A batch solve is interrupted only
/// during its one-step start, and then returns no step.
///
/// In independent coordinates the run goes in segments: where the coordinates in use
/// approach a configuration where they stop determining the others while Φ_q keeps
/// its rank, the segment ends at the current step and the next one starts there with
/// a well-conditioned set chosen from q ([`Determinacy::reselect`]), conditioned on
/// that step's state (its graph's initial priors), as generalized coordinate
/// partitioning does. Where Φ_q itself loses rank no set helps: the run stops.
pub fn simulate_interruptible(
    model: Arc<Model>,
    options: &ForwardOptions,
    progress: &mut dyn FnMut(usize, usize) -> ControlFlow<()>,
) -> Result<(Trajectory, RunSummary)> {
    let (mut trajectory, mut summary) = simulate_integrators(model.clone(), options, progress)?;
    if !options.refine {
        return Ok((trajectory, summary));
    }
    // A step too coarse for the motion: the implicit equations of a step over which a
    // body turns a radian or more have no nearby solution, at any window. The run is
    // made again at a step that keeps the turn near TARGET_TURN, as many times as the
    // finer run still fails that way, and the output stays on the grid asked for.
    let mut factor: usize = 1;
    // The unsampled motion of the last refined run, for the check of its turns.
    let mut fine: Option<(Trajectory, f64)> = None;
    while summary.interrupted.is_none() {
        let failure = match summary.failures.first() {
            Some(f) if f.singular.is_none() => f.clone(),
            Some(_) => break,
            // A run that converged while a body turned more than LARGE_TURN a step
            // converged to a poor answer (Andrews' squeezer at 1 ms, 0.9-1.3 rad a
            // step, ended 7e-4 m off where its failed 5 ms run, refined, ended 5e-5
            // m off); so does a finer run whose motion sped up after the step the
            // first failure measured: both are refined from that step.
            None => {
                let (tr, dt) = fine
                    .as_ref()
                    .map_or((&trajectory, options.dt), |(tr, dt)| (tr, *dt));
                match coarse_turn(&model, tr, dt) {
                    Some(f) => f,
                    None => break,
                }
            }
        };
        let turn = match &failure.fast_body {
            Some((_, turn)) if *turn >= Refinement::MIN_TURN => *turn,
            _ => break,
        };
        let more = ((turn / Refinement::TARGET_TURN).ceil() as usize).max(2);
        let next = factor.saturating_mul(more);
        if next > Refinement::MAX_FACTOR {
            break;
        }
        factor = next;
        let mut finer = options.clone();
        finer.dt = options.dt / factor as f64;
        finer.t_end = (options.steps().saturating_sub(1) * factor) as f64 * finer.dt;
        let (fine_trajectory, mut fine_summary) =
            simulate_integrators(model.clone(), &finer, progress)?;
        fine_summary.wall_time += summary.wall_time;
        fine_summary.refinement = Some(Refinement {
            factor,
            dt: finer.dt,
            after: failure,
        });
        trajectory = fine_trajectory.every(factor, options.dt);
        fine_summary.steps = trajectory.len();
        summary = fine_summary;
        fine = Some((fine_trajectory, finer.dt));
    }
    Ok((trajectory, summary))
}

/// The first step of a converged run over which a body turned more than
/// [`StepFailure::LARGE_TURN`], as a failure to refine from (its solve converged).
fn coarse_turn(model: &Model, trajectory: &Trajectory, dt: f64) -> Option<StepFailure> {
    (0..trajectory.len()).find_map(|k| {
        let (body, omega) = model.fastest_body(trajectory.q_at(k), trajectory.dq_at(k))?;
        let turn = omega * dt;
        (turn > StepFailure::LARGE_TURN).then(|| StepFailure {
            step: k + 1,
            t: trajectory.t[k] + dt,
            report: SolveReport {
                iterations: 0,
                termination: Termination::Converged,
                cost: 0.0,
            },
            constraint_conditioning: 1.0,
            singular: None,
            warm_start: false,
            batch: false,
            cause: None,
            fast_body: Some((body, turn)),
        })
    })
}

/// One run at `options.dt`; with [`DcIntegrators::Auto`], made again with tangent
/// integrators where the paper's do not converge.
fn simulate_integrators(
    model: Arc<Model>,
    options: &ForwardOptions,
    progress: &mut dyn FnMut(usize, usize) -> ControlFlow<()>,
) -> Result<(Trajectory, RunSummary)> {
    let (trajectory, summary) = simulate_with(model.clone(), options, progress)?;
    let retry = options.retries_tangent()
        && summary.interrupted.is_none()
        && summary.failures.iter().all(|f| f.singular.is_none());
    let Some(failure) = summary.failures.first().filter(|_| retry) else {
        return Ok((trajectory, summary));
    };
    // The paper's factors ask more equations than a step has unknowns; where their
    // least-squares compromise does not converge, the tangent ones (one equation per
    // unknown) usually do.
    let failure = failure.clone();
    let mut tangent = options.clone();
    tangent.dc_integrators = DcIntegrators::Tangent;
    let first_attempt = summary.wall_time;
    let (trajectory, mut summary) = simulate_with(model, &tangent, progress)?;
    summary.tangent_after = Some(failure);
    summary.wall_time += first_attempt;
    Ok((trajectory, summary))
}

fn simulate_with(
    model: Arc<Model>,
    options: &ForwardOptions,
    progress: &mut dyn FnMut(usize, usize) -> ControlFlow<()>,
) -> Result<(Trajectory, RunSummary)> {
    options.validate(&model)?;
    let total = options.steps();
    let start = Instant::now();
    let mut run = Run::default();
    let mut trajectory: Option<Trajectory> = None;
    let mut segment_model = model.clone();
    let mut first = 0;
    loop {
        let seg = segment(
            segment_model.clone(),
            options,
            first,
            total,
            progress,
            &mut run,
        )?;
        let next = seg.reselect.filter(|_| run.interrupted.is_none());
        match trajectory.as_mut() {
            None => trajectory = Some(seg.trajectory),
            Some(tr) => tr.append_after_first(&seg.trajectory),
        }
        let Some((k, independent)) = next else { break };
        let tr = trajectory.as_ref().expect("a segment was run");
        run.reselections.push(Reselection {
            step: k,
            t: round_time(tr.t[k]),
            from: names_of(&model, &segment_model.independent),
            to: names_of(&model, &independent),
        });
        let mut next_model = (*segment_model).clone();
        next_model.independent = independent;
        next_model.initial.q = nalgebra::DVector::from_column_slice(tr.q_at(k));
        next_model.initial.dq = nalgebra::DVector::from_column_slice(tr.dq_at(k));
        // The rest of the run continues from step k (its row is kept from this
        // segment; the next segment's first row is the same state).
        trajectory.as_mut().unwrap().truncate(k + 1);
        segment_model = Arc::new(next_model);
        first = k;
    }
    let mut trajectory = trajectory.expect("a segment was run");
    if let Some(f) = first_non_finite(&model, &trajectory)? {
        // Keep the steps before it; the step itself is a failure, named.
        trajectory.truncate(f.step);
        run.failures.retain(|g| g.step < f.step);
        run.failures.push(f);
    }
    let wall_time = start.elapsed();
    let mut summary = summarize(
        &model,
        &trajectory,
        wall_time,
        &run.iterations,
        run.failures,
    )?;
    summary.conditioned_from = run.conditioned_from;
    summary.reselections = run.reselections;
    summary.interrupted = run.interrupted;
    Ok((trajectory, summary))
}

fn names_of(model: &Model, idx: &[usize]) -> Vec<String> {
    idx.iter().map(|&i| model.names[i].clone()).collect()
}

/// What the segments of a run add up.
#[derive(Default)]
struct Run {
    iterations: Vec<usize>,
    failures: Vec<StepFailure>,
    conditioned_from: Option<(usize, f64)>,
    reselections: Vec<Reselection>,
    interrupted: Option<usize>,
}

/// A segment's motion, and where (global step) and to which independent coordinates
/// the next segment switches.
struct Segment {
    trajectory: Trajectory,
    reselect: Option<(usize, Vec<usize>)>,
}

/// Steps first..total of a run with `model` (its initial state is step `first`'s).
fn segment(
    model: Arc<Model>,
    options: &ForwardOptions,
    first: usize,
    total: usize,
    progress: &mut dyn FnMut(usize, usize) -> ControlFlow<()>,
    run: &mut Run,
) -> Result<Segment> {
    let mut fg = ForwardGraph::new(model.clone(), options)?;
    fg.graph.t0 = first as f64 * options.dt;
    let steps = total - first;
    let s = fg.graph.layout.size();
    let mut values = vec![0.0; steps * s];
    values[..s].copy_from_slice(&fg.initial_block(&model)?);
    let mut completed = steps;
    let mut reselect = None;
    let n = model.n();
    // The body turning fastest over step k: its turn estimated from the step
    // before's velocities and accelerations (the rate at mid-step), so that a run
    // from rest is measured too.
    let fast_body = |k: usize, v: &[f64]| {
        let before = &v[k.checked_sub(1)? * s..k * s];
        let mid: Vec<f64> = (0..n)
            .map(|i| before[n + i] + 0.5 * options.dt * before[2 * n + i])
            .collect();
        let (body, omega) = model.fastest_body(&before[..n], &mid)?;
        Some((body, omega * options.dt))
    };
    let failure = |k: usize, report: &SolveReport, v: &[f64]| {
        let q = &v[k * s..k * s + n];
        // A non-finite cost: look for the effect that cannot be evaluated, at the
        // step's state or, where that is not finite, at the step before's.
        let cause = (!report.cost.is_finite()).then(|| {
            let at = |j: usize| (&v[j * s..j * s + n], &v[j * s + n..j * s + 2 * n]);
            let (mut qk, mut dqk) = at(k);
            if !qk.iter().chain(dqk).all(|x| x.is_finite()) {
                (qk, dqk) = at(k.saturating_sub(1));
            }
            model.effect_fault(qk, dqk, fg.graph.time(k))
        });
        StepFailure {
            step: first + k,
            t: fg.graph.time(k),
            report: *report,
            constraint_conditioning: constraint_conditioning(&model, q),
            singular: None,
            warm_start: false,
            batch: false,
            cause: cause.flatten(),
            fast_body: fast_body(k, v),
        }
    };
    match options.mode {
        Mode::FixedLag(window) => {
            // In independent coordinates, how well z determines the rest, step by step.
            let mut determinacy = (options.coordinates == Coordinates::Independent).then(|| {
                let far = (0.0, f64::INFINITY);
                (Determinacy::new(&model), far, far)
            });
            let mut failures = Vec::new();
            let mut iterations = Vec::new();
            let mut conditioned_from = None;
            let mut interrupted = None;
            let settings = Settings {
                // The DC graph's integrators conflict with its constraints.
                tangent_priors: options.coordinates == Coordinates::Dependent,
                // Independent coordinates and tangent integrators leave every step with
                // as many equations as unknowns: a marginal prior adds nothing to the
                // next step's solution (each window has N_w = 1's) but its
                // linearization about the step's prediction; the exact conditional is
                // the step's own solution, and the batch's. In a stiff transient that
                // linearization's error is no longer small: Andrews' squeezer in IC
                // ended 0.1 rad off at dt = 50 µs with marginal priors, 7.8e-4 rad
                // with conditioned ones (and a batch of the mm slider-crank at 1 ms
                // had a cost of 6.3 to remove from the marginal run's start).
                past: if options.is_square() && options.settings.past == Past::Adaptive {
                    Past::Conditioned
                } else {
                    options.settings.past
                },
                second_order: options.settings.second_order && !options.is_square(),
                ..options.settings
            };
            smoother::fixed_lag_with_rescue(
                &fg.graph,
                &mut values,
                steps,
                window,
                settings,
                |v, k| fg.predict(v, k),
                |v, k| fg.substep_guess(&model, options, settings, first + k, v, k),
                |k, report, v| {
                    iterations.push(report.iterations);
                    // Asked to stop: after this step's own outcome is recorded.
                    let stop = progress(first + k + 1, total).is_break();
                    // The positions of step j of the window's values.
                    let q_at = |j: usize| &v[j * s..j * s + model.n()];
                    let q = q_at(k);
                    if report.termination != Termination::Converged {
                        let mut f = failure(k, report, v);
                        if let Some((det, before, older)) = determinacy.as_mut() {
                            // A solve that fails while z and every other set of
                            // coordinates approach a rank loss fails because of it:
                            // name the singular configuration, located from the last
                            // two converged steps.
                            let (prev, older_q) = (q_at(k.max(1) - 1), q_at(k.max(2) - 2));
                            let rate = (older.1 - before.1) / (before.0 - older.0);
                            let steps_to_rank_loss = before.1 / (rate * fg.graph.dt);
                            // A step too coarse for the motion fails for that reason: in
                            // a violent transient s moves fast too (Andrews' squeezer at
                            // 1.7 ms, a body turning 1.8 rad a step, s = 0.026 falling),
                            // and the extrapolation alone would name a singular point.
                            let too_coarse = f
                                .fast_body
                                .as_ref()
                                .is_some_and(|(_, turn)| *turn > StepFailure::LARGE_TURN);
                            if k >= 2
                                && rate > 0.0
                                && ((steps_to_rank_loss <= Determinacy::ATTRIBUTE_WITHIN
                                    && before.1 < Determinacy::ATTRIBUTE_BELOW
                                    && !too_coarse)
                                    || before.1 < Determinacy::SEARCH_BELOW)
                            {
                                let (best, _) = det.best(&model, prev);
                                if best < Determinacy::SWITCH_GAIN * before.1 {
                                    f.singular = Some(det.singular_configuration(
                                        &model, older_q, prev, *older, *before,
                                    ));
                                    failures.push(f);
                                    completed = k;
                                    return Next::Stop;
                                }
                            }
                        }
                        failures.push(f);
                        if !options.continue_on_failure
                            || report.termination == Termination::Diverged
                        {
                            // The failed step is left out of the trajectory.
                            completed = k;
                            return Next::Stop;
                        }
                    }
                    if let Some((det, before, older)) = determinacy.as_mut() {
                        // Approaching a configuration where z stops determining the
                        // other coordinates: switch to coordinates that do, or, where
                        // Φ_q itself loses rank (the problem is ill-posed), stop while
                        // the solves are still sound, and say where.
                        let now = (fg.graph.time(k), det.distance(&model, q));
                        // At coarse steps s can fall from well above the thresholds
                        // to beyond the singular point in one step: judge by the
                        // lower of s and its linear extrapolation to the next step.
                        let ahead = if before.1.is_finite() {
                            now.1.min(2.0 * now.1 - before.1).max(0.0)
                        } else {
                            now.1
                        };
                        let falling = now.1 < before.1;
                        if falling && ahead < Determinacy::SEARCH_BELOW {
                            let (best, set) = det.best(&model, q);
                            if k > 0 && best >= Determinacy::SWITCH_GAIN * now.1 {
                                reselect = Some((first + k, set));
                                completed = k + 1;
                                return Next::Stop;
                            }
                        }
                        // The stop on the extrapolation only where it crosses 0 within
                        // the step: a regular dip (the robot's s bottoms out at 3e-3)
                        // seen at coarse steps must not stop the run.
                        let crossing = before.1.is_finite() && 2.0 * now.1 <= before.1;
                        if falling && (now.1 < Determinacy::STOP_BELOW || crossing) {
                            let mut f = failure(k, report, v);
                            f.singular = Some(det.singular_configuration(
                                &model,
                                q_at(k - 1),
                                q,
                                *before,
                                now,
                            ));
                            failures.push(f);
                            completed = k;
                            return Next::Stop;
                        }
                        *older = *before;
                        *before = now;
                    }
                    if stop {
                        // Interrupted: this step is kept as the last one.
                        interrupted = Some(first + k);
                        completed = k + 1;
                        return Next::Stop;
                    }
                    Next::Continue
                },
                |k| conditioned_from = Some((first + k, round_time(fg.graph.time(k)))),
            )?;
            run.iterations.extend(iterations);
            run.failures.extend(failures);
            run.interrupted = run.interrupted.or(interrupted);
            if run.conditioned_from.is_none() {
                run.conditioned_from = conditioned_from;
            }
        }
        Mode::Batch => {
            // Start from the one-step smoother's solution over this segment (which
            // may end it where the independent coordinates are re-selected), then
            // solve all of it at once.
            let mut warm_options = options.clone();
            warm_options.mode = Mode::FixedLag(1);
            let mut warm = Run::default();
            let guess = segment(
                model.clone(),
                &warm_options,
                first,
                total,
                progress,
                &mut warm,
            )?;
            if warm.interrupted.is_some() {
                // The one-step start is not the batch solution: nothing to return.
                run.interrupted = warm.interrupted;
                completed = 0;
            } else if let Some(f) = warm.failures.iter().find(|f| f.singular.is_some()) {
                // Ill-posed ahead: no batch solve of the whole horizon exists.
                run.failures.push(f.clone());
                completed = 0;
            } else if let Some(f) = warm.failures.first() {
                // No batch solve without its start: the step that failed there ends
                // the run, named as such.
                run.failures.push(StepFailure {
                    warm_start: true,
                    ..f.clone()
                });
                completed = 0;
            } else {
                reselect = guess.reselect;
                completed = guess.trajectory.len();
                fg.fill_from_trajectory(&model, &guess.trajectory, &mut values);
                let mut settings = options.settings;
                // One equation per unknown: Gauss-Newton is Newton's method.
                settings.second_order &= !options.is_square();
                if options.retries_tangent() {
                    // The paper's factors get the iterations a window needs; past them
                    // their compromise crawls (the double pendulum at 1 ms: 30
                    // iterations, 35 s) where tangent ones converge in one.
                    settings.max_iterations = settings.max_iterations.min(AUTO_BATCH_ITERATIONS);
                }
                let report = smoother::batch(&fg.graph, &mut values, completed, settings)?;
                run.iterations.push(report.iterations);
                if report.termination != Termination::Converged {
                    let k = completed - 1;
                    run.failures.push(StepFailure {
                        batch: true,
                        ..failure(k, &report, &values)
                    });
                }
            }
        }
    }
    Ok(Segment {
        trajectory: extract(&fg, &model, &values[..completed * s], completed),
        reselect,
    })
}

/// The iterations a batch solve with the paper's integrator factors gets under
/// [`DcIntegrators::Auto`] before the run is made again with tangent ones.
pub const AUTO_BATCH_ITERATIONS: usize = 10;

/// The substep counts tried, in turn, for a step whose solve failed from its guess:
/// a few, then finer (at most 74 substep solves per failed step).
const SUBSTEPS: [usize; 3] = [2, 8, 64];
/// Iterations a substep's solve gets: a step 8–64 times finer than one that failed
/// converges in a few, or that count of substeps is given up.
const SUBSTEP_ITERATIONS: usize = 10;

impl ForwardGraph {
    /// A guess for step k (run step `step`) from the state of step k − 1 in `values`,
    /// integrated over the step in [`SUBSTEPS`] substeps by the same graph at the
    /// finer step (N_w = 1), until all of them converge. Where the
    /// step's own solve fails from the Taylor guess (a coarse step through a fast or
    /// stiff stretch, whose implicit equations Newton's method does not reach from
    /// so far), this guess lies within the step's error of its solution. Writes the
    /// guess and returns true, or false when no substep count converged.
    fn substep_guess(
        &self,
        model: &Arc<Model>,
        options: &ForwardOptions,
        settings: Settings,
        step: usize,
        values: &mut [f64],
        k: usize,
    ) -> bool {
        let (n, s) = (self.n, self.graph.layout.size());
        let before = &values[(k - 1) * s..k * s];
        let mut start = (**model).clone();
        start.initial = State {
            q: DVector::from_column_slice(&before[..n]),
            dq: DVector::from_column_slice(&before[n..2 * n]),
        };
        let start = Arc::new(start);
        let settings = Settings {
            max_iterations: settings.max_iterations.min(SUBSTEP_ITERATIONS),
            ..settings
        };
        for substeps in SUBSTEPS {
            let mut fine = options.clone();
            fine.dt = options.dt / substeps as f64;
            fine.mode = Mode::FixedLag(1);
            let Ok(mut graph) = ForwardGraph::new(start.clone(), &fine) else {
                return false;
            };
            graph.graph.t0 = (step - 1) as f64 * options.dt;
            let Ok(first) = graph.initial_block(&start) else {
                return false;
            };
            let mut fine_values = vec![0.0; (substeps + 1) * s];
            fine_values[..s].copy_from_slice(&first);
            let mut converged = true;
            let solved = smoother::fixed_lag(
                &graph.graph,
                &mut fine_values,
                substeps + 1,
                1,
                settings,
                |v, j| graph.predict(v, j),
                |_, report, _| {
                    converged &= report.termination == Termination::Converged;
                    if converged {
                        Next::Continue
                    } else {
                        Next::Stop
                    }
                },
                |_| {},
            );
            if solved.is_ok() && converged {
                values[k * s..(k + 1) * s].copy_from_slice(&fine_values[substeps * s..]);
                return true;
            }
        }
        false
    }

    /// The graph's variables (step-major) filled from a trajectory of the same model:
    /// a starting point for a solve, or the state a benchmark linearizes at.
    pub fn fill_from_trajectory(&self, model: &Model, tr: &Trajectory, values: &mut [f64]) {
        let fg = self;
        let (n, s) = (fg.n, fg.graph.layout.size());
        for k in 0..tr.len() {
            let block = &mut values[k * s..(k + 1) * s];
            block[..n].copy_from_slice(&tr.q[k * n..(k + 1) * n]);
            block[n..2 * n].copy_from_slice(&tr.dq[k * n..(k + 1) * n]);
            block[2 * n..3 * n].copy_from_slice(&tr.ddq[k * n..(k + 1) * n]);
            if fg.coordinates == Coordinates::Independent {
                for (j, src) in [&tr.q, &tr.dq, &tr.ddq].iter().enumerate() {
                    for (i, &c) in model.independent.iter().enumerate() {
                        block[3 * n + j * fg.f + i] = src[k * n + c];
                    }
                }
            }
        }
    }
}

fn extract(fg: &ForwardGraph, model: &Model, values: &[f64], steps: usize) -> Trajectory {
    let (n, s) = (fg.n, fg.graph.layout.size());
    let mut tr = Trajectory {
        names: model.names.clone(),
        t: (0..steps).map(|k| fg.graph.time(k)).collect(),
        q: Vec::with_capacity(steps * n),
        dq: Vec::with_capacity(steps * n),
        ddq: Vec::with_capacity(steps * n),
    };
    for k in 0..steps {
        let b = &values[k * s..(k + 1) * s];
        tr.q.extend_from_slice(&b[..n]);
        tr.dq.extend_from_slice(&b[n..2 * n]);
        tr.ddq.extend_from_slice(&b[2 * n..3 * n]);
    }
    tr
}

fn summarize(
    model: &Model,
    tr: &Trajectory,
    wall_time: Duration,
    iterations: &[usize],
    failures: Vec<StepFailure>,
) -> Result<RunSummary> {
    let (n, m) = (model.n(), model.m());
    let mut phi = vec![0.0; m];
    let mut jac = vec![0.0; m * n];
    let (mut worst_phi, mut worst_vel) = (0.0f64, 0.0f64);
    let conservative = model.scene.is_conservative();
    let mut e0 = None;
    let mut drift = 0.0f64;
    let mut peak_kinetic = 0.0f64;
    for k in 0..tr.len() {
        let (q, dq) = (tr.q_at(k), tr.dq_at(k));
        if !q.iter().chain(dq).all(|v| v.is_finite()) {
            return Err(Error::Singular(format!("non-finite state at step {k}")));
        }
        model.phi_into(q, &mut phi);
        model.jacobian_into(q, &mut jac);
        worst_phi = phi.iter().fold(worst_phi, |w, v| w.max(v.abs()));
        for r in 0..m {
            let v: f64 = (0..n).map(|j| jac[r * n + j] * dq[j]).sum();
            worst_vel = worst_vel.max(v.abs());
        }
        let dv = nalgebra::DVector::from_column_slice(dq);
        let kinetic = model.kinetic_energy(&dv);
        peak_kinetic = peak_kinetic.max(kinetic);
        if conservative {
            let qv = nalgebra::DVector::from_column_slice(q);
            let e = kinetic + model.potential_energy(&qv);
            let e0 = *e0.get_or_insert(e);
            drift = drift.max((e - e0).abs());
        }
    }
    let total: usize = iterations.iter().sum();
    Ok(RunSummary {
        steps: tr.len(),
        wall_time,
        mean_iterations: total as f64 / iterations.len().max(1) as f64,
        max_iterations: iterations.iter().copied().max().unwrap_or(0),
        worst_phi,
        worst_velocity_constraint: worst_vel,
        energy_drift: conservative.then_some(drift),
        peak_kinetic_energy: peak_kinetic,
        failures,
        conditioned_from: None,
        reselections: Vec::new(),
        interrupted: None,
        tangent_after: None,
        refinement: None,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn failure(batch: bool, cause: Option<&str>) -> StepFailure {
        StepFailure {
            step: 100,
            t: 1.0000000000000002,
            report: SolveReport {
                iterations: 50,
                termination: Termination::IterationLimit,
                cost: 3.3,
            },
            constraint_conditioning: 0.5,
            singular: None,
            warm_start: false,
            batch,
            cause: cause.map(str::to_string),
            fast_body: None,
        }
    }

    #[test]
    fn failures_say_what_failed() {
        assert_eq!(
            failure(false, None).message(),
            "step 100 (t = 1 s) did not converge: iteration limit, cost 3.300e0 after 50 iterations"
        );
        assert_eq!(
            failure(true, None).message(),
            "the batch solve of 101 steps (t = 0 to 1 s) did not converge: iteration limit, \
             cost 3.300e0 after 50 iterations"
        );
        assert_eq!(
            failure(false, Some("effect e is not finite")).message(),
            "step 100 (t = 1 s) cannot be solved: effect e is not finite"
        );
    }
}
