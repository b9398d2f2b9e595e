//! One step of a dependent-coordinate run with tangent integrators, or of an
//! independent-coordinate run, solved as the square system it is, with a sparse
//! Jacobian: per-step cost that grows with the number of bodies, not with its cube.
//!
//! With tangent integrators a DC step has as many equations as unknowns and they
//! hold exactly (see [`crate::tangent`]): Φ(q) = 0, Φ_q q̇ = 0, f_dyn = 0, and the
//! projected integrators P(q) e = 0. Each projection is dense (P couples every
//! coordinate of a chain), but P e = 0 says e lies in the row space of Φ_q, that is
//! e = Φ_qᵀμ for a multiplier μ; and f_dyn = 0 is the augmented system with its
//! multiplier λ. So the step is also the root of
//!
//! ```text
//!   Φ(q) = 0                       Φ_q q̈ + q̇ᵀΦ_qq q̇ = 0
//!   Φ_q q̇ = 0                      M q̈ + Φ_qᵀλ − Q(q, q̇, t) = 0
//!   e_q(q, q̇) − Φ_qᵀμ₁ = 0         e_v(q̇, q̈) − Φ_qᵀμ₂ = 0
//! ```
//!
//! (active constraints only; e_q, e_v the trapezoidal or Euler residuals of the
//! positions and velocities), whose Jacobian has a few nonzeros per row: Newton's
//! method with faer's sparse LU, its symbolic analysis done once per mechanism.
//!
//! An IC step is the same system with the integrators on the independent
//! coordinates z only and no μ: q follows from z through Φ(q) = 0, and f^i_dyn = 0
//! is the augmented system's q̈ on z. Its equations are as many as its unknowns
//! where the constraints have full rank (m + f = n); the weak f_eq between
//! consecutive q, which the general solver also weighs, is left out (at its default
//! σ its weight is 1e-16 of the integrators').
//!
//! The general solver's dynamics regularize the augmented system near a singular
//! configuration (see [`crate::dynamics::DynamicsKernel`]); there the two systems
//! differ. A step is therefore taken from here only where the kernel's measure of
//! the distance to a rank loss, s = (tr G⁻¹)^(−1/2) with G the Gram matrix of the
//! normalized rows of Φ_q, is at least [`DynamicsKernel::REGULAR_ABOVE`] at the
//! solution (tr G⁻¹ by selected inversion of G's sparse Cholesky factor), and
//! where Newton converges within a few iterations. Anything else (and every
//! failure) goes back to the general solver.

use crate::dynamics::{self, DynamicsKernel};
use crate::graph::{ExactStep, StepIteration, StepLimits, StepWork};
use crate::linalg::sparse::{selected_inverse_trace, simplicial_symbolic};
use crate::model::{Model, MAX_LOCAL};
use crate::tangent::Rule;

mod factors;
use factors::Factors;
use faer::dyn_stack::{MemBuffer, MemStack};
use faer::linalg::cholesky::llt::factor::LltRegularization;
use faer::sparse::linalg::cholesky::{SymbolicCholesky, SymbolicCholeskyRaw, SymmetricOrdering};
use faer::sparse::{SparseColMatRef, SymbolicSparseColMatRef};
use faer::{Par, Side};
use nalgebra::DVector;
use std::sync::{Arc, Mutex};

/// s must pass [`DynamicsKernel::REGULAR_ABOVE`] by this factor: the kernel
/// computes it densely, in another order of rounding.
const REGULAR_MARGIN: f64 = 1.001;

/// Iterations after which a step goes back to the general solver: from a step's
/// prediction Newton converges in two to four, the simplified iteration (factors
/// of an earlier Jacobian) in five to eight.
const MAX_ITERATIONS: usize = 24;

/// Where the simplified iteration stops: an estimated error below this fraction of
/// the step tolerance (a converged Newton iteration's error is about the square of
/// its last update).
const SETTLED: f64 = 1e-6;

/// A contraction from which updates below the step tolerance count as the
/// rounding of the residual: they no longer shrink.
const ROUNDING_FLOOR: f64 = 0.5;

/// Fresh factorizations after which a step goes back to the general solver.
const MAX_FACTORIZATIONS: usize = 8;

/// The largest contraction (an update's size over the one before) accepted from
/// an iteration with factors of an earlier Jacobian: then the error left after an
/// update below the tolerance is below the tolerance too. Slower, the iterate is
/// linearized and factored afresh.
const MAX_CONTRACTION: f64 = 0.25;

/// A compressed-column pattern and, for each entry the assembly emits (in its
/// fixed order), where it adds up.
struct Pattern {
    size: usize,
    col_ptr: Vec<usize>,
    row_idx: Vec<usize>,
    slots: Vec<usize>,
}

impl Pattern {
    /// The pattern of the (row, column) pairs in emission order.
    fn new(size: usize, emitted: &[(usize, usize)]) -> Pattern {
        let mut order: Vec<usize> = (0..emitted.len()).collect();
        order.sort_unstable_by_key(|&t| (emitted[t].1, emitted[t].0));
        let mut col_ptr = vec![0; size + 1];
        let mut row_idx = Vec::new();
        let mut slots = vec![0; emitted.len()];
        let mut last = None;
        for &t in &order {
            let (row, col) = emitted[t];
            if last != Some((row, col)) {
                row_idx.push(row);
                col_ptr[col + 1] += 1;
                last = Some((row, col));
            }
            slots[t] = row_idx.len() - 1;
        }
        for c in 0..size {
            col_ptr[c + 1] += col_ptr[c];
        }
        Pattern {
            size,
            col_ptr,
            row_idx,
            slots,
        }
    }

    fn symbolic(&self) -> SymbolicSparseColMatRef<'_, usize> {
        SymbolicSparseColMatRef::new_checked(
            self.size,
            self.size,
            &self.col_ptr,
            None,
            &self.row_idx,
        )
    }
}

/// Where the emitted entries go: collected as a pattern, or added into the values.
enum Sink<'a> {
    Pattern(&'a mut Vec<(usize, usize)>),
    Values {
        slots: &'a [usize],
        values: &'a mut [f64],
        next: usize,
    },
}

impl Sink<'_> {
    #[inline]
    fn add(&mut self, row: usize, col: usize, value: f64) {
        match self {
            Sink::Pattern(list) => list.push((row, col)),
            Sink::Values {
                slots,
                values,
                next,
            } => {
                values[slots[*next]] += value;
                *next += 1;
            }
        }
    }
}

/// The scratch of the regularity test: G, its Cholesky factor and G⁻¹ on the
/// factor's pattern.
struct GramWork {
    /// Each active row's gradient, the entries of AAᵀ and the row norms.
    gradients: Vec<[f64; MAX_LOCAL]>,
    dots: Vec<f64>,
    norms: Vec<f64>,
    values: Vec<f64>,
    factor: Vec<f64>,
    /// (LLᵀ)⁻¹ on L's pattern.
    inverse: Vec<f64>,
    memory: MemBuffer,
}

/// The scratch of one step's Newton iteration.
struct Work {
    x: Vec<f64>,
    residual: Vec<f64>,
    values: Vec<f64>,
    q_force: Vec<f64>,
    kq: Vec<f64>,
    kv: Vec<f64>,
    factors: Factors,
    gram: GramWork,
    /// The multipliers of the last step solved: the next step's first guess.
    multipliers: Vec<f64>,
    /// The iterate before an update that may be undone.
    saved: Vec<f64>,
    /// Whether `factors` hold the LU of a Jacobian of this system (of an earlier
    /// iterate, maybe of an earlier step), which the next iterations may reuse.
    factored: bool,
}

/// The equations of a DC step with tangent integrators (see the module's
/// documentation): residual and Jacobian.
struct System {
    model: Arc<Model>,
    rule: Rule,
    dt: f64,
    /// The nonzeros of M: (row, column, value).
    mass: Vec<(usize, usize, f64)>,
    /// (row, column) of the entries of ∂Q/∂q and ∂Q/∂q̇ any effect can write.
    force_entries: Vec<(usize, usize)>,
    /// The coordinates the integrators hold: every one (DC), or z's (IC).
    integrated: Vec<usize>,
    /// Whether the integrators are projected on the tangent space (DC: with
    /// multipliers μ₁, μ₂) or hold as they are (IC).
    projected: bool,
}

impl System {
    /// The unknowns: q, q̇, q̈, λ and (projected) μ₁, μ₂.
    fn size(&self) -> usize {
        let multipliers = if self.projected { 3 } else { 1 };
        3 * self.model.n() + multipliers * self.model.active.len()
    }

    /// In IC, z, ż, z̈ of a step's `block` (after q, q̇, q̈) from its q, q̇, q̈.
    fn fill_independent(&self, block: &mut [f64]) {
        if self.projected {
            return;
        }
        let (n, f) = (self.model.n(), self.integrated.len());
        let (state, z) = block.split_at_mut(3 * n);
        for j in 0..3 {
            for (k, &i) in self.integrated.iter().enumerate() {
                z[j * f + k] = state[j * n + i];
            }
        }
    }

    /// The equations: the constraints at three levels, the dynamics and the
    /// integrators.
    fn equations(&self) -> usize {
        3 * self.model.active.len() + self.model.n() + 2 * self.integrated.len()
    }
}

/// The square system of a DC step with tangent integrators or of an IC step, with
/// its sparsity analysed once.
pub struct SquareStep {
    system: System,
    jacobian: Pattern,
    /// The lower triangle of G = ÂÂᵀ: per entry the pair of active rows (i, j ≤ i)
    /// and the pairs of their local coordinates that are one coordinate of q.
    gram_entries: Vec<GramEntry>,
    gram: Pattern,
    cholesky: SymbolicCholesky<usize>,
    work: Mutex<Work>,
}

impl SquareStep {
    /// The step system of a DC graph of `model` with tangent integrators of `rule`
    /// at `dt`; `None` where its sparse analysis fails (the general solver then
    /// takes every step).
    pub fn dependent(model: Arc<Model>, rule: Rule, dt: f64) -> Option<SquareStep> {
        let integrated = (0..model.n()).collect();
        SquareStep::new(model, rule, dt, integrated, true)
    }

    /// The step system of an IC graph of `model` (integrators of `rule` on its
    /// independent coordinates) at `dt`; `None` where it is not square (redundant
    /// constraints) or its sparse analysis fails.
    pub fn independent(model: Arc<Model>, rule: Rule, dt: f64) -> Option<SquareStep> {
        if model.active.len() != model.m() {
            return None;
        }
        let integrated = model.independent.clone();
        SquareStep::new(model, rule, dt, integrated, false)
    }

    fn new(
        model: Arc<Model>,
        rule: Rule,
        dt: f64,
        integrated: Vec<usize>,
        projected: bool,
    ) -> Option<SquareStep> {
        let (n, ma) = (model.n(), model.active.len());
        let mut force_entries = Vec::new();
        for force in &model.forces {
            match force.jacobian_pattern(&model) {
                Some((rows, cols)) => {
                    for &r in &rows {
                        force_entries.extend(cols.iter().map(|&c| (r, c)));
                    }
                }
                None => force_entries.extend((0..n).flat_map(|r| (0..n).map(move |c| (r, c)))),
            }
        }
        force_entries.sort_unstable();
        force_entries.dedup();
        let mass = (0..n)
            .flat_map(|i| (0..n).map(move |j| (i, j)))
            .filter_map(|(i, j)| {
                let m = model.mass[(i, j)];
                (m != 0.0).then_some((i, j, m))
            })
            .collect();
        let system = System {
            model,
            rule,
            dt,
            mass,
            force_entries,
            integrated,
            projected,
        };
        let size = system.size();
        if system.equations() != size {
            return None;
        }
        // The Jacobian's pattern from one structural pass of its assembly.
        let mut emitted = Vec::new();
        let x = vec![0.0; size];
        let dense = if system.force_entries.is_empty() {
            0
        } else {
            n * n
        };
        let (kq, kv) = (vec![0.0; dense], vec![0.0; dense]);
        system.assemble(&x, &kq, &kv, &mut Sink::Pattern(&mut emitted));
        let jacobian = Pattern::new(size, &emitted);
        let factors = Factors::new(&jacobian)?;
        let gram_entries = gram_entries(&system.model);
        let lower: Vec<(usize, usize)> = gram_entries.iter().map(|e| (e.0, e.1)).collect();
        let gram = Pattern::new(ma, &lower);
        let cholesky = simplicial_symbolic(gram.symbolic(), Side::Lower, SymmetricOrdering::Amd)?;
        let work = Work {
            x,
            residual: vec![0.0; size],
            values: vec![0.0; jacobian.row_idx.len()],
            q_force: vec![0.0; n],
            kq,
            kv,
            factors,
            factored: false,
            saved: vec![0.0; size],
            gram: GramWork {
                gradients: vec![[0.0; MAX_LOCAL]; ma],
                dots: vec![0.0; gram_entries.len()],
                norms: vec![0.0; ma],
                values: vec![0.0; gram.row_idx.len()],
                factor: vec![0.0; cholesky.len_val()],
                inverse: vec![0.0; cholesky.len_val()],
                memory: MemBuffer::new(
                    cholesky.factorize_numeric_llt_scratch::<f64>(Par::Seq, Default::default()),
                ),
            },
            multipliers: vec![0.0; size - 3 * n],
        };
        Some(SquareStep {
            system,
            jacobian,
            gram_entries,
            gram,
            cholesky,
            work: Mutex::new(work),
        })
    }
}

impl System {
    /// Emits the Jacobian of the step system at `x` into `sink` (∂Q/∂q and ∂Q/∂q̇
    /// in `kq`, `kv`, row-major n × n, read at `force_entries` only).
    fn assemble(&self, x: &[f64], kq: &[f64], kv: &[f64], sink: &mut Sink) {
        let model = &*self.model;
        let (n, ma) = (model.n(), model.active.len());
        let (q, v, a) = (&x[..n], &x[n..2 * n], &x[2 * n..3 * n]);
        let mult = &x[3 * n..];
        // Rows: Φ, Φ_q q̇, the acceleration equations, then M q̈ + Φ_qᵀλ − Q and
        // the two integrators (of every coordinate in DC, where the μ rows of
        // coordinate i are its integrators'). Columns: q, q̇, q̈, λ, μ₁, μ₂.
        let ni = self.integrated.len();
        let (r_vel, r_acc, r_dyn, r_pos_int, r_vel_int) =
            (ma, 2 * ma, 3 * ma, 3 * ma + n, 3 * ma + n + ni);
        let (c_lambda, c_mu1, c_mu2) = (3 * n, 3 * n + ma, 3 * n + 2 * ma);
        let half = match self.rule {
            Rule::Trapezoidal => 0.5 * self.dt,
            Rule::Euler => 0.0,
        };
        for (r, &i) in self.integrated.iter().enumerate() {
            sink.add(r_pos_int + r, i, 1.0);
            sink.add(r_vel_int + r, n + i, 1.0);
            if self.rule == Rule::Trapezoidal {
                sink.add(r_pos_int + r, n + i, -half);
                sink.add(r_vel_int + r, 2 * n + i, -half);
            }
        }
        for &(i, j, mass) in &self.mass {
            sink.add(r_dyn + i, 2 * n + j, mass);
        }
        for &(r, c) in &self.force_entries {
            sink.add(r_dyn + r, c, -kq[r * n + c]);
            sink.add(r_dyn + r, n + c, -kv[r * n + c]);
        }
        let mut local = Local::default();
        for (row, &k) in model.active.iter().enumerate() {
            let c = &model.constraints[k];
            local.at(c, q, v, a);
            let len = local.len;
            let index = c.local_index();
            let lambda = mult[row];
            let (mu1, mu2) = if self.projected {
                (mult[ma + row], mult[2 * ma + row])
            } else {
                (0.0, 0.0)
            };
            for (p, ip) in index.iter().enumerate() {
                let Some(ip) = *ip else { continue };
                let g = local.gradient[p];
                sink.add(row, ip, g);
                sink.add(r_vel + row, n + ip, g);
                sink.add(r_acc + row, 2 * n + ip, g);
                sink.add(r_dyn + ip, c_lambda + row, g);
                if self.projected {
                    sink.add(r_pos_int + ip, c_mu1 + row, -g);
                    sink.add(r_vel_int + ip, c_mu2 + row, -g);
                }
                // ∂(Φ_q q̇)/∂q = (Φ_qq q̇)ᵀ; the acceleration row's
                // ∂/∂q = (Φ_qq q̈)ᵀ + ∂(q̇ᵀΦ_qq q̇)/∂q and ∂/∂q̇ = 2 (Φ_qq q̇)ᵀ.
                sink.add(r_vel + row, ip, local.hv[p]);
                sink.add(r_acc + row, ip, local.ha[p] + local.third[p]);
                sink.add(r_acc + row, n + ip, 2.0 * local.hv[p]);
                for (s, is) in index.iter().enumerate() {
                    let Some(is) = *is else { continue };
                    // ∂(Φ_qᵀw)/∂q: entry (coordinate p, coordinate s) is w·H[p][s].
                    let h = local.hessian[p * len + s];
                    sink.add(r_dyn + ip, is, lambda * h);
                    if self.projected {
                        sink.add(r_pos_int + ip, is, -mu1 * h);
                        sink.add(r_vel_int + ip, is, -mu2 * h);
                    }
                }
            }
        }
    }

    /// The residual of the step system at `x`, given the step before (`before`: q,
    /// q̇, q̈) and the generalized forces Q in `work.q_force`.
    fn residual(&self, x: &[f64], before: &[f64], q_force: &[f64], out: &mut [f64]) {
        let model = &*self.model;
        let (n, ma) = (model.n(), model.active.len());
        let (q, v, a) = (&x[..n], &x[n..2 * n], &x[2 * n..3 * n]);
        let (qp, vp, ap) = (&before[..n], &before[n..2 * n], &before[2 * n..3 * n]);
        let mult = &x[3 * n..];
        let dt = self.dt;
        let ni = self.integrated.len();
        let (r_dyn, r_pos_int, r_vel_int) = (3 * ma, 3 * ma + n, 3 * ma + n + ni);
        for (r, force) in out[r_dyn..r_dyn + n].iter_mut().zip(q_force) {
            *r = -force;
        }
        for (r, &i) in self.integrated.iter().enumerate() {
            (out[r_pos_int + r], out[r_vel_int + r]) = match self.rule {
                Rule::Trapezoidal => (
                    q[i] - qp[i] - 0.5 * dt * (vp[i] + v[i]),
                    v[i] - vp[i] - 0.5 * dt * (ap[i] + a[i]),
                ),
                Rule::Euler => (q[i] - qp[i] - dt * vp[i], v[i] - vp[i] - dt * ap[i]),
            };
        }
        for &(i, j, mass) in &self.mass {
            out[r_dyn + i] += mass * a[j];
        }
        let mut local = Local::default();
        for (row, &k) in model.active.iter().enumerate() {
            let c = &model.constraints[k];
            local.values_at(c, q, v);
            out[row] = local.phi;
            let (mut vel, mut acc) = (0.0, 0.0);
            for (p, ip) in c.local_index().iter().enumerate() {
                let Some(ip) = *ip else { continue };
                let g = local.gradient[p];
                vel += g * v[ip];
                acc += g * a[ip] + local.hv[p] * v[ip];
                out[r_dyn + ip] += g * mult[row];
                if self.projected {
                    out[r_pos_int + ip] -= g * mult[ma + row];
                    out[r_vel_int + ip] -= g * mult[2 * ma + row];
                }
            }
            out[ma + row] = vel;
            out[2 * ma + row] = acc;
        }
    }
}

impl SquareStep {
    /// Whether the active rows of Φ_q at q are far enough from a rank loss that the
    /// dynamics kernel uses the plain augmented system: its measure
    /// s = (tr G⁻¹)^(−1/2) at least [`DynamicsKernel::REGULAR_ABOVE`] (with a
    /// margin for rounding), tr G⁻¹ from the sparse Cholesky factor of G.
    fn regular(&self, q: &[f64], gram: &mut GramWork) -> bool {
        self.distance_to_rank_loss(q, gram) >= REGULAR_MARGIN * DynamicsKernel::REGULAR_ABOVE
    }

    /// The dynamics kernel's s at q (0 where G does not factor).
    fn distance_to_rank_loss(&self, q: &[f64], gram: &mut GramWork) -> f64 {
        let model = &*self.system.model;
        let ma = model.active.len();
        if ma == 0 {
            return f64::INFINITY;
        }
        let GramWork {
            gradients,
            dots,
            norms,
            ..
        } = gram;
        let mut u = [0.0; MAX_LOCAL];
        for (row, &k) in model.active.iter().enumerate() {
            let c = &model.constraints[k];
            c.gather(q, &mut u);
            c.equation.gradient(&u, &mut gradients[row]);
        }
        // AAᵀ over the shared coordinates (a coordinate a row holds twice adds up),
        // the row norms from its diagonal, then G.
        for ((i, j, shared), dot) in self.gram_entries.iter().zip(dots.iter_mut()) {
            *dot = shared
                .iter()
                .map(|&(p, s)| gradients[*i][p] * gradients[*j][s])
                .sum();
        }
        for ((i, j, _), dot) in self.gram_entries.iter().zip(dots.iter()) {
            if i == j {
                norms[*i] = dot.sqrt();
            }
        }
        if !norms.iter().all(|v| *v > 0.0 && v.is_finite()) {
            return 0.0;
        }
        gram.values.fill(0.0);
        for (t, ((i, j, _), dot)) in self.gram_entries.iter().zip(&gram.dots).enumerate() {
            gram.values[self.gram.slots[t]] += dot / (gram.norms[*i] * gram.norms[*j]);
        }
        let matrix = SparseColMatRef::new(self.gram.symbolic(), &gram.values);
        let factored = self.cholesky.factorize_numeric_llt(
            &mut gram.factor,
            matrix,
            Side::Lower,
            LltRegularization::default(),
            Par::Seq,
            MemStack::new(&mut gram.memory),
            Default::default(),
        );
        let SymbolicCholeskyRaw::Simplicial(l) = self.cholesky.raw() else {
            return 0.0;
        };
        if factored.is_err() {
            return 0.0;
        }
        let trace =
            selected_inverse_trace(l.col_ptr(), l.row_idx(), &gram.factor, &mut gram.inverse);
        trace.map_or(0.0, |t| t.recip().sqrt())
    }

    /// The residual of the step system at `work.x` in `work.residual`; `None`
    /// where an effect cannot be evaluated or it is not finite.
    fn residual(&self, t: f64, before: &[f64], work: &mut Work) -> Option<()> {
        let system = &self.system;
        let model = &*system.model;
        let n = model.n();
        let (q, v) = (&work.x[..n], &work.x[n..2 * n]);
        work.q_force.fill(0.0);
        for force in &model.forces {
            force.add_to(model, q, v, t, &mut work.q_force).ok()?;
        }
        system.residual(&work.x, before, &work.q_force, &mut work.residual);
        work.residual.iter().all(|v| v.is_finite()).then_some(())
    }

    /// The residual (`work.residual`) and the Jacobian's values (`work.values`) of
    /// the step system at `work.x`, and the Jacobian's LU (`work.factors`); `None`
    /// where an effect cannot be evaluated, either is not finite or the LU fails.
    fn linearize(&self, t: f64, before: &[f64], work: &mut Work) -> Option<()> {
        let system = &self.system;
        let model = &*system.model;
        let n = model.n();
        work.factored = false;
        self.residual(t, before, work)?;
        let (q, v) = (&work.x[..n], &work.x[n..2 * n]);
        if !system.force_entries.is_empty() {
            for force in &model.forces {
                force
                    .add_jacobians(model, (q, v, t), &mut work.kq, &mut work.kv)
                    .ok()?;
            }
        }
        work.values.fill(0.0);
        system.assemble(
            &work.x,
            &work.kq,
            &work.kv,
            &mut Sink::Values {
                slots: &self.jacobian.slots,
                values: &mut work.values,
                next: 0,
            },
        );
        for &(r, c) in &system.force_entries {
            work.kq[r * n + c] = 0.0;
            work.kv[r * n + c] = 0.0;
        }
        if !work.values.iter().all(|v| v.is_finite()) {
            return None;
        }
        work.factors.factor(&self.jacobian, &work.values)?;
        work.factored = true;
        Some(())
    }

    /// Newton's method on the step system from the guess in `block`; the
    /// iterations taken when it converged. Simplified where it may be: the LU of
    /// an earlier Jacobian (of this step or of one before) is used as long as the
    /// updates shrink by [`MAX_CONTRACTION`] or faster (a step's Jacobian changes
    /// little from the one before it); the first update that does not is discarded
    /// and the iterate factored afresh.
    fn newton(
        &self,
        t: f64,
        before: &[f64],
        block: &mut [f64],
        limits: StepLimits,
        work: &mut Work,
        mut watch: Option<&mut dyn FnMut(&StepIteration)>,
    ) -> Option<StepWork> {
        let system = &self.system;
        let model = &*system.model;
        let n = model.n();
        work.x[..3 * n].copy_from_slice(&block[..3 * n]);
        work.x[3 * n..].copy_from_slice(&work.multipliers);
        // The size of the last update taken with the factors now held.
        let mut last = f64::INFINITY;
        let mut factorizations = 0;
        // Whether the last update was taken with an earlier step's factors and
        // nothing to judge them by: undone (from `work.saved`) if the next one shows
        // they do not carry the iteration.
        let mut blind = false;
        for iteration in 1..=limits.max_iterations.min(MAX_ITERATIONS) {
            let fresh = !work.factored;
            if fresh {
                factorizations += 1;
                if factorizations > MAX_FACTORIZATIONS {
                    return None;
                }
                self.linearize(t, before, work)?;
            } else {
                self.residual(t, before, work)?;
            }
            let cost = match watch {
                Some(_) => 0.5 * work.residual.iter().map(|r| r * r).sum::<f64>(),
                None => 0.0,
            };
            work.factors.solve_in_place(&mut work.residual);
            if !work.residual.iter().all(|d| d.is_finite()) {
                return None;
            }
            let update = work.x[..3 * n]
                .iter()
                .zip(&work.residual)
                .map(|(xi, di)| di.abs() / (1.0 + xi.abs()))
                .fold(0.0, f64::max);
            // The error left after this update: about its square after a Newton
            // update; after a simplified one, θ/(1 − θ) of it at the contraction θ
            // seen. Updates that stop shrinking below the tolerance are the
            // residual's rounding, as far as any iteration gets.
            // (None: no update taken with these factors yet.)
            let contraction = (!fresh && last.is_finite()).then(|| update / last);
            let settled = match contraction {
                _ if fresh => update <= limits.step_tolerance,
                None => false,
                Some(c) => {
                    c < 1.0 && c / (1.0 - c) * update <= SETTLED * limits.step_tolerance
                        || (c >= ROUNDING_FLOOR && update <= limits.step_tolerance)
                }
            };
            if let Some(watch) = watch.as_mut() {
                watch(&StepIteration {
                    iteration,
                    cost,
                    update,
                    fresh,
                    settled,
                });
            }
            if !settled && contraction.is_some_and(|c| c > MAX_CONTRACTION) {
                // The earlier Jacobian no longer carries the iteration.
                work.factored = false;
                if blind {
                    work.x.copy_from_slice(&work.saved);
                    blind = false;
                }
                continue;
            }
            blind = !fresh && contraction.is_none();
            if blind {
                work.saved.copy_from_slice(&work.x);
            }
            last = update;
            for (xi, di) in work.x.iter_mut().zip(&work.residual) {
                *xi -= di;
            }
            if settled {
                if !self.regular(&work.x[..n], &mut work.gram) {
                    return None;
                }
                block[..3 * n].copy_from_slice(&work.x[..3 * n]);
                system.fill_independent(block);
                work.multipliers.copy_from_slice(&work.x[3 * n..]);
                return Some(StepWork {
                    iterations: iteration,
                    factorizations,
                });
            }
        }
        None
    }
}

impl ExactStep for SquareStep {
    /// Step 0 holds q and q̇ at the model's initial state (in `block`), and f_dyn
    /// asks q̈ of the augmented system there, which is regular where the steps are
    /// taken from here: its solution, once the configuration passes the same test.
    fn solve_first(&self, t: f64, block: &mut [f64]) -> Option<StepWork> {
        let model = &*self.system.model;
        let n = model.n();
        let mut work = self.work.lock().ok()?;
        if !self.regular(&block[..n], &mut work.gram) {
            return None;
        }
        let q = DVector::from_column_slice(&block[..n]);
        let dq = DVector::from_column_slice(&block[n..2 * n]);
        let ddq = dynamics::accelerations_guess(model, &q, &dq, t).ok()?;
        if !ddq.iter().all(|v| v.is_finite()) {
            return None;
        }
        block[2 * n..3 * n].copy_from_slice(ddq.as_slice());
        self.system.fill_independent(block);
        Some(StepWork {
            iterations: 1,
            factorizations: 1,
        })
    }

    fn solve(
        &self,
        t: f64,
        before: &[f64],
        block: &mut [f64],
        limits: StepLimits,
        watch: Option<&mut dyn FnMut(&StepIteration)>,
    ) -> Option<StepWork> {
        let mut work = self.work.lock().ok()?;
        let solved = self.newton(t, before, block, limits, &mut work, watch);
        if solved.is_none() {
            // The next step starts its multipliers and its Jacobian afresh.
            work.multipliers.fill(0.0);
            work.factored = false;
        }
        solved
    }
}

/// One active constraint's local quantities at (q, q̇, q̈): Φ, ∇Φ, Φ_qq (row-major
/// len × len), Φ_qq q̇, Φ_qq q̈ and ∂(q̇ᵀΦ_qq q̇)/∂q.
struct Local {
    len: usize,
    phi: f64,
    gradient: [f64; MAX_LOCAL],
    hessian: [f64; MAX_LOCAL * MAX_LOCAL],
    hv: [f64; MAX_LOCAL],
    ha: [f64; MAX_LOCAL],
    third: [f64; MAX_LOCAL],
}

impl Default for Local {
    fn default() -> Local {
        Local {
            len: 0,
            phi: 0.0,
            gradient: [0.0; MAX_LOCAL],
            hessian: [0.0; MAX_LOCAL * MAX_LOCAL],
            hv: [0.0; MAX_LOCAL],
            ha: [0.0; MAX_LOCAL],
            third: [0.0; MAX_LOCAL],
        }
    }
}

impl Local {
    /// What the residual needs: Φ, ∇Φ and Φ_qq q̇.
    fn values_at(&mut self, c: &crate::model::Constraint, q: &[f64], v: &[f64]) {
        let (mut u, mut w) = ([0.0; MAX_LOCAL], [0.0; MAX_LOCAL]);
        self.len = c.equation.len();
        c.gather(q, &mut u);
        c.gather_rate(v, &mut w);
        self.phi = c.equation.phi(&u);
        c.equation.gradient(&u, &mut self.gradient);
        c.equation.hessian_times(&u, &w, &mut self.hv);
    }

    /// Everything, for the Jacobian.
    fn at(&mut self, c: &crate::model::Constraint, q: &[f64], v: &[f64], a: &[f64]) {
        let len = c.equation.len();
        self.len = len;
        let (mut u, mut w, mut acc, mut e) = (
            [0.0; MAX_LOCAL],
            [0.0; MAX_LOCAL],
            [0.0; MAX_LOCAL],
            [0.0; MAX_LOCAL],
        );
        c.gather(q, &mut u);
        c.gather_rate(v, &mut w);
        c.gather_rate(a, &mut acc);
        self.phi = c.equation.phi(&u);
        c.equation.gradient(&u, &mut self.gradient);
        c.equation.hessian_times(&u, &w, &mut self.hv);
        c.equation.hessian_times(&u, &acc, &mut self.ha);
        c.equation.third_order(&u, &w, &mut self.third);
        let mut column = [0.0; MAX_LOCAL];
        for s in 0..len {
            e[..len].fill(0.0);
            e[s] = 1.0;
            c.equation.hessian_times(&u, &e, &mut column);
            for p in 0..len {
                self.hessian[p * len + s] = column[p];
            }
        }
    }
}

/// An entry of G's lower triangle: rows (i, j ≤ i) and the pairs of their local
/// coordinates that are one coordinate of q.
type GramEntry = (usize, usize, Vec<(usize, usize)>);

/// The lower triangle of G = ÂÂᵀ over the active rows: (i, j ≤ i, the local
/// coordinate pairs of rows j and i that are one coordinate of q).
fn gram_entries(model: &Model) -> Vec<GramEntry> {
    let ma = model.active.len();
    let mut rows_of = vec![Vec::new(); model.n()];
    for (row, &k) in model.active.iter().enumerate() {
        for (p, ip) in model.constraints[k].local_index().iter().enumerate() {
            if let Some(ip) = *ip {
                rows_of[ip].push((row, p));
            }
        }
    }
    let mut pairs: Vec<(usize, usize, usize, usize)> = Vec::new();
    for list in &rows_of {
        for &(i, p) in list {
            for &(j, s) in list {
                if j <= i {
                    pairs.push((i, j, p, s));
                }
            }
        }
    }
    pairs.sort_unstable();
    let mut entries: Vec<GramEntry> = Vec::new();
    for (i, j, p, s) in pairs {
        match entries.last_mut() {
            Some(last) if last.0 == i && last.1 == j => last.2.push((p, s)),
            _ => entries.push((i, j, vec![(p, s)])),
        }
    }
    // Every row's diagonal, even one whose gradient touches no free coordinate.
    let mut diagonal = vec![false; ma];
    for e in &entries {
        diagonal[e.0] |= e.0 == e.1;
    }
    for (i, _) in diagonal.iter().enumerate().filter(|(_, d)| !**d) {
        entries.push((i, i, Vec::new()));
    }
    entries
}

#[cfg(test)]
mod tests;
