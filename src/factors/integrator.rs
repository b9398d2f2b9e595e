//! The integrator between consecutive steps ([`Integrator`]): its rule, its factors
//! in every form a graph asks for ([`Integrator::factors`]), and the per-coordinate
//! formula of the two-point rules ([`Integrator::residual`], [`Integrator::partials`])
//! that both their factors and the forward square step evaluate. Also the soft link
//! f_eq ([`Equality`]) and the two-point factors f_ei ([`Euler`]) and f_ti
//! ([`Trapezoidal`]).
//!
//! Adding an integrator: a variant here and its arms below (its order, whether the
//! square step has its equations, its formula or its factors; a factor family of its
//! own in `factors/` if it needs one, as Hermite–Simpson has `collocation`), then
//! its name and description (the CLI and Python list [`Integrator::ALL`]).

use super::collocation;
use super::shared::{identity, key_accessor};
use super::tangent::Projected;
use crate::error::Result;
use crate::graph::{Factor, Key, VarKind, Workspace};
use crate::model::Model;
use std::sync::Arc;

/// The integrator factor between consecutive steps.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Integrator {
    /// The paper's trapezoidal rule, e = x₁ − x₀ − Δt/2 (ẋ₀ + ẋ₁): second order.
    Trapezoidal,
    /// Explicit Euler, e = x₁ − x₀ − Δt ẋ₀: first order.
    Euler,
    /// Hermite–Simpson collocation, fourth order ([`collocation`]).
    HermiteSimpson,
}

/// The variables an integrator's factors integrate, and whether they are projected.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Form<'a> {
    /// Dependent coordinates q, q̇, q̈, on all n rows (the paper's factors).
    Full,
    /// Dependent coordinates, projected on the constraints' tangent space at the
    /// step's positions ([`Projected`]).
    Tangent,
    /// Independent coordinates z, ż, z̈: those of q at these indices.
    Independent(&'a [usize]),
}

/// The partial derivatives of one coordinate's residual e of a two-point rule.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Partials {
    /// ∂e/∂x₀.
    pub x0: f64,
    /// ∂e/∂x₁.
    pub x1: f64,
    /// ∂e/∂ẋ₀.
    pub dx0: f64,
    /// ∂e/∂ẋ₁; `None` where e does not involve ẋ₁ (an explicit rule).
    pub dx1: Option<f64>,
}

impl Integrator {
    /// Every integrator, in the order the CLI lists them.
    pub const ALL: [Integrator; 3] = [
        Integrator::Trapezoidal,
        Integrator::Euler,
        Integrator::HermiteSimpson,
    ];

    /// The name the CLI (`--integrator`) and Python take.
    pub fn name(self) -> &'static str {
        match self {
            Integrator::Trapezoidal => "trapezoidal",
            Integrator::Euler => "euler",
            Integrator::HermiteSimpson => "hermite-simpson",
        }
    }

    /// One line on the integrator, for a list of them (the CLI's help).
    pub fn description(self) -> &'static str {
        match self {
            Integrator::Trapezoidal => "The paper's trapezoidal rule, second order",
            Integrator::Euler => "Explicit Euler, first order",
            Integrator::HermiteSimpson => {
                "Hermite–Simpson collocation, fourth order (the dynamics also at each step's middle)"
            }
        }
    }

    /// The integrator named `name` ([`Integrator::name`]).
    pub fn from_name(name: &str) -> Option<Integrator> {
        Integrator::ALL.into_iter().find(|i| i.name() == name)
    }

    /// The order of the global error in Δt.
    pub fn order(self) -> u32 {
        match self {
            Integrator::Trapezoidal => 2,
            Integrator::Euler => 1,
            Integrator::HermiteSimpson => 4,
        }
    }

    /// Whether the forward square step has this integrator's equations: the
    /// two-point rules, whose per-coordinate formula is [`Integrator::residual`],
    /// and Hermite–Simpson, with its stage's dynamics as equations of the step.
    pub fn has_square_step(self) -> bool {
        match self {
            Integrator::Trapezoidal | Integrator::Euler | Integrator::HermiteSimpson => true,
        }
    }

    /// The residual e of one coordinate of a two-point rule, from the value x₀ and
    /// rate ẋ₀ at the step before and x₁, ẋ₁ at the step.
    ///
    /// # Panics
    /// For an integrator without a two-point formula (Hermite–Simpson, whose
    /// factors also read the accelerations: see [`collocation`]).
    #[inline]
    pub fn residual(self, x0: f64, dx0: f64, x1: f64, dx1: f64, dt: f64) -> f64 {
        match self {
            Integrator::Trapezoidal => x1 - x0 - 0.5 * dt * (dx0 + dx1),
            Integrator::Euler => x1 - x0 - dt * dx0,
            Integrator::HermiteSimpson => no_two_point_formula(),
        }
    }

    /// The partial derivatives of [`Integrator::residual`] (constant in the
    /// variables: the two-point rules are linear).
    ///
    /// # Panics
    /// As [`Integrator::residual`].
    pub fn partials(self, dt: f64) -> Partials {
        let (dx0, dx1) = match self {
            Integrator::Trapezoidal => (-(0.5 * dt), Some(-(0.5 * dt))),
            Integrator::Euler => (-dt, None),
            Integrator::HermiteSimpson => no_two_point_formula(),
        };
        Partials {
            x0: -1.0,
            x1: 1.0,
            dx0,
            dx1,
        }
    }

    /// The integrator's two factors between consecutive steps of a graph of `model`
    /// at `dt`, in `form`: the integration of the rates into the values, then of the
    /// accelerations into the rates.
    pub fn factors(self, model: &Arc<Model>, form: Form<'_>, dt: f64) -> [Box<dyn Factor>; 2] {
        let independent = match form {
            Form::Independent(set) => Some(set),
            Form::Full | Form::Tangent => None,
        };
        let (x, dx, ddx, dim) = match independent {
            Some(set) => (VarKind::Z, VarKind::Dz, VarKind::Ddz, set.len()),
            None => (VarKind::Q, VarKind::Dq, VarKind::Ddq, model.n()),
        };
        let factors = match self {
            Integrator::HermiteSimpson => collocation::factors(model, independent, dt),
            rule => [
                rule.two_point(x, dx, dim, dt),
                rule.two_point(dx, ddx, dim, dt),
            ],
        };
        project(model, form, factors)
    }

    /// [`Integrator::factors`], with Hermite–Simpson's stage in dependent coordinates
    /// evaluated by `stage`, a dynamics factor with variables of its own (an
    /// estimate's, with its identified parameters and unknown inputs:
    /// [`collocation::SimpsonVelocityThrough`]). The two-point rules have no stage.
    pub fn factors_through(
        self,
        model: &Arc<Model>,
        form: Form<'_>,
        dt: f64,
        stage: Box<dyn Factor>,
    ) -> [Box<dyn Factor>; 2] {
        match (self, form) {
            (Integrator::HermiteSimpson, Form::Full | Form::Tangent) => {
                let n = model.n();
                let factors: [Box<dyn Factor>; 2] = [
                    Box::new(collocation::HermitePosition::new(
                        VarKind::Q,
                        VarKind::Dq,
                        VarKind::Ddq,
                        n,
                        dt,
                    )),
                    Box::new(collocation::SimpsonVelocityThrough::new(stage, dt)),
                ];
                project(model, form, factors)
            }
            _ => self.factors(model, form, dt),
        }
    }

    /// The factor of a two-point rule integrating `dx` into `x` (`dim` rows).
    fn two_point(self, x: VarKind, dx: VarKind, dim: usize, dt: f64) -> Box<dyn Factor> {
        match self {
            Integrator::Trapezoidal => Box::new(Trapezoidal::new(x, dx, dim, dt)),
            Integrator::Euler => Box::new(Euler::new(x, dx, dim, dt)),
            Integrator::HermiteSimpson => no_two_point_formula(),
        }
    }
}

/// `factors` as `form` asks: projected on the tangent space, or as they are.
fn project(
    model: &Arc<Model>,
    form: Form<'_>,
    factors: [Box<dyn Factor>; 2],
) -> [Box<dyn Factor>; 2] {
    match form {
        Form::Tangent => {
            factors.map(|f| Box::new(Projected::new(model.clone(), f)) as Box<dyn Factor>)
        }
        Form::Full | Form::Independent(_) => factors,
    }
}

#[cold]
fn no_two_point_formula() -> ! {
    panic!("Hermite–Simpson has no two-point formula: its factors are collocation's")
}

/// f_eq: e = x_t − x_{t−1}, a soft link between consecutive steps.
pub struct Equality {
    name: String,
    keys: [Key; 2],
    dim: usize,
}

impl Equality {
    pub fn new(kind: VarKind, dim: usize) -> Self {
        Equality {
            name: format!("f_eq({})", kind.symbol()),
            keys: [Key::before(kind), Key::now(kind)],
            dim,
        }
    }
}

impl Factor for Equality {
    fn name(&self) -> &str {
        &self.name
    }
    key_accessor!();
    fn size(&self, _key: usize) -> usize {
        self.dim
    }
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

/// A two-point integrator factor of `rule` (its residual and partials,
/// [`Integrator::residual`]): f_ei, e = x_t − x_{t−1} − Δt ẋ_{t−1} (Euler: no ẋ_t
/// key), or f_ti, e = x_t − x_{t−1} − Δt/2 (ẋ_{t−1} + ẋ_t) (trapezoidal).
pub struct TwoPoint {
    rule: Integrator,
    name: String,
    /// x_{t−1}, x_t, ẋ_{t−1}, and ẋ_t where the rule reads it.
    keys: Vec<Key>,
    dim: usize,
    dt: f64,
}

/// f_ei, the explicit Euler factor ([`TwoPoint`]).
pub struct Euler;

impl Euler {
    #[allow(clippy::new_ret_no_self)] // the factor is the Euler rule's TwoPoint
    pub fn new(x: VarKind, dx: VarKind, dim: usize, dt: f64) -> TwoPoint {
        TwoPoint::new(Integrator::Euler, x, dx, dim, dt)
    }
}

/// f_ti, the paper's trapezoidal factor ([`TwoPoint`]).
pub struct Trapezoidal;

impl Trapezoidal {
    #[allow(clippy::new_ret_no_self)] // the factor is the trapezoidal rule's TwoPoint
    pub fn new(x: VarKind, dx: VarKind, dim: usize, dt: f64) -> TwoPoint {
        TwoPoint::new(Integrator::Trapezoidal, x, dx, dim, dt)
    }
}

impl TwoPoint {
    /// The factor of `rule` (the trapezoidal rule or Euler) between x and its rate dx.
    fn new(rule: Integrator, x: VarKind, dx: VarKind, dim: usize, dt: f64) -> Self {
        let (symbol, keys) = match rule {
            Integrator::Euler => ("ei", vec![Key::before(x), Key::now(x), Key::before(dx)]),
            _ => (
                "ti",
                vec![Key::before(x), Key::now(x), Key::before(dx), Key::now(dx)],
            ),
        };
        TwoPoint {
            rule,
            name: format!("f_{symbol}({})", x.symbol()),
            keys,
            dim,
            dt,
        }
    }
}

impl Factor for TwoPoint {
    fn name(&self) -> &str {
        &self.name
    }
    key_accessor!();
    fn size(&self, _key: usize) -> usize {
        self.dim
    }
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
        // ẋ_t's slot is absent for Euler, whose residual does not read it.
        let dx1 = x.get(3);
        for (i, ri) in r.iter_mut().enumerate() {
            let rate = dx1.map_or(0.0, |v| v[i]);
            *ri = self.rule.residual(x[0][i], x[2][i], x[1][i], rate, self.dt);
        }
        if let Some(j) = jac {
            let d = self.rule.partials(self.dt);
            identity(&mut j[0], self.dim, d.x0);
            identity(&mut j[1], self.dim, d.x1);
            identity(&mut j[2], self.dim, d.dx0);
            if let Some(dx1) = d.dx1 {
                identity(&mut j[3], self.dim, dx1);
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The formula's partials against central differences, at a coarse step.
    #[test]
    fn two_point_partials_match_finite_differences() {
        let (dt, h) = (0.05, 1e-6);
        let at = [0.3, -1.2, 0.45, 0.8];
        for rule in [Integrator::Trapezoidal, Integrator::Euler] {
            let d = rule.partials(dt);
            let expected = [d.x0, d.dx0, d.x1, d.dx1.unwrap_or(0.0)];
            for (k, want) in expected.into_iter().enumerate() {
                let shifted = |s: f64| {
                    let mut v = at;
                    v[k] += s;
                    rule.residual(v[0], v[1], v[2], v[3], dt)
                };
                let numeric = (shifted(h) - shifted(-h)) / (2.0 * h);
                assert!(
                    (numeric - want).abs() < 1e-9,
                    "{rule:?} ∂{k}: {numeric} {want}"
                );
            }
        }
    }

    #[test]
    fn square_step_and_order() {
        assert!(Integrator::ALL.into_iter().all(Integrator::has_square_step));
        let orders = Integrator::ALL.map(Integrator::order);
        assert_eq!(orders, [2, 1, 4]);
        for i in Integrator::ALL {
            assert_eq!(Integrator::from_name(i.name()), Some(i));
        }
        assert_eq!(Integrator::from_name("rk4"), None);
    }
}
