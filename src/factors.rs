//! The factors of the paper's section 6, each with closed-form Jacobians.
//!
//! Generic: [`Prior`] (f_prior), [`Equality`] (f_eq), [`Euler`] (f_ei),
//! [`Trapezoidal`] (f_ti). Dependent coordinates: [`PositionConstraints`] (f^d_pc),
//! [`VelocityConstraints`] (f^d_vc), [`Dynamics`] (f^d_dyn). Independent coordinates:
//! [`IndependentPosition`] (f^i_pc), [`IndependentVelocity`] (f^i_vc),
//! [`IndependentAcceleration`] (f^i_ac), [`IndependentDynamics`] (f^i_dyn).
//!
//! The dynamics factors need ∂q̈/∂q and ∂q̈/∂q̇, which the paper took numerically. We
//! differentiate the augmented system [M Φ_qᵀ; Φ_q 0][q̈; λ] = [Q; c] instead: with
//! its LU factors already at hand for q̈, each Jacobian column costs one more pair of
//! triangular solves, against a full re-factorization per column (two per column for
//! central differences) for a numerical Jacobian — exact and several times cheaper.

use crate::error::{Error, Result};
use crate::graph::{Factor, Key, Noise, VarKind, Workspace};
use crate::linalg::dense;
use crate::model::Model;
use std::sync::Arc;

/// The `keys` and `noise` methods every factor here answers from its own fields.
macro_rules! key_and_noise_accessors {
    () => {
        fn keys(&self) -> &[Key] {
            &self.keys
        }
        fn noise(&self) -> &Noise {
            &self.noise
        }
    };
}
pub(crate) use key_and_noise_accessors;

/// f_prior: e = x − x₀ on one variable.
pub struct Prior {
    name: String,
    keys: [Key; 1],
    target: Vec<f64>,
    noise: Noise,
}

impl Prior {
    pub fn new(kind: VarKind, target: Vec<f64>, noise: Noise) -> Self {
        Prior {
            name: format!("f_prior({})", kind.symbol()),
            keys: [Key::now(kind)],
            target,
            noise,
        }
    }
}

impl Factor for Prior {
    fn name(&self) -> &str {
        &self.name
    }
    key_and_noise_accessors!();
    fn dim(&self) -> usize {
        self.target.len()
    }
    fn diagonal_jacobian(&self, _key: usize) -> bool {
        true
    }
    fn evaluate(
        &self,
        _t: f64,
        x: &[&[f64]],
        r: &mut [f64],
        jac: Option<&mut [Vec<f64>]>,
        _ws: &mut Workspace,
    ) -> Result<()> {
        for (i, ri) in r.iter_mut().enumerate() {
            *ri = x[0][i] - self.target[i];
        }
        if let Some(j) = jac {
            identity(&mut j[0], self.dim(), 1.0);
        }
        Ok(())
    }
}

/// Writes `scale`·I into a row-major d × d block.
pub(crate) fn identity(block: &mut [f64], d: usize, scale: f64) {
    block.fill(0.0);
    for i in 0..d {
        block[i * d + i] = scale;
    }
}

/// f_eq: e = x_t − x_{t−1}, a soft link between consecutive steps.
pub struct Equality {
    name: String,
    keys: [Key; 2],
    dim: usize,
    noise: Noise,
}

impl Equality {
    pub fn new(kind: VarKind, dim: usize, noise: Noise) -> Self {
        Equality {
            name: format!("f_eq({})", kind.symbol()),
            keys: [Key::before(kind), Key::now(kind)],
            dim,
            noise,
        }
    }
}

impl Factor for Equality {
    fn name(&self) -> &str {
        &self.name
    }
    key_and_noise_accessors!();
    fn dim(&self) -> usize {
        self.dim
    }
    fn diagonal_jacobian(&self, _key: usize) -> bool {
        true
    }
    fn evaluate(
        &self,
        _t: f64,
        x: &[&[f64]],
        r: &mut [f64],
        jac: Option<&mut [Vec<f64>]>,
        _ws: &mut Workspace,
    ) -> Result<()> {
        for (i, ri) in r.iter_mut().enumerate() {
            *ri = x[1][i] - x[0][i];
        }
        if let Some(j) = jac {
            identity(&mut j[0], self.dim, -1.0);
            identity(&mut j[1], self.dim, 1.0);
        }
        Ok(())
    }
}

/// f_ei: e = x_t − x_{t−1} − Δt ẋ_{t−1}.
pub struct Euler {
    name: String,
    keys: [Key; 3],
    dim: usize,
    dt: f64,
    noise: Noise,
}

impl Euler {
    pub fn new(x: VarKind, dx: VarKind, dim: usize, dt: f64, noise: Noise) -> Self {
        Euler {
            name: format!("f_ei({})", x.symbol()),
            keys: [Key::before(x), Key::now(x), Key::before(dx)],
            dim,
            dt,
            noise,
        }
    }
}

impl Factor for Euler {
    fn name(&self) -> &str {
        &self.name
    }
    key_and_noise_accessors!();
    fn dim(&self) -> usize {
        self.dim
    }
    fn diagonal_jacobian(&self, _key: usize) -> bool {
        true
    }
    fn evaluate(
        &self,
        _t: f64,
        x: &[&[f64]],
        r: &mut [f64],
        jac: Option<&mut [Vec<f64>]>,
        _ws: &mut Workspace,
    ) -> Result<()> {
        for (i, ri) in r.iter_mut().enumerate() {
            *ri = x[1][i] - x[0][i] - self.dt * x[2][i];
        }
        if let Some(j) = jac {
            identity(&mut j[0], self.dim, -1.0);
            identity(&mut j[1], self.dim, 1.0);
            identity(&mut j[2], self.dim, -self.dt);
        }
        Ok(())
    }
}

/// f_ti: e = x_t − x_{t−1} − Δt/2 (ẋ_{t−1} + ẋ_t).
pub struct Trapezoidal {
    name: String,
    keys: [Key; 4],
    dim: usize,
    dt: f64,
    noise: Noise,
}

impl Trapezoidal {
    pub fn new(x: VarKind, dx: VarKind, dim: usize, dt: f64, noise: Noise) -> Self {
        Trapezoidal {
            name: format!("f_ti({})", x.symbol()),
            keys: [Key::before(x), Key::now(x), Key::before(dx), Key::now(dx)],
            dim,
            dt,
            noise,
        }
    }
}

impl Factor for Trapezoidal {
    fn name(&self) -> &str {
        &self.name
    }
    key_and_noise_accessors!();
    fn dim(&self) -> usize {
        self.dim
    }
    fn diagonal_jacobian(&self, _key: usize) -> bool {
        true
    }
    fn evaluate(
        &self,
        _t: f64,
        x: &[&[f64]],
        r: &mut [f64],
        jac: Option<&mut [Vec<f64>]>,
        _ws: &mut Workspace,
    ) -> Result<()> {
        let h = 0.5 * self.dt;
        for (i, ri) in r.iter_mut().enumerate() {
            *ri = x[1][i] - x[0][i] - h * (x[2][i] + x[3][i]);
        }
        if let Some(j) = jac {
            identity(&mut j[0], self.dim, -1.0);
            identity(&mut j[1], self.dim, 1.0);
            identity(&mut j[2], self.dim, -h);
            identity(&mut j[3], self.dim, -h);
        }
        Ok(())
    }
}

/// f^d_pc: e = Φ(q).
pub struct PositionConstraints {
    model: Arc<Model>,
    keys: [Key; 1],
    noise: Noise,
}

impl PositionConstraints {
    pub fn new(model: Arc<Model>, noise: Noise) -> Self {
        PositionConstraints {
            model,
            keys: [Key::now(VarKind::Q)],
            noise,
        }
    }
}

impl Factor for PositionConstraints {
    fn name(&self) -> &str {
        "f^d_pc"
    }
    key_and_noise_accessors!();
    fn dim(&self) -> usize {
        self.model.m()
    }
    fn evaluate(
        &self,
        _t: f64,
        x: &[&[f64]],
        r: &mut [f64],
        jac: Option<&mut [Vec<f64>]>,
        _ws: &mut Workspace,
    ) -> Result<()> {
        self.model.phi_into(x[0], r);
        if let Some(j) = jac {
            self.model.jacobian_into(x[0], &mut j[0]);
        }
        Ok(())
    }
}

/// f^d_vc: e = Φ_q(q) q̇, with ∂e/∂q = Φ_qq q̇ = Φ̇_q and ∂e/∂q̇ = Φ_q.
pub struct VelocityConstraints {
    model: Arc<Model>,
    keys: [Key; 2],
    noise: Noise,
}

impl VelocityConstraints {
    pub fn new(model: Arc<Model>, noise: Noise) -> Self {
        VelocityConstraints {
            model,
            keys: [Key::now(VarKind::Q), Key::now(VarKind::Dq)],
            noise,
        }
    }
}

impl Factor for VelocityConstraints {
    fn name(&self) -> &str {
        "f^d_vc"
    }
    key_and_noise_accessors!();
    fn dim(&self) -> usize {
        self.model.m()
    }
    fn scratch(&self) -> (usize, usize) {
        (self.model.m() * self.model.n(), 0)
    }
    fn evaluate(
        &self,
        _t: f64,
        x: &[&[f64]],
        r: &mut [f64],
        jac: Option<&mut [Vec<f64>]>,
        ws: &mut Workspace,
    ) -> Result<()> {
        let (m, n) = (self.model.m(), self.model.n());
        let a = &mut ws.reals[..m * n];
        self.model.jacobian_into(x[0], a);
        mat_vec(a, m, n, x[1], r);
        if let Some(j) = jac {
            self.model.jacobian_derivative_into(x[0], x[1], &mut j[0]);
            j[1].copy_from_slice(a);
        }
        Ok(())
    }
}

/// y = A x for a row-major rows × cols A.
fn mat_vec(a: &[f64], rows: usize, cols: usize, x: &[f64], y: &mut [f64]) {
    for i in 0..rows {
        y[i] = (0..cols).map(|j| a[i * cols + j] * x[j]).sum();
    }
}

/// Forward dynamics q̈(q, q̇, t) by the augmented system, and optionally its exact
/// Jacobians, without allocating.
///
/// With K = [M Aᵀ; A −E] (A: the active rows of Φ_q, E = diag(εₖ), see below) and
/// [q̈; λ] = K⁻¹[Q; c]:
///   K [∂q̈/∂q; ∂λ/∂q] = [∂Q/∂q − ∂(Φ_qᵀλ)/∂q; −∂(Φ̇_q q̇)/∂q − Φ_qq q̈ + E_q λ]
///   K [∂q̈/∂q̇; ∂λ/∂q̇] = [∂Q/∂q̇; −2 Φ̇_q]
/// (rows of the right-hand sides restricted to the active constraints; row k of
/// E_q λ is λₖ ∂εₖ/∂q).
///
/// **Singular configurations.** Where Φ_q is regular, E = 0: the KKT system of the
/// paper (eq. "qDynSys"), computed exactly as before. Where Φ_q loses a rank (the
/// parallelogram's flat configurations) K is singular, and near it the KKT q̈
/// answers a velocity off the constraint manifold by round-off with an acceleration
/// 1/σ larger (σ the smallest singular value of Φ_q); the hard constraints cannot
/// remove that round-off there (they fix the velocity along the lost rank only to
/// ε_mach/σ²), ∂q̈/∂q grows like 1/σ, and K no longer factors below σ ≈ 1e-8. So
/// near rank loss the bottom block is −E with εₖ = w(s) ε_rel ‖aₖ‖²/m̄ (aₖ row k of
/// A, m̄ the largest diagonal entry of M): the Tikhonov-regularized (penalty) form
/// (M + AᵀE⁻¹A) q̈ = Q + AᵀE⁻¹c, regular at every configuration, with a bounded
/// response to such velocities, and within O(ε/σ²) of the KKT q̈ where σ² ≫ ε.
/// s = (tr G⁻¹)^(−1/2), G = ÂÂᵀ with Â the rows of A normalized, measures the
/// distance to rank loss (√λ_min(G/m) ≤ s ≤ √λ_min(G)); w = 0 above
/// [`DynamicsKernel::REGULAR_ABOVE`], 1 below [`DynamicsKernel::SINGULAR_BELOW`] and
/// the cubic 1 − x²(3 − 2x) of x = log(s/below)/log(above/below) between, so q̈ is C¹
/// and the Jacobians above exact everywhere.
pub struct DynamicsKernel;

/// Where the kernel's scratch lives inside `ws.reals`: the augmented system and its
/// right-hand sides, then the singularity measure's scratch ([`MeasureLayout`]).
struct KernelLayout {
    n: usize,
    ma: usize,
    sol: usize,
    tmp: usize,
    mat: usize,
    kq: usize,
    kv: usize,
    cols: usize,
    c: usize,
    measure: usize,
    end: usize,
}

impl KernelLayout {
    fn new(model: &Model) -> Self {
        let (n, m, ma) = (model.n(), model.m(), model.active.len());
        let big = n + ma;
        let sol = big * big;
        let tmp = sol + big;
        let mat = tmp + 2 * n * big;
        let kq = mat + m * n;
        let kv = kq + n * n;
        let cols = kv + n * n;
        let c = cols + 2 * n * big;
        let measure = c + m;
        let end = measure + MeasureLayout::new(model).end;
        KernelLayout {
            n,
            ma,
            sol,
            tmp,
            mat,
            kq,
            kv,
            cols,
            c,
            measure,
            end,
        }
    }
}

/// The singularity measure's scratch, relative to its start: Â (ma × n), G and its
/// Cholesky factor, L⁻¹, G⁻¹ (ma × ma each), per-row vectors and their Hessian
/// products (m × n each), εₖ and ‖aₖ‖ (ma each), ∂s/∂q (n).
struct MeasureLayout {
    gram: usize,
    linv: usize,
    ginv: usize,
    vrows: usize,
    hrows: usize,
    eps: usize,
    norms: usize,
    ds: usize,
    end: usize,
}

impl MeasureLayout {
    fn new(model: &Model) -> Self {
        let (n, m, ma) = (model.n(), model.m(), model.active.len());
        let gram = ma * n;
        let linv = gram + ma * ma;
        let ginv = linv + ma * ma;
        let vrows = ginv + ma * ma;
        let hrows = vrows + m * n;
        let eps = hrows + m * n;
        let norms = eps + ma;
        let ds = norms + ma;
        let end = ds + n;
        MeasureLayout {
            gram,
            linv,
            ginv,
            vrows,
            hrows,
            eps,
            norms,
            ds,
            end,
        }
    }
}

/// The regularization at one configuration: the weight w(s), dw/ds and s.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Regularization {
    w: f64,
    dw: f64,
    s: f64,
}

/// m̄: the largest diagonal entry of M (1 for a massless model).
fn mass_scale(model: &Model) -> f64 {
    let m = (0..model.n()).fold(0.0f64, |m, i| m.max(model.mass[(i, i)]));
    if m > 0.0 {
        m
    } else {
        1.0
    }
}

impl DynamicsKernel {
    /// ε_rel: εₖ = w ε_rel ‖aₖ‖²/m̄. With the ramp below, ε_rel from 5e-8 to 5e-5
    /// lets DC pass the parallelogram's five flat points at Δt = 1e-3 to 1e-5 s and
    /// seven phases of the motion; 5e-9 does not. 1e-6 sits in the middle.
    pub const REGULARIZATION: f64 = 1e-6;
    /// Below this s the regularization is full (w = 1).
    pub const SINGULAR_BELOW: f64 = 1e-4;
    /// At or above this s the system is the plain KKT system (w = 0). With the
    /// damped corrections of [`crate::linalg::nullspace::NullSpace`] the KKT system
    /// serves down to s ≈ 1e-4: ramps from (1e-5, 1e-4) to (1e-3, 1e-2) all pass the
    /// parallelogram, (1e-7, 1e-6) does not. The top stays below the regular motion
    /// of every scene: pick-and-place comes closest (s = 4.5e-3 at t = 0.39 s; a
    /// ramp up to 1e-2 changed its run), the four-bar stays above 0.37.
    pub const REGULAR_ABOVE: f64 = 1e-3;

    /// Scratch needed: (reals, indices).
    pub fn scratch(model: &Model) -> (usize, usize) {
        let l = KernelLayout::new(model);
        (l.end, l.n + l.ma)
    }

    /// The distance to rank loss s(q) = (tr G⁻¹)^(−1/2) of the active rows of Φ_q
    /// (see [`DynamicsKernel`]), the weight w(s) of the regularization there (w = 0,
    /// the plain KKT system, for s ≥ [`DynamicsKernel::REGULAR_ABOVE`]) and, where
    /// w is in its ramp, ∂s/∂q (else `None`). Allocates; for diagnostics and tests.
    pub fn regularization_at(model: &Model, q: &[f64]) -> (f64, f64, Option<Vec<f64>>) {
        let (n, m) = (model.n(), model.m());
        let mut mat = vec![0.0; m * n];
        model.jacobian_into(q, &mut mat);
        let ml = MeasureLayout::new(model);
        let mut scratch = vec![0.0; ml.end];
        let reg = Self::measure(model, &mat, &mut scratch, true);
        let gradient = (reg.dw != 0.0).then(|| {
            Self::measure_gradient(model, q, reg.s, &mut scratch);
            scratch[ml.ds..ml.ds + n].to_vec()
        });
        (reg.s, reg.w, gradient)
    }

    /// The distance s to rank loss of the active rows of Φ_q (`mat`, row-major
    /// m × n) and the weight w(s); leaves ‖aₖ‖ and, below
    /// [`DynamicsKernel::REGULAR_ABOVE`], G⁻¹ in `scratch` for
    /// [`DynamicsKernel::measure_gradient`]. s = 0 where Φ_q has lost a rank or has
    /// a zero row. Unless `exact`, s may be reported as REGULAR_ABOVE where a bound
    /// shows it is at least that (w = 0 either way).
    fn measure(model: &Model, mat: &[f64], scratch: &mut [f64], exact: bool) -> Regularization {
        let (n, ma) = (model.n(), model.active.len());
        let ml = MeasureLayout::new(model);
        let singular = Regularization {
            w: 1.0,
            dw: 0.0,
            s: 0.0,
        };
        if ma == 0 {
            return Regularization {
                w: 0.0,
                dw: 0.0,
                s: f64::INFINITY,
            };
        }
        let (_, rest) = scratch[..ml.end].split_at_mut(ml.gram);
        let (chol, rest) = rest.split_at_mut(ml.linv - ml.gram);
        let (linv, rest) = rest.split_at_mut(ml.ginv - ml.linv);
        let (ginv, rest) = rest.split_at_mut(ml.vrows - ml.ginv);
        let norms = &mut rest[ml.norms - ml.vrows..ml.ds - ml.vrows];
        // AAᵀ (lower triangle) and the row norms from its diagonal.
        for (i, &ki) in model.active.iter().enumerate() {
            let ri = &mat[ki * n..(ki + 1) * n];
            for (j, &kj) in model.active[..=i].iter().enumerate() {
                let rj = &mat[kj * n..(kj + 1) * n];
                chol[i * ma + j] = ri.iter().zip(rj).map(|(a, b)| a * b).sum();
            }
            let n2 = chol[i * ma + i];
            if !(n2 > 0.0) {
                return singular;
            }
            norms[i] = n2.sqrt();
        }
        // In place, the Cholesky factor L of G = ÂÂᵀ, G_ij = (AAᵀ)_ij/(‖aᵢ‖‖aⱼ‖).
        for i in 0..ma {
            for j in 0..=i {
                let mut g = chol[i * ma + j] / (norms[i] * norms[j]);
                for k in 0..j {
                    g -= chol[i * ma + k] * chol[j * ma + k];
                }
                if i == j {
                    if !(g > 0.0) {
                        return singular;
                    }
                    chol[i * ma + i] = g.sqrt();
                } else {
                    chol[i * ma + j] = g / chol[j * ma + j];
                }
            }
        }
        // λ_min(G) ≥ det G / λ_max^(m−1) ≥ det G / m^(m−1) (tr G = m), and
        // s² ≥ λ_min/m: far from rank loss that settles w = 0 without G⁻¹.
        if !exact {
            let det: f64 = (0..ma)
                .map(|i| chol[i * ma + i] * chol[i * ma + i])
                .product();
            let hi = Self::REGULAR_ABOVE;
            if det >= hi * hi * (ma as f64).powi(ma as i32) {
                return Regularization {
                    w: 0.0,
                    dw: 0.0,
                    s: hi,
                };
            }
        }
        // L⁻¹ (lower triangular) column by column; tr G⁻¹ = ‖L⁻¹‖_F².
        let mut trace = 0.0;
        for j in 0..ma {
            for i in j..ma {
                let mut v = if i == j { 1.0 } else { 0.0 };
                for k in j..i {
                    v -= chol[i * ma + k] * linv[k * ma + j];
                }
                v /= chol[i * ma + i];
                linv[i * ma + j] = v;
                trace += v * v;
            }
        }
        let s = trace.recip().sqrt();
        if !(s > 0.0) {
            return singular;
        }
        let (lo, hi) = (Self::SINGULAR_BELOW, Self::REGULAR_ABOVE);
        if s >= hi {
            return Regularization { w: 0.0, dw: 0.0, s };
        }
        // G⁻¹ = L⁻ᵀL⁻¹, for the gradient of s.
        for i in 0..ma {
            for j in 0..=i {
                let g: f64 = (i..ma).map(|k| linv[k * ma + i] * linv[k * ma + j]).sum();
                ginv[i * ma + j] = g;
                ginv[j * ma + i] = g;
            }
        }
        if s <= lo {
            return Regularization { w: 1.0, dw: 0.0, s };
        }
        let span = (hi / lo).ln();
        let x = (s / lo).ln() / span;
        Regularization {
            w: 1.0 - x * x * (3.0 - 2.0 * x),
            dw: -6.0 * x * (1.0 - x) / (s * span),
            s,
        }
    }

    /// ∂s/∂q into the scratch's `ds`, from what [`DynamicsKernel::measure`] left:
    /// s = T^(−1/2) with T = tr G⁻¹ and ∂T = −tr(G⁻²∂G), G = ÂÂᵀ, so
    /// ∂s/∂q = s³ Σₖ Φᵏ_qq yₖ with zₖ = Σₗ (G⁻²)ₖₗ âₗ and
    /// yₖ = (zₖ − (âₖ·zₖ) âₖ)/‖aₖ‖ (âₖ = aₖ/‖aₖ‖ moves by (I − âₖâₖᵀ) ∂aₖ/‖aₖ‖,
    /// ∂aₖ/∂q = Φᵏ_qq).
    fn measure_gradient(model: &Model, q: &[f64], s: f64, scratch: &mut [f64]) {
        let (n, ma, m) = (model.n(), model.active.len(), model.m());
        let ml = MeasureLayout::new(model);
        let (abar, rest) = scratch[..ml.end].split_at_mut(ml.gram);
        let (_, rest) = rest.split_at_mut(ml.linv - ml.gram);
        let (g2, rest) = rest.split_at_mut(ml.ginv - ml.linv);
        let (ginv, rest) = rest.split_at_mut(ml.vrows - ml.ginv);
        let (vrows, rest) = rest.split_at_mut(m * n);
        let (hrows, rest) = rest.split_at_mut(m * n);
        let (norms, ds) = rest[ma..].split_at_mut(ma);
        // Â from the active rows of Φ_q.
        model.jacobian_into(q, hrows);
        for (r, &k) in model.active.iter().enumerate() {
            for (a, v) in abar[r * n..(r + 1) * n]
                .iter_mut()
                .zip(&hrows[k * n..(k + 1) * n])
            {
                *a = v / norms[r];
            }
        }
        // G⁻² where L⁻¹ was.
        for i in 0..ma {
            for j in 0..ma {
                g2[i * ma + j] = (0..ma).map(|k| ginv[i * ma + k] * ginv[k * ma + j]).sum();
            }
        }
        vrows.fill(0.0);
        for (r, &k) in model.active.iter().enumerate() {
            let y = &mut vrows[k * n..(k + 1) * n];
            for (c, yc) in y.iter_mut().enumerate() {
                *yc = (0..ma).map(|j| g2[r * ma + j] * abar[j * n + c]).sum();
            }
            let a = &abar[r * n..(r + 1) * n];
            let dot: f64 = a.iter().zip(y.iter()).map(|(x, z)| x * z).sum();
            for (yc, ac) in y.iter_mut().zip(a) {
                *yc = (*yc - dot * ac) / norms[r];
            }
        }
        model.hessian_rows_into(q, vrows, hrows);
        let s3 = s * s * s;
        for (j, d) in ds[..n].iter_mut().enumerate() {
            *d = s3 * model.active.iter().map(|&k| hrows[k * n + j]).sum::<f64>();
        }
    }

    /// Adds λₖ ∂εₖ/∂q to the bottom rows' q columns of the right-hand sides `cols`
    /// (row-major, `width` columns): εₖ = w(s) ε_rel ‖aₖ‖²/m̄, ∂‖aₖ‖² = 2 Φᵏ_qq aₖ,
    /// ∂w = w'(s) ∂s/∂q.
    #[allow(clippy::too_many_arguments)]
    fn add_regularization_terms(
        model: &Model,
        q: &[f64],
        reg: Regularization,
        lambda: &[f64],
        cols: &mut [f64],
        width: usize,
        scratch: &mut [f64],
    ) {
        let (n, m) = (model.n(), model.m());
        let ml = MeasureLayout::new(model);
        if reg.dw != 0.0 {
            Self::measure_gradient(model, q, reg.s, scratch);
        }
        let (head, rest) = scratch[..ml.end].split_at_mut(ml.hrows);
        let vrows = &mut head[ml.vrows..];
        let (hrows, rest) = rest.split_at_mut(m * n);
        let norms = &rest[ml.norms - ml.eps..ml.ds - ml.eps];
        let ds = &rest[ml.ds - ml.eps..ml.end - ml.eps];
        model.jacobian_into(q, vrows);
        model.hessian_rows_into(q, vrows, hrows);
        let scale = Self::REGULARIZATION / mass_scale(model);
        for (r, &k) in model.active.iter().enumerate() {
            let norm2 = norms[r] * norms[r];
            let row = &mut cols[(n + r) * width..(n + r) * width + n];
            for (j, o) in row.iter_mut().enumerate() {
                let mut de = 2.0 * reg.w * hrows[k * n + j];
                if reg.dw != 0.0 {
                    de += norm2 * reg.dw * ds[j];
                }
                *o += lambda[r] * scale * de;
            }
        }
    }

    /// Computes q̈ into `ddq`; with `jac`, ∂q̈/∂q and ∂q̈/∂q̇ into the row-major n × n
    /// blocks. `force`, when given, is added to the scene's Q (the unknown actuator
    /// forces of inverse dynamics). The LU factors of the augmented system stay in
    /// the scratch for [`DynamicsKernel::force_jacobian`].
    #[allow(clippy::too_many_arguments)]
    pub fn evaluate(
        model: &Model,
        q: &[f64],
        dq: &[f64],
        t: f64,
        force: Option<&[f64]>,
        ddq: &mut [f64],
        jac: Option<(&mut [f64], &mut [f64])>,
        reals: &mut [f64],
        indices: &mut [usize],
    ) -> Result<()> {
        let l = KernelLayout::new(model);
        let (n, ma) = (l.n, l.ma);
        let big = n + ma;
        let m = model.m();
        let perm = &mut indices[..big];
        let (main, scratch) = reals[..l.end].split_at_mut(l.measure);
        let (kkt, rest) = main.split_at_mut(l.sol);
        let (sol, rest) = rest.split_at_mut(l.tmp - l.sol);
        let (tmp, rest) = rest.split_at_mut(l.mat - l.tmp);
        let (mat, rest) = rest.split_at_mut(l.kq - l.mat);
        let (kq, rest) = rest.split_at_mut(l.kv - l.kq);
        let (kv, rest) = rest.split_at_mut(l.cols - l.kv);
        let (cols, rest) = rest.split_at_mut(l.c - l.cols);
        let c = &mut rest[..m];

        // K = [M Aᵀ; A −E] and the right-hand side [Q; c].
        model.jacobian_into(q, mat);
        let reg = Self::measure(model, mat, scratch, false);
        kkt.fill(0.0);
        for i in 0..n {
            for j in 0..n {
                kkt[i * big + j] = model.mass[(i, j)];
            }
        }
        for (r, &k) in model.active.iter().enumerate() {
            for j in 0..n {
                let a = mat[k * n + j];
                kkt[(n + r) * big + j] = a;
                kkt[j * big + n + r] = a;
            }
        }
        if reg.w > 0.0 {
            let ml = MeasureLayout::new(model);
            let scale = Self::REGULARIZATION * reg.w / mass_scale(model);
            for r in 0..ma {
                let norm = scratch[ml.norms + r];
                let e = scale * norm * norm;
                scratch[ml.eps + r] = e;
                kkt[(n + r) * big + n + r] = -e;
            }
        }
        sol.fill(0.0);
        for f in &model.forces {
            f.add_to(model, q, dq, t, &mut sol[..n])?;
        }
        if let Some(f) = force {
            for (s, v) in sol[..n].iter_mut().zip(f) {
                *s += v;
            }
        }
        model.acceleration_rhs_into(q, dq, c);
        for (r, &k) in model.active.iter().enumerate() {
            sol[n + r] = c[k];
        }
        dense::lu(kkt, big, perm).map_err(|_| {
            Error::Singular("the augmented (KKT) system is singular: a singular configuration or dependent constraints".into())
        })?;
        dense::lu_solve(kkt, big, perm, sol, tmp);
        ddq.copy_from_slice(&sol[..n]);
        let Some((jq, jv)) = jac else {
            return Ok(());
        };

        // Right-hand sides, column-major: n columns for q, then n for q̇.
        kq.fill(0.0);
        kv.fill(0.0);
        for f in &model.forces {
            f.add_jacobians(model, (q, dq, t), kq, kv)?;
        }
        // kq −= ∂(Φ_qᵀλ)/∂q, accumulated with −λ.
        for (t, l) in tmp.iter_mut().zip(&sol[n..big]) {
            *t = -l;
        }
        model.add_weighted_hessians(q, &tmp[..ma], kq);
        // The right-hand sides, row-major big × 2n: n columns for q, then n for q̇.
        let w = 2 * n;
        for i in 0..n {
            cols[i * w..i * w + n].copy_from_slice(&kq[i * n..(i + 1) * n]);
            cols[i * w + n..(i + 1) * w].copy_from_slice(&kv[i * n..(i + 1) * n]);
        }
        // Bottom rows for q: −∂(Φ̇_q q̇)/∂q − Φ_qq q̈.
        model.third_order_into(q, dq, mat);
        for (r, &k) in model.active.iter().enumerate() {
            let row = &mut cols[(n + r) * w..(n + r) * w + n];
            for (o, v) in row.iter_mut().zip(&mat[k * n..(k + 1) * n]) {
                *o = -v;
            }
        }
        let ddq_now: &[f64] = ddq;
        model.jacobian_derivative_into(q, ddq_now, mat);
        for (r, &k) in model.active.iter().enumerate() {
            let row = &mut cols[(n + r) * w..(n + r) * w + n];
            for (o, v) in row.iter_mut().zip(&mat[k * n..(k + 1) * n]) {
                *o -= v;
            }
        }
        if reg.w > 0.0 {
            Self::add_regularization_terms(model, q, reg, &sol[n..big], cols, w, scratch);
        }
        // Bottom rows for q̇: −2 Φ̇_q.
        model.jacobian_derivative_into(q, dq, mat);
        for (r, &k) in model.active.iter().enumerate() {
            let row = &mut cols[(n + r) * w + n..(n + r + 1) * w];
            for (o, v) in row.iter_mut().zip(&mat[k * n..(k + 1) * n]) {
                *o = -2.0 * v;
            }
        }
        dense::lu_solve_many(kkt, big, perm, &mut cols[..big * w], w, tmp);
        for i in 0..n {
            jq[i * n..(i + 1) * n].copy_from_slice(&cols[i * w..i * w + n]);
            jv[i * n..(i + 1) * n].copy_from_slice(&cols[i * w + n..(i + 1) * w]);
        }
        Ok(())
    }

    /// ∂q̈/∂Q_c for forces Q_c on the coordinates `columns` (row-major n × columns.len())
    /// with the factors a preceding [`DynamicsKernel::evaluate`] left in the scratch:
    /// the first n rows of K⁻¹[E; 0], E the columns of I they act on.
    pub fn force_jacobian(
        model: &Model,
        columns: &[usize],
        jf: &mut [f64],
        reals: &mut [f64],
        indices: &[usize],
    ) {
        let l = KernelLayout::new(model);
        let (n, ma) = (l.n, l.ma);
        let big = n + ma;
        let perm = &indices[..big];
        let (kkt, rest) = reals[..l.end].split_at_mut(l.sol);
        let (_, rest) = rest.split_at_mut(l.tmp - l.sol);
        let (tmp, rest) = rest.split_at_mut(l.mat - l.tmp);
        let (_, rest) = rest.split_at_mut(l.cols - l.mat);
        let (cols, _) = rest.split_at_mut(l.c - l.cols);
        let p = columns.len();
        let rhs = &mut cols[..big * p];
        rhs.fill(0.0);
        for (c, &j) in columns.iter().enumerate() {
            rhs[j * p + c] = 1.0;
        }
        dense::lu_solve_many(kkt, big, perm, rhs, p, tmp);
        jf[..n * p].copy_from_slice(&rhs[..n * p]);
    }
}

/// Where [`DynamicsKernel::along`]'s scratch lives: after the kernel's in
/// `ws.reals` (the part passed as `extra`), and after the kernel's permutation in
/// `ws.indices`.
struct AlongLayout {
    kv: usize,
    mat: usize,
    bq: usize,
    bv: usize,
    b: usize,
    tmp: usize,
    end: usize,
}

impl AlongLayout {
    /// For up to `max_cols` directions solved for.
    fn new(model: &Model, max_cols: usize) -> Self {
        let (n, m, ma) = (model.n(), model.m(), model.active.len());
        let big = n + ma;
        let kv = n * n;
        let mat = kv + n * n;
        let bq = mat + m * n;
        let bv = bq + ma * n;
        let b = bv + ma * n;
        let tmp = b + big * max_cols.max(1);
        let end = tmp + big * max_cols.max(1);
        AlongLayout {
            kv,
            mat,
            bq,
            bv,
            b,
            tmp,
            end,
        }
    }
}

impl DynamicsKernel {
    /// Scratch [`DynamicsKernel::along`] needs beyond the kernel's, for up to
    /// `max_cols` directions: (reals, indices).
    pub fn along_scratch(model: &Model, max_cols: usize) -> (usize, usize) {
        (AlongLayout::new(model, max_cols).end, max_cols)
    }

    /// Rows `rows` (all n without) of Σ_a ∂q̈/∂x_a V_a over x = q, q̇ and the forces, for directions
    /// V_q, V_v (row-major n × c) and V_f (row-major columns.len() × c, the forces on
    /// the coordinates `columns`), into the row-major rows.len() × c `out`, at the
    /// point of a preceding [`DynamicsKernel::evaluate`] without Jacobians (its LU
    /// factors and [q̈; λ] are in `reals`): the first n rows of
    /// K⁻¹ (R_q V_q + R_v V_v + [E V_f; 0]), R_q and R_v the right-hand sides from
    /// which `evaluate` solves for ∂q̈/∂q and ∂q̈/∂q̇. Only the columns where some
    /// direction is nonzero are solved for (one pair of triangular solves each, where
    /// the Jacobians take one per coordinate and force); returns false when more
    /// than `max_cols` are (`out` then holds nothing of use).
    #[allow(clippy::too_many_arguments)]
    pub fn along(
        model: &Model,
        (q, dq, t): (&[f64], &[f64], f64),
        directions: [&[f64]; 3],
        columns: &[usize],
        rows: Option<&[usize]>,
        c: usize,
        out: &mut [f64],
        reals: &mut [f64],
        extra: &mut [f64],
        indices: &mut [usize],
        max_cols: usize,
    ) -> Result<bool> {
        let [vq, vv, vf] = directions;
        let l = KernelLayout::new(model);
        let (n, ma) = (l.n, l.ma);
        let big = n + ma;
        let a = AlongLayout::new(model, max_cols);
        let (perm, act) = indices.split_at_mut(big);
        // The columns where a direction is nonzero (flags in `out`'s first row).
        let flags = &mut out[..c];
        flags.fill(0.0);
        for v in [vq, vv, vf] {
            for row in v.chunks_exact(c) {
                for (f, x) in flags.iter_mut().zip(row) {
                    if *x != 0.0 {
                        *f = 1.0;
                    }
                }
            }
        }
        let mut na = 0;
        for (j, f) in flags.iter().enumerate() {
            if *f != 0.0 {
                if na == max_cols {
                    return Ok(false);
                }
                act[na] = j;
                na += 1;
            }
        }
        let act = &act[..na];
        let (kkt, rest) = reals[..l.end].split_at_mut(l.sol);
        let sol = &rest[..big];
        let (kq, rest) = extra[..a.end].split_at_mut(a.kv);
        let (kv, rest) = rest.split_at_mut(a.mat - a.kv);
        let (mat, rest) = rest.split_at_mut(a.bq - a.mat);
        let (bq, rest) = rest.split_at_mut(a.bv - a.bq);
        let (bv, rest) = rest.split_at_mut(a.b - a.bv);
        let (b, tmp) = rest.split_at_mut(a.tmp - a.b);
        // The right-hand sides of `evaluate`'s Jacobians (the same terms in the same
        // order): top rows ∂Q/∂q − ∂(Φ_qᵀλ)/∂q and ∂Q/∂q̇; bottom rows
        // −∂(Φ̇_q q̇)/∂q − Φ_qq q̈ and −2 Φ̇_q.
        kq.fill(0.0);
        kv.fill(0.0);
        for f in &model.forces {
            f.add_jacobians(model, (q, dq, t), kq, kv)?;
        }
        for (t, lam) in tmp.iter_mut().zip(&sol[n..big]) {
            *t = -lam;
        }
        model.add_weighted_hessians(q, &tmp[..ma], kq);
        model.third_order_into(q, dq, mat);
        for (r, &k) in model.active.iter().enumerate() {
            for (o, v) in bq[r * n..(r + 1) * n]
                .iter_mut()
                .zip(&mat[k * n..(k + 1) * n])
            {
                *o = -v;
            }
        }
        model.jacobian_derivative_into(q, &sol[..n], mat);
        for (r, &k) in model.active.iter().enumerate() {
            for (o, v) in bq[r * n..(r + 1) * n]
                .iter_mut()
                .zip(&mat[k * n..(k + 1) * n])
            {
                *o -= v;
            }
        }
        model.jacobian_derivative_into(q, dq, mat);
        for (r, &k) in model.active.iter().enumerate() {
            for (o, v) in bv[r * n..(r + 1) * n]
                .iter_mut()
                .zip(&mat[k * n..(k + 1) * n])
            {
                *o = -2.0 * v;
            }
        }
        // B = R_q V_q + R_v V_v + [E V_f; 0] on the active columns, big × na.
        let b = &mut b[..big * na];
        b.fill(0.0);
        let add = |out: &mut [f64], coef: &[f64], v: &[f64]| {
            for (i, row) in out.chunks_exact_mut(na).enumerate() {
                for (k, &cf) in coef[i * n..(i + 1) * n].iter().enumerate() {
                    if cf == 0.0 {
                        continue;
                    }
                    let vrow = &v[k * c..(k + 1) * c];
                    for (o, &j) in row.iter_mut().zip(act) {
                        *o += cf * vrow[j];
                    }
                }
            }
        };
        let (top, bottom) = b.split_at_mut(n * na);
        add(top, kq, vq);
        add(top, kv, vv);
        add(bottom, bq, vq);
        add(bottom, bv, vv);
        for (k, &i) in columns.iter().enumerate() {
            let vrow = &vf[k * c..(k + 1) * c];
            for (o, &j) in top[i * na..(i + 1) * na].iter_mut().zip(act) {
                *o += vrow[j];
            }
        }
        dense::lu_solve_many(kkt, big, perm, b, na, tmp);
        let count = rows.map_or(n, <[usize]>::len);
        out[..count * c].fill(0.0);
        for r in 0..count {
            let i = rows.map_or(r, |rows| rows[r]);
            for (t, &j) in act.iter().enumerate() {
                out[r * c + j] = b[i * na + t];
            }
        }
        Ok(true)
    }
}

/// f^d_dyn: e = q̈(q, q̇, t) − q̈_t; with [`Dynamics::inverse`], f^d_idyn:
/// e = q̈(q, q̇, t; Q_scene + Q) − q̈_t with the actuator forces Q a variable (fourth
/// key), ∂e/∂Q the first n rows of the augmented system's inverse applied to [I; 0].
pub struct Dynamics {
    model: Arc<Model>,
    keys: Vec<Key>,
    noise: Noise,
    /// Inverse dynamics: the coordinates the forces Q act on (see [`Actuated`]).
    actuated: Option<Actuated>,
}

/// The coordinates an inverse-dynamics factor's forces act on: all of them (Q has n
/// entries), or the listed ones (Q has one entry per listed coordinate, in that
/// order), which spares a pair of triangular solves per other column of ∂e/∂Q and
/// the solver the unknowns that would only be held at 0.
#[derive(Debug, Clone)]
struct Actuated {
    all: bool,
    indices: Vec<usize>,
}

impl Actuated {
    fn all(n: usize) -> Self {
        Actuated {
            all: true,
            indices: (0..n).collect(),
        }
    }

    fn only(n: usize, indices: Vec<usize>) -> Self {
        assert!(
            indices.iter().all(|&i| i < n),
            "an actuated coordinate past q"
        );
        let mut sorted = indices.clone();
        sorted.sort_unstable();
        sorted.dedup();
        assert_eq!(sorted.len(), indices.len(), "an actuated coordinate twice");
        Actuated {
            all: indices.iter().copied().eq(0..n),
            indices,
        }
    }

    /// The generalized forces on all n coordinates: Q itself, or Q spread into `own`.
    fn forces<'a>(&self, q: &'a [f64], own: &'a mut [f64]) -> &'a [f64] {
        if self.all {
            return q;
        }
        own.fill(0.0);
        for (&i, &v) in self.indices.iter().zip(q) {
            own[i] = v;
        }
        own
    }
}

impl Dynamics {
    pub fn new(model: Arc<Model>, noise: Noise) -> Self {
        Dynamics {
            model,
            keys: vec![
                Key::now(VarKind::Q),
                Key::now(VarKind::Dq),
                Key::now(VarKind::Ddq),
            ],
            noise,
            actuated: None,
        }
    }

    /// f^d_idyn, with forces on every coordinate.
    pub fn inverse(model: Arc<Model>, noise: Noise) -> Self {
        let n = model.n();
        let mut f = Dynamics::new(model, noise);
        f.keys.push(Key::now(VarKind::Force));
        f.actuated = Some(Actuated::all(n));
        f
    }

    /// f^d_idyn with forces on the coordinates `actuated` only: its Q variable has
    /// one entry per actuated coordinate, in that order.
    pub fn inverse_on(model: Arc<Model>, noise: Noise, actuated: Vec<usize>) -> Self {
        let n = model.n();
        let mut f = Dynamics::inverse(model, noise);
        f.actuated = Some(Actuated::only(n, actuated));
        f
    }
}

impl Factor for Dynamics {
    fn name(&self) -> &str {
        if self.actuated.is_some() {
            "f^d_idyn"
        } else {
            "f^d_dyn"
        }
    }
    key_and_noise_accessors!();
    fn dim(&self) -> usize {
        self.model.n()
    }
    fn scratch(&self) -> (usize, usize) {
        let (r, i) = DynamicsKernel::scratch(&self.model);
        let n = self.model.n();
        match &self.actuated {
            Some(a) => {
                let (ra, ia) = DynamicsKernel::along_scratch(&self.model, 2 * n + a.indices.len());
                (r + n + ra, i + ia)
            }
            None => (r + n, i),
        }
    }
    fn diagonal_jacobian(&self, key: usize) -> bool {
        key == 2
    }
    fn evaluates_along(&self) -> bool {
        self.actuated.is_some()
    }
    /// f^d_idyn only: e = q̈(q, q̇, t; Q) − q̈_t along V: K⁻¹ applied to the
    /// Jacobians' right-hand sides times V (see [`DynamicsKernel::along`]), minus V on
    /// q̈_t.
    fn evaluate_along(
        &self,
        t: f64,
        x: &[&[f64]],
        r: &mut [f64],
        dirs: &[&[f64]],
        c: usize,
        out: &mut [f64],
        ws: &mut Workspace,
    ) -> Result<bool> {
        let Some(a) = &self.actuated else {
            return Ok(false);
        };
        let n = self.model.n();
        let (kernel_len, _) = DynamicsKernel::scratch(&self.model);
        let (kernel, rest) = ws.reals.split_at_mut(kernel_len);
        let (own, extra) = rest.split_at_mut(n);
        let force = a.forces(x[3], own);
        DynamicsKernel::evaluate(
            &self.model,
            x[0],
            x[1],
            t,
            Some(force),
            r,
            None,
            kernel,
            &mut ws.indices,
        )?;
        if !DynamicsKernel::along(
            &self.model,
            (x[0], x[1], t),
            [dirs[0], dirs[1], dirs[3]],
            &a.indices,
            None,
            c,
            out,
            kernel,
            extra,
            &mut ws.indices,
            2 * n + a.indices.len(),
        )? {
            return Ok(false);
        }
        for (o, v) in out[..n * c].iter_mut().zip(&dirs[2][..n * c]) {
            *o -= v;
        }
        for i in 0..n {
            r[i] -= x[2][i];
        }
        Ok(true)
    }
    fn evaluate(
        &self,
        t: f64,
        x: &[&[f64]],
        r: &mut [f64],
        jac: Option<&mut [Vec<f64>]>,
        ws: &mut Workspace,
    ) -> Result<()> {
        let n = self.model.n();
        let (kernel_len, _) = DynamicsKernel::scratch(&self.model);
        let (kernel, own) = ws.reals.split_at_mut(kernel_len);
        let force = self
            .actuated
            .as_ref()
            .map(|a| a.forces(x[3], &mut own[..n]));
        match jac {
            Some(j) => {
                let (jq, rest) = j.split_at_mut(1);
                let (jv, rest) = rest.split_at_mut(1);
                let (ja, jf) = rest.split_at_mut(1);
                DynamicsKernel::evaluate(
                    &self.model,
                    x[0],
                    x[1],
                    t,
                    force,
                    r,
                    Some((&mut jq[0], &mut jv[0])),
                    kernel,
                    &mut ws.indices,
                )?;
                identity(&mut ja[0], n, -1.0);
                if let Some(a) = &self.actuated {
                    DynamicsKernel::force_jacobian(
                        &self.model,
                        &a.indices,
                        &mut jf[0],
                        kernel,
                        &ws.indices,
                    );
                }
            }
            None => DynamicsKernel::evaluate(
                &self.model,
                x[0],
                x[1],
                t,
                force,
                r,
                None,
                kernel,
                &mut ws.indices,
            )?,
        }
        for i in 0..n {
            r[i] -= x[2][i];
        }
        Ok(())
    }
}

/// f^i_pc: e = [Φ(q); q[idx] − z].
pub struct IndependentPosition {
    model: Arc<Model>,
    keys: [Key; 2],
    noise: Noise,
}

impl IndependentPosition {
    pub fn new(model: Arc<Model>, noise: Noise) -> Self {
        IndependentPosition {
            model,
            keys: [Key::now(VarKind::Q), Key::now(VarKind::Z)],
            noise,
        }
    }
}

/// Writes the selection rows q[idx] − z: I_idx into `jq` rows m.., −I into `jz`.
fn selection_rows(model: &Model, m: usize, jq: &mut [f64], jz: Option<&mut [f64]>) {
    let (n, f) = (model.n(), model.independent.len());
    jq[m * n..(m + f) * n].fill(0.0);
    for (k, &i) in model.independent.iter().enumerate() {
        jq[(m + k) * n + i] = 1.0;
    }
    if let Some(jz) = jz {
        jz.fill(0.0);
        for k in 0..f {
            jz[(m + k) * f + k] = -1.0;
        }
    }
}

impl Factor for IndependentPosition {
    fn name(&self) -> &str {
        "f^i_pc"
    }
    key_and_noise_accessors!();
    fn dim(&self) -> usize {
        self.model.m() + self.model.independent.len()
    }
    fn evaluate(
        &self,
        _t: f64,
        x: &[&[f64]],
        r: &mut [f64],
        jac: Option<&mut [Vec<f64>]>,
        _ws: &mut Workspace,
    ) -> Result<()> {
        let (m, n) = (self.model.m(), self.model.n());
        self.model.phi_into(x[0], &mut r[..m]);
        for (k, &i) in self.model.independent.iter().enumerate() {
            r[m + k] = x[0][i] - x[1][k];
        }
        if let Some(j) = jac {
            let (jq, jz) = j.split_at_mut(1);
            self.model.jacobian_into(x[0], &mut jq[0][..m * n]);
            selection_rows(&self.model, m, &mut jq[0], Some(&mut jz[0]));
        }
        Ok(())
    }
}

/// f^i_vc: e = [Φ_q q̇; q̇[idx] − ż].
pub struct IndependentVelocity {
    model: Arc<Model>,
    keys: [Key; 3],
    noise: Noise,
}

impl IndependentVelocity {
    pub fn new(model: Arc<Model>, noise: Noise) -> Self {
        IndependentVelocity {
            model,
            keys: [
                Key::now(VarKind::Q),
                Key::now(VarKind::Dq),
                Key::now(VarKind::Dz),
            ],
            noise,
        }
    }
}

impl Factor for IndependentVelocity {
    fn name(&self) -> &str {
        "f^i_vc"
    }
    key_and_noise_accessors!();
    fn dim(&self) -> usize {
        self.model.m() + self.model.independent.len()
    }
    fn scratch(&self) -> (usize, usize) {
        (self.model.m() * self.model.n(), 0)
    }
    fn evaluate(
        &self,
        _t: f64,
        x: &[&[f64]],
        r: &mut [f64],
        jac: Option<&mut [Vec<f64>]>,
        ws: &mut Workspace,
    ) -> Result<()> {
        let (m, n) = (self.model.m(), self.model.n());
        let a = &mut ws.reals[..m * n];
        self.model.jacobian_into(x[0], a);
        mat_vec(a, m, n, x[1], &mut r[..m]);
        for (k, &i) in self.model.independent.iter().enumerate() {
            r[m + k] = x[1][i] - x[2][k];
        }
        if let Some(j) = jac {
            let (jq, rest) = j.split_at_mut(1);
            let (jv, jz) = rest.split_at_mut(1);
            self.model
                .jacobian_derivative_into(x[0], x[1], &mut jq[0][..m * n]);
            jq[0][m * n..].fill(0.0);
            jv[0][..m * n].copy_from_slice(a);
            selection_rows(&self.model, m, &mut jv[0], Some(&mut jz[0]));
        }
        Ok(())
    }
}

/// f^i_ac: e = [Φ̇_q q̇ + Φ_q q̈; q̈[idx] − z̈].
pub struct IndependentAcceleration {
    model: Arc<Model>,
    keys: [Key; 4],
    noise: Noise,
}

impl IndependentAcceleration {
    pub fn new(model: Arc<Model>, noise: Noise) -> Self {
        IndependentAcceleration {
            model,
            keys: [
                Key::now(VarKind::Q),
                Key::now(VarKind::Dq),
                Key::now(VarKind::Ddq),
                Key::now(VarKind::Ddz),
            ],
            noise,
        }
    }
}

impl Factor for IndependentAcceleration {
    fn name(&self) -> &str {
        "f^i_ac"
    }
    key_and_noise_accessors!();
    fn dim(&self) -> usize {
        self.model.m() + self.model.independent.len()
    }
    fn scratch(&self) -> (usize, usize) {
        (self.model.m() * self.model.n() + self.model.m(), 0)
    }
    fn evaluate(
        &self,
        _t: f64,
        x: &[&[f64]],
        r: &mut [f64],
        jac: Option<&mut [Vec<f64>]>,
        ws: &mut Workspace,
    ) -> Result<()> {
        let (m, n) = (self.model.m(), self.model.n());
        let (q, dq, ddq, ddz) = (x[0], x[1], x[2], x[3]);
        let (a, rest) = ws.reals.split_at_mut(m * n);
        let c = &mut rest[..m];
        self.model.jacobian_into(q, a);
        self.model.acceleration_rhs_into(q, dq, c);
        mat_vec(a, m, n, ddq, &mut r[..m]);
        for k in 0..m {
            r[k] -= c[k]; // Φ_q q̈ + Φ̇_q q̇ with Φ̇_q q̇ = −c
        }
        for (k, &i) in self.model.independent.iter().enumerate() {
            r[m + k] = ddq[i] - ddz[k];
        }
        if let Some(j) = jac {
            let (jq, rest) = j.split_at_mut(1);
            let (jv, rest) = rest.split_at_mut(1);
            let (ja, jz) = rest.split_at_mut(1);
            // ∂/∂q = ∂(Φ̇_q q̇)/∂q + Φ_qq q̈; ∂/∂q̇ = 2 Φ̇_q; ∂/∂q̈ = [Φ_q; I_idx].
            ja[0][..m * n].copy_from_slice(a);
            selection_rows(&self.model, m, &mut ja[0], Some(&mut jz[0]));
            self.model.third_order_into(q, dq, &mut jq[0][..m * n]);
            self.model.jacobian_derivative_into(q, ddq, a);
            for (v, w) in jq[0][..m * n].iter_mut().zip(a.iter()) {
                *v += w;
            }
            jq[0][m * n..].fill(0.0);
            self.model
                .jacobian_derivative_into(q, dq, &mut jv[0][..m * n]);
            for v in &mut jv[0][..m * n] {
                *v *= 2.0;
            }
            jv[0][m * n..].fill(0.0);
        }
        Ok(())
    }
}

/// f^i_dyn: e = z̈(q, q̇, t) − z̈_t, with z̈ = q̈[idx] — the R-matrix result, computed
/// through the augmented system (the two agree to round-off; tested in `tests/model.rs`).
pub struct IndependentDynamics {
    model: Arc<Model>,
    keys: Vec<Key>,
    noise: Noise,
    inverse: bool,
    /// Every coordinate, the columns of ∂q̈/∂Q (forces act on all of them).
    all: Vec<usize>,
}

impl IndependentDynamics {
    pub fn new(model: Arc<Model>, noise: Noise) -> Self {
        IndependentDynamics {
            all: (0..model.n()).collect(),
            model,
            keys: vec![
                Key::now(VarKind::Q),
                Key::now(VarKind::Dq),
                Key::now(VarKind::Ddz),
            ],
            noise,
            inverse: false,
        }
    }

    /// f^i_idyn: e = z̈(q, q̇, t; Q_scene + Q) − z̈_t with the actuator forces Q a
    /// variable (fourth key); ∂e/∂Q is the independent rows of ∂q̈/∂Q.
    pub fn inverse(model: Arc<Model>, noise: Noise) -> Self {
        let mut f = IndependentDynamics::new(model, noise);
        f.keys.push(Key::now(VarKind::Force));
        f.inverse = true;
        f
    }
}

impl Factor for IndependentDynamics {
    fn name(&self) -> &str {
        if self.inverse {
            "f^i_idyn"
        } else {
            "f^i_dyn"
        }
    }
    key_and_noise_accessors!();
    fn dim(&self) -> usize {
        self.model.independent.len()
    }
    fn scratch(&self) -> (usize, usize) {
        let (r, i) = DynamicsKernel::scratch(&self.model);
        let n = self.model.n();
        if self.inverse {
            let (ra, ia) = DynamicsKernel::along_scratch(&self.model, 3 * n);
            (r + n + (3 * n * n).max(ra), i + ia)
        } else {
            (r + 3 * n * n + n, i)
        }
    }
    fn evaluates_along(&self) -> bool {
        self.inverse
    }
    /// f^i_idyn only: the independent rows of q̈(q, q̇, t; Q) along V (see
    /// [`DynamicsKernel::along`]), minus V on z̈_t.
    fn evaluate_along(
        &self,
        t: f64,
        x: &[&[f64]],
        r: &mut [f64],
        dirs: &[&[f64]],
        c: usize,
        out: &mut [f64],
        ws: &mut Workspace,
    ) -> Result<bool> {
        if !self.inverse {
            return Ok(false);
        }
        let n = self.model.n();
        let ind = &self.model.independent;
        let (kernel_len, _) = DynamicsKernel::scratch(&self.model);
        let (kernel, own) = ws.reals.split_at_mut(kernel_len);
        let (ddq, extra) = own.split_at_mut(n);
        DynamicsKernel::evaluate(
            &self.model,
            x[0],
            x[1],
            t,
            Some(x[3]),
            ddq,
            None,
            kernel,
            &mut ws.indices,
        )?;
        if !DynamicsKernel::along(
            &self.model,
            (x[0], x[1], t),
            [dirs[0], dirs[1], dirs[3]],
            &self.all,
            Some(ind),
            c,
            out,
            kernel,
            extra,
            &mut ws.indices,
            3 * n,
        )? {
            return Ok(false);
        }
        let f = ind.len();
        for (o, v) in out[..f * c].iter_mut().zip(&dirs[2][..f * c]) {
            *o -= v;
        }
        for (k, &i) in ind.iter().enumerate() {
            r[k] = ddq[i] - x[2][k];
        }
        Ok(true)
    }
    fn evaluate(
        &self,
        t: f64,
        x: &[&[f64]],
        r: &mut [f64],
        jac: Option<&mut [Vec<f64>]>,
        ws: &mut Workspace,
    ) -> Result<()> {
        let n = self.model.n();
        let f = self.model.independent.len();
        let (kernel_len, _) = DynamicsKernel::scratch(&self.model);
        let (kernel, own) = ws.reals.split_at_mut(kernel_len);
        let (ddq, own) = own.split_at_mut(n);
        let (jq, own) = own.split_at_mut(n * n);
        let (jv, own) = own.split_at_mut(n * n);
        let jf = &mut own[..n * n];
        let want = jac.is_some();
        let force = if self.inverse { Some(x[3]) } else { None };
        DynamicsKernel::evaluate(
            &self.model,
            x[0],
            x[1],
            t,
            force,
            ddq,
            want.then_some((&mut *jq, &mut *jv)),
            kernel,
            &mut ws.indices,
        )?;
        for (k, &i) in self.model.independent.iter().enumerate() {
            r[k] = ddq[i] - x[2][k];
        }
        if let Some(j) = jac {
            for (k, &i) in self.model.independent.iter().enumerate() {
                j[0][k * n..(k + 1) * n].copy_from_slice(&jq[i * n..(i + 1) * n]);
                j[1][k * n..(k + 1) * n].copy_from_slice(&jv[i * n..(i + 1) * n]);
            }
            identity(&mut j[2], f, -1.0);
            if self.inverse {
                DynamicsKernel::force_jacobian(&self.model, &self.all, jf, kernel, &ws.indices);
                for (k, &i) in self.model.independent.iter().enumerate() {
                    j[3][k * n..(k + 1) * n].copy_from_slice(&jf[i * n..(i + 1) * n]);
                }
            }
        }
        Ok(())
    }
}

/// f_prior on some components of a variable: e = x[idx] − x₀. Fixes the generalized
/// forces where no actuator acts (x₀ = 0), or the prescribed coordinates' initial
/// velocity and acceleration.
pub struct ComponentPrior {
    name: String,
    keys: [Key; 1],
    indices: Vec<usize>,
    target: Vec<f64>,
    noise: Noise,
}

impl ComponentPrior {
    pub fn new(kind: VarKind, indices: Vec<usize>, target: Vec<f64>, noise: Noise) -> Self {
        assert_eq!(indices.len(), target.len(), "one target per component");
        ComponentPrior {
            name: format!("f_prior({}[…])", kind.symbol()),
            keys: [Key::now(kind)],
            indices,
            target,
            noise,
        }
    }
}

impl Factor for ComponentPrior {
    fn name(&self) -> &str {
        &self.name
    }
    key_and_noise_accessors!();
    fn dim(&self) -> usize {
        self.indices.len()
    }
    fn evaluate(
        &self,
        _t: f64,
        x: &[&[f64]],
        r: &mut [f64],
        jac: Option<&mut [Vec<f64>]>,
        _ws: &mut Workspace,
    ) -> Result<()> {
        for (ri, (&i, &t)) in r.iter_mut().zip(self.indices.iter().zip(&self.target)) {
            *ri = x[0][i] - t;
        }
        if let Some(j) = jac {
            let d = x[0].len();
            j[0].fill(0.0);
            for (row, &i) in self.indices.iter().enumerate() {
                j[0][row * d + i] = 1.0;
            }
        }
        Ok(())
    }
}

/// f_prior on a prescribed motion: e = q[idx] − q_p(t_k), the values read from a
/// table with one row per time step t_k = t₀ + k·Δt.
pub struct PrescribedMotion {
    keys: [Key; 1],
    indices: Vec<usize>,
    /// Row-major steps × indices.len().
    table: Arc<Vec<f64>>,
    t0: f64,
    dt: f64,
    noise: Noise,
}

impl PrescribedMotion {
    /// On components `indices` of q (or of z, with `kind`).
    pub fn new(indices: Vec<usize>, table: Arc<Vec<f64>>, t0: f64, dt: f64, noise: Noise) -> Self {
        Self::on(VarKind::Q, indices, table, t0, dt, noise)
    }

    pub fn on(
        kind: VarKind,
        indices: Vec<usize>,
        table: Arc<Vec<f64>>,
        t0: f64,
        dt: f64,
        noise: Noise,
    ) -> Self {
        PrescribedMotion {
            keys: [Key::now(kind)],
            indices,
            table,
            t0,
            dt,
            noise,
        }
    }
}

impl Factor for PrescribedMotion {
    fn name(&self) -> &str {
        "f_prior(q prescribed)"
    }
    key_and_noise_accessors!();
    fn dim(&self) -> usize {
        self.indices.len()
    }
    fn evaluate(
        &self,
        t: f64,
        x: &[&[f64]],
        r: &mut [f64],
        jac: Option<&mut [Vec<f64>]>,
        _ws: &mut Workspace,
    ) -> Result<()> {
        let p = self.indices.len();
        let k = ((t - self.t0) / self.dt).round() as usize;
        let row = self.table.get(k * p..(k + 1) * p).ok_or_else(|| {
            Error::InvalidArgument(format!("no prescribed values at t = {t} (step {k})"))
        })?;
        for (ri, (&i, &v)) in r.iter_mut().zip(self.indices.iter().zip(row)) {
            *ri = x[0][i] - v;
        }
        if let Some(j) = jac {
            let d = x[0].len();
            j[0].fill(0.0);
            for (row, &i) in self.indices.iter().enumerate() {
                j[0][row * d + i] = 1.0;
            }
        }
        Ok(())
    }
}
