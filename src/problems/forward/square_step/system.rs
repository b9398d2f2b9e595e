//! The equations of a square step (see the module above): their residual and their
//! Jacobian, emitted entry by entry in a fixed order onto a compressed-column pattern.

use super::stage::Stage;
use crate::factors::{HermitePosition, Integrator};
use crate::model::{Model, MAX_LOCAL};
use std::sync::Arc;

/// Where the emitted entries go: collected as a pattern, or added into the values.
pub(super) enum Sink<'a> {
    Pattern(&'a mut Vec<(usize, usize)>),
    Values {
        slots: &'a [usize],
        values: &'a mut [f64],
        next: usize,
    },
}

impl Sink<'_> {
    #[inline]
    pub(super) fn add(&mut self, row: usize, col: usize, value: f64) {
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

/// The equations of a DC step with tangent integrators or of an IC step (see
/// the documentation of `forward::square_step`): residual and Jacobian.
#[derive(Clone)]
pub(super) struct System {
    pub(super) model: Arc<Model>,
    /// The rule of the integrator rows: a two-point rule's per-coordinate
    /// residual and partials, or Hermite–Simpson's with its stage ([`Stage`]).
    pub(super) integrator: Integrator,
    pub(super) dt: f64,
    /// The nonzeros of M: (row, column, value).
    pub(super) mass: Vec<(usize, usize, f64)>,
    /// (row, column) of the entries of ∂Q/∂q and ∂Q/∂q̇ any effect can write.
    pub(super) force_entries: Vec<(usize, usize)>,
    /// The coordinates the integrators hold: every one (DC), or z's (IC).
    pub(super) integrated: Vec<usize>,
    /// Whether the integrators are projected on the tangent space (DC: with
    /// multipliers μ₁, μ₂) or hold as they are (IC).
    pub(super) projected: bool,
    /// κ of the damped projections ([`System::row_damping`]): 0 for undamped ones.
    pub(super) projection_damping: f64,
}

impl System {
    /// The unknowns: q, q̇, q̈, λ, (projected) μ₁, μ₂, and Hermite–Simpson's
    /// stage q̈_m, λ_m.
    pub(super) fn size(&self) -> usize {
        let multipliers = if self.projected { 3 } else { 1 };
        3 * self.model.n() + multipliers * self.model.active.len() + self.stage_size()
    }

    /// Whether the step has Hermite–Simpson's collocation stage at its middle.
    pub(super) fn staged(&self) -> bool {
        self.integrator == Integrator::HermiteSimpson
    }

    /// The stage's unknowns (q̈_m, λ_m) and equations (its dynamics and
    /// acceleration constraints): n + m_a, or none.
    pub(super) fn stage_size(&self) -> usize {
        match self.staged() {
            true => self.model.n() + self.model.active.len(),
            false => 0,
        }
    }

    /// The first unknown of the stage, q̈_m (then λ_m); also its first equation.
    pub(super) fn stage_start(&self) -> usize {
        self.size() - self.stage_size()
    }

    /// In IC, z, ż, z̈ of a step's `block` (after q, q̇, q̈) from its q, q̇, q̈.
    pub(super) fn fill_independent(&self, block: &mut [f64]) {
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

    /// Whether the projections of the integrators are damped
    /// ([`System::row_damping`]).
    pub(super) fn damped(&self) -> bool {
        self.projected && self.projection_damping > 0.0
    }

    /// The damping of each active row's projections at the step's start q₀, from
    /// its rows' norms there (`row_norms`: |∇Φᵢ(q₀)|, [`Regularity::row_norms`]):
    /// κ |∇Φᵢ(q₀)|², with κ the system's `projection_damping`. The position and
    /// velocity rows then read Φᵢ + dᵢ μ₁ᵢ = 0 and ∇Φᵢ q̇ + dᵢ μ₂ᵢ = 0: each projection
    /// is the minimum of |Δq|² + |Φ|²/d, which enforces a constraint along the
    /// directions of Φ_q whose normalized singular value σ has σ² ≫ κ, and leaves
    /// one with σ² ≪ κ (a rank about to be lost) to the integrators and inertia.
    /// Undamped, a rounding of Φ near a rank loss is amplified like 1/σ⁴ through
    /// the nested projections into the step's motion.
    ///
    /// [`Regularity::row_norms`]: super::regularity::Regularity::row_norms
    pub(super) fn row_damping(&self, row_norms: &[f64], out: &mut Vec<f64>) {
        out.clear();
        out.extend(row_norms.iter().map(|r| self.projection_damping * r * r));
    }

    /// The equations: the constraints at three levels, the dynamics and the
    /// integrators.
    pub(super) fn equations(&self) -> usize {
        3 * self.model.active.len() + self.model.n() + 2 * self.integrated.len() + self.stage_size()
    }
}

impl System {
    /// Emits the Jacobian of the step system at `x` into `sink` (∂Q/∂q and ∂Q/∂q̇
    /// in `kq`, `kv`, row-major n × n, read at `force_entries` only; the stage's
    /// at its state in `stage`; the step's [`System::row_damping`] in `damping`,
    /// empty where it is not damped).
    pub(super) fn assemble(
        &self,
        x: &[f64],
        (kq, kv): (&[f64], &[f64]),
        stage: &Stage,
        damping: &[f64],
        sink: &mut Sink,
    ) {
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
        // The step before is fixed: ∂e/∂x₁, ∂e/∂ẋ₁ (and Hermite–Simpson's ∂e/∂ẍ₁,
        // ∂e/∂q̈_m) only.
        if self.staged() {
            let c = HermitePosition::coefficients(self.dt);
            let (h6, c_am) = (self.dt / 6.0, self.stage_start());
            for (r, &i) in self.integrated.iter().enumerate() {
                sink.add(r_pos_int + r, i, c[1]);
                sink.add(r_pos_int + r, n + i, c[3]);
                sink.add(r_pos_int + r, 2 * n + i, c[5]);
                sink.add(r_vel_int + r, n + i, 1.0);
                sink.add(r_vel_int + r, 2 * n + i, -h6);
                sink.add(r_vel_int + r, c_am + i, -4.0 * h6);
            }
        } else {
            let d = self.integrator.partials(self.dt);
            for (r, &i) in self.integrated.iter().enumerate() {
                sink.add(r_pos_int + r, i, d.x1);
                sink.add(r_vel_int + r, n + i, d.x1);
                if let Some(dx1) = d.dx1 {
                    sink.add(r_pos_int + r, n + i, dx1);
                    sink.add(r_vel_int + r, 2 * n + i, dx1);
                }
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
        for (row, &d) in damping.iter().enumerate() {
            sink.add(row, c_mu1 + row, d);
            sink.add(r_vel + row, c_mu2 + row, d);
        }
        if self.staged() {
            stage.assemble(self, x, sink);
        }
    }

    /// The residual of the step system at `x`, given the step before (`before`: q,
    /// q̇, q̈), the generalized forces Q in `q_force`, the stage's in `stage` and
    /// the step's [`System::row_damping`] in `damping` (empty where it is not
    /// damped).
    pub(super) fn residual(
        &self,
        x: &[f64],
        before: &[f64],
        (q_force, stage): (&[f64], &Stage),
        damping: &[f64],
        out: &mut [f64],
    ) {
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
        if self.staged() {
            // e_q = q₁ − q₀ − h/2 (q̇₀ + q̇₁) − h²/12 (q̈₀ − q̈₁) and
            // e_v = q̇₁ − q̇₀ − h/6 (q̈₀ + 4 q̈_m + q̈₁), as the collocation factors.
            let c = HermitePosition::coefficients(dt);
            let (h6, am) = (dt / 6.0, &x[self.stage_start()..self.stage_start() + n]);
            for (r, &i) in self.integrated.iter().enumerate() {
                out[r_pos_int + r] = c[0] * qp[i]
                    + c[1] * q[i]
                    + c[2] * vp[i]
                    + c[3] * v[i]
                    + c[4] * ap[i]
                    + c[5] * a[i];
                out[r_vel_int + r] = v[i] - vp[i] - h6 * (ap[i] + 4.0 * am[i] + a[i]);
            }
        } else {
            let rule = self.integrator;
            for (r, &i) in self.integrated.iter().enumerate() {
                out[r_pos_int + r] = rule.residual(qp[i], vp[i], q[i], v[i], dt);
                out[r_vel_int + r] = rule.residual(vp[i], ap[i], v[i], a[i], dt);
            }
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
            if let Some(&d) = damping.get(row) {
                out[row] += d * mult[ma + row];
                out[ma + row] += d * mult[2 * ma + row];
            }
        }
        if self.staged() {
            stage.residual(self, x, out);
        }
    }
}

/// One active constraint's local quantities at (q, q̇, q̈): Φ, ∇Φ, Φ_qq (row-major
/// len × len), Φ_qq q̇, Φ_qq q̈ and ∂(q̇ᵀΦ_qq q̇)/∂q.
pub(super) struct Local {
    pub(super) len: usize,
    pub(super) phi: f64,
    pub(super) gradient: [f64; MAX_LOCAL],
    pub(super) hessian: [f64; MAX_LOCAL * MAX_LOCAL],
    pub(super) hv: [f64; MAX_LOCAL],
    pub(super) ha: [f64; MAX_LOCAL],
    pub(super) third: [f64; MAX_LOCAL],
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
    pub(super) fn values_at(&mut self, c: &crate::model::Constraint, q: &[f64], v: &[f64]) {
        let (mut u, mut w) = ([0.0; MAX_LOCAL], [0.0; MAX_LOCAL]);
        self.len = c.equation.len();
        c.gather(q, &mut u);
        c.gather_rate(v, &mut w);
        self.phi = c.equation.phi(&u);
        c.equation.gradient(&u, &mut self.gradient);
        c.equation.hessian_times(&u, &w, &mut self.hv);
    }

    /// Everything, for the Jacobian.
    pub(super) fn at(&mut self, c: &crate::model::Constraint, q: &[f64], v: &[f64], a: &[f64]) {
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
