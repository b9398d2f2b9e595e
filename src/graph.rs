//! Factor graphs over time steps: variables keyed by kind and step, one [`Factor`]
//! trait, constraints and soft factors with their noise models ([`Term`]).
//!
//! Every step holds the same variables (laid out by a [`Layout`]); a factor belongs to
//! one step and touches variables of that step or of the step before (`lag` 1), so
//! the normal equations are block tridiagonal when unknowns are ordered by step.

use crate::error::{Error, Result};
use faer::dyn_stack::PodBuffer;
/// faer's scratch mechanism (the `dyn-stack` crate), in which factors state and carve
/// their scratch.
pub use faer::dyn_stack::{PodStack, StackReq};

/// The kind of a variable; its size comes from the model.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum VarKind {
    /// Positions q (dependent coordinates).
    Q,
    /// Velocities q̇.
    Dq,
    /// Accelerations q̈.
    Ddq,
    /// Independent positions z.
    Z,
    /// Independent velocities ż.
    Dz,
    /// Independent accelerations z̈.
    Ddz,
    /// Generalized forces Q (inverse dynamics).
    Force,
    /// Parameters constant over the whole horizon (a length, a stiffness): every
    /// step holds a copy, and the link [`ChainGraphBuilder::constant_link`] holds
    /// consecutive copies equal, so that marginalizing a step passes the
    /// parameters' information on to the next.
    Param,
}

impl VarKind {
    pub fn symbol(self) -> &'static str {
        match self {
            VarKind::Q => "q",
            VarKind::Dq => "dq",
            VarKind::Ddq => "ddq",
            VarKind::Z => "z",
            VarKind::Dz => "dz",
            VarKind::Ddz => "ddz",
            VarKind::Force => "Q",
            VarKind::Param => "p",
        }
    }

    /// The time derivative a variable holds (positions 0, velocities 1,
    /// accelerations 2), forces after them (3): hard equations on a step are block
    /// triangular in this order (position constraints touch positions, velocity
    /// constraints positions and velocities, ...), which their reduction exploits.
    /// Parameters go with positions (0): they enter equations as the configuration
    /// does, so an equation on positions and parameters stays a position equation.
    pub fn order(self) -> usize {
        match self {
            VarKind::Q | VarKind::Z | VarKind::Param => 0,
            VarKind::Dq | VarKind::Dz => 1,
            VarKind::Ddq | VarKind::Ddz => 2,
            VarKind::Force => 3,
        }
    }
}

/// A variable a factor touches: its kind, at the factor's step (`lag` 0) or the step
/// before (`lag` 1).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Key {
    pub kind: VarKind,
    pub lag: usize,
}

impl Key {
    pub const fn now(kind: VarKind) -> Key {
        Key { kind, lag: 0 }
    }
    pub const fn before(kind: VarKind) -> Key {
        Key { kind, lag: 1 }
    }
}

/// The variables of one time step and where each sits in the step's block.
#[derive(Debug, Clone, PartialEq)]
pub struct Layout {
    vars: Vec<(VarKind, usize, usize)>,
    size: usize,
}

impl Layout {
    /// Variables in block order, with their sizes.
    pub fn new(vars: &[(VarKind, usize)]) -> Layout {
        let mut offset = 0;
        let vars = vars
            .iter()
            .map(|&(k, d)| {
                let v = (k, d, offset);
                offset += d;
                v
            })
            .collect();
        Layout { vars, size: offset }
    }

    /// Unknowns per step.
    pub fn size(&self) -> usize {
        self.size
    }

    /// (offset in the step block, size) of a variable kind.
    pub fn slot(&self, kind: VarKind) -> Option<(usize, usize)> {
        self.vars
            .iter()
            .find(|v| v.0 == kind)
            .map(|&(_, d, o)| (o, d))
    }

    pub fn kinds(&self) -> impl Iterator<Item = (VarKind, usize)> + '_ {
        self.vars.iter().map(|&(k, d, _)| (k, d))
    }
}

/// How strongly a soft factor's residual is enforced: the residual is divided by a
/// standard deviation σ per row before squaring. Constraints have no noise: the
/// solver holds them exactly ([`Term::Constraint`]).
#[derive(Debug, Clone, PartialEq)]
pub enum Noise {
    /// The same σ on every row.
    Isotropic(f64),
    /// One σ per row.
    Diagonal(Vec<f64>),
}

impl Noise {
    /// 1/σ for row `i`.
    pub fn weight(&self, i: usize) -> f64 {
        match self {
            Noise::Isotropic(s) => 1.0 / s,
            Noise::Diagonal(s) => 1.0 / s[i],
        }
    }

    /// Checks the noise model against the residual dimension.
    pub fn validate(&self, dim: usize) -> std::result::Result<(), String> {
        let ok = |s: f64| s > 0.0 && s.is_finite();
        match self {
            Noise::Isotropic(s) if !ok(*s) => {
                Err(format!("σ must be positive and finite, got {s}"))
            }
            Noise::Diagonal(v) if v.len() != dim => Err(format!(
                "{} sigmas for a residual of dimension {dim}",
                v.len()
            )),
            Noise::Diagonal(v) if !v.iter().all(|s| ok(*s)) => {
                Err("every σ must be positive and finite".into())
            }
            _ => Ok(()),
        }
    }
}

/// Scratch memory that evaluation may use: one buffer, allocated once from the
/// factors' combined [`StackReq`] ([`ChainGraph::workspace`]), from which each
/// evaluation carves its arrays ([`zeros`], [`carve`]), so that no evaluation
/// allocates.
pub struct Workspace {
    buffer: PodBuffer,
}

impl Workspace {
    /// A workspace large enough for the request `req`.
    pub fn new(req: StackReq) -> Self {
        Workspace {
            buffer: PodBuffer::new(req),
        }
    }

    /// The whole buffer as a stack to carve from.
    pub fn stack(&mut self) -> &mut PodStack {
        PodStack::new(&mut self.buffer)
    }
}

/// `len` zeros carved from `stack`, and the rest of `stack`.
pub fn zeros(stack: &mut PodStack, len: usize) -> (&mut [f64], &mut PodStack) {
    stack.make_with(len, |_| 0.0)
}

/// `len` values carved from `stack` as an earlier evaluation left them, and the
/// rest of `stack`: for arrays whose every entry is written before it is read,
/// which zeroing would only cost (a large mechanism's n × n blocks).
pub fn carve(stack: &mut PodStack, len: usize) -> (&mut [f64], &mut PodStack) {
    stack.make_raw(len)
}

impl std::fmt::Debug for Workspace {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Workspace")
            .field("bytes", &self.buffer.len())
            .finish()
    }
}

/// The most keys a factor may have (the solver's per-instance arrays): an
/// estimate's Hermite–Simpson velocity factor reads q, q̇, q̈ at both ends and the
/// parameters and inputs at both.
pub const MAX_KEYS: usize = 12;

/// One factor: a residual over a few variables and its Jacobian blocks. Whether it
/// is held exactly or weighted, and by which noise, is up to the graph it is put in
/// ([`ChainGraphBuilder`]).
pub trait Factor: Send + Sync {
    /// A short name for messages (`f_ti(q)`, `f^d_dyn`, …).
    fn name(&self) -> &str;

    /// The variables, in the order of `evaluate`'s inputs.
    fn keys(&self) -> &[Key];

    /// The size of the variable of key `key` (the length `evaluate` expects of
    /// `x[key]`); [`ChainGraphBuilder::build`] checks it against the layout.
    fn size(&self, key: usize) -> usize;

    /// Residual dimension.
    fn dim(&self) -> usize;

    /// Scratch this factor's evaluations carve from a [`Workspace`].
    fn scratch(&self) -> StackReq {
        StackReq::EMPTY
    }

    /// Whether the Jacobian block of key `key` is square and nonzero on its diagonal
    /// only (integrators, priors, the q̈ of f_dyn): the solver then reads that
    /// diagonal and skips the zeros around it.
    fn diagonal_jacobian(&self, _key: usize) -> bool {
        false
    }

    /// The factor's linearization along directions, when it has one (see
    /// [`AlongDirections`]); `None` by default.
    fn along(&self) -> Option<&dyn AlongDirections> {
        None
    }

    /// Evaluates the residual at time `t` from the variables `x` (one slice per key)
    /// into `r`; with `jacobians`, also ∂r/∂x_k for every key into the row-major
    /// dim × size(x_k) blocks.
    fn evaluate(
        &self,
        t: f64,
        x: &[&[f64]],
        r: &mut [f64],
        jacobians: Option<&mut [Vec<f64>]>,
        ws: &mut Workspace,
    ) -> Result<()>;
}

/// The optional capability of a [`Factor`] to linearize along given directions
/// instead of forming its Jacobians ([`Factor::along`]).
pub trait AlongDirections {
    /// Evaluates the residual into `r` and, instead of the Jacobians, their products
    /// with directions: Σ_a J_a V_a into the row-major dim × c `out`, V_a = `dirs[a]`
    /// (row-major size(x_a) × c, the same c columns for every key). A factor whose
    /// Jacobian comes out of a factorization (the dynamics factors: one pair of
    /// triangular solves per column) then solves for the few directions that are
    /// nonzero instead of for every column. Returns `Ok(false)`, having written
    /// nothing, when it would not be cheaper than the Jacobians.
    #[allow(clippy::too_many_arguments)]
    fn evaluate_along(
        &self,
        t: f64,
        x: &[&[f64]],
        r: &mut [f64],
        dirs: &[&[f64]],
        c: usize,
        out: &mut [f64],
        ws: &mut Workspace,
    ) -> Result<bool>;
}

/// A factor of a [`ChainGraph`] and how the solver treats it.
pub enum Term {
    /// An equation held exactly: the solver eliminates it step by step.
    Constraint(Box<dyn Factor>),
    /// A residual weighted row by row by 1/σ of its noise.
    Soft(Box<dyn Factor>, Noise),
}

impl Term {
    pub fn factor(&self) -> &dyn Factor {
        match self {
            Term::Constraint(f) | Term::Soft(f, _) => f.as_ref(),
        }
    }

    /// The noise of a soft factor; `None` for a constraint.
    pub fn noise(&self) -> Option<&Noise> {
        match self {
            Term::Constraint(_) => None,
            Term::Soft(_, noise) => Some(noise),
        }
    }

    pub fn is_constraint(&self) -> bool {
        matches!(self, Term::Constraint(_))
    }
}

/// A factor graph over a uniform time grid t_k = t₀ + k·dt, built and checked by a
/// [`ChainGraphBuilder`] ([`ChainGraph::builder`]).
pub struct ChainGraph {
    layout: Layout,
    dt: f64,
    t0: f64,
    /// Factors present at every step (those with lag-1 keys from step 1 on).
    step: Vec<Term>,
    /// Factors of step 0 only (priors on the initial state).
    initial: Vec<Term>,
    /// Factors of chosen run steps only (readings that exist at some steps), each
    /// with its run step, sorted by step (in the order added within a step).
    at: Vec<(usize, Term)>,
    /// How many factors of chosen steps [`ChainGraph::drop_at_before`] has dropped
    /// from the front of `at` over the graph's life (a solver's buffers per factor
    /// follow the list by it).
    dropped_at: usize,
}

impl ChainGraph {
    /// A builder of a graph over the variables `layout`, at times t₀ + k·dt.
    pub fn builder(layout: Layout, dt: f64, t0: f64) -> ChainGraphBuilder {
        ChainGraphBuilder {
            graph: ChainGraph {
                layout,
                dt,
                t0,
                step: Vec::new(),
                initial: Vec::new(),
                at: Vec::new(),
                dropped_at: 0,
            },
        }
    }

    /// The variables of each step.
    pub fn layout(&self) -> &Layout {
        &self.layout
    }

    /// The time step.
    pub fn dt(&self) -> f64 {
        self.dt
    }

    /// The time of step 0.
    pub fn t0(&self) -> f64 {
        self.t0
    }

    /// Moves the grid to start at `t0` (a run resumed from a later time).
    pub fn set_t0(&mut self, t0: f64) {
        self.t0 = t0;
    }

    /// The factors present at every step, in the order they were added.
    pub fn step_terms(&self) -> &[Term] {
        &self.step
    }

    /// The factors of step 0 only, in the order they were added.
    pub fn initial_terms(&self) -> &[Term] {
        &self.initial
    }

    /// The factors of chosen run steps, each with its step, sorted by step (see
    /// [`ChainGraphBuilder::soft_at`]).
    pub fn sparse_terms(&self) -> &[(usize, Term)] {
        &self.at
    }

    /// The factors of run step `step` only, in the order they were added.
    pub fn terms_at(&self, step: usize) -> &[(usize, Term)] {
        &self.at[self.sparse_range(step, step + 1)]
    }

    /// The indices into [`ChainGraph::sparse_terms`] of the factors of run steps
    /// `first..end`.
    pub fn sparse_range(&self, first: usize, end: usize) -> std::ops::Range<usize> {
        let lo = self.at.partition_point(|(k, _)| *k < first);
        let hi = self.at.partition_point(|(k, _)| *k < end);
        lo..hi.max(lo)
    }

    /// The time of the run's step `step`, t₀ + step·dt.
    pub fn run_time(&self, step: usize) -> f64 {
        self.t0 + step as f64 * self.dt
    }

    /// Adds a soft factor at run step `step`, after the graph was built: a reading
    /// that arrives while the graph is being solved (an online estimator). Steps
    /// come in order: `step` is at or after every step already holding one. The
    /// factor is checked as [`ChainGraphBuilder::build`] checks the others; the
    /// solver lists the factors of chosen steps afresh for every window, so it sees
    /// the new one at its next solve.
    pub fn add_soft_at(
        &mut self,
        step: usize,
        factor: Box<dyn Factor>,
        noise: Noise,
    ) -> Result<()> {
        if self.at.last().is_some_and(|(k, _)| *k > step) {
            return Err(Error::InvalidArgument(format!(
                "factor {} added at step {step}, before a later step's",
                factor.name()
            )));
        }
        let term = Term::Soft(factor, noise);
        check_term(&self.layout, Place::At(step), &term)?;
        self.at.push((step, term));
        Ok(())
    }

    /// Drops the factors of chosen run steps before `step` (steps no window will
    /// hold again), so that a long online run keeps a bounded graph.
    pub fn drop_at_before(&mut self, step: usize) {
        let end = self.at.partition_point(|(k, _)| *k < step);
        self.at.drain(..end);
        self.dropped_at += end;
    }

    /// How many factors of chosen steps have been dropped from the front of
    /// [`ChainGraph::sparse_terms`] since the graph was built.
    pub fn dropped_at(&self) -> usize {
        self.dropped_at
    }

    /// Workspace large enough for every factor (one evaluates at a time).
    pub fn workspace(&self) -> Workspace {
        let req = self
            .step
            .iter()
            .chain(&self.initial)
            .chain(self.at.iter().map(|(_, t)| t))
            .fold(StackReq::EMPTY, |req, t| req.or(t.factor().scratch()));
        Workspace::new(req)
    }
}

/// Collects the factors of a [`ChainGraph`], constraints and soft factors apart, and
/// checks them against the layout in [`ChainGraphBuilder::build`].
pub struct ChainGraphBuilder {
    graph: ChainGraph,
}

impl ChainGraphBuilder {
    /// A constraint at every step: held exactly, so it must stay within one step.
    pub fn step_constraint(mut self, factor: Box<dyn Factor>) -> Self {
        self.graph.step.push(Term::Constraint(factor));
        self
    }

    /// A soft factor at every step, weighted by 1/σ of `noise`.
    pub fn step_soft(mut self, factor: Box<dyn Factor>, noise: Noise) -> Self {
        self.graph.step.push(Term::Soft(factor, noise));
        self
    }

    /// A constraint on step 0 only.
    pub fn initial_constraint(mut self, factor: Box<dyn Factor>) -> Self {
        self.graph.initial.push(Term::Constraint(factor));
        self
    }

    /// A soft factor on step 0 only, weighted by 1/σ of `noise`.
    pub fn initial_soft(mut self, factor: Box<dyn Factor>, noise: Noise) -> Self {
        self.graph.initial.push(Term::Soft(factor, noise));
        self
    }

    /// A constraint at run step `step` only: held exactly, so it must stay within
    /// one step.
    pub fn constraint_at(mut self, step: usize, factor: Box<dyn Factor>) -> Self {
        self.graph.at.push((step, Term::Constraint(factor)));
        self
    }

    /// A soft factor at run step `step` only (a reading that exists there, its datum
    /// in the factor), weighted by 1/σ of `noise`.
    pub fn soft_at(mut self, step: usize, factor: Box<dyn Factor>, noise: Noise) -> Self {
        self.graph.at.push((step, Term::Soft(factor, noise)));
        self
    }

    /// Holds the layout's parameters ([`VarKind::Param`]) constant over the horizon:
    /// a soft link p_k − p_{k−1} = 0 of standard deviation `sigma` at every step. The
    /// copies then agree to about σ (an augmented-state filter whose parameters walk
    /// with process noise σ per step): choose σ well below the uncertainty of the
    /// estimate, but not so small that 1/σ² swamps the other information in double
    /// precision (marginalization subtracts terms of size 1/σ²; their round-off,
    /// 1e-16/σ², must stay below the parameters' own information). Levenberg-Marquardt
    /// scales its damping by H's diagonal, 1/σ² on the parameters, so a damped step
    /// barely moves them: Gauss-Newton suits a solve far from its optimum.
    pub fn constant_link(self, sigma: f64) -> Self {
        let dim = self.graph.layout.slot(VarKind::Param).map_or(0, |(_, d)| d);
        self.step_soft(
            Box::new(crate::factors::Equality::new(VarKind::Param, dim)),
            Noise::Isotropic(sigma),
        )
    }

    /// The graph, once every factor touches variables the layout holds, at the
    /// factor's step or the one before (step 0 only for initial factors, none before
    /// step 0 for the factors of chosen steps), with the sizes the layout gives them;
    /// every constraint stays within one step; every noise fits its factor's
    /// dimension; parameters ([`VarKind::Param`]) come with their link.
    pub fn build(mut self) -> Result<ChainGraph> {
        // Stable: the factors of one step keep the order they were added in.
        self.graph.at.sort_by_key(|(k, _)| *k);
        let g = &self.graph;
        let invalid = |what: String| Err(Error::InvalidArgument(what));
        let every = g.step.iter().map(|t| (Place::Every, t));
        let initial = g.initial.iter().map(|t| (Place::Initial, t));
        let at = g.at.iter().map(|(k, t)| (Place::At(*k), t));
        for (place, term) in every.chain(initial).chain(at) {
            check_term(&g.layout, place, term)?;
        }
        // Without the link, every step's copy of the parameters would be a free
        // variable of its own: a graph that says "constant" and means nothing of it.
        if g.layout.slot(VarKind::Param).is_some()
            && !g.step.iter().any(|t| {
                !t.is_constraint()
                    && t.factor().keys().contains(&Key::before(VarKind::Param))
                    && t.factor().keys().contains(&Key::now(VarKind::Param))
            })
        {
            return invalid(
                "the layout holds parameters p but no step factor links p to p(lag 1); \
                 ChainGraphBuilder::constant_link adds it"
                    .into(),
            );
        }
        Ok(self.graph)
    }
}

/// Checks one factor of a graph against its layout where it sits (see
/// [`ChainGraphBuilder::build`]).
fn check_term(layout: &Layout, place: Place, term: &Term) -> Result<()> {
    let invalid = |what: String| Err(Error::InvalidArgument(what));
    let f = term.factor();
    let what = match place {
        Place::At(k) => format!("factor {} at step {k}", f.name()),
        _ => format!("factor {}", f.name()),
    };
    if let Some(noise) = term.noise() {
        if let Err(e) = noise.validate(f.dim()) {
            return invalid(format!("noise of {}: {e}", f.name()));
        }
    }
    if f.keys().len() > MAX_KEYS {
        return invalid(format!(
            "{what} has {} keys; a factor has at most {MAX_KEYS}",
            f.keys().len()
        ));
    }
    for (a, k) in f.keys().iter().enumerate() {
        let Some((_, d)) = layout.slot(k.kind).filter(|_| k.lag <= 1) else {
            return invalid(format!(
                "{what} touches {}(lag {}), which the graph does not hold",
                k.kind.symbol(),
                k.lag
            ));
        };
        if f.size(a) != d {
            return invalid(format!(
                "{what} takes {}(lag {}) of size {}, the graph holds it with size {d}",
                k.kind.symbol(),
                k.lag,
                f.size(a)
            ));
        }
        if !matches!(place, Place::Every) && k.lag > place.first() {
            let role = if let Place::Initial = place {
                "initial "
            } else {
                ""
            };
            return invalid(format!(
                "{role}{what} touches {}(lag {}), before step 0",
                k.kind.symbol(),
                k.lag
            ));
        }
    }
    if term.is_constraint() && f.keys().iter().any(|k| k.lag > 0) {
        return invalid(format!(
            "constraint {} spans two steps; constraints must stay within one",
            f.name()
        ));
    }
    Ok(())
}

/// Where a factor of a graph being built sits (for `build`'s checks).
#[derive(Clone, Copy)]
enum Place {
    Every,
    Initial,
    At(usize),
}

impl Place {
    /// The first run step the factor sits at.
    fn first(self) -> usize {
        match self {
            Place::Every | Place::Initial => 0,
            Place::At(step) => step,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::factors::{Equality, Prior, Trapezoidal};

    fn builder() -> ChainGraphBuilder {
        ChainGraph::builder(Layout::new(&[(VarKind::Q, 2), (VarKind::Dq, 2)]), 0.1, 0.0)
    }

    fn message(b: ChainGraphBuilder) -> String {
        match b.build() {
            Err(Error::InvalidArgument(m)) => m,
            Err(e) => panic!("another error: {e}"),
            Ok(_) => panic!("built"),
        }
    }

    #[test]
    fn keeps_each_factor_with_its_role_in_order() {
        let g = builder()
            .step_constraint(Box::new(Prior::new(VarKind::Q, vec![0.0; 2])))
            .step_soft(
                Box::new(Trapezoidal::new(VarKind::Q, VarKind::Dq, 2, 0.1)),
                Noise::Isotropic(0.5),
            )
            .initial_soft(
                Box::new(Prior::new(VarKind::Dq, vec![0.0; 2])),
                Noise::Diagonal(vec![1.0, 2.0]),
            )
            .build()
            .unwrap();
        let step: Vec<_> = g.step_terms().iter().map(|t| t.factor().name()).collect();
        assert_eq!(step, ["f_prior(q)", "f_ti(q)"]);
        assert!(g.step_terms()[0].is_constraint());
        assert_eq!(g.step_terms()[1].noise(), Some(&Noise::Isotropic(0.5)));
        assert_eq!(g.initial_terms().len(), 1);
        assert_eq!(g.run_time(3), 0.1 * 3.0);
    }

    #[test]
    fn rejects_what_the_layout_does_not_hold() {
        let m = message(builder().step_soft(
            Box::new(Prior::new(VarKind::Z, vec![0.0; 2])),
            Noise::Isotropic(1.0),
        ));
        assert!(m.contains("f_prior(z) touches z(lag 0)"), "{m}");
        let m = message(builder().step_constraint(Box::new(Prior::new(VarKind::Q, vec![0.0; 3]))));
        assert!(m.contains("f_prior(q) takes q(lag 0) of size 3"), "{m}");
        assert!(m.contains("size 2"), "{m}");
    }

    #[test]
    fn rejects_constraints_across_steps_and_initial_factors_before_step_0() {
        let m = message(builder().step_constraint(Box::new(Equality::new(VarKind::Q, 2))));
        assert!(m.contains("constraint f_eq(q) spans two steps"), "{m}");
        let m = message(builder().initial_soft(
            Box::new(Equality::new(VarKind::Q, 2)),
            Noise::Isotropic(1.0),
        ));
        assert!(m.contains("initial factor f_eq(q)"), "{m}");
    }

    #[test]
    fn rejects_a_noise_that_does_not_fit() {
        let prior = || Box::new(Prior::new(VarKind::Q, vec![0.0; 2]));
        let m = message(builder().step_soft(prior(), Noise::Isotropic(0.0)));
        assert!(m.contains("noise of f_prior(q)"), "{m}");
        let m = message(builder().initial_soft(prior(), Noise::Diagonal(vec![1.0; 3])));
        assert!(m.contains("3 sigmas for a residual of dimension 2"), "{m}");
    }

    #[test]
    fn keeps_factors_of_chosen_steps_sorted_by_step_in_order_within_one() {
        let prior = |v: f64| Box::new(Prior::new(VarKind::Q, vec![v; 2]));
        let g = builder()
            .soft_at(7, prior(7.0), Noise::Isotropic(1.0))
            .soft_at(2, prior(2.0), Noise::Isotropic(1.0))
            .constraint_at(7, prior(7.5))
            .build()
            .unwrap();
        let steps: Vec<_> = g.sparse_terms().iter().map(|(k, _)| *k).collect();
        assert_eq!(steps, [2, 7, 7]);
        assert_eq!(g.terms_at(7).len(), 2);
        assert!(!g.terms_at(7)[0].1.is_constraint());
        assert!(g.terms_at(7)[1].1.is_constraint());
        assert!(g.terms_at(3).is_empty());
        assert_eq!(g.sparse_range(3, 8), 1..3);
        assert_eq!(g.sparse_range(8, 20), 3..3);
    }

    #[test]
    fn rejects_factors_of_chosen_steps_that_do_not_fit() {
        let m = message(builder().soft_at(
            4,
            Box::new(Prior::new(VarKind::Z, vec![0.0; 2])),
            Noise::Isotropic(1.0),
        ));
        assert!(m.contains("f_prior(z) at step 4 touches z(lag 0)"), "{m}");
        let m = message(builder().soft_at(
            0,
            Box::new(Equality::new(VarKind::Q, 2)),
            Noise::Isotropic(1.0),
        ));
        assert!(
            m.contains("f_eq(q) at step 0 touches q(lag 1), before step 0"),
            "{m}"
        );
        let m = message(builder().constraint_at(3, Box::new(Equality::new(VarKind::Q, 2))));
        assert!(m.contains("constraint f_eq(q) spans two steps"), "{m}");
        let m = message(builder().soft_at(
            1,
            Box::new(Prior::new(VarKind::Q, vec![0.0; 2])),
            Noise::Diagonal(vec![1.0]),
        ));
        assert!(m.contains("1 sigmas for a residual of dimension 2"), "{m}");
    }

    #[test]
    fn parameters_need_their_link() {
        let layout = || Layout::new(&[(VarKind::Q, 2), (VarKind::Param, 1)]);
        let m = message(ChainGraph::builder(layout(), 0.1, 0.0));
        assert!(m.contains("no step factor links p to p(lag 1)"), "{m}");
        let g = ChainGraph::builder(layout(), 0.1, 0.0)
            .constant_link(1e-6)
            .build()
            .unwrap();
        assert_eq!(g.step_terms()[0].factor().name(), "f_eq(p)");
        assert_eq!(g.step_terms()[0].noise(), Some(&Noise::Isotropic(1e-6)));
        // A link without parameters to link is refused, not a panic.
        let m = message(builder().constant_link(1e-6));
        assert!(m.contains("f_eq(p) touches p(lag 1)"), "{m}");
    }
}
