//! The energy balance of a run with non-conservative effects ([`Balance`]),
//! accumulated step by step as the steps become final: kinetic + potential energy
//! against the work of every effect that has no potential (a damper's damping, a
//! torque, a force, a motor). A run whose steps all converged can still be off its
//! balance: the step is too coarse for the motion, or the equations solved are not
//! the motion's. Conservative scenes have the energy drift instead.
//!
//! The work is integrated over each step to the integrator's order, so that what the
//! balance measures is the integrator's error and not the quadrature's: with the
//! trapezoidal rule on the power at the steps for the first- and second-order rules,
//! and for Hermite–Simpson with Simpson's rule, the power at the step's middle taken
//! on the cubic Hermite interpolant of its ends (q, q̇, q̈ at both): the trapezoidal
//! rule, second order, would read its own error as the fourth-order run's.
//!
//! The scene's constraints do no work: they do not depend on time, and their forces
//! are normal to the velocities they allow (a run's |Φ_q q̇| is checked separately).

use super::Integrator;
use crate::derived::WorkRule;
use crate::model::forces::Force;
use crate::model::Model;

/// The energy balance's measures over the steps added.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct BalanceOff {
    /// max |E(t) − E(0) − W(t)| over the run, J.
    pub worst: f64,
    /// The time of that worst value.
    pub t: f64,
    /// The largest |work| of any one effect along the run, J.
    pub peak_work: f64,
}

pub(super) struct Balance {
    /// The rule the work is integrated by over each step.
    rule: WorkRule,
    /// The non-conservative part of each such effect.
    effects: Vec<Force>,
    /// Each effect's work so far, and its largest |value|.
    work: Vec<f64>,
    /// Each effect's power at the last step's end.
    power_before: Vec<f64>,
    /// Scratch: a generalized force, a state in a step's middle.
    generalized: Vec<f64>,
    q_mid: Vec<f64>,
    dq_mid: Vec<f64>,
    e0: Option<f64>,
    off: BalanceOff,
    /// Cleared when an effect could not be evaluated (the run reports that itself).
    valid: bool,
}

impl Balance {
    /// The balance of a scene with non-conservative effects; None for a conservative
    /// one.
    pub(super) fn new(model: &Model, integrator: Integrator) -> Option<Self> {
        let effects: Vec<Force> = model
            .forces
            .iter()
            .filter_map(crate::derived::non_conservative)
            .collect();
        if effects.is_empty() {
            return None;
        }
        let (k, n) = (effects.len(), model.n());
        Some(Balance {
            rule: WorkRule::of(integrator),
            effects,
            work: vec![0.0; k],
            power_before: vec![0.0; k],
            generalized: vec![0.0; n],
            q_mid: vec![0.0; n],
            dq_mid: vec![0.0; n],
            e0: None,
            off: BalanceOff::default(),
            valid: true,
        })
    }

    /// The potential energy at q (gravity and springs).
    fn potential(model: &Model, q: &[f64]) -> f64 {
        model.forces.iter().map(|f| f.potential(model, q)).sum()
    }

    /// Effect e's power at (q, q̇, t).
    fn power(&mut self, model: &Model, e: usize, q: &[f64], dq: &[f64], t: f64) -> Option<f64> {
        self.generalized.fill(0.0);
        self.effects[e]
            .add_to(model, q, dq, t, &mut self.generalized)
            .ok()?;
        let p: f64 = self.generalized.iter().zip(dq).map(|(f, v)| f * v).sum();
        p.is_finite().then_some(p)
    }

    /// The run's first state (q, q̇ at time t) with its kinetic energy.
    pub(super) fn start(&mut self, model: &Model, t: f64, q: &[f64], dq: &[f64], kinetic: f64) {
        self.e0 = Some(kinetic + Self::potential(model, q));
        for e in 0..self.effects.len() {
            match self.power(model, e, q, dq, t) {
                Some(p) => self.power_before[e] = p,
                None => self.valid = false,
            }
        }
    }

    /// The step from `a` (time t0) to `b` (time t1), each q, q̇, q̈ in a row; the
    /// kinetic energy at `b`.
    pub(super) fn step(
        &mut self,
        model: &Model,
        (t0, a): (f64, &[f64]),
        (t1, b): (f64, &[f64]),
        kinetic: f64,
    ) {
        let Some(e0) = self.e0 else { return };
        if !self.valid {
            return;
        }
        let n = model.n();
        let h = t1 - t0;
        if self.rule == WorkRule::HermiteSimpson {
            crate::derived::hermite_middle(a, b, h, &mut self.q_mid, &mut self.dq_mid);
        }
        let (q_mid, dq_mid) = (
            std::mem::take(&mut self.q_mid),
            std::mem::take(&mut self.dq_mid),
        );
        let t_mid = t0 + 0.5 * h;
        for e in 0..self.effects.len() {
            let Some(end) = self.power(model, e, &b[..n], &b[n..2 * n], t1) else {
                self.valid = false;
                break;
            };
            let middle = if self.rule == WorkRule::HermiteSimpson {
                let Some(mid) = self.power(model, e, &q_mid, &dq_mid, t_mid) else {
                    self.valid = false;
                    break;
                };
                Some(mid)
            } else {
                None
            };
            let increment = WorkRule::over_step(h, self.power_before[e], middle, end);
            self.work[e] += increment;
            self.power_before[e] = end;
            self.off.peak_work = self.off.peak_work.max(self.work[e].abs());
        }
        (self.q_mid, self.dq_mid) = (q_mid, dq_mid);
        if !self.valid {
            return;
        }
        let energy = kinetic + Self::potential(model, &b[..n]);
        let off = (energy - e0 - self.work.iter().sum::<f64>()).abs();
        if off > self.off.worst {
            self.off.worst = off;
            self.off.t = t1;
        }
    }

    /// The measures, where every effect could be evaluated along the run.
    pub(super) fn finish(&self) -> Option<BalanceOff> {
        (self.valid && self.e0.is_some()).then_some(self.off)
    }
}
