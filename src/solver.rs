//! Sparse nonlinear least squares over a window of time steps of a [`ChainGraph`]:
//! Gauss-Newton or Levenberg-Marquardt on the block-tridiagonal normal equations, and
//! the marginalization that turns the oldest step of a window into a Gaussian prior on
//! the next one (the Schur complement of the linearized system).
//!
//! Hard factors ([`Noise::Hard`]) are not weighted: each iteration linearizes them per
//! step, C_k δ_k = −c_k, and solves for δ_k = p_k + N_k y_k ([`NullSpace`]), so only
//! the soft factors enter the normal equations in y. Weighting them by 1/σ² with a tiny
//! σ instead squares a condition number that is already large: on a long four-bar
//! run the soft information along the motion decays to ~1e-5 while 1/σ² = 1e12, and
//! the window solves stall.

use crate::error::{Error, Result};
use crate::graph::{ChainGraph, Factor, Noise, Workspace};
use crate::linalg::banded::{BandedCholesky, BlockTridiagonal};
use crate::linalg::dense::Summation;
use crate::linalg::nullspace::NullSpace;

/// The nonlinear least-squares method.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Method {
    GaussNewton,
    LevenbergMarquardt,
}

/// Stopping rules. A solve stops when an undamped step satisfies
/// |δᵢ| ≤ `step_tolerance`·(1 + |xᵢ|) for every component, or restores the hard
/// factors within that tolerance and either is predicted to lower the cost by less
/// than 1e-12 of itself or fails to lower it while below 1e-6 relative or predicting
/// less than 1e-6 of it, or when a damped step below the tolerance fails to lower the
/// cost (converged: the cost's round-off is reached), after `max_iterations` linear solves (iteration limit), or when the cost
/// is not finite or LM's damping exceeds 1e16 without progress (diverged).
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
    /// Smallest 1/cond(H) (as the Cholesky factor's pivots bound it) at which a
    /// one-block window's Gauss-Newton step still comes from the normal equations;
    /// below it the step is the least-squares solution of J itself, whose condition
    /// is the square root of H's: a light crank against a stiff spring in
    /// independent coordinates makes J's 1e8 into H's 1e16, where the Cholesky step
    /// has no correct digit and the six-bar press's window solves wander for dozens
    /// of iterations.
    pub normal_equations_limit: f64,
}

/// Singular values of a one-block window's reduced Jacobian below this fraction of the
/// largest are taken as 0 by `least_squares_step` (round-off in J itself).
const LEAST_SQUARES_CUTOFF: f64 = 1e-14;

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
            normal_equations_limit: 1e-10,
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
        if !(self.initial_damping >= 0.0 && self.initial_damping.is_finite()) {
            return Err(Error::InvalidArgument(format!(
                "initial_damping must be ≥ 0, got {}",
                self.initial_damping
            )));
        }
        Ok(())
    }
}

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
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SolveReport {
    /// Linear solves performed.
    pub iterations: usize,
    pub termination: Termination,
    /// ½ Σ‖whitened residual‖² at the returned estimate (prior included; hard
    /// factors weighted by 1/[`Noise::HARD_SIGMA`]).
    pub cost: f64,
}

/// A Gaussian prior on one step's block left by marginalization, in information
/// form: c + ηᵀδ + ½ δᵀΛδ with δ = x − x̄. With the hard equations eliminated
/// exactly, Λ holds only soft information (no 1/σ_hard² next to 1/σ_soft²), so the
/// information form loses nothing that a square-root form would keep.
#[derive(Debug, Clone, PartialEq)]
pub struct LinearPrior {
    /// Row-major s × s.
    pub information: Vec<f64>,
    pub eta: Vec<f64>,
    /// The cost at δ = 0 (what the marginalized factors leave behind).
    pub constant: f64,
    pub xbar: Vec<f64>,
}

/// Buffers of one factor: residual and Jacobian blocks, and its rows' 1/σ.
struct FactorBuffers {
    r: Vec<f64>,
    jac: Vec<Vec<f64>>,
    weights: Vec<f64>,
    /// Per key, the size of its variable.
    sizes: Vec<usize>,
}

impl FactorBuffers {
    fn new(graph: &ChainGraph, f: &dyn Factor) -> Self {
        FactorBuffers {
            weights: (0..f.dim()).map(|r| f.noise().weight(r)).collect(),
            sizes: f
                .keys()
                .iter()
                .map(|k| graph.layout.slot(k.kind).map_or(0, |(_, d)| d))
                .collect(),
            r: vec![0.0; f.dim()],
            jac: f
                .keys()
                .iter()
                .map(|k| {
                    let (_, d) = graph.layout.slot(k.kind).unwrap_or((0, 0));
                    vec![0.0; f.dim() * d]
                })
                .collect(),
        }
    }

    /// Divides the residual's rows, and with `jacobians` the Jacobians' rows, by their
    /// σ (a diagonal Jacobian block only on its diagonal: the rest is 0).
    fn whiten(&mut self, factor: &dyn Factor, jacobians: bool) {
        for (r, w) in self.r.iter_mut().zip(&self.weights) {
            *r *= w;
        }
        if !jacobians {
            return;
        }
        for (a, (jac, &d)) in self.jac.iter_mut().zip(&self.sizes).enumerate() {
            if d == 0 {
                continue;
            }
            if factor.diagonal_jacobian(a) {
                for (r, w) in self.weights.iter().enumerate() {
                    jac[r * d + r] *= w;
                }
                continue;
            }
            for (row, w) in jac.chunks_exact_mut(d).zip(&self.weights) {
                for v in row {
                    *v *= w;
                }
            }
        }
    }
}

/// Which factors a linearization takes.
#[derive(Clone, Copy)]
enum Scope {
    /// Every factor inside the window [k0, k1).
    Window,
    /// Only the factors touching step k0 (for its marginalization; k1 = k0 + 2).
    Oldest,
}

/// One factor at one step: `initial` factors come from `graph.initial_factors`.
#[derive(Clone, Copy)]
struct Instance {
    initial: bool,
    index: usize,
    step: usize,
}

/// The buffers of one factor instance.
fn buffers<'a>(
    initial: &'a mut [FactorBuffers],
    step: &'a mut [FactorBuffers],
    inst: Instance,
) -> &'a mut FactorBuffers {
    if inst.initial {
        &mut initial[inst.index]
    } else {
        &mut step[inst.index]
    }
}

/// Names the factor, step and time in a factor's `Singular` error.
fn located(factor: &dyn Factor, step: usize, t: f64) -> impl FnOnce(Error) -> Error + '_ {
    move |e| match e {
        Error::Singular(m) => {
            Error::Singular(format!("{} at step {step} (t = {t}): {m}", factor.name()))
        }
        other => other,
    }
}

fn factor_of(graph: &ChainGraph, inst: Instance) -> &dyn Factor {
    if inst.initial {
        graph.initial_factors[inst.index].as_ref()
    } else {
        graph.step_factors[inst.index].as_ref()
    }
}

/// What a pass over the hard factors computes.
#[derive(Clone, Copy, PartialEq, Eq)]
enum HardPass {
    Linearize,
    Cost,
    Residuals,
}

fn is_hard(f: &dyn Factor) -> bool {
    matches!(f.noise(), Noise::Hard)
}

/// What a window solve that converged on a small step leaves for marginalizing its
/// first block.
#[derive(Clone, Copy)]
struct LastSolve {
    k0: usize,
    k1: usize,
}

/// The reduction of one step's hard equations C δ = −c (C and c themselves live in
/// the solver's scratch only while the step is reduced or corrected).
struct HardBlock {
    rows: usize,
    reduction: NullSpace,
    /// Every residual of the last linearization within NOISE_MARGIN of its round-off:
    /// the block's equations hold, and its particular solution is round-off divided
    /// by its pivots, no correction to wait for.
    at_round_off: bool,
}

/// A reusable solver for windows of up to `capacity` steps; it allocates once.
pub struct WindowSolver {
    settings: Settings,
    s: usize,
    h: BlockTridiagonal,
    chol: BandedCholesky,
    g: Vec<f64>,
    delta: Vec<f64>,
    damping: Vec<f64>,
    saved: Vec<f64>,
    hd: Vec<f64>,
    step_buffers: Vec<FactorBuffers>,
    initial_buffers: Vec<FactorBuffers>,
    hard: Vec<HardBlock>,
    /// A factor's Jacobian in reduced coordinates, per block it touches (lag 0, lag 1).
    reduced: [Vec<f64>; 2],
    /// A factor's residual linearized at x + p.
    shifted: Vec<f64>,
    /// Per row of `reduced`, the columns outside which it is 0.
    reduced_spans: [Vec<(usize, usize)>; 2],
    instances: Vec<Instance>,
    /// The last full step δ = p + N y of the window (for `backtrack`).
    direction: Vec<f64>,
    /// The instances in step order (indices into `instances`), and where each block's
    /// begin in it (one more entry than blocks).
    by_step: Vec<usize>,
    block_start: Vec<usize>,
    next_slot: Vec<usize>,
    /// Per instance, the cost of a hard one (summed in `instances` order).
    hard_cost: Vec<f64>,
    /// One step's hard equations: C row-major rows × s, and −c.
    hard_jac: Vec<f64>,
    hard_rhs: Vec<f64>,
    /// Round-off in each hard residual (see [`NullSpace::set_noise`]).
    hard_noise: Vec<f64>,
    /// Evaluate step by step (see `optimize_for_batch`).
    step_major: bool,
    /// Directions and products of [`Factor::evaluate_along`]: per key size × c, and
    /// dim × c (c ≤ 1 + 2s); empty when no factor evaluates along directions.
    along_dirs: Vec<f64>,
    along_out: Vec<f64>,
    /// In a conditional solve the step before the window is held fixed.
    conditional: bool,
    /// The whitened, reduced rows [J N | r + J p] of a one-block window without a
    /// prior, kept beside H for the least-squares step where H cannot be factored or
    /// is conditioned past `Settings::normal_equations_limit` (see
    /// `least_squares_step`); row-major, `d + 1` columns.
    rows: Vec<f64>,
    rows_width: Option<usize>,
    /// Set when a window solve ended on a small step: its linearization of the
    /// oldest block is still at hand (see `marginalize`).
    last: Option<LastSolve>,
    /// Cost of the factors touching the first block, from the last evaluation.
    cost_first: f64,
    correction: Vec<f64>,
    /// The nonzeros of a Jacobian row (per block it touches, for `accumulate`).
    nonzero: Vec<(usize, f64)>,
    nonzeros: [Vec<(usize, f64)>; 2],
    ws: Workspace,
    scratch: Vec<f64>,
    newton: NewtonBuffers,
    /// Step whose hard equations `project_prior` linearized and reduced in block 0 at
    /// the current values (their costs in `hard_cost`).
    hard_cache: Option<usize>,
}

/// Buffers of the exact (Newton) model: the Lagrangian's gradient in full
/// coordinates at the point and at its perturbations, each block's multipliers, and
/// the Gauss-Newton diagonal that scales LM's damping in its place.
struct NewtonBuffers {
    lambda: Vec<f64>,
    grad: Vec<f64>,
    plus: Vec<f64>,
    minus: Vec<f64>,
    scale: Vec<f64>,
    /// Per block, the hard rows seen so far; one reduced column.
    rows: Vec<usize>,
    column: Vec<f64>,
    max_hard: usize,
}

impl WindowSolver {
    pub fn new(graph: &ChainGraph, capacity: usize, settings: Settings) -> Result<Self> {
        settings.validate()?;
        let mut max_dim = 0;
        let (mut hard_step, mut hard_initial) = (0, 0);
        for (initial, list) in [(false, &graph.step_factors), (true, &graph.initial_factors)] {
            for f in list {
                f.noise()
                    .validate(f.dim())
                    .map_err(|e| Error::InvalidArgument(format!("noise of {}: {e}", f.name())))?;
                for k in f.keys() {
                    if graph.layout.slot(k.kind).is_none() || k.lag > 1 {
                        return Err(Error::InvalidArgument(format!(
                            "factor {} touches {}(lag {}), which the graph does not hold",
                            f.name(),
                            k.kind.symbol(),
                            k.lag
                        )));
                    }
                }
                max_dim = max_dim.max(f.dim());
                if is_hard(f.as_ref()) {
                    if f.keys().iter().any(|k| k.lag > 0) {
                        return Err(Error::InvalidArgument(format!(
                            "hard factor {} spans two steps; hard factors must stay within one",
                            f.name()
                        )));
                    }
                    if initial {
                        hard_initial += f.dim();
                    } else {
                        hard_step += f.dim();
                    }
                }
            }
        }
        let s = graph.layout.size();
        let capacity = capacity.max(2);
        let n = capacity * s;
        let max_hard = hard_step + hard_initial;
        // Room for the factors that linearize along directions.
        let (mut along_keys, mut along_dim) = (0, 0);
        for f in graph.step_factors.iter().chain(&graph.initial_factors) {
            if f.evaluates_along() {
                let sizes: usize = f
                    .keys()
                    .iter()
                    .map(|k| graph.layout.slot(k.kind).map_or(0, |(_, d)| d))
                    .sum();
                along_keys = along_keys.max(sizes);
                along_dim = along_dim.max(f.dim());
            }
        }
        let mut solver = WindowSolver {
            settings,
            s,
            h: BlockTridiagonal::new(capacity, s),
            chol: BandedCholesky::new(capacity, s),
            g: vec![0.0; n],
            delta: vec![0.0; n],
            damping: vec![0.0; n],
            saved: vec![0.0; n],
            direction: vec![0.0; n],
            hd: vec![0.0; n],
            step_buffers: graph
                .step_factors
                .iter()
                .map(|f| FactorBuffers::new(graph, f.as_ref()))
                .collect(),
            initial_buffers: graph
                .initial_factors
                .iter()
                .map(|f| FactorBuffers::new(graph, f.as_ref()))
                .collect(),
            hard: (0..capacity)
                .map(|_| HardBlock {
                    rows: 0,
                    at_round_off: false,
                    reduction: NullSpace::new(s, max_hard),
                })
                .collect(),
            by_step: Vec::with_capacity(
                capacity * graph.step_factors.len() + graph.initial_factors.len(),
            ),
            block_start: Vec::with_capacity(capacity + 1),
            next_slot: Vec::with_capacity(capacity),
            hard_cost: Vec::with_capacity(
                capacity * graph.step_factors.len() + graph.initial_factors.len(),
            ),
            hard_jac: vec![0.0; max_hard * s],
            hard_rhs: vec![0.0; max_hard],
            hard_noise: vec![0.0; max_hard],
            step_major: false,
            along_dirs: vec![0.0; along_keys * (1 + 2 * s)],
            along_out: vec![0.0; along_dim * (1 + 2 * s)],
            reduced: [vec![0.0; max_dim.max(s) * s], vec![0.0; max_dim.max(s) * s]],
            shifted: vec![0.0; max_dim.max(s)],
            reduced_spans: [vec![(0, 0); max_dim.max(s)], vec![(0, 0); max_dim.max(s)]],
            instances: Vec::with_capacity(
                capacity * graph.step_factors.len() + graph.initial_factors.len(),
            ),
            conditional: false,
            rows: Vec::new(),
            rows_width: None,
            last: None,
            cost_first: 0.0,
            correction: vec![0.0; s],
            nonzero: Vec::with_capacity(s),
            nonzeros: [Vec::with_capacity(s), Vec::with_capacity(s)],
            ws: graph.workspace(),
            scratch: vec![0.0; 4 * s * s + 4 * s],
            hard_cache: None,
            newton: NewtonBuffers {
                lambda: vec![0.0; capacity * max_hard],
                grad: vec![0.0; n],
                plus: vec![0.0; n],
                minus: vec![0.0; n],
                scale: vec![0.0; n],
                rows: vec![0; capacity],
                column: vec![0.0; s],
                max_hard,
            },
        };
        solver.segment_by_order(graph);
        Ok(solver)
    }

    /// Sets the solver up for long batch horizons (inverse dynamics):
    /// - linearizations go step by step (a step's hard equations, then its factors
    ///   into its blocks of H) instead of factor by factor over the whole horizon, so
    ///   each block of H is filled while it is in cache;
    /// - dot products in the reductions, the banded factorization and its solves are
    ///   summed in four lanes ([`Summation::Lanes`]).
    ///
    /// The sums run in another order, so results agree with the default to the
    /// solve's tolerance, not to the bit. Off by default, so that forward runs keep
    /// theirs.
    pub fn optimize_for_batch(&mut self) {
        for block in &mut self.hard {
            block.reduction.set_summation(Summation::Lanes);
        }
        self.h.set_summation(Summation::Lanes);
        self.chol.set_summation(Summation::Lanes);
        self.step_major = true;
    }

    /// Reduces each step's hard equations segment by segment, positions first, then
    /// velocities, accelerations, forces ([`VarKind::order`],
    /// [`NullSpace::set_segments`]): each equation's pivot is then measured against
    /// the equation on its own unknowns (an acceleration row's coefficients on q and
    /// q̇ grow like q̇², its pivot on q̈ does not), the basis is exactly 0 on what the
    /// earlier segments fix, and block-triangular equations cost a fraction of one
    /// QR of them all.
    ///
    /// [`VarKind::order`]: crate::graph::VarKind::order
    fn segment_by_order(&mut self, graph: &ChainGraph) {
        let mut segment = vec![0; self.s];
        for (kind, d) in graph.layout.kinds() {
            let (off, _) = graph.layout.slot(kind).expect("a kind of the layout");
            segment[off..off + d].fill(kind.order());
        }
        for block in &mut self.hard {
            block.reduction.set_segments(&segment);
        }
    }

    /// Whether marginalization conditions on the leaving step (see [`Past`]).
    fn past_conditioned(&self) -> bool {
        self.settings.past == Past::Conditioned
    }

    /// From now on, marginalization conditions on the leaving step.
    pub fn condition_on_past(&mut self) {
        self.settings.past = Past::Conditioned;
    }

    pub fn settings(&self) -> &Settings {
        &self.settings
    }

    /// Lists the factor instances of a scope.
    fn collect_instances(&mut self, graph: &ChainGraph, k0: usize, k1: usize, scope: Scope) {
        self.instances.clear();
        if k0 == 0 {
            for index in 0..graph.initial_factors.len() {
                self.instances.push(Instance {
                    initial: true,
                    index,
                    step: 0,
                });
            }
        }
        for (index, factor) in graph.step_factors.iter().enumerate() {
            let keys = factor.keys();
            let max_lag = keys.iter().map(|k| k.lag).max().unwrap_or(0);
            // Conditional solves hold the step before the window fixed and keep the
            // factors that reach back to it.
            let first = if self.conditional {
                k0.max(max_lag)
            } else {
                k0 + max_lag
            };
            for step in first..k1 {
                if let Scope::Oldest = scope {
                    if !keys.iter().any(|k| step - k.lag == k0) {
                        continue;
                    }
                }
                self.instances.push(Instance {
                    initial: false,
                    index,
                    step,
                });
            }
        }
        // Step order, `instances` order within a step (initial factors first): a
        // counting sort by step.
        let inst = &self.instances;
        let blocks = k1 - k0;
        self.block_start.clear();
        self.block_start.resize(blocks + 1, 0);
        for i in inst {
            self.block_start[i.step - k0 + 1] += 1;
        }
        for b in 0..blocks {
            self.block_start[b + 1] += self.block_start[b];
        }
        self.by_step.clear();
        self.by_step.resize(inst.len(), 0);
        self.next_slot.clear();
        self.next_slot
            .extend_from_slice(&self.block_start[..blocks]);
        for (i, it) in inst.iter().enumerate() {
            let slot = &mut self.next_slot[it.step - k0];
            self.by_step[*slot] = i;
            *slot += 1;
        }
        self.hard_cost.clear();
        self.hard_cost.resize(inst.len(), 0.0);
    }

    /// Evaluates one factor instance into its buffers (residual not yet whitened).
    fn evaluate_instance(
        &mut self,
        graph: &ChainGraph,
        values: &[f64],
        inst: Instance,
        linearize: bool,
    ) -> Result<()> {
        let s = self.s;
        let factor = factor_of(graph, inst);
        let buf = buffers(&mut self.initial_buffers, &mut self.step_buffers, inst);
        let keys = factor.keys();
        let mut xs: [&[f64]; 8] = [&[]; 8];
        for (slot, k) in xs.iter_mut().zip(keys) {
            let (off, d) = graph.layout.slot(k.kind).unwrap_or((0, 0));
            let base = (inst.step - k.lag) * s + off;
            *slot = &values[base..base + d];
        }
        let t = graph.time(inst.step);
        factor
            .evaluate(
                t,
                &xs[..keys.len()],
                &mut buf.r,
                linearize.then_some(buf.jac.as_mut_slice()),
                &mut self.ws,
            )
            .map_err(located(factor, inst.step, t))
    }

    /// Evaluates the hard factors of block `b` (step k0 + b) of the listed instances,
    /// records their costs in `hard_cost`, and with `Linearize` reduces the block's
    /// equations C δ = −c; with `Residuals` leaves −c (in the same row order) in
    /// `hard_rhs` for a correction with the current C.
    fn hard_block(
        &mut self,
        graph: &ChainGraph,
        values: &[f64],
        b: usize,
        mode: HardPass,
    ) -> Result<()> {
        let s = self.s;
        let linearize = mode == HardPass::Linearize;
        self.hard_cache = None;
        let mut rows = 0;
        let mut at_round_off = true;
        for at in self.block_start[b]..self.block_start[b + 1] {
            let i = self.by_step[at];
            let inst = self.instances[i];
            let factor = factor_of(graph, inst);
            if !is_hard(factor) {
                continue;
            }
            self.evaluate_instance(graph, values, inst, linearize)?;
            let buf = &*buffers(&mut self.initial_buffers, &mut self.step_buffers, inst);
            let w = Noise::Hard.weight(0);
            self.hard_cost[i] = buf.r.iter().map(|r| 0.5 * (w * r) * (w * r)).sum();
            if mode == HardPass::Cost {
                continue;
            }
            let dim = factor.dim();
            if linearize {
                self.hard_jac[rows * s..(rows + dim) * s].fill(0.0);
                for (a, k) in factor.keys().iter().enumerate() {
                    let (off, d) = graph.layout.slot(k.kind).unwrap_or((0, 0));
                    for r in 0..dim {
                        let row =
                            &mut self.hard_jac[(rows + r) * s + off..(rows + r) * s + off + d];
                        row.copy_from_slice(&buf.jac[a][r * d..(r + 1) * d]);
                    }
                }
            }
            for r in 0..dim {
                self.hard_rhs[rows + r] = -buf.r[r];
            }
            if linearize {
                // Round-off in each residual: ε times the size of its terms, Σ|C||x|.
                let x = &values[inst.step * s..(inst.step + 1) * s];
                for r in 0..dim {
                    let row = &self.hard_jac[(rows + r) * s..(rows + r + 1) * s];
                    let terms: f64 = row.iter().zip(x).map(|(c, v)| (c * v).abs()).sum();
                    let noise = f64::EPSILON * (terms + buf.r[r].abs());
                    self.hard_noise[rows + r] = noise;
                    at_round_off &= buf.r[r].abs() <= NullSpace::NOISE_MARGIN * noise;
                }
            }
            rows += dim;
        }
        let block = &mut self.hard[b];
        block.rows = rows;
        if linearize {
            block.at_round_off = at_round_off;
            block.reduction.set_noise(&self.hard_noise[..rows]);
            block
                .reduction
                .reduce(&self.hard_jac, &self.hard_rhs[..rows], rows);
        }
        Ok(())
    }

    /// The hard factors' share of the cost, summed in `instances` order, and the part
    /// of it at the first block.
    fn hard_cost_sum(&self, graph: &ChainGraph, k0: usize) -> (f64, f64) {
        let (mut cost, mut first) = (0.0, 0.0);
        for (inst, &c) in self.instances.iter().zip(&self.hard_cost) {
            if !is_hard(factor_of(graph, *inst)) {
                continue;
            }
            cost += c;
            if inst.step == k0 {
                first += c;
            }
        }
        (cost, first)
    }

    /// Second-order correction after a step: moves each block of the window back onto
    /// its hard equations with the least-norm step of the current C. Without it a step
    /// along the linearized constraints leaves an O(|δ|²) violation that the cost's
    /// 1/σ_hard² weight makes look like a failure (the Maratos effect).
    fn correct(
        &mut self,
        graph: &ChainGraph,
        values: &mut [f64],
        k0: usize,
        k1: usize,
    ) -> Result<()> {
        let s = self.s;
        for b in 0..k1 - k0 {
            // A block's hard factors read that block only.
            self.hard_block(graph, values, b, HardPass::Residuals)?;
            let block = &mut self.hard[b];
            if block.rows == 0 {
                continue;
            }
            block
                .reduction
                .solve(&self.hard_rhs[..block.rows], &mut self.correction);
            let x = &mut values[(k0 + b) * s..(k0 + b + 1) * s];
            for (xi, c) in x.iter_mut().zip(&self.correction) {
                *xi += c;
            }
        }
        Ok(())
    }

    /// Evaluates soft factor instance `i` at `values` and adds its cost (and to
    /// `cost_first` when it touches block k0); with `linearize` also adds its
    /// reduced JᵀJ and Jᵀr to H and g.
    #[allow(clippy::too_many_arguments)]
    fn soft_instance(
        &mut self,
        graph: &ChainGraph,
        values: &[f64],
        k0: usize,
        i: usize,
        linearize: bool,
        cost: &mut f64,
        cost_first: &mut f64,
    ) -> Result<()> {
        let s = self.s;
        let inst = self.instances[i];
        let factor = factor_of(graph, inst);
        let along = linearize
            && factor.evaluates_along()
            && self.evaluate_along(graph, values, k0, inst)?;
        if !along {
            self.evaluate_instance(graph, values, inst, linearize)?;
        }
        let buf = buffers(&mut self.initial_buffers, &mut self.step_buffers, inst);
        let keys = factor.keys();
        let touches_first = keys.iter().any(|k| inst.step - k.lag == k0);
        buf.whiten(factor, linearize && !along);
        for r in &buf.r {
            let c = 0.5 * r * r;
            *cost += c;
            if touches_first {
                *cost_first += c;
            }
        }
        if linearize {
            let step = inst.step - k0;
            let lagged = step >= 1 && keys.iter().any(|k| k.lag == 1);
            if along {
                // The rows J [p N] came back unwhitened: [p | N(step) | N(step − 1)].
                let d0 = self.hard[step].reduction.dim;
                let d1 = if lagged {
                    self.hard[step - 1].reduction.dim
                } else {
                    0
                };
                let c = 1 + d0 + d1;
                self.reduced_spans[0][..buf.r.len()].fill((0, d0));
                self.reduced_spans[1][..buf.r.len()].fill((0, d1));
                for (row, (&w, &r)) in buf.weights.iter().zip(&buf.r).enumerate() {
                    let out = &self.along_out[row * c..(row + 1) * c];
                    self.shifted[row] = r + w * out[0];
                    for (o, v) in self.reduced[0][row * s..row * s + d0]
                        .iter_mut()
                        .zip(&out[1..1 + d0])
                    {
                        *o = w * v;
                    }
                    for (o, v) in self.reduced[1][row * s..row * s + d1]
                        .iter_mut()
                        .zip(&out[1 + d0..])
                    {
                        *o = w * v;
                    }
                }
            } else {
                reduce_factor(
                    &mut self.reduced,
                    &mut self.reduced_spans,
                    &mut self.shifted,
                    &self.hard,
                    graph,
                    factor,
                    step,
                    buf,
                    s,
                );
            }
            if let Some(d) = self.rows_width.filter(|_| step == 0 && !lagged) {
                for (row, &rr) in self.shifted[..factor.dim()].iter().enumerate() {
                    let (lo, hi) = self.reduced_spans[0][row];
                    let jr = &self.reduced[0][row * s..row * s + d];
                    self.rows
                        .extend((0..d).map(|a| if a >= lo && a < hi { jr[a] } else { 0.0 }));
                    self.rows.push(rr);
                }
            }
            accumulate(
                &mut self.h,
                &mut self.g,
                &self.reduced,
                &self.reduced_spans,
                &self.shifted[..factor.dim()],
                step,
                lagged,
                s,
                &mut self.nonzeros,
            );
        }
        Ok(())
    }

    /// Linearizes a soft factor instance along its blocks' reductions,
    /// J [p N] per key ([`Factor::evaluate_along`]), into `along_out` (columns: p,
    /// then block step's reduced coordinates, then those of the block before), its
    /// residual into its buffer; returns false when the factor declines.
    fn evaluate_along(
        &mut self,
        graph: &ChainGraph,
        values: &[f64],
        k0: usize,
        inst: Instance,
    ) -> Result<bool> {
        let s = self.s;
        let factor = factor_of(graph, inst);
        let keys = factor.keys();
        let step = inst.step - k0;
        let lagged = step >= 1 && keys.iter().any(|k| k.lag == 1);
        let d0 = self.hard[step].reduction.dim;
        let d1 = if lagged {
            self.hard[step - 1].reduction.dim
        } else {
            0
        };
        let c = 1 + d0 + d1;
        let mut xs: [&[f64]; 8] = [&[]; 8];
        let mut ranges = [(0, 0); 8];
        let mut at = 0;
        for (a, k) in keys.iter().enumerate() {
            let (off, d) = graph.layout.slot(k.kind).unwrap_or((0, 0));
            let base = (inst.step - k.lag) * s + off;
            xs[a] = &values[base..base + d];
            let v = &mut self.along_dirs[at..at + d * c];
            v.fill(0.0);
            // A variable held fixed before the window (k.lag > step) moves not.
            if k.lag <= step {
                let red = &self.hard[step - k.lag].reduction;
                let col0 = if k.lag == 0 { 1 } else { 1 + d0 };
                for (i, row) in v.chunks_exact_mut(c).enumerate() {
                    row[0] = red.particular[off + i];
                    let (start, nrow) = red.row(off + i);
                    row[col0 + start..col0 + start + nrow.len()].copy_from_slice(nrow);
                }
            }
            ranges[a] = (at, at + d * c);
            at += d * c;
        }
        let mut dirs: [&[f64]; 8] = [&[]; 8];
        for (d, &(a, b)) in dirs.iter_mut().zip(&ranges[..keys.len()]) {
            *d = &self.along_dirs[a..b];
        }
        let buf = buffers(&mut self.initial_buffers, &mut self.step_buffers, inst);
        let t = graph.time(inst.step);
        factor
            .evaluate_along(
                t,
                &xs[..keys.len()],
                &mut buf.r,
                &dirs[..keys.len()],
                c,
                &mut self.along_out[..factor.dim() * c],
                &mut self.ws,
            )
            .map_err(located(factor, inst.step, t))
    }

    /// Evaluates the factors of a scope at `values` (the whole trajectory, step-major)
    /// and returns the cost; with `linearize`, also reduces each block's hard
    /// equations and fills H and g of the soft factors in reduced coordinates.
    #[allow(clippy::too_many_arguments)]
    fn evaluate(
        &mut self,
        graph: &ChainGraph,
        values: &[f64],
        k0: usize,
        k1: usize,
        prior: Option<&LinearPrior>,
        scope: Scope,
        linearize: bool,
    ) -> Result<f64> {
        let s = self.s;
        let blocks = k1 - k0;
        self.last = None;
        self.collect_instances(graph, k0, k1, scope);
        let mode = if linearize {
            HardPass::Linearize
        } else {
            HardPass::Cost
        };
        let (mut soft, mut soft_first) = (0.0, 0.0);
        self.rows.clear();
        self.rows_width = None;
        let record = linearize && blocks == 1 && prior.is_none();
        if self.step_major && linearize {
            // Step by step: each step's hard equations, then its factors into its
            // blocks of H (and the lagged ones into the previous step's) while they
            // are in cache.
            self.h.set_blocks(blocks);
            let cached = self.hard_cache.take() == Some(k0) && blocks == 1;
            for b in 0..blocks {
                if !cached {
                    self.hard_block(graph, values, b, mode)?;
                }
                self.h.reset_block(b, self.hard[b].reduction.dim);
                self.g[b * s..(b + 1) * s].fill(0.0);
                if record {
                    self.rows_width = Some(self.hard[0].reduction.dim);
                }
                for at in self.block_start[b]..self.block_start[b + 1] {
                    let i = self.by_step[at];
                    if !is_hard(factor_of(graph, self.instances[i])) {
                        self.soft_instance(graph, values, k0, i, true, &mut soft, &mut soft_first)?;
                    }
                }
            }
        } else {
            // Hard factors first: their linearization defines each block's reduction
            // (unless `project_prior` has just made it for this one-step window).
            let cached = self.hard_cache.take() == Some(k0) && blocks == 1 && linearize;
            for b in 0..blocks {
                if !cached {
                    self.hard_block(graph, values, b, mode)?;
                }
            }
            if linearize {
                // Directions the hard equations fix carry no unknown.
                let hard = &self.hard;
                self.h.reset_active(blocks, |b| hard[b].reduction.dim);
                self.g[..blocks * s].fill(0.0);
                if record {
                    self.rows_width = Some(self.hard[0].reduction.dim);
                }
            }
        }
        let (mut cost, mut cost_first) = self.hard_cost_sum(graph, k0);
        if self.step_major && linearize {
            cost += soft;
            cost_first += soft_first;
        } else {
            for i in 0..self.instances.len() {
                if !is_hard(factor_of(graph, self.instances[i])) {
                    self.soft_instance(
                        graph,
                        values,
                        k0,
                        i,
                        linearize,
                        &mut cost,
                        &mut cost_first,
                    )?;
                }
            }
        }
        if let Some(p) = prior {
            let x = &values[k0 * s..(k0 + 1) * s];
            let (d, rest) = self.scratch.split_at_mut(s);
            let (grad, rest) = rest.split_at_mut(s);
            for i in 0..s {
                d[i] = x[i] - p.xbar[i];
            }
            // grad = Λδ + η; cost = c + ηᵀδ + ½δᵀΛδ.
            let mut quad = 0.0;
            for i in 0..s {
                let row = &p.information[i * s..(i + 1) * s];
                let ld: f64 = row.iter().zip(d.iter()).map(|(a, b)| a * b).sum();
                quad += d[i] * ld;
                grad[i] = ld + p.eta[i];
            }
            let lin: f64 = p.eta.iter().zip(d.iter()).map(|(a, b)| a * b).sum();
            cost += p.constant + lin + 0.5 * quad;
            cost_first += p.constant + lin + 0.5 * quad;
            if linearize {
                // In reduced coordinates δ₀ = p₀ + N₀y: H += N₀ᵀΛN₀, g += N₀ᵀ(grad + Λp₀).
                let red = &self.hard[0].reduction;
                let dim = red.dim;
                let ln = &mut rest[..s * dim];
                // ΛN₀ over N₀'s nonzeros: its first q columns on the rows `free`, then
                // one unit column per untouched unknown (each sum over rows in order).
                let (free, untouched) = red.structure();
                let q = dim - untouched.len();
                for i in 0..s {
                    let row = &p.information[i * s..(i + 1) * s];
                    grad[i] += row
                        .iter()
                        .zip(&red.particular)
                        .map(|(a, b)| a * b)
                        .sum::<f64>();
                    let out = &mut ln[i * dim..(i + 1) * dim];
                    for (c, o) in out[..q].iter_mut().enumerate() {
                        *o = free
                            .iter()
                            .fold(0.0, |acc, &k| acc + row[k] * red.free_row(k)[c]);
                    }
                    for (o, &k) in out[q..].iter_mut().zip(untouched) {
                        *o = 0.0 + row[k];
                    }
                }
                let h0 = self.h.diag_mut(0);
                for k in 0..s {
                    let (start, nrow) = red.row(k);
                    let lrow = &ln[k * dim..(k + 1) * dim];
                    for (a, &na) in nrow.iter().enumerate() {
                        let a = start + a;
                        if na == 0.0 {
                            continue;
                        }
                        for (o, lv) in h0[a * dim..(a + 1) * dim].iter_mut().zip(lrow) {
                            *o += na * lv;
                        }
                        self.g[a] += na * grad[k];
                    }
                }
            }
        }

        if !cost.is_finite() {
            return Err(Error::Singular("the cost is not finite".into()));
        }
        self.cost_first = cost_first;
        Ok(cost)
    }

    /// The gradient of the Lagrangian of the window's problem in full coordinates,
    /// Σ Jᵢᵀrᵢ over the soft factors (whitened), the prior's Λ(x − x̄) + η, and
    /// Σ C_bᵀλ_b over each block's hard equations (rows in `hard_block` order) with the
    /// multipliers in `self.newton.lambda`; into `out` (blocks × s).
    #[allow(clippy::too_many_arguments)]
    fn lagrangian_gradient(
        &mut self,
        graph: &ChainGraph,
        values: &[f64],
        k0: usize,
        k1: usize,
        prior: Option<&LinearPrior>,
        out: &mut [f64],
    ) -> Result<()> {
        let s = self.s;
        let blocks = k1 - k0;
        out[..blocks * s].fill(0.0);
        self.newton.rows[..blocks].fill(0);
        for i in 0..self.instances.len() {
            let inst = self.instances[i];
            let factor = factor_of(graph, inst);
            self.evaluate_instance(graph, values, inst, true)?;
            let buf = buffers(&mut self.initial_buffers, &mut self.step_buffers, inst);
            let hard = is_hard(factor);
            let dim = factor.dim();
            // What multiplies each row: its whitened residual, or its multiplier.
            let weights: &[f64] = if hard {
                let b = inst.step - k0;
                let row0 = self.newton.rows[b];
                self.newton.rows[b] += dim;
                let base = b * self.newton.max_hard + row0;
                &self.newton.lambda[base..base + dim]
            } else {
                buf.whiten(factor, true);
                &buf.r
            };
            for (a, k) in factor.keys().iter().enumerate() {
                if inst.step < k0 + k.lag {
                    continue; // a variable held fixed before the window
                }
                let (off, d) = graph.layout.slot(k.kind).unwrap_or((0, 0));
                let base = (inst.step - k.lag - k0) * s + off;
                let jac = &buf.jac[a];
                let diagonal = factor.diagonal_jacobian(a);
                for (r, &w) in weights.iter().enumerate() {
                    let columns = if diagonal { r..r + 1 } else { 0..d };
                    for j in columns {
                        out[base + j] += jac[r * d + j] * w;
                    }
                }
            }
        }
        if let Some(p) = prior {
            let x = &values[k0 * s..(k0 + 1) * s];
            for i in 0..s {
                let row = &p.information[i * s..(i + 1) * s];
                let ld: f64 = (0..s).map(|j| row[j] * (x[j] - p.xbar[j])).sum();
                out[i] += ld + p.eta[i];
            }
        }
        Ok(())
    }

    /// Replaces the Gauss-Newton matrix in H by the reduced Hessian of the Lagrangian,
    /// Nᵀ(JᵀJ + Σ rᵢ∇²rᵢ + Σ λⱼ∇²cⱼ)N per block pair, by central differences of the
    /// Lagrangian's exact gradient along the null-space columns. Blocks three apart
    /// share no factor, so one perturbation serves every third block (3·d gradients
    /// per difference side, whatever the window's length). The gradient g is kept.
    ///
    /// Gauss-Newton leaves the second-order terms out, which is right when they are
    /// small against JᵀJ. Along the motion of a dependent-coordinate graph they are
    /// not: that direction is informed only by the marginal prior, whose information
    /// decays over a run, while the conflict between the integrated motion and the
    /// constraints keeps the residuals finite; Gauss-Newton then converges linearly
    /// with a rate near 1, or alternates (docs/dc-stall.md).
    fn exact_hessian(
        &mut self,
        graph: &ChainGraph,
        values: &mut [f64],
        k0: usize,
        k1: usize,
        prior: Option<&LinearPrior>,
    ) -> Result<()> {
        let s = self.s;
        let blocks = k1 - k0;
        let n = blocks * s;
        self.collect_instances(graph, k0, k1, Scope::Window);
        // Multipliers from the soft gradient at the point.
        let mut grad = std::mem::take(&mut self.newton.grad);
        self.newton.lambda.fill(0.0);
        let result = self.lagrangian_gradient(graph, values, k0, k1, prior, &mut grad);
        if let Err(e) = result {
            self.newton.grad = grad;
            return Err(e);
        }
        let mh = self.newton.max_hard;
        for b in 0..blocks {
            let red = &mut self.hard[b].reduction;
            red.multipliers(
                &grad[b * s..(b + 1) * s],
                &mut self.newton.lambda[b * mh..(b + 1) * mh],
            );
        }
        self.newton.grad = grad;
        for b in 0..blocks {
            let (diag, d) = (self.h.diag(b), self.h.dim(b));
            for r in 0..d {
                self.newton.scale[b * s + r] = diag[r * d + r];
            }
        }
        let colors = blocks.min(3);
        let dmax = (0..blocks)
            .map(|b| self.hard[b].reduction.dim)
            .max()
            .unwrap_or(0);
        self.saved[..n].copy_from_slice(&values[k0 * s..k1 * s]);
        let (mut plus, mut minus) = (
            std::mem::take(&mut self.newton.plus),
            std::mem::take(&mut self.newton.minus),
        );
        // ε per block, relative to its largest entry.
        // ε per direction, relative to the size of the values it moves: a block holds
        // q, q̇ and q̈ of very different sizes (a 7 mm crank at 6e5 rad/s²), and an ε
        // taken from the block's largest entry moved the positions by 0.1 m.
        let step = |red: &NullSpace, j: usize, x: &[f64]| {
            let along: f64 = (0..x.len())
                .map(|i| {
                    let (start, row) = red.row(i);
                    if j >= start && j < start + row.len() {
                        row[j - start].abs() * x[i].abs()
                    } else {
                        0.0
                    }
                })
                .sum();
            1e-6 * (1.0 + along)
        };
        let mut column = std::mem::take(&mut self.newton.column);
        let mut result: Result<()> = Ok(());
        'columns: for color in 0..colors {
            for j in 0..dmax {
                for (out, sign) in [(&mut plus, 1.0), (&mut minus, -1.0)] {
                    let window = &mut values[k0 * s..k1 * s];
                    window.copy_from_slice(&self.saved[..n]);
                    for b in (color..blocks).step_by(3) {
                        let red = &self.hard[b].reduction;
                        if j >= red.dim {
                            continue;
                        }
                        let x = &mut window[b * s..(b + 1) * s];
                        let eps = sign * step(red, j, x);
                        for (i, xi) in x.iter_mut().enumerate() {
                            let (start, row) = red.row(i);
                            if j >= start && j < start + row.len() {
                                *xi += eps * row[j - start];
                            }
                        }
                    }
                    result = self.lagrangian_gradient(graph, values, k0, k1, prior, out);
                    if result.is_err() {
                        break 'columns;
                    }
                }
                // Column j of H_bb and H_{b+1,b} in reduced coordinates for every
                // perturbed block b.
                for b in (color..blocks).step_by(3) {
                    if j >= self.hard[b].reduction.dim {
                        continue;
                    }
                    let h = 2.0 * step(&self.hard[b].reduction, j, &self.saved[b * s..(b + 1) * s]);
                    // H_bb and H_{b+1,b} both have d_b columns (packed, stride d_b).
                    let db = self.hard[b].reduction.dim;
                    for target in [b, b + 1] {
                        if target >= blocks {
                            continue;
                        }
                        let red = &self.hard[target].reduction;
                        let col = &mut column[..red.dim];
                        col.fill(0.0);
                        for i in 0..s {
                            let hv = (plus[target * s + i] - minus[target * s + i]) / h;
                            let (start, row) = red.row(i);
                            for (c, nv) in col[start..].iter_mut().zip(row) {
                                *c += nv * hv;
                            }
                        }
                        let block = if target == b {
                            self.h.diag_mut(target)
                        } else {
                            self.h.lower_mut(target)
                        };
                        for (a, v) in col.iter().enumerate() {
                            block[a * db + j] = *v;
                        }
                    }
                }
            }
        }
        self.newton.column = column;
        values[k0 * s..k1 * s].copy_from_slice(&self.saved[..n]);
        self.newton.plus = plus;
        self.newton.minus = minus;
        result?;
        // The differences are symmetric only to their error: symmetrize.
        for b in 0..blocks {
            let d = self.hard[b].reduction.dim;
            let diag = self.h.diag_mut(b);
            for i in 0..d {
                for j in 0..i {
                    let v = 0.5 * (diag[i * d + j] + diag[j * d + i]);
                    diag[i * d + j] = v;
                    diag[j * d + i] = v;
                }
            }
        }
        Ok(())
    }

    /// Restricts a prior on step k to the tangent space of k's hard equations: with
    /// x̃ = x_k + p̄ on their linearization and P = N̄N̄ᵀ the projector onto its null
    /// space, the prior becomes Q(x̃) + (P∇Q(x̃))ᵀ(x − x̃) + ½(x − x̃)ᵀPΛP(x − x̃).
    ///
    /// On the constraint manifold the two agree to second order but for one term:
    /// the prior's pull across the manifold (the conflict between the integrated
    /// motion and the constraints) times the manifold's curvature. Where the prior
    /// knows little along the motion (its information there decays over a run) that
    /// term dominates and has the wrong sign on the concave side: the window's cost
    /// gets two minima on either side of the motion, a phase jump between them, and
    /// Gauss-Newton stalls between them (docs/dc-stall.md). A Gaussian on the
    /// manifold is a Gaussian in its tangent coordinates; this is that Gaussian.
    pub fn project_prior(
        &mut self,
        graph: &ChainGraph,
        values: &[f64],
        k: usize,
        prior: &mut LinearPrior,
    ) -> Result<()> {
        let s = self.s;
        self.collect_instances(graph, k, k + 1, Scope::Window);
        self.hard_block(graph, values, 0, HardPass::Linearize)?;
        // A one-step window solve of step k that follows finds it reduced.
        self.hard_cache = Some(k);
        let block = &mut self.hard[0];
        if block.rows == 0 {
            return Ok(());
        }
        let red = &block.reduction;
        let d = red.dim;
        let x = &values[k * s..(k + 1) * s];
        let (delta, rest) = self.scratch.split_at_mut(s);
        let (grad, rest) = rest.split_at_mut(s);
        let (gt, rest) = rest.split_at_mut(s);
        let (ln, rest) = rest.split_at_mut(s * s);
        let (reduced, rest) = rest.split_at_mut(s * s);
        let nr = &mut rest[..s * s];
        // δ = x̃ − x̄, ∇Q(x̃) = η + Λδ and Q(x̃).
        let (mut lin, mut quad) = (0.0, 0.0);
        for i in 0..s {
            delta[i] = x[i] + red.particular[i] - prior.xbar[i];
        }
        for i in 0..s {
            let row = &prior.information[i * s..(i + 1) * s];
            let ld: f64 = row.iter().zip(delta.iter()).map(|(a, b)| a * b).sum();
            grad[i] = prior.eta[i] + ld;
            quad += delta[i] * ld;
            lin += prior.eta[i] * delta[i];
        }
        let constant = prior.constant + lin + 0.5 * quad;
        // N̄'s structure: columns 0..q dense on the rows `free`, column q + u the unit
        // vector of `untouched[u]`, rows of fixed unknowns 0.
        let (free, untouched) = red.structure();
        let q = d - untouched.len();
        // ΛN̄ (s × d).
        for i in 0..s {
            let row = &prior.information[i * s..(i + 1) * s];
            let out = &mut ln[i * d..(i + 1) * d];
            out[..q].fill(0.0);
            for &j in free {
                let lij = row[j];
                for (o, b) in out[..q].iter_mut().zip(red.free_row(j)) {
                    *o += lij * b;
                }
            }
            for (o, &j) in out[q..].iter_mut().zip(untouched) {
                *o = row[j];
            }
        }
        // N̄ᵀΛN̄ (d × d) and N̄ᵀ∇Q.
        reduced[..q * d].fill(0.0);
        gt[..q].fill(0.0);
        for &i in free {
            let li = &ln[i * d..(i + 1) * d];
            for (a, &b) in red.free_row(i).iter().enumerate() {
                gt[a] += b * grad[i];
                for (o, l) in reduced[a * d..(a + 1) * d].iter_mut().zip(li) {
                    *o += b * l;
                }
            }
        }
        for (u, &i) in untouched.iter().enumerate() {
            let a = q + u;
            gt[a] = grad[i];
            reduced[a * d..(a + 1) * d].copy_from_slice(&ln[i * d..(i + 1) * d]);
        }
        // Back to full coordinates: R = N̄(N̄ᵀΛN̄) (s × d), PΛP = R N̄ᵀ, P∇Q = N̄(N̄ᵀ∇Q).
        nr[..s * d].fill(0.0);
        prior.eta.fill(0.0);
        for &i in free {
            let out = &mut nr[i * d..(i + 1) * d];
            for (a, &b) in red.free_row(i).iter().enumerate() {
                prior.eta[i] += b * gt[a];
                for (o, r) in out.iter_mut().zip(&reduced[a * d..(a + 1) * d]) {
                    *o += b * r;
                }
            }
        }
        for (u, &i) in untouched.iter().enumerate() {
            let a = q + u;
            prior.eta[i] = gt[a];
            nr[i * d..(i + 1) * d].copy_from_slice(&reduced[a * d..(a + 1) * d]);
        }
        prior.information.fill(0.0);
        for i in 0..s {
            let row = &nr[i * d..(i + 1) * d];
            let out = &mut prior.information[i * s..(i + 1) * s];
            for &j in free {
                out[j] = row[..q]
                    .iter()
                    .zip(red.free_row(j))
                    .map(|(a, b)| a * b)
                    .sum::<f64>();
            }
            for (u, &j) in untouched.iter().enumerate() {
                out[j] = row[q + u];
            }
        }
        // Exactly symmetric (the two triangles summed in different orders).
        for i in 0..s {
            for j in 0..i {
                let v = 0.5 * (prior.information[i * s + j] + prior.information[j * s + i]);
                prior.information[i * s + j] = v;
                prior.information[j * s + i] = v;
            }
            prior.xbar[i] = x[i] + red.particular[i];
        }
        prior.constant = constant;
        Ok(())
    }

    /// After a full step from `saved` along `direction` failed to lower the cost:
    /// the first of its halves, quarters, … (down to 1/256) that does, linearized for
    /// the next iteration, or `None` with the window back at `saved`.
    #[allow(clippy::too_many_arguments)]
    fn backtrack(
        &mut self,
        graph: &ChainGraph,
        values: &mut [f64],
        k0: usize,
        k1: usize,
        prior: Option<&LinearPrior>,
        cost: f64,
    ) -> Result<Option<f64>> {
        let s = self.s;
        let n = (k1 - k0) * s;
        let mut t = 1.0;
        for _ in 0..8 {
            t *= 0.5;
            for ((x, x0), d) in values[k0 * s..k1 * s]
                .iter_mut()
                .zip(&self.saved[..n])
                .zip(&self.direction[..n])
            {
                *x = x0 + t * d;
            }
            let trial = match self.correct(graph, values, k0, k1) {
                Ok(()) => self.evaluate(graph, values, k0, k1, prior, Scope::Window, false),
                Err(e) => Err(e),
            };
            if let Ok(c) = trial {
                if c < cost {
                    return match self.evaluate(graph, values, k0, k1, prior, Scope::Window, true) {
                        Ok(c) => Ok(Some(c)),
                        Err(_) => break,
                    };
                }
            }
        }
        values[k0 * s..k1 * s].copy_from_slice(&self.saved[..n]);
        Ok(None)
    }

    /// Optimizes steps k0..k1 (k0 ≥ 1) with step k0 − 1 held at its value: the factors
    /// joining them stay, as constraints on the window rather than unknowns. The
    /// fixed-lag smoother uses it to bring a new step close to its optimum before the
    /// whole window is solved, which then mostly converges in one iteration.
    pub fn solve_conditional(
        &mut self,
        graph: &ChainGraph,
        values: &mut [f64],
        k0: usize,
        k1: usize,
    ) -> Result<SolveReport> {
        if k0 == 0 {
            return Err(Error::InvalidArgument(
                "a conditional solve needs a step before the window".into(),
            ));
        }
        self.conditional = true;
        let report = self.solve(graph, values, k0, k1, None);
        self.conditional = false;
        report
    }

    /// Optimizes steps k0..k1 of `values` (step-major, the whole trajectory) with an
    /// optional prior on step k0; the rest of `values` is read, not changed.
    pub fn solve(
        &mut self,
        graph: &ChainGraph,
        values: &mut [f64],
        k0: usize,
        k1: usize,
        prior: Option<&LinearPrior>,
    ) -> Result<SolveReport> {
        if k1 <= k0 || k1 - k0 > self.h.capacity() {
            return Err(Error::InvalidArgument(format!(
                "window {k0}..{k1} is empty or larger than the solver's capacity {}",
                self.h.capacity()
            )));
        }
        let s = self.s;
        let n = (k1 - k0) * s;
        let lm = self.settings.method == Method::LevenbergMarquardt;
        // Start undamped: with a good guess the Gauss-Newton step is accepted; damping
        // (relative to diag H) is switched on only when a step fails to lower the cost.
        let mut mu: f64 = 0.0;
        let mut nu = 2.0;
        let diverged = |cost: f64, iterations| SolveReport {
            iterations,
            termination: Termination::Diverged,
            cost,
        };
        let mut cost = match self.evaluate(graph, values, k0, k1, prior, Scope::Window, true) {
            Ok(c) => c,
            Err(_) => return Ok(diverged(f64::INFINITY, 0)),
        };
        let mut iterations = 0;
        // Gauss-Newton until it shows the slow linear convergence or the failed step
        // of a poor model; then the exact reduced Hessian (`exact_hessian`) for the
        // rest of the solve. `gauss_newton` says H holds a fresh Gauss-Newton matrix.
        let mut newton = false;
        let mut gauss_newton = true;
        let mut previous = f64::INFINITY;
        let mut slow = false;
        // The last accepted step was below the tolerance and kept the hard equations:
        // the point is an optimum as far as a damped model can tell.
        let mut settled = false;
        while iterations < self.settings.max_iterations {
            iterations += 1;
            if newton && gauss_newton {
                if self.exact_hessian(graph, values, k0, k1, prior).is_err() {
                    return Ok(diverged(cost, iterations));
                }
                gauss_newton = false;
            }
            for (b, damping) in self.damping[..n].chunks_exact_mut(s).enumerate() {
                let (diag, d) = (self.h.diag(b), self.h.dim(b));
                let scale = &self.newton.scale[b * s..(b + 1) * s];
                for (r, v) in damping[..d].iter_mut().enumerate() {
                    let x = if newton { scale[r] } else { diag[r * d + r] };
                    *v = mu * x.max(1e-12);
                }
            }
            let factored = self
                .chol
                .factor(&self.h, if lm { &self.damping[..n] } else { &[] })
                .is_ok();
            // Gauss-Newton from J itself where H = JᵀJ is too ill-conditioned for its
            // Cholesky factor to give the step to more than a few digits.
            let from_rows = mu == 0.0
                && !newton
                && (!factored || self.chol.pivot_ratio() < self.settings.normal_equations_limit)
                && self.least_squares_step();
            if factored && !from_rows {
                for i in 0..n {
                    self.delta[i] = -self.g[i];
                }
                self.chol.solve(&mut self.delta[..n]);
            } else if !from_rows {
                if mu == 0.0 && settled {
                    // H is singular to working precision where the damped steps have
                    // already come to rest: no undamped step can say more (the six-bar
                    // press's windows in IC, cycling from 1e-4 down to 1e-12 and back).
                    return Ok(SolveReport {
                        iterations,
                        termination: Termination::Converged,
                        cost,
                    });
                }
                if !lm || mu > 1e16 {
                    return Ok(diverged(cost, iterations));
                }
                mu = (mu * 10.0).max(self.settings.initial_damping);
                continue;
            }
            // The decrease the linear model predicts for the soft factors in y:
            // −gᵀy − ½yᵀHy.
            self.h.multiply(&self.delta[..n], &mut self.hd[..n]);
            let predicted: f64 = (0..n)
                .map(|i| -self.g[i] * self.delta[i] - 0.5 * self.delta[i] * self.hd[i])
                .sum();
            let window = &mut values[k0 * s..k1 * s];
            self.saved[..n].copy_from_slice(window);
            // δ = p + N y per block; `largest` is max |δᵢ| / (1 + |xᵢ|).
            let (mut largest, mut restored) = (0.0f64, true);
            for b in 0..k1 - k0 {
                let red = &self.hard[b].reduction;
                let at_round_off = self.hard[b].at_round_off;
                let y = &self.delta[b * s..(b + 1) * s];
                let x = &mut window[b * s..(b + 1) * s];
                for i in 0..s {
                    let p = red.particular[i];
                    let (start, nrow) = red.row(i);
                    let step = p + nrow
                        .iter()
                        .zip(&y[start..])
                        .map(|(a, b)| a * b)
                        .sum::<f64>();
                    let scale = 1.0 + x[i].abs();
                    largest = largest.max(step.abs() / scale);
                    restored &= at_round_off || p.abs() <= self.settings.step_tolerance * scale;
                    x[i] += step;
                    self.direction[b * s + i] = step;
                }
            }
            let small = largest <= self.settings.step_tolerance;
            if small && mu == 0.0 {
                // Converged: the point moved by less than the tolerance, so the cost
                // the model predicts is the cost there, to far below its round-off,
                // and the hard equations, exact to first order along δ, are off by
                // O(|δ|²) ≤ 1e-16: no correction needed.
                if !self.conditional && !newton {
                    self.last = Some(LastSolve { k0, k1 });
                }
                return Ok(SolveReport {
                    iterations,
                    termination: Termination::Converged,
                    cost: cost - predicted,
                });
            }
            // The trial is linearized at once: accepted (the usual case), it is the
            // next iteration's system; rejected, the old point is linearized again.
            let trial = match self.correct(graph, values, k0, k1) {
                Ok(()) => self.evaluate(graph, values, k0, k1, prior, Scope::Window, true),
                Err(e) => Err(e),
            };
            gauss_newton = true;
            // Converged when an undamped step is small; or when it restores the hard
            // factors and either the model predicts a decrease below 1e-12 of the cost,
            // or the step fails to lower the cost while it is below 1e-6 (relative) or
            // predicts less than 1e-6 of it: then the cost comparison only sees the
            // residuals' round-off (their evaluation goes through a factorization),
            // and what is left is a slow Gauss-Newton tail along a direction with
            // little information. A small damped step proves nothing: damping alone
            // can make it small.
            let no_progress = match &trial {
                Ok(c) => *c >= cost,
                Err(_) => true,
            };
            // A negative prediction is no "little left to gain": the model itself is
            // off (H's round-off), and the step may be anything.
            let little = |fraction: f64| (0.0..=fraction * cost.abs()).contains(&predicted);
            let flat =
                restored && (little(1e-12) || (no_progress && (largest <= 1e-6 || little(1e-6))));
            let converged = (small || flat) && mu == 0.0;
            if std::env::var("LMTRACE").is_ok() {
                eprintln!("k0={k0} k1={k1} it={iterations} newton={newton} cost={cost:.6e} trial={:?} mu={mu:.1e} pred={predicted:.3e} |d|={largest:.2e} small={small} restored={restored}", trial.as_ref().ok());
            }

            match trial {
                Ok(c) if converged || c <= cost || !lm => {
                    if converged && c > cost {
                        // Converged where the step could not lower the cost: the point
                        // before the step is the answer (within round-off of the trial
                        // where the comparison is round-off, far better where not).
                        values[k0 * s..k1 * s].copy_from_slice(&self.saved[..n]);
                        return Ok(SolveReport {
                            iterations,
                            termination: Termination::Converged,
                            cost,
                        });
                    }
                    if converged {
                        return Ok(SolveReport {
                            iterations,
                            termination: Termination::Converged,
                            cost: c,
                        });
                    }
                    // Where the model predicted the decrease well (ratio > 3/4), go back
                    // to Gauss-Newton at once: damping relative to diag H all but
                    // freezes directions with little information, and easing it off
                    // by thirds costs a dozen iterations.
                    // Undamped steps shrinking by less than 4× twice in a row: the
                    // linear convergence of a model missing its second-order terms.
                    if mu == 0.0 {
                        let slower = largest > 0.25 * previous;
                        newton |= slow && slower && self.settings.second_order;
                        slow = slower;
                        previous = largest;
                    }
                    settled = small && restored;
                    let ratio = (cost - c) / predicted.max(f64::MIN_POSITIVE);
                    // A step below the tolerance leaves only round-off to compare, and
                    // says no more about the model than that the undamped step is due.
                    mu = if ratio > 0.75 || mu < 1e-12 || settled {
                        0.0
                    } else {
                        mu / 3.0
                    };
                    cost = c;
                    nu = 2.0;
                }
                _ => {
                    // A failed full step after the first (which starts from a
                    // prediction off the constraints): the model is wrong at its scale.
                    newton |= iterations >= 2 && self.settings.second_order;
                    if lm && mu == 0.0 && !small {
                        // The full step overshot: try fractions of it before damping,
                        // which would turn the step away from the directions with
                        // little information, where it is most needed.
                        if let Some(c) = self.backtrack(graph, values, k0, k1, prior, cost)? {
                            previous = f64::INFINITY;
                            slow = false;
                            settled = false;
                            cost = c;
                            continue;
                        }
                    }
                    values[k0 * s..k1 * s].copy_from_slice(&self.saved[..n]);
                    if !lm {
                        return Ok(diverged(cost, iterations));
                    }
                    if self
                        .evaluate(graph, values, k0, k1, prior, Scope::Window, true)
                        .is_err()
                    {
                        return Ok(diverged(cost, iterations));
                    }
                    if small && restored {
                        // A damped step below the tolerance, along a descent direction,
                        // failed to lower the cost: the cost's changes are below its
                        // round-off (the residuals go through factorizations), so no
                        // step can be judged any more. This is the optimum.
                        return Ok(SolveReport {
                            iterations,
                            termination: Termination::Converged,
                            cost,
                        });
                    }
                    if small {
                        // The damped step vanished without lowering the cost: try the
                        // undamped one again.
                        mu = 0.0;
                        continue;
                    }
                    mu = (mu * nu).max(self.settings.initial_damping);
                    nu *= 2.0;
                    if mu > 1e16 {
                        return Ok(diverged(cost, iterations));
                    }
                }
            }
        }
        Ok(SolveReport {
            iterations,
            termination: Termination::IterationLimit,
            cost,
        })
    }

    /// The Gauss-Newton step of a one-block window from its rows (`rows`), by an SVD
    /// of the reduced Jacobian itself, into `delta`; false when the rows are not at
    /// hand or the step is not finite. H = JᵀJ squares J's condition number: a stiff
    /// force's row next to the integrators' (a light crank against a stiff spring, in
    /// independent coordinates) makes J's 1e8 into H's 1e16, where the Cholesky factor
    /// fails although J still determines the step to 8 digits.
    fn least_squares_step(&mut self) -> bool {
        let Some(d) = self.rows_width else {
            return false;
        };
        let m = self.rows.len() / (d + 1);
        if d == 0 || m < d {
            return false;
        }
        let a = nalgebra::DMatrix::from_fn(m, d, |i, j| self.rows[i * (d + 1) + j]);
        let b = nalgebra::DVector::from_fn(m, |i, _| -self.rows[i * (d + 1) + d]);
        let svd = a.svd(true, true);
        let Some(&largest) = svd.singular_values.iter().max_by(|x, y| x.total_cmp(y)) else {
            return false;
        };
        let Ok(y) = svd.solve(&b, largest * LEAST_SQUARES_CUTOFF) else {
            return false;
        };
        if !y.iter().all(|v| v.is_finite()) {
            return false;
        }
        self.delta[..self.s].fill(0.0);
        self.delta[..d].copy_from_slice(y.as_slice());
        true
    }

    /// Marginalizes step k0 (with `prior` on it, if any) into a prior on step k0+1:
    /// the factors touching k0 are linearized at `values`, k0's hard equations fix
    /// δ₀ = p₀ + N₀y₀, and y₀ is eliminated from the reduced normal equations by the
    /// Schur complement Λ = H₁₁ − H₁₀H₀₀⁻¹H₀₁, η = g₁ − H₁₀H₀₀⁻¹g₀. Block k0+1 carries
    /// no hard equation in this linearization, so its coordinates are the full ones.
    pub fn marginalize(
        &mut self,
        graph: &ChainGraph,
        values: &[f64],
        k0: usize,
        prior: Option<&LinearPrior>,
    ) -> Result<LinearPrior> {
        let s = self.s;
        if let Some(last) = self.last.take() {
            if last.k0 == k0 {
                return self.marginalize_last(graph, values, k0, last.k1);
            }
        }
        let cost = self.evaluate(graph, values, k0, k0 + 2, prior, Scope::Oldest, true)?;
        let d0 = self.h.dim(0);
        debug_assert_eq!(self.h.dim(1), s);
        // H₀₀, H₁₀ (block 1 rows × block 0 columns), H₁₁, g₀, g₁ into the scratch.
        let ss = s * s;
        let (h00, rest) = self.scratch.split_at_mut(ss);
        let (h10, rest) = rest.split_at_mut(ss);
        let (h11, rest) = rest.split_at_mut(ss);
        let (g01, _) = rest.split_at_mut(2 * s);
        restride(self.h.diag(0), d0, d0, h00, s);
        restride(self.h.lower(1), s, d0, h10, s);
        restride(self.h.diag(1), s, s, h11, s);
        g01[..s].copy_from_slice(&self.g[..s]);
        g01[s..].copy_from_slice(&self.g[s..2 * s]);
        self.schur(k0, d0, cost, values)
    }

    /// The Schur complement of block 0 in the 2-block system held in the scratch
    /// (H₀₀ d0 × d0, H₁₀ s × d0, H₁₁ s × s, all with stride s; g₀, g₁): the prior on
    /// block k0 + 1, whose values are x̄.
    fn schur(&mut self, k0: usize, d0: usize, cost: f64, values: &[f64]) -> Result<LinearPrior> {
        let s = self.s;
        let ss = s * s;
        if self.past_conditioned() {
            return conditional_prior(&self.scratch, s, cost, values, k0);
        }
        let (h00, rest) = self.scratch.split_at_mut(ss);
        let (h10, rest) = rest.split_at_mut(ss);
        let (h11, rest) = rest.split_at_mut(ss);
        let (g01, rest) = rest.split_at_mut(2 * s);
        let (w, rest) = rest.split_at_mut(s);
        let (y, rest) = rest.split_at_mut(ss);
        let acc = &mut rest[..s];
        // L₀ = chol(H₀₀) in place; Y = L₀⁻¹H₀₁ (d0 × s, row-major; row j of h10 is
        // column j of H₀₁); w = L₀⁻¹g₀.
        crate::linalg::dense::cholesky_strided(h00, d0, s).map_err(|_| {
            Error::Singular(format!(
                "marginalizing step {k0}: its soft factors leave a direction undetermined"
            ))
        })?;
        // Forward substitution a whole row of Y at a time (the same sums, in the same
        // order, as one column at a time, but along contiguous rows).
        for a in 0..d0 {
            acc.fill(0.0);
            let (done, row) = y.split_at_mut(a * s);
            for (l, yk) in h00[a * s..a * s + a].iter().zip(done.chunks_exact(s)) {
                for (c, v) in acc.iter_mut().zip(yk) {
                    *c += l * v;
                }
            }
            let lii = h00[a * s + a];
            for (j, out) in row[..s].iter_mut().enumerate() {
                *out = (h10[j * s + a] - acc[j]) / lii;
            }
        }
        w[..d0].copy_from_slice(&g01[..d0]);
        crate::linalg::dense::solve_lower_strided(h00, d0, s, &mut w[..d0]);
        // Λ = H₁₁ − YᵀY, η = g₁ − Yᵀw. YᵀY is summed over the rows of Y in order, one
        // triangle (Λ is symmetric, H₁₁ and YᵀY to the bit), then mirrored.
        let mut information = vec![0.0; ss];
        let mut eta = vec![0.0; s];
        for a in 0..d0 {
            let ya = &y[a * s..(a + 1) * s];
            for (i, &yi) in ya.iter().enumerate() {
                for (o, yj) in information[i * s..=i * s + i].iter_mut().zip(ya) {
                    *o += yi * yj;
                }
                eta[i] += yi * w[a];
            }
        }
        for i in 0..s {
            for j in 0..=i {
                let v = h11[i * s + j] - information[i * s + j];
                information[i * s + j] = v;
                information[j * s + i] = v;
            }
            eta[i] = g01[s + i] - eta[i];
        }
        // ≥ 0 in exact arithmetic (the least value of a sum of squares); round-off
        // near singular configurations can push it below.
        let constant = (cost - 0.5 * w[..d0].iter().map(|v| v * v).sum::<f64>()).max(0.0);
        if !information.iter().chain(&eta).all(|v| v.is_finite()) {
            return Err(Error::Singular(format!(
                "marginalizing step {k0}: non-finite values"
            )));
        }
        Ok(LinearPrior {
            information,
            eta,
            constant,
            xbar: values[(k0 + 1) * s..(k0 + 2) * s].to_vec(),
        })
    }

    /// Marginalization from the last window solve's linearization of its first block
    /// (it converged on a step below the tolerance, so that linearization is the one
    /// at the optimum up to O(tolerance)); only the factors joining k0 to k0 + 1 are
    /// evaluated again, for their columns on k0 + 1 in full coordinates.
    fn marginalize_last(
        &mut self,
        graph: &ChainGraph,
        values: &[f64],
        k0: usize,
        k1: usize,
    ) -> Result<LinearPrior> {
        let s = self.s;
        let ss = s * s;
        let d0 = self.h.dim(0);
        let window_holds_next = k1 > k0 + 1;
        // H₀₀ and g₀ at the optimum: the gradient moves by H δ with the last step.
        {
            let (h00, rest) = self.scratch.split_at_mut(ss);
            let (h10, rest) = rest.split_at_mut(ss);
            let (h11, rest) = rest.split_at_mut(ss);
            let g01 = &mut rest[..2 * s];
            restride(self.h.diag(0), d0, d0, h00, s);
            h10.fill(0.0);
            h11.fill(0.0);
            g01.fill(0.0);
            for a in 0..d0 {
                g01[a] = self.g[a] + self.hd[a];
            }
        }
        let mut cost = self.cost_first;
        // The factors joining k0 and k0 + 1.
        for index in 0..graph.step_factors.len() {
            let factor = graph.step_factors[index].as_ref();
            let keys = factor.keys();
            if is_hard(factor) || !keys.iter().any(|k| k.lag == 1) {
                continue;
            }
            let inst = Instance {
                initial: false,
                index,
                step: k0 + 1,
            };
            self.evaluate_instance(graph, values, inst, true)?;
            let buf = &mut self.step_buffers[index];
            let dim = factor.dim();
            buf.whiten(factor, true);
            if !window_holds_next {
                for r in &buf.r {
                    cost += 0.5 * r * r;
                }
            }
            // Rows: J₀N₀ (dim × d0) into reduced[1], J₁ full (dim × s) into reduced[0].
            let red = &self.hard[0].reduction;
            self.reduced[0][..dim * s].fill(0.0);
            self.reduced[1][..dim * s].fill(0.0);
            for (a, k) in keys.iter().enumerate() {
                let (off, d) = graph.layout.slot(k.kind).unwrap_or((0, 0));
                let diagonal = factor.diagonal_jacobian(a);
                for r in 0..dim {
                    let columns = if diagonal { r..r + 1 } else { 0..d };
                    for j in columns {
                        let v = buf.jac[a][r * d + j];
                        if v == 0.0 {
                            continue;
                        }
                        if k.lag == 0 {
                            self.reduced[0][r * s + off + j] += v;
                        } else {
                            let (start, nrow) = red.row(off + j);
                            let out = &mut self.reduced[1][r * s + start..r * s + d0];
                            for (o, nv) in out.iter_mut().zip(nrow) {
                                *o += v * nv;
                            }
                        }
                    }
                }
            }
            let (h00, rest) = self.scratch.split_at_mut(ss);
            let (h10, rest) = rest.split_at_mut(ss);
            let (h11, rest) = rest.split_at_mut(ss);
            let g01 = &mut rest[..2 * s];
            for r in 0..dim {
                let j1 = &self.reduced[0][r * s..(r + 1) * s];
                let j0 = &self.reduced[1][r * s..r * s + d0];
                let rr = buf.r[r];
                // J₁'s rows are sparse (integrators: two entries): its products over
                // the nonzeros only.
                self.nonzero.clear();
                self.nonzero
                    .extend((0..s).filter(|&i| j1[i] != 0.0).map(|i| (i, j1[i])));
                for &(i, vi) in &self.nonzero {
                    for (o, v) in h10[i * s..i * s + d0].iter_mut().zip(j0) {
                        *o += vi * v;
                    }
                    let out = &mut h11[i * s..(i + 1) * s];
                    for &(j, vj) in &self.nonzero {
                        out[j] += vi * vj;
                    }
                    g01[s + i] += vi * rr;
                }
                if !window_holds_next {
                    for (a, &va) in j0.iter().enumerate() {
                        for (o, vb) in h00[a * s..a * s + d0].iter_mut().zip(j0) {
                            *o += va * vb;
                        }
                        g01[a] += va * rr;
                    }
                }
            }
        }
        self.schur(k0, d0, cost, values)
    }
}

/// Copies a rows × cols matrix stored with row stride cols into `dst` with row
/// The prior on block k0 + 1 with block k0 held at its estimate: H₁₁ and g₁ of the
/// 2-block system in the scratch (see [`WindowSolver::schur`]), and the factors' cost.
fn conditional_prior(
    scratch: &[f64],
    s: usize,
    cost: f64,
    values: &[f64],
    k0: usize,
) -> Result<LinearPrior> {
    let ss = s * s;
    let h11 = &scratch[2 * ss..3 * ss];
    let g1 = &scratch[3 * ss + s..3 * ss + 2 * s];
    let mut information = vec![0.0; ss];
    for i in 0..s {
        for j in 0..=i {
            let v = 0.5 * (h11[i * s + j] + h11[j * s + i]);
            information[i * s + j] = v;
            information[j * s + i] = v;
        }
    }
    if !information.iter().chain(g1).all(|v| v.is_finite()) {
        return Err(Error::Singular(format!(
            "conditioning on step {k0}: non-finite values"
        )));
    }
    Ok(LinearPrior {
        information,
        eta: g1.to_vec(),
        constant: cost,
        xbar: values[(k0 + 1) * s..(k0 + 2) * s].to_vec(),
    })
}

/// stride `ld`.
fn restride(src: &[f64], rows: usize, cols: usize, dst: &mut [f64], ld: usize) {
    for r in 0..rows {
        dst[r * ld..r * ld + cols].copy_from_slice(&src[r * cols..(r + 1) * cols]);
    }
}

/// A whitened soft factor in reduced coordinates: per block it touches (lag 0 into
/// `reduced[0]`, lag 1 into `reduced[1]`) the rows J N (dim × s, padded with zeros
/// past the block's null-space dimension), and the residual r + J p linearized at the
/// point the hard equations' particular step leads to.
#[allow(clippy::too_many_arguments)]
fn reduce_factor(
    reduced: &mut [Vec<f64>; 2],
    spans: &mut [Vec<(usize, usize)>; 2],
    shifted: &mut [f64],
    hard: &[HardBlock],
    graph: &ChainGraph,
    factor: &dyn Factor,
    step: usize,
    buf: &FactorBuffers,
    s: usize,
) {
    let keys = factor.keys();
    let dim = buf.r.len();
    // Only the columns of the blocks' null spaces are filled and read.
    for (lag, part) in reduced.iter_mut().enumerate() {
        if lag <= step {
            let width = hard[step - lag].reduction.dim;
            for r in 0..dim {
                part[r * s..r * s + width].fill(0.0);
            }
        }
        spans[lag][..dim].fill((usize::MAX, 0));
    }
    shifted[..dim].copy_from_slice(&buf.r);
    for (a, k) in keys.iter().enumerate() {
        let (off, d) = graph.layout.slot(k.kind).unwrap_or((0, 0));
        if k.lag > step {
            continue; // a variable held fixed before the window
        }
        let red = &hard[step - k.lag].reduction;
        let out = &mut reduced[k.lag];
        let span = &mut spans[k.lag];
        let jac = &buf.jac[a];
        let diagonal = factor.diagonal_jacobian(a);
        for r in 0..dim {
            let row = &mut out[r * s..r * s + red.dim];
            let columns = if diagonal { r..r + 1 } else { 0..d };
            for j in columns {
                let v = jac[r * d + j];
                if v == 0.0 {
                    continue;
                }
                shifted[r] += v * red.particular[off + j];
                let (start, nrow) = red.row(off + j);
                if !nrow.is_empty() {
                    let (lo, hi) = &mut span[r];
                    *lo = (*lo).min(start);
                    *hi = (*hi).max(start + nrow.len());
                }
                for (o, nv) in row[start..].iter_mut().zip(nrow) {
                    *o += v * nv;
                }
            }
        }
    }
}

/// Adds a reduced factor's JᵀJ and Jᵀr into the block-tridiagonal system: block
/// `step` from `reduced[0]` and, when `lagged`, block `step − 1` from `reduced[1]`
/// (only their active columns, H's block sizes). Reduced rows are often sparse (a
/// scaled identity times a null-space basis with unit rows), so each row's products
/// run over its nonzeros, gathered into `nonzero`; every entry still sums the rows
/// in order.
#[allow(clippy::too_many_arguments)]
fn accumulate(
    h: &mut BlockTridiagonal,
    g: &mut [f64],
    reduced: &[Vec<f64>; 2],
    spans: &[Vec<(usize, usize)>; 2],
    r: &[f64],
    step: usize,
    lagged: bool,
    s: usize,
    nonzero: &mut [Vec<(usize, f64)>; 2],
) {
    let parts: &[(usize, usize)] = if lagged {
        &[(0, step), (1, step - 1)]
    } else {
        &[(0, step)]
    };
    for (row, &rr) in r.iter().enumerate() {
        for &(part, block) in parts {
            let d = h.dim(block);
            let jr = &reduced[part][row * s..row * s + d];
            // Past the row's span it is 0.
            let (lo, hi) = spans[part][row];
            let nz = &mut nonzero[part];
            nz.clear();
            if lo < hi {
                nz.extend(
                    jr[lo..hi]
                        .iter()
                        .enumerate()
                        .filter(|(_, v)| **v != 0.0)
                        .map(|(a, &v)| (lo + a, v)),
                );
            }
            let gb = &mut g[block * s..block * s + d];
            for &(a, va) in nz.iter() {
                gb[a] += va * rr;
            }
            let hb = h.diag_mut(block);
            for &(a, va) in nz.iter() {
                let out = &mut hb[a * d..(a + 1) * d];
                for &(b, vb) in nz.iter() {
                    out[b] += va * vb;
                }
            }
        }
        if lagged {
            // H[step][step−1] += J₀ᵀ J₁.
            let dp = h.dim(step - 1);
            let hl = h.lower_mut(step);
            for &(a, va) in &nonzero[0] {
                let out = &mut hl[a * dp..(a + 1) * dp];
                for &(b, vb) in &nonzero[1] {
                    out[b] += va * vb;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::forward::{simulate, Coordinates, ForwardGraph, ForwardOptions};
    use crate::smoother::Mode;
    use crate::{Model, Scene};
    use std::sync::Arc;

    /// The DC four-bar at dt = 10 ms (large residuals, so the second-order terms are
    /// far from 0) after 0.5 s: its graph, values on the constraint manifold, and the
    /// prior of a one-step window on step `k`.
    fn window() -> (ForwardGraph, Vec<f64>, LinearPrior, WindowSolver, usize) {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/scenes/fourbar.yaml");
        let model = Arc::new(Model::new(&Scene::load(path).unwrap()).unwrap());
        let opts = ForwardOptions::new(Coordinates::Dependent, 1e-2, 0.5, Mode::FixedLag(1));
        let (tr, summary) = simulate(model.clone(), &opts, &mut |_, _| {}).unwrap();
        assert!(summary.failures.is_empty());
        let fg = ForwardGraph::new(model.clone(), &opts).unwrap();
        let s = fg.graph.layout.size();
        let mut values = vec![0.0; tr.len() * s];
        fg.fill_from_trajectory(&model, &tr, &mut values);
        let mut solver = WindowSolver::new(&fg.graph, 2, Settings::default()).unwrap();
        let k = tr.len() - 1;
        let prior = solver.marginalize(&fg.graph, &values, k - 1, None).unwrap();
        (fg, values, prior, solver, k)
    }

    fn cost_on_manifold(
        solver: &mut WindowSolver,
        fg: &ForwardGraph,
        values: &mut [f64],
        k: usize,
        prior: &LinearPrior,
    ) -> f64 {
        // Projections along the fixed normal space of the linearization: a retraction.
        for _ in 0..6 {
            solver.correct(&fg.graph, values, k, k + 1).unwrap();
        }
        solver
            .evaluate(
                &fg.graph,
                values,
                k,
                k + 1,
                Some(prior),
                Scope::Window,
                false,
            )
            .unwrap()
    }

    #[test]
    fn exact_hessian_is_the_second_derivative_of_the_cost_on_the_manifold() {
        let (fg, mut values, prior, mut solver, k) = window();
        let s = solver.s;
        let linearize = |solver: &mut WindowSolver, values: &[f64]| {
            solver
                .evaluate(
                    &fg.graph,
                    values,
                    k,
                    k + 1,
                    Some(&prior),
                    Scope::Window,
                    true,
                )
                .unwrap();
        };
        // Away from the optimum (large residuals): a step along the manifold.
        linearize(&mut solver, &values);
        for i in 0..s {
            let (_, row) = solver.hard[0].reduction.row(i);
            values[k * s + i] += 0.2 * row.iter().sum::<f64>();
        }
        cost_on_manifold(&mut solver, &fg, &mut values, k, &prior);
        linearize(&mut solver, &values);
        let gauss_newton = solver.h.diag(0).to_vec();
        solver
            .exact_hessian(&fg.graph, &mut values, k, k + 1, Some(&prior))
            .unwrap();
        let red = solver.hard[0].reduction.clone();
        let d = red.dim;
        let mut missed = 0.0f64;
        let h: Vec<f64> = solver.h.diag(0)[..d * d].to_vec();
        let x0 = values.clone();
        let mut checked = 0;
        for seed in 0..4 {
            let v: Vec<f64> = (0..d)
                .map(|i| ((i * 7 + seed * 3) % 5) as f64 - 2.0)
                .collect();
            let vhv: f64 = (0..d)
                .map(|i| (0..d).map(|j| v[i] * h[i * d + j] * v[j]).sum::<f64>())
                .sum();
            let mut at = |t: f64| {
                values.copy_from_slice(&x0);
                for i in 0..s {
                    let (start, row) = red.row(i);
                    let step: f64 = row.iter().zip(&v[start..]).map(|(a, b)| a * b).sum();
                    values[k * s + i] += t * step;
                }
                cost_on_manifold(&mut solver, &fg, &mut values, k, &prior)
            };
            let e = 1e-4;
            let second = (at(e) - 2.0 * at(0.0) + at(-e)) / (e * e);
            let gn: f64 = (0..d)
                .map(|i| {
                    (0..d)
                        .map(|j| v[i] * gauss_newton[i * d + j] * v[j])
                        .sum::<f64>()
                })
                .sum();
            missed = missed.max((second - gn).abs() / vhv.abs().max(1.0));
            assert!(
                (second - vhv).abs() <= 1e-4 * vhv.abs().max(1.0),
                "direction {seed}: second difference {second:e}, vᵀHv {vhv:e}"
            );
            checked += 1;
        }
        assert_eq!(checked, 4);
        // What Gauss-Newton leaves out is far above the tolerance here.
        assert!(missed > 1e-2, "Gauss-Newton off by only {missed:e}");
    }

    #[test]
    fn tangent_prior_agrees_with_the_prior_in_value_and_reduced_gradient() {
        let (fg, values, prior, mut solver, k) = window();
        let s = solver.s;
        let mut tangent = prior.clone();
        solver
            .project_prior(&fg.graph, &values, k, &mut tangent)
            .unwrap();
        let red = solver.hard[0].reduction.clone();
        let value = |p: &LinearPrior, x: &[f64]| {
            let dx: Vec<f64> = (0..s).map(|i| x[i] - p.xbar[i]).collect();
            let quad: f64 = (0..s)
                .map(|i| {
                    dx[i]
                        * (0..s)
                            .map(|j| p.information[i * s + j] * dx[j])
                            .sum::<f64>()
                })
                .sum();
            p.constant + p.eta.iter().zip(&dx).map(|(a, b)| a * b).sum::<f64>() + 0.5 * quad
        };
        let grad = |p: &LinearPrior, x: &[f64]| -> Vec<f64> {
            (0..s)
                .map(|i| {
                    p.eta[i]
                        + (0..s)
                            .map(|j| p.information[i * s + j] * (x[j] - p.xbar[j]))
                            .sum::<f64>()
                })
                .collect()
        };
        let x = &tangent.xbar;
        let (a, b) = (value(&prior, x), value(&tangent, x));
        assert!((a - b).abs() <= 1e-12 * a.abs().max(1.0), "{a:e} vs {b:e}");
        let (ga, gb) = (grad(&prior, x), grad(&tangent, x));
        for c in 0..red.dim {
            let (mut pa, mut pb) = (0.0, 0.0);
            for i in 0..s {
                let (start, row) = red.row(i);
                if c >= start && c < start + row.len() {
                    pa += row[c - start] * ga[i];
                    pb += row[c - start] * gb[i];
                }
            }
            assert!(
                (pa - pb).abs() <= 1e-9 * pa.abs().max(1.0),
                "Nᵀ∇Q[{c}]: {pa:e} vs {pb:e}"
            );
        }
        // Across the manifold the tangent prior is flat.
        let normal: Vec<f64> = (0..s).map(|i| ga[i] - gb[i]).collect();
        assert!(tangent.information.iter().all(|v| v.is_finite()));
        assert!(
            normal.iter().any(|v| v.abs() > 0.0),
            "the prior pulled across the manifold"
        );
    }
}
