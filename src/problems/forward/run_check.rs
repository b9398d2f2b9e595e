//! A tolerance on the rows a run writes, not only on its steps
//! ([`ToleranceScope::Run`]): the error-controlled run is checked against a run at a
//! coarser step tolerance, and made again at tighter ones while its rows' estimated
//! error exceeds the tolerance asked.
//!
//! The step control keeps each step's local error within the tolerance per unit of
//! time. Where the motion amplifies those errors (a phase that drifts on a motion
//! near a separatrix, a chaotic one), the rows end far from it. The errors of an
//! error-controlled run grow about in proportion to its step tolerance, so two
//! runs at step tolerances `τ` and `ρτ` differ by about (ρ − 1) times the first
//! one's error: that difference estimates the error, and the step tolerance that
//! meets the one asked follows from it. A run made again is compared with the one
//! before, whose error the difference then measures directly.

use super::error_control::Tolerance;
use super::options::ForwardOptions;
use super::run::StepSink;
use super::summary::{RunCheck, RunSummary};
use crate::error::Result;
use crate::model::Model;
use std::ops::ControlFlow;
use std::sync::Arc;
use std::time::Instant;

/// What the tolerance asked of a run bounds.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum ToleranceScope {
    /// The rows written: the run is checked, and made again at a tighter step
    /// tolerance where its estimated error exceeds the tolerance.
    #[default]
    Run,
    /// Each step's local error per unit of time only (one run, no check).
    Steps,
}

impl ToleranceScope {
    /// The scope named as the CLI and Python name it ("run", "steps").
    pub fn parse(s: &str) -> Option<ToleranceScope> {
        match s {
            "run" => Some(ToleranceScope::Run),
            "steps" => Some(ToleranceScope::Steps),
            _ => None,
        }
    }
}

/// The check run's step tolerance, as a multiple of the checked run's: coarse
/// enough to cost well under the run itself (Hermite–Simpson takes 4^(1/4) ≈ 1.4
/// times fewer steps, the trapezoidal rule 2 times), close enough that both runs'
/// errors still grow in proportion to it.
pub const CHECK_RATIO: f64 = 4.0;

/// The estimated error, in units of the tolerance, that a run made again aims at:
/// below 1 by the margin the proportionality leaves.
const AIM: f64 = 0.5;

/// The most the first run made again tightens the step tolerance: the check run's
/// estimate comes from a coarser run, whose error can grow faster than its
/// tolerance (steps its bounds set, a motion that amplifies errors), and far
/// tighter the run's steps leave the regime it was measured in (steps that a bound
/// set become the tolerance's, whose errors fall faster than the tolerance); the
/// next comparison, with this run, measures again.
const FIRST_TIGHTENING: f64 = 8.0;

/// The most runs made again after the first.
pub const MAX_RERUNS: usize = 3;

/// The tightest step tolerance, as a fraction of the one asked: tighter, the run's
/// own rounding and the passages' handling, not its steps, make the error, and its
/// cost grows without a gain.
pub const MAX_TIGHTENING: f64 = 1e-4;

/// The tightest step rtol a run that passed a singular configuration with exact
/// projections, or kept steps at the smallest size, is made again at: below it the
/// steps' error estimates near a rank loss are the noise of the solves, and the
/// steps there shrink to the general solver's.
pub const TIGHTEST_STEP_RTOL: f64 = 1e-10;

/// The tightest step rtol of a run that met no rank loss: a step's error estimate
/// stays above the rounding of its solve (about 1e-14 of the state) by a margin.
pub const TIGHTEST_REGULAR_STEP_RTOL: f64 = 1e-12;

/// The most rows compared: a long run is compared at every k-th row.
const COMPARED_ROWS: usize = 4096;

/// The run at `tolerance` on its rows ([`ToleranceScope::Run`]): `adaptive` is one
/// error-controlled run at a step tolerance, handing its rows to a sink. The rows of
/// the last run made reach `sink` (restarted before each run made again), and its
/// summary's error control says what the check estimated.
pub(super) fn simulate(
    model: Arc<Model>,
    options: &ForwardOptions,
    tolerance: Tolerance,
    progress: &mut dyn FnMut(usize, usize) -> ControlFlow<()>,
    sink: &mut dyn StepSink,
) -> Result<RunSummary> {
    let start = Instant::now();
    let stride = options.steps().div_ceil(COMPARED_ROWS).max(1);
    // The steps' sizes go as the step tolerance to the power 1/order (the error per
    // unit step of an integrator of that order); their other bounds are scaled alike.
    let order = f64::from(options.integrator.order());
    let run = |factor: f64,
               progress: &mut dyn FnMut(usize, usize) -> ControlFlow<()>,
               sink: Option<&mut dyn StepSink>|
     -> Result<(RunSummary, Vec<Vec<f64>>)> {
        let mut sampled = Sampled::new(sink, stride);
        let s = super::adaptive::simulate(
            model.clone(),
            options,
            tolerance.scaled(factor),
            factor.powf(1.0 / order),
            progress,
            &mut sampled,
        )?;
        Ok((s, sampled.rows))
    };
    let finish = |mut s: RunSummary, check: RunCheck| {
        if let Some(c) = s.error_control.as_mut() {
            c.tolerance = tolerance;
            c.check = Some(check);
        }
        s.wall_time = start.elapsed();
        s
    };
    let (mut summary, mut rows) = run(1.0, progress, Some(&mut *sink))?;
    let mut check = RunCheck {
        step_rtols: vec![tolerance.rtol],
        estimated: None,
        unchecked: None,
    };
    if let Some(why) = unfinished(&summary) {
        check.unchecked = Some(why);
        return Ok(finish(summary, check));
    }
    let compared = match run(CHECK_RATIO, progress, None) {
        Ok((s, _)) if s.interrupted.is_some() => Err("the check was interrupted".to_string()),
        Ok((s, coarse)) if s.failures.is_empty() => compare(&tolerance, &rows, &coarse)
            .ok_or_else(|| "the check run's rows could not be compared".to_string()),
        _ => Err(format!(
            "the check run at {CHECK_RATIO} times the tolerance did not reach the end"
        )),
    };
    let difference = match compared {
        Ok(d) => d,
        Err(why) => {
            check.unchecked = Some(why);
            return Ok(finish(summary, check));
        }
    };
    let mut estimated = difference / (CHECK_RATIO - 1.0);
    // (A run that damped its steps near a rank loss kept them at the size that
    // reached it, unestimated: its estimates are those of regular steps.)
    let regular = summary
        .error_control
        .as_ref()
        .is_some_and(|c| c.at_floor == 0 && (summary.passages.count == 0 || c.damped > 0));
    let tightest_step = match regular {
        true => TIGHTEST_REGULAR_STEP_RTOL,
        false => TIGHTEST_STEP_RTOL,
    };
    let tightest = MAX_TIGHTENING.max(tightest_step / tolerance.rtol).min(1.0);
    let mut factor = 1.0;
    for rerun in 0..MAX_RERUNS {
        if estimated <= 1.0 || factor <= tightest {
            break;
        }
        // The check's estimate, from a coarser run, is bounded in what it tightens;
        // the later ones measure the run before directly.
        let least = match rerun {
            0 => 1.0 / FIRST_TIGHTENING,
            _ => 0.0,
        };
        let next = (factor * (AIM / estimated).max(least)).max(tightest);
        sink.restart()?;
        let (s, r) = run(next, progress, Some(&mut *sink))?;
        check.step_rtols.push(tolerance.rtol * next);
        if let Some(why) = unfinished(&s) {
            check.unchecked = Some(why);
            return Ok(finish(s, check));
        }
        // The run before was `factor / next` times as coarse: the difference is
        // its error, and this run's about that much smaller.
        let before = compare(&tolerance, &rows, &r).unwrap_or(f64::INFINITY);
        estimated = before * next / factor;
        (summary, rows, factor) = (s, r, next);
    }
    check.estimated = Some(estimated);
    Ok(finish(summary, check))
}

/// Why a run's rows are not checked: it stopped at a failure or was interrupted.
fn unfinished(s: &RunSummary) -> Option<String> {
    if s.interrupted.is_some() {
        Some("the run was interrupted".into())
    } else if !s.failures.is_empty() {
        Some("the run stopped at a failure".into())
    } else {
        None
    }
}

/// The weighted RMS difference of two runs' q over the rows compared and the
/// coordinates, each weighed by atol + rtol·|q| ([`Tolerance::norm`]); `None` where
/// they hold different rows, or a difference is not finite.
fn compare(tolerance: &Tolerance, a: &[Vec<f64>], b: &[Vec<f64>]) -> Option<f64> {
    if a.is_empty() || a.len() != b.len() {
        return None;
    }
    let mut sum = 0.0;
    let mut diff = Vec::new();
    for (x, y) in a.iter().zip(b) {
        diff.clear();
        diff.extend(x.iter().zip(y).map(|(u, v)| u - v));
        let d = tolerance.norm(&diff, x, y);
        if !d.is_finite() {
            return None;
        }
        sum += d * d;
    }
    Some((sum / a.len() as f64).sqrt())
}

/// A sink that keeps q of every `stride`-th row, and hands every row on to
/// `inner` where there is one.
struct Sampled<'a> {
    inner: Option<&'a mut dyn StepSink>,
    stride: usize,
    next: usize,
    rows: Vec<Vec<f64>>,
}

impl<'a> Sampled<'a> {
    fn new(inner: Option<&'a mut dyn StepSink>, stride: usize) -> Self {
        Sampled {
            inner,
            stride,
            next: 0,
            rows: Vec::new(),
        }
    }
}

impl StepSink for Sampled<'_> {
    fn step(&mut self, t: f64, q: &[f64], dq: &[f64], ddq: &[f64]) -> Result<()> {
        if self.next % self.stride == 0 {
            self.rows.push(q.to_vec());
        }
        self.next += 1;
        match self.inner.as_mut() {
            Some(s) => s.step(t, q, dq, ddq),
            None => Ok(()),
        }
    }

    fn restart(&mut self) -> Result<()> {
        self.next = 0;
        self.rows.clear();
        match self.inner.as_mut() {
            Some(s) => s.restart(),
            None => Ok(()),
        }
    }

    fn between(&mut self, t: f64, q: &[f64], dq: &[f64], ddq: &[f64]) -> Result<()> {
        match self.inner.as_mut() {
            Some(s) => s.between(t, q, dq, ddq),
            None => Ok(()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn compare_weighs_by_the_tolerance_and_refuses_unequal_rows() {
        let tol = Tolerance::new(1e-3, Some(1e-3)).unwrap();
        let a = vec![vec![0.0, 1.0], vec![0.0, 0.0]];
        let b = vec![vec![1e-3, 1.0], vec![0.0, 0.0]];
        // One coordinate of four off, by 1e-3 against a weight of 1e-3 + 1e-6:
        // √((1/1.001)² / 4).
        let d = compare(&tol, &a, &b).unwrap();
        assert!((d - 0.5 / 1.001).abs() < 1e-12, "{d}");
        assert_eq!(compare(&tol, &a, &b[..1]), None);
        assert_eq!(compare(&tol, &[vec![f64::NAN]], &[vec![0.0]]), None);
    }

    #[test]
    fn the_sampled_sink_keeps_every_strideth_row_and_forgets_on_restart() {
        let mut s = Sampled::new(None, 2);
        for k in 0..5 {
            s.step(k as f64, &[k as f64], &[0.5], &[0.0]).unwrap();
        }
        assert_eq!(s.rows, vec![vec![0.0], vec![2.0], vec![4.0]]);
        s.restart().unwrap();
        s.step(0.0, &[7.0], &[1.0], &[0.0]).unwrap();
        assert_eq!(s.rows, vec![vec![7.0]]);
    }
}
