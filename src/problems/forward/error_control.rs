//! The choice of each step's size from the accuracy asked ([`Tolerance`]): the
//! local error of a step estimated from the accelerations of the steps around it
//! ([`local_error`]), measured in a weighted norm ([`Tolerance::norm`]) per unit of
//! time, and the controller that accepts or rejects a step and sizes the next
//! ([`Controller`]).
//!
//! The error is controlled per unit step: a step of size h is accepted where its
//! local error is at most h/[`TIME_SCALE`] of the tolerance. Summed over a run the
//! local errors then add up to about the tolerance per second simulated (where the
//! motion does not amplify them), so that the error of the run follows the
//! tolerance in proportion, at every tolerance, as a per-step control (whose global
//! error goes as tol^(p/(p+1))) would not.

use super::options::Integrator;
use crate::error::{Error, Result};

/// The time over which a step's local error may add up to the tolerance (s).
pub const TIME_SCALE: f64 = 1.0;

/// The accuracy asked of a run: a step's error in coordinate i is weighed by
/// 1/(atol + rtol·|xᵢ|), as IDA and DOP853 weigh theirs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Tolerance {
    pub rtol: f64,
    pub atol: f64,
}

impl Tolerance {
    /// The smallest tolerance taken: below it the steps' own Newton solves and the
    /// rounding of their equations are the error.
    pub const SMALLEST: f64 = 1e-14;

    /// `rtol`, and `atol` (by default equal to `rtol`), both positive, finite and
    /// at least [`Tolerance::SMALLEST`].
    pub fn new(rtol: f64, atol: Option<f64>) -> Result<Tolerance> {
        let atol = atol.unwrap_or(rtol);
        for (name, v) in [("rtol", rtol), ("atol", atol)] {
            if !(Self::SMALLEST..1.0).contains(&v) {
                return Err(Error::InvalidArgument(format!(
                    "{name} must be a number in [{:e}, 1), got {}",
                    Self::SMALLEST,
                    crate::io::number(v)
                )));
            }
        }
        Ok(Tolerance { rtol, atol })
    }

    /// The tolerance `factor` times as tight or loose, both rtol and atol (no tighter
    /// than [`Tolerance::SMALLEST`]).
    pub fn scaled(&self, factor: f64) -> Tolerance {
        Tolerance {
            rtol: (self.rtol * factor).max(Self::SMALLEST),
            atol: (self.atol * factor).max(Self::SMALLEST),
        }
    }

    /// The weighted root mean square of `error` (per coordinate of `x0`, `x1`, the
    /// state at both ends of the step): √(mean (eᵢ / (atol + rtol·max(|x0ᵢ|, |x1ᵢ|)))²).
    pub fn norm(&self, error: &[f64], x0: &[f64], x1: &[f64]) -> f64 {
        if error.is_empty() {
            return 0.0;
        }
        let sum: f64 = error
            .iter()
            .zip(x0.iter().zip(x1))
            .map(|(e, (a, b))| {
                let w = self.atol + self.rtol * a.abs().max(b.abs());
                (e / w) * (e / w)
            })
            .sum();
        (sum / error.len() as f64).sqrt()
    }
}

/// The accelerations q̈ at the last few step ends, the newest last: what the local
/// error estimates differentiate.
#[derive(Debug, Clone, Default)]
pub struct History {
    /// (t, q̈) of up to [`History::KEPT`] step ends, oldest first.
    points: std::collections::VecDeque<(f64, Vec<f64>)>,
}

impl History {
    /// Points kept: four steps back, for Hermite–Simpson's fourth divided difference.
    pub const KEPT: usize = 4;

    /// Whether fewer step ends are kept than `integrator`'s estimate differentiates
    /// over: a run's first steps, whose estimate is the overestimate of the
    /// missing orders ([`local_error`]), not their error.
    pub fn short_for(&self, integrator: Integrator) -> bool {
        let needed = leading_terms(integrator, 1.0).map_or(0, |[_, (_, velocities)]| velocities);
        self.points.len() < needed
    }

    /// A kept step's end (time t, accelerations `ddq`).
    pub fn push(&mut self, t: f64, ddq: &[f64]) {
        if self.points.len() == Self::KEPT {
            let mut oldest = self.points.pop_front().expect("full");
            oldest.0 = t;
            oldest.1.copy_from_slice(ddq);
            self.points.push_back(oldest);
        } else {
            self.points.push_back((t, ddq.to_vec()));
        }
    }

    /// The `order`-th derivative of coordinate i's q̈ at the end of a step to (t₁,
    /// `end`), from the divided difference of that order over the newest points; where
    /// fewer are kept, the highest divided difference there is, over a time scale of
    /// the step `h` for each missing order (an overestimate while the step is smaller
    /// than the motion's time scale, as a run's first steps are).
    fn derivative(&self, order: usize, i: usize, (t1, end): (f64, &[f64]), h: f64) -> f64 {
        let kept = self.points.len().min(order);
        // Newton's divided differences over the newest kept + 1 points.
        let mut times = [0.0; Self::KEPT + 1];
        let mut values = [0.0; Self::KEPT + 1];
        let first = self.points.len() - kept;
        for (j, (t, a)) in self.points.iter().skip(first).enumerate() {
            times[j] = *t;
            values[j] = a[i];
        }
        times[kept] = t1;
        values[kept] = end[i];
        for level in 1..=kept {
            for j in (level..=kept).rev() {
                values[j] = (values[j] - values[j - 1]) / (times[j] - times[j - level]);
            }
        }
        let factorial: f64 = (1..=kept).map(|k| k as f64).product();
        factorial * values[kept] / h.powi((order - kept) as i32)
    }
}

/// The local error of a step of `h` from (q₀, q̇₀, q̈₀) = `start` to `end` (each q, q̇,
/// q̈ of n coordinates), into `out` (2n: positions, then velocities), from the
/// accelerations of the steps before (`history`, `start`'s the newest) and the step's
/// end: the leading term of each rule's local error, its derivative from divided
/// differences.
///
/// The trapezoidal rule's local error is h³/12 of the third derivative (of q, q⃛ the
/// first derivative of q̈; of q̇, its second). Euler's is h²/2 of the second: h/2 (q̇₁
/// − q̇₀) for q, h/2 (q̈₁ − q̈₀) for q̇. Hermite–Simpson's positions follow the
/// two-point Hermite quadrature of q̇, −h⁵/720 of q⁽⁵⁾; its velocities Simpson's rule,
/// h⁵/2880 of q̇⁽⁵⁾.
pub fn local_error(
    integrator: Integrator,
    n: usize,
    h: f64,
    start: &[f64],
    end: &[f64],
    history: &History,
    out: &mut [f64],
) {
    let (t1, a1) = (
        history.points.back().map_or(0.0, |(t, _)| *t) + h,
        &end[2 * n..3 * n],
    );
    let Some(terms) = leading_terms(integrator, h) else {
        // Euler's, from the step's ends.
        let (v0, v1) = (&start[n..2 * n], &end[n..2 * n]);
        let a0 = &start[2 * n..3 * n];
        for i in 0..n {
            out[i] = 0.5 * h * (v1[i] - v0[i]);
            out[n + i] = 0.5 * h * (a1[i] - a0[i]);
        }
        return;
    };
    for i in 0..n {
        for (part, (factor, order)) in terms.iter().enumerate() {
            out[part * n + i] = factor * history.derivative(*order, i, (t1, a1), h);
        }
    }
}

/// The leading terms of the local error of a step of `h` with `integrator`, of its
/// positions and of its velocities ([`local_error`]): (factor, the derivative of q̈
/// it multiplies); `None` for Euler's, read off the step's ends.
fn leading_terms(integrator: Integrator, h: f64) -> Option<[(f64, usize); 2]> {
    match integrator {
        Integrator::Trapezoidal => Some([(h * h * h / 12.0, 1), (h * h * h / 12.0, 2)]),
        Integrator::HermiteSimpson => Some([(-h.powi(5) / 720.0, 3), (h.powi(5) / 2880.0, 4)]),
        Integrator::Euler => None,
    }
}

/// What the controller decides about a step.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Decision {
    /// The step is kept; the next is tried at this size.
    Accept { next: f64 },
    /// The step is taken again at this size.
    Reject { retry: f64 },
}

/// The elementary controller of an error per unit step: a step's size scaled by
/// (1/E)^(1/p), E its error over its allowance, p the integrator's order, with a
/// safety factor and bounds on the change.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Controller {
    /// The integrator's order p: the error per unit step goes as h^p.
    pub order: u32,
    /// The smallest and largest step.
    pub h_min: f64,
    pub h_max: f64,
}

impl Controller {
    /// The fraction of the size the error asks for that is taken.
    pub const SAFETY: f64 = 0.9;
    /// The largest growth from one step to the next.
    pub const MAX_GROWTH: f64 = 4.0;
    /// The largest shrink a rejected step's error asks for.
    pub const MAX_SHRINK: f64 = 0.1;
    /// The shrink after a step whose solve failed.
    pub const FAILED_SHRINK: f64 = 0.25;

    /// The error of a step of `h` whose local error has the weighted norm
    /// `norm`, over what the tolerance allows it ([`TIME_SCALE`]): at most 1 to
    /// accept.
    pub fn error_ratio(h: f64, norm: f64) -> f64 {
        norm * TIME_SCALE / h
    }

    /// The decision on a step of `h` with error ratio `ratio` (see
    /// [`Controller::error_ratio`]); `after_reject`: the step before this try was
    /// rejected, and the next may not grow.
    pub fn decide(&self, h: f64, ratio: f64, after_reject: bool) -> Decision {
        let p = f64::from(self.order.max(1));
        let ideal = if ratio > 0.0 && ratio.is_finite() {
            Self::SAFETY * ratio.powf(-1.0 / p)
        } else if ratio == 0.0 {
            Self::MAX_GROWTH
        } else {
            Self::MAX_SHRINK
        };
        if ratio <= 1.0 {
            let grow = match after_reject {
                true => ideal.min(1.0),
                false => ideal.min(Self::MAX_GROWTH),
            };
            Decision::Accept {
                next: (h * grow).clamp(self.h_min, self.h_max),
            }
        } else {
            Decision::Reject {
                retry: (h * ideal.clamp(Self::MAX_SHRINK, 0.9)).max(self.h_min),
            }
        }
    }

    /// The size to try again after a step of `h` whose solve failed; `None` below
    /// the smallest step.
    pub fn after_failure(&self, h: f64) -> Option<f64> {
        let next = h * Self::FAILED_SHRINK;
        (next >= self.h_min).then_some(next)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn controller() -> Controller {
        Controller {
            order: 2,
            h_min: 1e-8,
            h_max: 0.5,
        }
    }

    #[test]
    fn a_small_error_is_accepted_and_the_step_grows_as_its_order_says() {
        // E = 1/16 at order 2: the ideal growth is 0.9·4 = 3.6.
        match controller().decide(1e-3, 1.0 / 16.0, false) {
            Decision::Accept { next } => assert!((next - 3.6e-3).abs() < 1e-12, "{next}"),
            other => panic!("{other:?}"),
        }
        // Growth is bounded, and none right after a rejection.
        match controller().decide(1e-3, 1e-12, false) {
            Decision::Accept { next } => assert!((next - 4e-3).abs() < 1e-15),
            other => panic!("{other:?}"),
        }
        match controller().decide(1e-3, 1.0 / 16.0, true) {
            Decision::Accept { next } => assert_eq!(next, 1e-3),
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn a_large_error_is_rejected_and_the_step_shrinks() {
        // E = 4 at order 2: 0.9/2 of the step.
        match controller().decide(1e-3, 4.0, false) {
            Decision::Reject { retry } => assert!((retry - 4.5e-4).abs() < 1e-15, "{retry}"),
            other => panic!("{other:?}"),
        }
        // A huge or non-finite error shrinks by the largest factor, not to nothing.
        for ratio in [1e12, f64::INFINITY, f64::NAN] {
            match controller().decide(1e-3, ratio, false) {
                Decision::Reject { retry } => assert!((retry - 1e-4).abs() < 1e-16, "{ratio}"),
                other => panic!("{ratio}: {other:?}"),
            }
        }
        // Just over 1: still at least a 10 % cut, so that the next try is not the same.
        match controller().decide(1e-3, 1.0001, false) {
            Decision::Reject { retry } => assert!(retry <= 0.9e-3 + 1e-18),
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn a_failed_solve_shrinks_the_step_until_the_smallest() {
        let c = controller();
        assert_eq!(c.after_failure(1e-3), Some(2.5e-4));
        assert_eq!(c.after_failure(2e-8), None);
    }

    #[test]
    fn steps_stay_within_their_bounds() {
        let c = controller();
        match c.decide(0.4, 1e-9, false) {
            Decision::Accept { next } => assert_eq!(next, 0.5),
            other => panic!("{other:?}"),
        }
        match c.decide(2e-8, 1e9, false) {
            Decision::Reject { retry } => assert_eq!(retry, 1e-8),
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn the_norm_weighs_each_coordinate_by_its_tolerance() {
        let tol = Tolerance::new(1e-3, Some(1e-6)).unwrap();
        // Weights 1e-6 + 1e-3·|x|: 1e-6 at 0, ≈1e-3 at 1.
        let norm = tol.norm(&[1e-6, 1.001e-3], &[0.0, 1.0], &[0.0, 0.5]);
        assert!((norm - 1.0).abs() < 1e-12, "{norm}");
    }

    #[test]
    fn bad_tolerances_are_refused_by_name() {
        for (rtol, atol, name) in [
            (0.0, None, "rtol"),
            (-1e-6, None, "rtol"),
            (f64::NAN, None, "rtol"),
            (1e-20, None, "rtol"),
            (2.0, None, "rtol"),
            (1e-6, Some(f64::INFINITY), "atol"),
            (1e-6, Some(0.0), "atol"),
        ] {
            let e = Tolerance::new(rtol, atol).unwrap_err().to_string();
            assert!(e.contains(name), "{e}");
        }
        assert_eq!(Tolerance::new(1e-6, None).unwrap().atol, 1e-6);
    }

    /// The trapezoidal estimate is the rule's own local error on a motion with a
    /// constant third derivative: q = t³, a step of h from t = 1.
    #[test]
    fn the_trapezoidal_estimate_is_its_local_error() {
        let (t0, h, hp) = (1.0, 0.1, 0.05);
        let q = |t: f64| t * t * t;
        let v = |t: f64| 3.0 * t * t;
        let a = |t: f64| 6.0 * t;
        // The rule's q₁ from the exact q̇ at both ends, against the exact q₁.
        let q1_rule = q(t0) + 0.5 * h * (v(t0) + v(t0 + h));
        let start = [q(t0), v(t0), a(t0)];
        let end = [q(t0 + h), v(t0 + h), a(t0 + h)];
        let mut history = History::default();
        history.push(t0 - hp, &[a(t0 - hp)]);
        history.push(t0, &[a(t0)]);
        let mut out = [0.0; 2];
        local_error(
            Integrator::Trapezoidal,
            1,
            h,
            &start,
            &end,
            &history,
            &mut out,
        );
        assert!((out[0] - (q1_rule - q(t0 + h))).abs() < 1e-15, "{out:?}");
        // q̇'s third derivative is 0 here: q̈ is linear.
        assert!(out[1].abs() < 1e-12, "{out:?}");
        // For q = t⁴ the velocities' error is h³/12 · q⁽⁴⁾ = 2h³.
        let a4 = |t: f64| 12.0 * t * t;
        let mut history = History::default();
        history.push(t0 - hp, &[a4(t0 - hp)]);
        history.push(t0, &[a4(t0)]);
        let (start, end) = ([0.0, 0.0, a4(t0)], [0.0, 0.0, a4(t0 + h)]);
        local_error(
            Integrator::Trapezoidal,
            1,
            h,
            &start,
            &end,
            &history,
            &mut out,
        );
        assert!((out[1] - 2.0 * h * h * h).abs() < 1e-12, "{out:?}");
    }

    /// Hermite–Simpson's estimate is the two-point Hermite quadrature's error on a
    /// motion with a constant fifth derivative (q = t⁵), from unequal steps before.
    #[test]
    fn the_hermite_simpson_estimate_is_its_local_error() {
        let q = |t: f64| t.powi(5);
        let v = |t: f64| 5.0 * t.powi(4);
        let a = |t: f64| 20.0 * t.powi(3);
        let (t0, h) = (1.0, 0.1);
        let mut history = History::default();
        for t in [0.7, 0.82, 0.9, t0] {
            history.push(t, &[a(t)]);
        }
        // q₁ = q₀ + h/2 (q̇₀ + q̇₁) + h²/12 (q̈₀ − q̈₁): the rule's positions.
        let t1 = t0 + h;
        let q1_rule = q(t0) + 0.5 * h * (v(t0) + v(t1)) + h * h / 12.0 * (a(t0) - a(t1));
        let start = [q(t0), v(t0), a(t0)];
        let end = [q(t1), v(t1), a(t1)];
        let mut out = [0.0; 2];
        local_error(
            Integrator::HermiteSimpson,
            1,
            h,
            &start,
            &end,
            &history,
            &mut out,
        );
        let exact = q1_rule - q(t1);
        assert!(
            (out[0] - exact).abs() < 1e-9 * exact.abs(),
            "{out:?} against {exact:e}"
        );
        // q̈ is cubic: its fourth derivative, the velocities' term, is 0.
        assert!(out[1].abs() < 1e-9, "{out:?}");
    }

    /// Without the points a derivative needs, the estimate takes the step as the
    /// time scale of each missing order: larger than the true error of a small step.
    #[test]
    fn a_first_step_overestimates_its_error() {
        let a = |t: f64| (3.0 * t).sin();
        let h = 1e-3;
        let mut history = History::default();
        history.push(0.0, &[a(0.0)]);
        let (start, end) = ([0.0, 0.0, a(0.0)], [0.0, 0.0, a(h)]);
        let mut out = [0.0; 2];
        local_error(
            Integrator::Trapezoidal,
            1,
            h,
            &start,
            &end,
            &history,
            &mut out,
        );
        // q̇'s true term h³/12 · q̈'' is about 0 at t = 0 (sin); its estimate h³/12 · 3/h.
        assert!(
            (out[1] - h * h / 12.0 * (a(h) - a(0.0)) / h).abs() < 1e-18,
            "{out:?}"
        );
        assert!(out[1] > 0.0);
    }
}
