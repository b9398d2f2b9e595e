//! Forward dynamics as factor graphs (paper, sections 4.1, 4.2 and 5): the graph in
//! dependent coordinates (DC) and in independent coordinates (IC), and a simulation
//! run over a horizon by the fixed-lag smoother or in batch.

use crate::dynamics;
use crate::error::{Error, Result};
use crate::factors::*;
use crate::graph::{ChainGraph, Factor, Layout, Noise, VarKind};
use crate::linalg::dense;

use crate::model::Model;
use crate::smoother::{self, Mode, Next};
use crate::solver::{Past, Settings, SolveReport, Termination};
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
    pub noise: NoiseModels,
    pub settings: Settings,
    /// Go on after a step whose solve did not converge (it is still reported).
    pub continue_on_failure: bool,
}

impl ForwardOptions {
    pub fn new(coordinates: Coordinates, dt: f64, t_end: f64, mode: Mode) -> Self {
        ForwardOptions {
            coordinates,
            dt,
            t_end,
            mode,
            integrator: Integrator::Trapezoidal,
            noise: NoiseModels::default(),
            // Marginal priors while they carry the solves, then conditioned (see [`Past`]).
            settings: Settings {
                past: Past::Adaptive,
                ..Settings::default()
            },
            continue_on_failure: false,
        }
    }

    /// Number of steps including t = 0: t_k = k·dt for k = 0..=round(t_end/dt).
    pub fn steps(&self) -> usize {
        (self.t_end / self.dt).round() as usize + 1
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
        self.settings.validate()
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
                Integrator::Trapezoidal => {
                    Box::new(Trapezoidal::new(x, dx, dim, dt, Noise::Isotropic(sigma)))
                }
                Integrator::Euler => Box::new(Euler::new(x, dx, dim, dt, Noise::Isotropic(sigma))),
            }
        };
        let graph = match options.coordinates {
            Coordinates::Dependent => ChainGraph {
                layout: Layout::new(&[(VarKind::Q, n), (VarKind::Dq, n), (VarKind::Ddq, n)]),
                dt,
                t0: 0.0,
                step_factors: vec![
                    Box::new(PositionConstraints::new(model.clone(), hard.clone())),
                    Box::new(VelocityConstraints::new(model.clone(), hard.clone())),
                    Box::new(Dynamics::new(model.clone(), Noise::Isotropic(nm.dynamics))),
                    integrate(VarKind::Q, VarKind::Dq, n, nm.integrator_position),
                    integrate(VarKind::Dq, VarKind::Ddq, n, nm.integrator_velocity),
                ],
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
                    step_factors: vec![
                        Box::new(IndependentPosition::new(model.clone(), hard.clone())),
                        Box::new(IndependentVelocity::new(model.clone(), hard.clone())),
                        Box::new(IndependentAcceleration::new(model.clone(), hard.clone())),
                        Box::new(IndependentDynamics::new(
                            model.clone(),
                            Noise::Isotropic(nm.dynamics),
                        )),
                        integrate(VarKind::Z, VarKind::Dz, f, nm.integrator_position),
                        integrate(VarKind::Dz, VarKind::Ddz, f, nm.integrator_velocity),
                        Box::new(Equality::new(VarKind::Q, n, Noise::Isotropic(nm.equality))),
                    ],
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
        let ddq = dynamics::lagrange(model, &init.q, &init.dq, 0.0)?.ddq;
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
    /// σ_r/σ₁ of Φ_q at the step's configuration, r the constraints' rank at the
    /// start: near 0 where the mechanism approaches a singular configuration.
    pub constraint_conditioning: f64,
    /// Set when the run stopped because the independent coordinates approach a
    /// configuration where they do not determine the others (the step's own solve
    /// converged; `report` is its report).
    pub singular: Option<SingularConfiguration>,
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
    /// The reason for the failure, naming the step and the time (not what was
    /// written).
    pub fn message(&self) -> String {
        let t = round_time(self.t);
        match &self.singular {
            Some(c) => format!(
                "singular configuration at t ≈ {:.6} s (extrapolated): the independent \
                 coordinates [{}] do not determine the other coordinates' velocities there \
                 (rank of Φ_q over the dependent coordinates [{}] {} < {}); stopped at step {} \
                 (t = {t} s), where its distance to rank loss is {:.1e} and falling",
                c.t_singular,
                c.independent.join(", "),
                c.dependent.join(", "),
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
                format!(
                    "step {} (t = {t} s) did not converge: {}, cost {:.3e} after {} \
                     iterations{singular}",
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
    rows: Vec<f64>,
    chol: Vec<f64>,
    linv: Vec<f64>,
}

impl Determinacy {
    /// A run in independent coordinates stops where s falls below this. In the
    /// regular motion of the scene suite s stays above 0.04 (the slider-crank's dead
    /// centres and the four-bars come closest). Approaching the parallelogram's flat
    /// configuration the solves in independent coordinates fail from s ≈ 1.2e-3 (at
    /// every Δt and phase tried; s ≈ 0.5 |θ − kπ| there), so the run stops about 3 ms
    /// (at 3 rad/s) ahead of it with its steps sound. Pick-and-place heads for such a
    /// configuration at t ≈ 0.33 s and stops at 0.18 s.
    pub const STOP_BELOW: f64 = 5e-3;

    pub fn new(model: &Model) -> Self {
        let dependent: Vec<usize> = (0..model.n())
            .filter(|i| !model.independent.contains(i))
            .collect();
        let ma = model.active.len();
        Determinacy {
            jac: vec![0.0; model.m() * model.n()],
            rows: vec![0.0; ma * dependent.len()],
            chol: vec![0.0; ma * ma],
            linv: vec![0.0; ma * ma],
            dependent,
        }
    }

    /// s at q: 0 where the dependent block has lost a rank (or is not square).
    pub fn distance(&mut self, model: &Model, q: &[f64]) -> f64 {
        let (n, ma, d) = (model.n(), model.active.len(), self.dependent.len());
        if ma != d {
            return 0.0;
        }
        if ma == 0 {
            return f64::INFINITY;
        }
        model.jacobian_into(q, &mut self.jac);
        for (r, &k) in model.active.iter().enumerate() {
            let row = &mut self.rows[r * d..(r + 1) * d];
            for (o, &c) in row.iter_mut().zip(&self.dependent) {
                *o = self.jac[k * n + c];
            }
            let norm = row.iter().map(|v| v * v).sum::<f64>().sqrt();
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
    /// at (t0, s0): where s extrapolates to 0, and the rank kept there.
    fn singular_configuration(
        &mut self,
        model: &Model,
        q: &[f64],
        (t0, s0): (f64, f64),
        (t, s): (f64, f64),
    ) -> SingularConfiguration {
        let t_singular = if s0 > s {
            t + s * (t - t0) / (s0 - s)
        } else {
            t
        };
        self.distance(model, q);
        let d = self.dependent.len();
        let rows = nalgebra::DMatrix::from_row_slice(model.active.len(), d, &self.rows);
        let rank = rows
            .singular_values()
            .iter()
            .filter(|&&v| v > 10.0 * s)
            .count();
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

/// σ_r/σ₁ of Φ_q(q), r = the number of independent constraints at the start.
fn constraint_conditioning(model: &Model, q: &[f64]) -> f64 {
    let r = model.active.len();
    if r == 0 {
        return 1.0;
    }
    let jac = model.jacobian(&nalgebra::DVector::from_column_slice(q));
    let mut sv: Vec<f64> = jac.singular_values().iter().copied().collect();
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
    pub failures: Vec<StepFailure>,
    /// With [`Past::Adaptive`], the step from which the smoother conditioned on its
    /// past: its window solve had not converged after a marginal prior.
    pub conditioned_from: Option<(usize, f64)>,
}

/// Simulates the model's motion. `progress(done, total)` is called after each step.
pub fn simulate(
    model: Arc<Model>,
    options: &ForwardOptions,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<(Trajectory, RunSummary)> {
    let fg = ForwardGraph::new(model.clone(), options)?;
    let steps = options.steps();
    let s = fg.graph.layout.size();
    let mut values = vec![0.0; steps * s];
    values[..s].copy_from_slice(&fg.initial_block(&model)?);
    let start = Instant::now();
    let mut iterations: Vec<usize> = Vec::new();
    let mut failures = Vec::new();
    let mut completed = steps;
    let mut conditioned_from = None;
    // In independent coordinates, how well z determines the rest, step by step.
    let mut determinacy = (options.coordinates == Coordinates::Independent)
        .then(|| (Determinacy::new(&model), (0.0, f64::INFINITY)));
    match options.mode {
        Mode::FixedLag(window) => {
            smoother::fixed_lag(
                &fg.graph,
                &mut values,
                steps,
                window,
                Settings {
                    // The DC graph's integrators conflict with its constraints.
                    tangent_priors: options.coordinates == Coordinates::Dependent,
                    ..options.settings
                },
                |v, k| fg.predict(v, k),
                |k, report, v| {
                    iterations.push(report.iterations);
                    progress(k + 1, steps);
                    if report.termination != Termination::Converged {
                        let q = &v[k * s..k * s + model.n()];
                        failures.push(StepFailure {
                            step: k,
                            t: fg.graph.time(k),
                            report: *report,
                            constraint_conditioning: constraint_conditioning(&model, q),
                            singular: None,
                        });
                        if !options.continue_on_failure
                            || report.termination == Termination::Diverged
                        {
                            // The failed step is left out of the trajectory.
                            completed = k;
                            return Next::Stop;
                        }
                    }
                    if let Some((det, before)) = determinacy.as_mut() {
                        // Approaching a configuration where z stops determining the
                        // other coordinates, the problem itself becomes ill-posed:
                        // stop while the solves are still sound, and say where.
                        let q = &v[k * s..k * s + model.n()];
                        let now = (fg.graph.time(k), det.distance(&model, q));
                        if now.1 < Determinacy::STOP_BELOW && now.1 < before.1 {
                            failures.push(StepFailure {
                                step: k,
                                t: now.0,
                                report: *report,
                                constraint_conditioning: constraint_conditioning(&model, q),
                                singular: Some(det.singular_configuration(&model, q, *before, now)),
                            });
                            completed = k;
                            return Next::Stop;
                        }
                        *before = now;
                    }
                    Next::Continue
                },
                |k| conditioned_from = Some((k, fg.graph.time(k))),
            )?;
        }
        Mode::Batch => {
            // Start from the one-step smoother's solution, then solve all at once.
            let mut warm = options.clone();
            warm.mode = Mode::FixedLag(1);
            let (guess, summary) = simulate(model.clone(), &warm, &mut |_, _| {})?;
            if let Some(f) = summary.failures.iter().find(|f| f.singular.is_some()) {
                // Ill-posed ahead: no batch solve of the whole horizon exists.
                failures.push(f.clone());
                completed = 0;
            } else if !summary.failures.is_empty() {
                let f = &summary.failures[0];
                return Err(Error::InvalidArgument(format!(
                    "the warm start for the batch solve failed at step {} (t = {}): {}",
                    f.step, f.t, f.report.termination
                )));
            }
            if failures.is_empty() {
                fg.fill_from_trajectory(&model, &guess, &mut values);
                let report = smoother::batch(&fg.graph, &mut values, steps, options.settings)?;
                iterations.push(report.iterations);
                progress(steps, steps);
                if report.termination != Termination::Converged {
                    let q = &values[(steps - 1) * s..(steps - 1) * s + model.n()];
                    failures.push(StepFailure {
                        step: steps - 1,
                        t: fg.graph.time(steps - 1),
                        report,
                        constraint_conditioning: constraint_conditioning(&model, q),
                        singular: None,
                    });
                }
            }
        }
    }
    let wall_time = start.elapsed();
    let trajectory = extract(&fg, &model, &values[..completed * s], completed);
    let mut summary = summarize(&model, &trajectory, wall_time, &iterations, failures)?;
    summary.conditioned_from = conditioned_from;
    Ok((trajectory, summary))
}

impl ForwardGraph {
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
        if conservative {
            let qv = nalgebra::DVector::from_column_slice(q);
            let dv = nalgebra::DVector::from_column_slice(dq);
            let e = model.kinetic_energy(&dv) + model.potential_energy(&qv);
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
        failures,
        conditioned_from: None,
    })
}
