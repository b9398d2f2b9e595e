//! Sparse nonlinear least squares over a window of time steps of a [`ChainGraph`]:
//! Gauss-Newton or Levenberg-Marquardt on the block-tridiagonal normal equations, and
//! the marginalization that turns the oldest step of a window into a Gaussian prior on
//! the next one (the Schur complement of the linearized system).
//!
//! Hard factors (the graph's constraints, [`Term::Constraint`]) are not weighted:
//! each iteration linearizes them per step, C_k δ_k = −c_k, and solves for
//! δ_k = p_k + N_k y_k ([`NullSpace`]), so only the soft factors enter the normal
//! equations in y. Weighting them by 1/σ² with a tiny σ instead squares a condition
//! number that is already large: on a long four-bar run the soft information along
//! the motion decays to ~1e-5 while 1/σ² = 1e12, and the window solves stall.

use crate::error::{Error, Result};
#[cfg(doc)]
use crate::graph::AlongDirections;
use crate::graph::{ChainGraph, Term};
use crate::linalg::dense::Summation;
use crate::linalg::nullspace::NullSpace;

mod chord;
mod covariance;
mod iterate;
mod linearize;
mod marginal;
mod newton;
mod normal;
mod observer;
mod prior;
mod reuse;
mod settings;
mod structure;
#[cfg(test)]
mod tests;

pub use crate::convergence::{SolveReport, Termination};
pub use covariance::Marginals;
pub use observer::{Iteration, Observer, Trace};
pub use prior::{Information, LinearPrior, Projection, TangentInformation, TANGENT_FORM_FROM};
pub use settings::{Method, Past, Settings, Thresholds};

use linearize::{AllBuffers, HardBlock, KeptRows, Linearization, ReducedRows};
use marginal::{LastSolve, Marginalization};
use newton::{NewtonBuffers, PriorRoots};
use normal::NormalEquations;
use structure::{Scope, Structure};

/// σ by which a hard factor's residual is weighted in the reported cost
/// ([`SolveReport::cost`]). Hard factors are eliminated, not weighted: this only
/// scales their share of that cost.
pub const HARD_SIGMA: f64 = 1e-6;

/// A reusable solver for windows of up to `capacity` steps; it allocates once.
pub struct WindowSolver {
    settings: Settings,
    /// The least information a marginal prior keeps in any direction, as a share
    /// of its largest diagonal entry (0: none added; see
    /// [`WindowSolver::set_prior_floor`]).
    prior_floor: f64,
    s: usize,
    /// Which factor instances the current window holds (the structure stage).
    structure: Structure,
    /// H y = −g in the window's reduced unknowns, and its step.
    normal: NormalEquations,
    saved: Vec<f64>,
    /// Each step's hard equations reduced, and the buffers a linearization works in.
    lin: Linearization,
    /// The last full step δ = p + N y of the window (for `backtrack`).
    direction: Vec<f64>,
    /// The rows a one-block linearization keeps beside H.
    kept: KeptRows,
    /// The current solve's prior as rows, made when a least-squares step first
    /// needs them.
    prior_roots: Option<PriorRoots>,
    /// Set when a window solve ended on a small step: its linearization of the
    /// oldest block is still at hand (see `marginalize`).
    last: Option<LastSolve>,
    /// Cost of the factors touching the first block, from the last evaluation.
    cost_first: f64,
    correction: Vec<f64>,
    /// What marginalization works in.
    marginal: Marginalization,
    scratch: Vec<f64>,
    newton: NewtonBuffers,
    observer: Option<Box<dyn Observer>>,
    /// Each variable's entries in a step (offset, length), for
    /// [`Settings::step_per_variable`].
    variables: Vec<(usize, usize)>,
    /// Per entry of a step, what its step is measured against (`take_step`).
    step_scale: Vec<f64>,
    /// Linearizations of the window's steps kept for its next solves
    /// ([`Settings::relinearize_beyond`]).
    reuse: reuse::Reuse,
    /// Unknowns per step from which a projected prior is kept as N̄CN̄ᵀ
    /// ([`TANGENT_FORM_FROM`]; the tests set it to compare the two forms).
    tangent_form_from: usize,
}

impl WindowSolver {
    pub fn new(graph: &ChainGraph, capacity: usize, settings: Settings) -> Result<Self> {
        settings.validate()?;
        let mut max_dim = 0;
        let (mut hard_step, mut hard_initial) = (0, 0);
        // The graph was checked when it was built (`ChainGraphBuilder::build`).
        for (initial, list) in [(false, graph.step_terms()), (true, graph.initial_terms())] {
            for term in list {
                let f = term.factor();
                max_dim = max_dim.max(f.dim());
                if term.is_constraint() {
                    if initial {
                        hard_initial += f.dim();
                    } else {
                        hard_step += f.dim();
                    }
                }
            }
        }
        // The factors of chosen steps: the most hard rows one step adds.
        let (mut hard_at, mut at_step, mut at_rows) = (0, usize::MAX, 0);
        for (step, term) in graph.sparse_terms() {
            max_dim = max_dim.max(term.factor().dim());
            if *step != at_step {
                (at_step, at_rows) = (*step, 0);
            }
            if term.is_constraint() {
                at_rows += term.factor().dim();
                hard_at = hard_at.max(at_rows);
            }
        }
        let s = graph.layout().size();
        let capacity = capacity.max(2);
        let n = capacity * s;
        let max_hard = hard_step + hard_initial + hard_at;
        // Room for the factors that linearize along directions.
        let (mut along_keys, mut along_dim) = (0, 0);
        for f in graph
            .step_terms()
            .iter()
            .chain(graph.initial_terms())
            .chain(graph.sparse_terms().iter().map(|(_, t)| t))
            .map(Term::factor)
        {
            if f.along().is_some() {
                let sizes: usize = (0..f.keys().len()).map(|a| f.size(a)).sum();
                along_keys = along_keys.max(sizes);
                along_dim = along_dim.max(f.dim());
            }
        }
        let mut solver = WindowSolver {
            settings,
            s,
            normal: NormalEquations::new(capacity, s),
            saved: vec![0.0; n],
            direction: vec![0.0; n],
            structure: Structure::new(graph, capacity),
            lin: Linearization {
                s,
                buffers: AllBuffers::new(graph),
                hard: (0..capacity)
                    .map(|_| {
                        Box::new(HardBlock {
                            rows: 0,
                            at_round_off: false,
                            kept: 0,
                            reduction: NullSpace::new(s, max_hard),
                        })
                    })
                    .collect(),
                hard_cost: Vec::with_capacity(
                    capacity * graph.step_terms().len() + graph.initial_terms().len(),
                ),
                hard_jac: vec![0.0; max_hard * s],
                hard_rhs: vec![0.0; max_hard],
                hard_noise: vec![0.0; max_hard],
                step_major: false,
                along_dirs: vec![0.0; along_keys * (1 + 2 * s)],
                along_out: vec![0.0; along_dim * (1 + 2 * s)],
                reduced: ReducedRows::new(max_dim.max(s), s),
                ws: graph.workspace(),
                generation: 0,
            },
            kept: KeptRows::default(),
            prior_roots: None,
            last: None,
            cost_first: 0.0,
            correction: vec![0.0; s],
            marginal: Marginalization::new(s),
            scratch: vec![0.0; 4 * s * s + 4 * s],
            prior_floor: 0.0,
            observer: settings.trace.then(|| Box::new(Trace) as Box<dyn Observer>),
            tangent_form_from: TANGENT_FORM_FROM,
            reuse: reuse::Reuse::default(),
            variables: graph
                .layout()
                .kinds()
                .filter_map(|(k, _)| graph.layout().slot(k))
                .collect(),
            step_scale: vec![0.0; s],
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
        for block in &mut self.lin.hard {
            block.reduction.set_summation(Summation::Lanes);
        }
        self.normal.set_summation(Summation::Lanes);
        self.lin.step_major = true;
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
        for (kind, d) in graph.layout().kinds() {
            let (off, _) = graph.layout().slot(kind).expect("a kind of the layout");
            segment[off..off + d].fill(kind.order());
        }
        for block in &mut self.lin.hard {
            block.reduction.set_segments(&segment);
        }
    }

    /// From now on, each marginal prior keeps at least `share` of its largest
    /// diagonal entry of information in every direction (0: as the factors leave it).
    /// Over a long stretch without readings the information along the motion decays
    /// to the round-off of the Schur complement, where the prior stops being
    /// positive definite on the tangent space; the floor holds it there, at σ's
    /// far beyond any the motion allows.
    pub fn set_prior_floor(&mut self, share: f64) {
        self.prior_floor = share;
    }

    /// Whether marginalization conditions on the leaving step (see [`Past`]).
    fn past_conditioned(&self) -> bool {
        self.settings.past == Past::Conditioned
    }

    /// From now on, marginalization conditions on the leaving step.
    pub fn condition_on_past(&mut self) {
        self.settings.past = Past::Conditioned;
    }

    /// Installs an observer of every iteration (replacing any before it).
    pub fn observe(&mut self, observer: Box<dyn Observer>) {
        self.observer = Some(observer);
    }

    /// The installed observer, for solves made beside this solver (a graph's exact
    /// steps) to report their iterations to it.
    pub fn observer(&mut self) -> Option<&mut dyn Observer> {
        match &mut self.observer {
            Some(observer) => Some(observer.as_mut()),
            None => None,
        }
    }

    pub fn settings(&self) -> &Settings {
        &self.settings
    }

    /// The run step that step 0 of the values stands for.
    pub fn base(&self) -> usize {
        self.structure.base
    }

    /// The time of step `step` of the values.
    pub fn time(&self, graph: &ChainGraph, step: usize) -> f64 {
        graph.run_time(self.structure.base + step)
    }
}

impl WindowSolver {
    /// Lists the factor instances of a scope ([`Structure::collect_instances`]) and
    /// makes room for the costs of its hard ones.
    fn collect_instances(&mut self, graph: &ChainGraph, k0: usize, k1: usize, scope: Scope) {
        self.lin.buffers.follow(graph);
        self.structure.collect_instances(graph, k0, k1, scope);
        self.lin.clear_costs(&self.structure);
    }

    /// The values moved `by` steps toward the start of their buffer (a fixed-lag run
    /// that keeps only its newest steps, [`crate::smoother::fixed_lag`] with a buffer):
    /// what the solver keeps by step follows them, so that the next solve and
    /// marginalization reuse it as they would have in place.
    pub fn shift_steps(&mut self, by: usize) {
        self.structure.base += by;
        if let Some(last) = self.last.as_mut() {
            last.k0 -= by;
            last.k1 -= by;
        }
    }
}

impl LinearPrior {
    /// The values moved `by` steps toward the start of their buffer (see
    /// [`WindowSolver::shift_steps`]): a projection names its step there.
    pub fn shift_steps(&mut self, by: usize) {
        if let Some(p) = self.projection.as_mut() {
            p.step -= by;
        }
    }
}
