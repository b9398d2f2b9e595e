//! The collocation stage of a Hermite–Simpson step as equations of its square
//! system.
//!
//! The collocation factors ([`crate::factors::SimpsonVelocity`]) evaluate the
//! dynamics at the step's middle inside themselves: q̈_m = f(q_m, q̇_m, t − h/2), the
//! augmented (KKT) system's solution at the Hermite interpolants
//!
//! ```text
//!   q_m = (q₀ + q₁)/2 + h/8 (q̇₀ − q̇₁)      q̇_m = (q̇₀ + q̇₁)/2 + h/8 (q̈₀ − q̈₁)
//! ```
//!
//! Here q̈_m and its multiplier λ_m are unknowns of the step, and that KKT system
//! is two more blocks of equations:
//!
//! ```text
//!   M q̈_m + Φ_q(q_m)ᵀλ_m − Q(q_m, q̇_m, t − h/2) = 0
//!   Φ_q(q_m) q̈_m + q̇_mᵀΦ_qq(q_m) q̇_m = 0
//! ```
//!
//! q_m and q̇_m stay eliminated: linear in the step's q₁, q̇₁, q̈₁, their
//! derivatives enter the Jacobian through ∂q_m/∂q₁ = 1/2, ∂q_m/∂q̇₁ = −h/8,
//! ∂q̇_m/∂q̇₁ = 1/2, ∂q̇_m/∂q̈₁ = −h/8. Every entry lands where an entry of the
//! step's own dynamics and acceleration rows already does, shifted to the stage's
//! rows: the step's Jacobian grows by n + m_a rows and columns of the same
//! sparsity, not by the dense ∂q̈_m/∂(q, q̇) the factors form.

use super::system::{Local, Sink, System};

/// The stage's state and the effects' terms there.
pub(super) struct Stage<'a> {
    /// q_m, then q̇_m (2n; empty without a stage).
    pub(super) state: &'a [f64],
    /// Q(q_m, q̇_m, t − h/2) (n).
    pub(super) force: &'a [f64],
    /// ∂Q/∂q and ∂Q/∂q̇ there, row-major n × n, read at the system's
    /// `force_entries` only.
    pub(super) kq: &'a [f64],
    pub(super) kv: &'a [f64],
}

impl Stage<'_> {
    /// No stage: a two-point rule's step.
    pub(super) const NONE: Stage<'static> = Stage {
        state: &[],
        force: &[],
        kq: &[],
        kv: &[],
    };
}

impl System {
    /// The stage's time, for a step ending at `t`.
    pub(super) fn stage_time(&self, t: f64) -> f64 {
        t - 0.5 * self.dt
    }

    /// q_m and q̇_m (into `out`, 2n) from the step `x` and the step before.
    pub(super) fn stage_state(&self, x: &[f64], before: &[f64], out: &mut [f64]) {
        let n = self.model.n();
        let e = 0.125 * self.dt;
        let (q, v, a) = (&x[..n], &x[n..2 * n], &x[2 * n..3 * n]);
        let (qp, vp, ap) = (&before[..n], &before[n..2 * n], &before[2 * n..3 * n]);
        let (qm, vm) = out[..2 * n].split_at_mut(n);
        for i in 0..n {
            qm[i] = 0.5 * (qp[i] + q[i]) + e * (vp[i] - v[i]);
            vm[i] = 0.5 * (vp[i] + v[i]) + e * (ap[i] - a[i]);
        }
    }
}

impl Stage<'_> {
    /// The stage's rows of the residual (from `system.stage_start()`).
    pub(super) fn residual(&self, system: &System, x: &[f64], out: &mut [f64]) {
        let model = &*system.model;
        let (n, ma) = (model.n(), model.active.len());
        let start = system.stage_start();
        let (am, lm) = (&x[start..start + n], &x[start + n..start + n + ma]);
        let (r_dyn, r_acc) = (start, start + n);
        let (qm, vm) = self.state.split_at(n);
        for (r, force) in out[r_dyn..r_dyn + n].iter_mut().zip(self.force) {
            *r = -force;
        }
        for &(i, j, mass) in &system.mass {
            out[r_dyn + i] += mass * am[j];
        }
        let mut local = Local::default();
        for (row, &k) in model.active.iter().enumerate() {
            let c = &model.constraints[k];
            local.values_at(c, qm, vm);
            let mut acc = 0.0;
            for (p, ip) in c.local_index().iter().enumerate() {
                let Some(ip) = *ip else { continue };
                let g = local.gradient[p];
                acc += g * am[ip] + local.hv[p] * vm[ip];
                out[r_dyn + ip] += g * lm[row];
            }
            out[r_acc + row] = acc;
        }
    }

    /// The stage's rows of the Jacobian, into `sink`.
    pub(super) fn assemble(&self, system: &System, x: &[f64], sink: &mut Sink) {
        let model = &*system.model;
        let (n, ma) = (model.n(), model.active.len());
        let start = system.stage_start();
        let (am, lm) = (&x[start..start + n], &x[start + n..start + n + ma]);
        let (r_dyn, r_acc) = (start, start + n);
        let (c_am, c_lm) = (start, start + n);
        let (qm, vm) = self.state.split_at(n);
        // ∂q_m/∂q₁, ∂q_m/∂q̇₁ = ∂q̇_m/∂q̈₁, ∂q̇_m/∂q̇₁.
        let (half, e) = (0.5, -0.125 * system.dt);
        for &(i, j, mass) in &system.mass {
            sink.add(r_dyn + i, c_am + j, mass);
        }
        for &(r, c) in &system.force_entries {
            let (kq, kv) = (self.kq[r * n + c], self.kv[r * n + c]);
            sink.add(r_dyn + r, c, -half * kq);
            sink.add(r_dyn + r, n + c, -e * kq - half * kv);
            sink.add(r_dyn + r, 2 * n + c, -e * kv);
        }
        let mut local = Local::default();
        for (row, &k) in model.active.iter().enumerate() {
            let c = &model.constraints[k];
            local.at(c, qm, vm, am);
            let len = local.len;
            let index = c.local_index();
            let lambda = lm[row];
            for (p, ip) in index.iter().enumerate() {
                let Some(ip) = *ip else { continue };
                let g = local.gradient[p];
                sink.add(r_dyn + ip, c_lm + row, g);
                sink.add(r_acc + row, c_am + ip, g);
                // The acceleration row through q_m: (Φ_qq q̈_m)ᵀ + ∂(q̇ᵀΦ_qq q̇)/∂q;
                // through q̇_m: 2 (Φ_qq q̇_m)ᵀ.
                let (dq, dv) = (local.ha[p] + local.third[p], 2.0 * local.hv[p]);
                sink.add(r_acc + row, ip, half * dq);
                sink.add(r_acc + row, n + ip, e * dq + half * dv);
                sink.add(r_acc + row, 2 * n + ip, e * dv);
                for (s, is) in index.iter().enumerate() {
                    let Some(is) = *is else { continue };
                    let h = lambda * local.hessian[p * len + s];
                    sink.add(r_dyn + ip, is, half * h);
                    sink.add(r_dyn + ip, n + is, e * h);
                }
            }
        }
    }
}
