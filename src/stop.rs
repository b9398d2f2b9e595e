//! Stop conditions (`mbfg simulate --until EXPR`): an expression of the time and the
//! state, in the names effects use (`theta`, `rate(theta)`, `x(P)`, `vy(P)`,
//! `angle(B)`, `omega(B)`), whose sign change between two steps ends a run. The time
//! of the zero is located within the step on the cubic Hermite interpolant of q through
//! both steps' q and q̇ (its derivative for q̇), which is as accurate as the
//! trapezoidal rule's steps themselves.

use crate::error::{Error, Result};
use crate::expr::Expr;
use crate::forward::StepSink;
use crate::model::forces::Load;
use crate::scene::LoadFunction;
use crate::Model;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

/// A compiled stop condition.
#[derive(Debug, Clone)]
pub struct StopCondition {
    load: Load,
    /// The expression as given.
    pub text: String,
}

/// One step's time, positions and velocities.
pub type Sample<'a> = (f64, &'a [f64], &'a [f64]);

impl StopCondition {
    /// Compiles `text` against the model: every name must be `t` or a state quantity
    /// of the scene; the error names the first that is not, and the closest valid.
    pub fn new(model: &Model, text: &str) -> Result<StopCondition> {
        let bad = |m: String| Error::InvalidArgument(format!("--until '{text}': {m}"));
        let expr = Expr::parse(text).map_err(|e| bad(e.to_string()))?;
        for name in expr.names() {
            if name != "t" && model.scene.state_quantity(&name).is_none() {
                let known = crate::scene::coordinate_names(&model.scene);
                let relative = model.scene.coordinates.iter().map(|c| c.name.as_str());
                let near = crate::scene::did_you_mean(
                    &name,
                    relative.chain(known.iter().map(|s| s.as_str())),
                );
                return Err(bad(format!(
                    "'{name}' is not a state quantity{near} (relative coordinates by name, \
                     rate(c), x(P), y(P), vx(P), vy(P), angle(B), omega(B), and t)"
                )));
            }
        }
        let load = Load::compile(model, &LoadFunction::new(expr, text.to_string()))?;
        Ok(StopCondition {
            load,
            text: text.to_string(),
        })
    }

    /// The expression's value at (q, q̇, t).
    pub fn value(&self, model: &Model, q: &[f64], dq: &[f64], t: f64) -> Result<f64> {
        self.load.value(model, q, dq, t)
    }

    /// Whether the value changes sign from `g0` to `g1` (reaching zero counts; leaving
    /// it does not).
    pub fn crosses(g0: f64, g1: f64) -> bool {
        g0 != 0.0 && (g1 == 0.0 || g0.signum() != g1.signum())
    }

    /// The time in [t0, t1] where the value is zero, between two steps across which it
    /// changes sign: bisection on the interpolated state, to a 1e-12 fraction of the
    /// step.
    pub fn crossing(&self, model: &Model, a: Sample, b: Sample) -> Result<f64> {
        let (t0, q0, v0) = a;
        let (t1, q1, v1) = b;
        let h = t1 - t0;
        let n = q0.len();
        let (mut q, mut v) = (vec![0.0; n], vec![0.0; n]);
        let mut at = |s: f64| -> Result<f64> {
            let ([h00, h10, h01, h11], [d00, d10, d01, d11]) = crate::trajectory::cubic_hermite(s);
            for i in 0..n {
                q[i] = h00 * q0[i] + h10 * h * v0[i] + h01 * q1[i] + h11 * h * v1[i];
                v[i] = (d00 * q0[i] + d01 * q1[i]) / h + d10 * v0[i] + d11 * v1[i];
            }
            self.value(model, &q, &v, t0 + s * h)
        };
        let (mut lo, mut hi) = (0.0, 1.0);
        let g_lo = at(lo)?;
        if at(hi)? == 0.0 {
            return Ok(t1);
        }
        while hi - lo > 1e-12 {
            let mid = 0.5 * (lo + hi);
            let g = at(mid)?;
            if g == 0.0 {
                return Ok(t0 + mid * h);
            }
            if g.signum() == g_lo.signum() {
                lo = mid;
            } else {
                hi = mid;
            }
        }
        Ok(t0 + 0.5 * (lo + hi) * h)
    }
}

/// A [`StepSink`] that hands every step to `inner` and watches a stop condition: the
/// step after which it changed sign is the last handed on, the time of its zero is
/// `stopped`, and `hit` is set for the run's progress callback to end the run.
pub struct Watch<'a> {
    model: &'a Model,
    condition: &'a StopCondition,
    inner: &'a mut dyn StepSink,
    hit: Arc<AtomicBool>,
    last: Option<(f64, Vec<f64>, Vec<f64>, f64)>,
    steps: usize,
    /// The step (its index) after which the condition changed sign, and the time of
    /// its zero.
    pub stopped: Option<(usize, f64)>,
}

impl<'a> Watch<'a> {
    pub fn new(
        model: &'a Model,
        condition: &'a StopCondition,
        inner: &'a mut dyn StepSink,
        hit: Arc<AtomicBool>,
    ) -> Self {
        Watch {
            model,
            condition,
            inner,
            hit,
            last: None,
            steps: 0,
            stopped: None,
        }
    }
}

impl StepSink for Watch<'_> {
    fn step(&mut self, t: f64, q: &[f64], dq: &[f64], ddq: &[f64]) -> Result<()> {
        if self.stopped.is_some() {
            // Steps solved before the run noticed: past the condition, not kept.
            return Ok(());
        }
        let g = self.condition.value(self.model, q, dq, t)?;
        if let Some((t0, q0, dq0, g0)) = &self.last {
            if StopCondition::crosses(*g0, g) {
                let at = self
                    .condition
                    .crossing(self.model, (*t0, q0, dq0), (t, q, dq))?;
                self.stopped = Some((self.steps, at));
                self.hit.store(true, Ordering::Relaxed);
            }
        }
        self.inner.step(t, q, dq, ddq)?;
        self.last = Some((t, q.to_vec(), dq.to_vec(), g));
        self.steps += 1;
        Ok(())
    }

    fn between(&mut self, t: f64, q: &[f64], dq: &[f64], ddq: &[f64]) -> Result<()> {
        match self.stopped {
            Some(_) => Ok(()),
            None => self.inner.between(t, q, dq, ddq),
        }
    }

    fn restart(&mut self) -> Result<()> {
        self.last = None;
        self.steps = 0;
        self.stopped = None;
        self.hit.store(false, Ordering::Relaxed);
        self.inner.restart()
    }
}
