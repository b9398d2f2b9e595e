//! Factor graphs over time steps: variables keyed by kind and step, one [`Factor`]
//! trait, noise models.
//!
//! Every step holds the same variables (laid out by a [`Layout`]); a factor belongs to
//! one step and touches variables of that step or of the step before (`lag` 1), so
//! the normal equations are block tridiagonal when unknowns are ordered by step.

use crate::error::Result;

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
        }
    }

    /// The time derivative a variable holds (positions 0, velocities 1,
    /// accelerations 2), forces after them (3): hard equations on a step are block
    /// triangular in this order (position constraints touch positions, velocity
    /// constraints positions and velocities, ...), which their reduction exploits.
    pub fn order(self) -> usize {
        match self {
            VarKind::Q | VarKind::Z => 0,
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

/// How strongly a factor's residual is enforced: the residual is divided by a
/// standard deviation σ per row before squaring.
#[derive(Debug, Clone, PartialEq)]
pub enum Noise {
    /// The same σ on every row.
    Isotropic(f64),
    /// One σ per row.
    Diagonal(Vec<f64>),
    /// An equation to satisfy exactly: σ = [`Noise::HARD_SIGMA`].
    Hard,
}

impl Noise {
    /// σ of hard factors: small enough that the solution satisfies them to round-off
    /// against soft factors of σ ≥ 1e-6, large enough to keep the normal equations
    /// well conditioned in double precision.
    pub const HARD_SIGMA: f64 = 1e-6;

    /// 1/σ for row `i`.
    pub fn weight(&self, i: usize) -> f64 {
        match self {
            Noise::Isotropic(s) => 1.0 / s,
            Noise::Diagonal(s) => 1.0 / s[i],
            Noise::Hard => 1.0 / Self::HARD_SIGMA,
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

/// Scratch memory that evaluation may use, sized once from the factors' needs so
/// that no evaluation allocates.
#[derive(Debug, Default)]
pub struct Workspace {
    pub reals: Vec<f64>,
    pub indices: Vec<usize>,
}

impl Workspace {
    pub fn with_capacity(reals: usize, indices: usize) -> Self {
        Workspace {
            reals: vec![0.0; reals],
            indices: vec![0; indices],
        }
    }
}

/// One factor: a residual over a few variables, its Jacobian blocks, and its noise.
pub trait Factor: Send + Sync {
    /// A short name for messages (`f_ti(q)`, `f^d_dyn`, …).
    fn name(&self) -> &str;

    /// The variables, in the order of `evaluate`'s inputs.
    fn keys(&self) -> &[Key];

    /// Residual dimension.
    fn dim(&self) -> usize;

    fn noise(&self) -> &Noise;

    /// Scratch this factor needs in a [`Workspace`]: (reals, indices).
    fn scratch(&self) -> (usize, usize) {
        (0, 0)
    }

    /// Whether the Jacobian block of key `key` is square and nonzero on its diagonal
    /// only (integrators, priors, the q̈ of f_dyn): the solver then reads that
    /// diagonal and skips the zeros around it.
    fn diagonal_jacobian(&self, _key: usize) -> bool {
        false
    }

    /// Whether [`Factor::evaluate_along`] is implemented.
    fn evaluates_along(&self) -> bool {
        false
    }

    /// Evaluates the residual into `r` and, instead of the Jacobians, their products
    /// with directions: Σ_a J_a V_a into the row-major dim × c `out`, V_a = `dirs[a]`
    /// (row-major size(x_a) × c, the same c columns for every key). A factor whose
    /// Jacobian comes out of a factorization (the dynamics factors: one pair of
    /// triangular solves per column) then solves for the few directions that are
    /// nonzero instead of for every column. Returns `Ok(false)`, having written
    /// nothing, when it does not do this (the default) or it would not be cheaper
    /// than the Jacobians.
    #[allow(clippy::too_many_arguments)]
    fn evaluate_along(
        &self,
        _t: f64,
        _x: &[&[f64]],
        _r: &mut [f64],
        _dirs: &[&[f64]],
        _c: usize,
        _out: &mut [f64],
        _ws: &mut Workspace,
    ) -> Result<bool> {
        Ok(false)
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

/// A factor graph over a uniform time grid t_k = t₀ + k·dt.
pub struct ChainGraph {
    pub layout: Layout,
    pub dt: f64,
    pub t0: f64,
    /// Factors present at every step (those with lag-1 keys from step 1 on).
    pub step_factors: Vec<Box<dyn Factor>>,
    /// Factors of step 0 only (priors on the initial state).
    pub initial_factors: Vec<Box<dyn Factor>>,
}

impl ChainGraph {
    pub fn time(&self, step: usize) -> f64 {
        self.t0 + step as f64 * self.dt
    }

    /// Whether a step factor exists at `step` (its lagged variables must exist).
    pub fn exists_at(factor: &dyn Factor, step: usize) -> bool {
        factor.keys().iter().all(|k| k.lag <= step)
    }

    /// Workspace large enough for every factor.
    pub fn workspace(&self) -> Workspace {
        let (mut r, mut i) = (0, 0);
        for f in self.step_factors.iter().chain(&self.initial_factors) {
            let (a, b) = f.scratch();
            r = r.max(a);
            i = i.max(b);
        }
        Workspace::with_capacity(r, i)
    }
}
