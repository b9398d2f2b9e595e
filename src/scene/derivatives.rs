//! The derivatives of a scene's numbers with respect to the parameters an estimate
//! identifies (`estimation: parameters:`): computed as the file is read, by the
//! chain rule over the expression engine's symbolic derivatives, and kept for the
//! quantities the model lets vary ([`Identified`]): masses (of bodies and points),
//! inertias, gravity, spring and damper constants. A number of anything else (a length, a point, a
//! start) that depends on an identified parameter is refused by name.

use crate::expr::ExprError;
use std::cell::RefCell;

/// (body, ∂mass/∂p, ∂I₀/∂p).
pub type BodyGradient = (usize, Vec<f64>, Vec<f64>);
/// (effect, ∂/∂p of its two constants).
pub type EffectGradient = (usize, [Vec<f64>; 2]);

/// What the readers share about the identified parameters while a file is read.
#[derive(Debug, Default)]
pub struct Derivatives {
    /// The identified parameters' names, in `estimation: parameters:` order.
    pub unknown: Vec<String>,
    /// The gradient of each parameter read so far (in the reader's order), `None`
    /// where it does not depend on the identified ones.
    pub params: Vec<Option<Vec<f64>>>,
    /// Gradients of numbers read, by key, waiting for the reader that uses them.
    pending: RefCell<Vec<(String, u64, Vec<f64>)>>,
    /// Gradients of the names a reader adds to an expression's scope (`mass`).
    extras: RefCell<Vec<(String, Vec<f64>)>>,
    /// What the readers claimed, as [`Identified`] keeps it.
    bodies: RefCell<Vec<BodyGradient>>,
    points: RefCell<Vec<(usize, Vec<f64>)>>,
    effects: RefCell<Vec<EffectGradient>>,
}

/// Why a number's gradient cannot be taken.
pub enum GradientError {
    Expr(ExprError),
    /// The second derivative in these two names does not vanish.
    Nonlinear(String, String),
}

impl Derivatives {
    pub fn record(&self, key: &str, line: u64, gradient: Vec<f64>) {
        self.pending
            .borrow_mut()
            .push((key.to_string(), line, gradient));
    }

    /// The gradient of the number read under `key`, claimed by its reader.
    pub fn take(&self, key: &str) -> Option<Vec<f64>> {
        let mut pending = self.pending.borrow_mut();
        let i = pending.iter().position(|(k, _, _)| k == key)?;
        Some(pending.remove(i).2)
    }

    /// Sets (or clears) the gradient of a name the next expressions see as `extra`.
    pub fn set_extra(&self, name: &str, gradient: Option<Vec<f64>>) {
        let mut extras = self.extras.borrow_mut();
        extras.retain(|(n, _)| n != name);
        if let Some(g) = gradient {
            extras.push((name.to_string(), g));
        }
    }

    pub fn extra(&self, name: &str) -> Option<Vec<f64>> {
        let extras = self.extras.borrow();
        extras
            .iter()
            .find(|(n, _)| n == name)
            .map(|(_, g)| g.clone())
    }

    /// A body's ∂mass/∂p and ∂I₀/∂p.
    pub fn body(&self, index: usize, mass: Vec<f64>, i0: Vec<f64>) {
        self.bodies.borrow_mut().push((index, mass, i0));
    }

    /// A point mass's ∂mass/∂p.
    pub fn point(&self, index: usize, mass: Vec<f64>) {
        self.points.borrow_mut().push((index, mass));
    }

    /// An effect's two constants' gradients, claimed under `keys` (absent, or an
    /// empty key: zero).
    pub fn effect(&self, index: usize, keys: [&str; 2]) {
        let p = self.unknown.len();
        if p == 0 {
            return;
        }
        let [a, b] = keys.map(|k| if k.is_empty() { None } else { self.take(k) });
        if a.is_some() || b.is_some() {
            let zero = || vec![0.0; p];
            self.effects
                .borrow_mut()
                .push((index, [a.unwrap_or_else(zero), b.unwrap_or_else(zero)]));
        }
    }

    /// What the model needs, once the whole file is read: the parameters' names and
    /// values (`params` as the reader holds them) and the claimed gradients.
    pub fn identified(&self, params: &[(String, f64)]) -> Identified {
        let values = self
            .unknown
            .iter()
            .map(|n| {
                params
                    .iter()
                    .rev()
                    .find(|(m, _)| m == n)
                    .map_or(f64::NAN, |(_, v)| *v)
            })
            .collect();
        Identified {
            names: self.unknown.clone(),
            values,
            bodies: self.bodies.borrow().clone(),
            points: self.points.borrow().clone(),
            effects: self.effects.borrow().clone(),
        }
    }

    /// The first number that depends on an identified parameter and that no reader
    /// claimed: a quantity the estimate cannot vary. (key, line)
    pub fn unclaimed(&self) -> Option<(String, u64)> {
        let pending = self.pending.borrow();
        pending.first().map(|(k, l, _)| (k.clone(), *l))
    }
}

/// The identified parameters of a scene and the derivatives of the quantities that
/// depend on them, each a vector over the parameters.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Identified {
    /// Names, in `estimation: parameters:` order.
    pub names: Vec<String>,
    /// Their values in the file: the priors' means.
    pub values: Vec<f64>,
    /// (body, ∂mass/∂p, ∂I₀/∂p) of the bodies whose inertia depends on them.
    pub bodies: Vec<BodyGradient>,
    /// (point, ∂mass/∂p) of the point masses that depend on them.
    pub points: Vec<(usize, Vec<f64>)>,
    /// (effect, ∂/∂p of its two constants): gravity's vector [x, y]; a spring's or
    /// a rotational spring's [stiffness, damping]; a DC motor's [stall torque, 0].
    pub effects: Vec<EffectGradient>,
}

impl Identified {
    pub fn is_empty(&self) -> bool {
        self.names.is_empty()
    }
}
