//! The process σ a record's readings ask for, where the scene gives none.
//!
//! The default σ is a guess at how wrong a model is. A filter pass over the record
//! (window 1: the mean NIS hardly depends on the window) tells whether the guess
//! fits (covariance matching), and the σ is moved by secant steps on ln NIS against
//! ln σ until the pass's mean NIS falls inside its 95 % bounds:
//!
//! - above the bounds, the readings disagree with the model more than the σ's
//!   allow and the σ's the estimate reports would be too small: σ rises to where
//!   the mean NIS meets its expected value, up to [`SIGMA_RANGE`] times the default;
//! - below them, the σ's are too large: σ falls only as far as the bounds ask, to a
//!   mean NIS just inside the lower bound ([`LOWER_TARGET`]), down to the default
//!   over [`SIGMA_RANGE_BELOW`]. Where the model's error is a bias (a wrong constant) a σ
//!   that matches the innovations exactly may leave the smoothed estimate off by
//!   more than its σ's; the largest consistent σ keeps the σ's on the honest side.
//!   A σ is lowered only where a pass at it lands inside the bounds with white
//!   enough innovations ([`Whiteness`]): readings that keep disagreeing with the model
//!   the same way step after step say its error is a bias the process noise does
//!   not describe, and then the default stays.

use super::consistency::{Nis, Whiteness};
use super::online::Estimator;
use super::options::{EstimateOptions, Uncertainty, DEFAULT_PROCESS_SIGMA};
use super::record::Record;
use super::run::{graph_with, reading_factors};
use crate::error::Result;
use crate::model::Model;
use std::sync::Arc;

/// How far above the default the σ may go: to a model whose errors are of gravity's
/// own size.
pub const SIGMA_RANGE: f64 = 10.0 / 3.0;
/// How far below the default the σ may go.
pub const SIGMA_RANGE_BELOW: f64 = 10.0;
/// Where a lowered σ aims: this fraction of the way from the lower bound of the
/// mean NIS to its expected value (inside the bounds, with a margin for the run's
/// own NIS, which differs from the pass's by a little).
const LOWER_TARGET: f64 = 0.25;
/// A pass's mean NIS that changes by less than this power of σ does not come from
/// the process noise (the sensors' σ, or a model error the process noise cannot
/// explain): the default stays.
const LEAST_RESPONSE: f64 = 0.1;
/// Steps of the record the passes read (its start): enough readings for NIS bounds
/// within a few percent, at a bounded cost on long records.
pub const PASS_STEPS: usize = 4000;
/// Passes after the default's.
const MAX_PASSES: usize = 6;
/// Close enough: the mean NIS within this fraction of its expected value.
const TOLERANCE: f64 = 0.02;

/// Where a run's process σ came from.
#[derive(Debug, Clone, PartialEq)]
pub enum ProcessSource {
    /// `estimation: process_sigma` in the scene.
    Scene,
    /// The default (the scene declares inputs or parameters, which carry the
    /// model's error; or the default's pass did not ask for more).
    Default,
    /// Chosen from the readings: the default left the pass's mean NIS at `nis`,
    /// outside `bounds`.
    Readings { nis: f64, bounds: (f64, f64) },
    /// The default, whose pass's mean NIS `nis` was outside its bounds, kept: at
    /// the σ `tried` the pass's mean NIS was still `then` (it does not come from
    /// the process noise).
    Unresponsive { nis: f64, tried: f64, then: f64 },
    /// The default, whose pass's mean NIS `nis` was below its bounds, kept: at the
    /// smaller σ `tried`, where the mean NIS was inside them, the innovations'
    /// lag-one autocorrelation was `lag_one`, too far from white ones'.
    Correlated { nis: f64, tried: f64, lag_one: f64 },
}

/// The process σ for an estimate of `record`, and where it came from.
pub fn choose(
    model: &Arc<Model>,
    options: &EstimateOptions,
    record: &Record,
    uncertainty: &Uncertainty,
) -> Result<(f64, ProcessSource)> {
    if model.estimation.process_sigma.is_some() {
        return Ok((uncertainty.process, ProcessSource::Scene));
    }
    if uncertainty.process != DEFAULT_PROCESS_SIGMA {
        return Ok((uncertainty.process, ProcessSource::Default));
    }
    let sigma0 = uncertainty.process;
    // A pass that fails (a reading no estimate explains) decides nothing: the run
    // itself meets the failure, and keeps the steps final before it.
    let Ok(nis0) = pass(model, options, record, uncertainty, sigma0) else {
        return Ok((sigma0, ProcessSource::Default));
    };
    let (lo, hi) = nis0.bounds();
    if nis0.count == 0 || (lo..=hi).contains(&nis0.mean()) {
        return Ok((sigma0, ProcessSource::Default));
    }
    let expected = nis0.expected();
    let raise = nis0.mean() > hi;
    let (target, range) = if raise {
        (expected, (sigma0, sigma0 * SIGMA_RANGE))
    } else {
        (
            lo + LOWER_TARGET * (expected - lo),
            (sigma0 / SIGMA_RANGE_BELOW, sigma0),
        )
    };
    let misfit = |n: f64| (n / target).ln();
    let (mut s_prev, mut f_prev) = (sigma0, misfit(nis0.mean()));
    // The best σ so far, with its misfit; a lowered one only if its pass was
    // inside the bounds.
    let mut best = (f_prev, sigma0);
    // First step: NIS taken inversely proportional to σ; then secants.
    let mut slope = -1.0;
    for _ in 0..MAX_PASSES {
        let step = (-f_prev / slope).clamp(-10f64.ln(), 10f64.ln());
        let s = (s_prev * step.exp()).clamp(range.0, range.1);
        if s == s_prev {
            break; // at an end of the range, still asking to go beyond it
        }
        let Ok(nis) = pass(model, options, record, uncertainty, s) else {
            break; // a σ at which the filter fails says nothing of the NIS
        };
        let f = misfit(nis.mean());
        if !f.is_finite() {
            break;
        }
        slope = (f - f_prev) / (s.ln() - s_prev.ln());
        if slope > -LEAST_RESPONSE {
            if best.1 == sigma0 {
                let source = ProcessSource::Unresponsive {
                    nis: nis0.mean(),
                    tried: s,
                    then: nis.mean(),
                };
                return Ok((sigma0, source));
            }
            break;
        }
        let consistent = (lo..=hi).contains(&nis.mean());
        if !raise && consistent && !white(&nis.whiteness) {
            // A smaller σ only correlates the innovations more.
            if best.1 == sigma0 {
                let source = ProcessSource::Correlated {
                    nis: nis0.mean(),
                    tried: s,
                    lag_one: nis.whiteness.lag_one().unwrap_or(f64::NAN),
                };
                return Ok((sigma0, source));
            }
            break;
        }
        let admissible = raise || consistent;
        if admissible && (f.abs() < best.0.abs() || (!raise && best.1 == sigma0)) {
            best = (f, s);
        }
        if admissible && f.abs() < TOLERANCE.ln_1p() {
            break;
        }
        (s_prev, f_prev) = (s, f);
    }
    if best.1 == sigma0 {
        return Ok((sigma0, ProcessSource::Default));
    }
    Ok((
        best.1,
        ProcessSource::Readings {
            nis: nis0.mean(),
            bounds: nis0.bounds(),
        },
    ))
}

/// How much the innovations' correlation may make the smoothed σ's understate the
/// errors: innovations correlated step to step at ρ (first order) make the errors
/// of an average over steps (1 + ρ)/(1 − ρ) times the variance white ones would.
const UNDERSTATEMENT: f64 = 1.1;

/// Whether a pass's innovations are white enough: their lag-one autocorrelation
/// at most the ρ at which the σ's would understate the errors by [`UNDERSTATEMENT`]
/// (0.095; negatively correlated ones make the σ's overstate them).
fn white(w: &Whiteness) -> bool {
    let u2 = UNDERSTATEMENT * UNDERSTATEMENT;
    w.lag_one().is_some_and(|r| r <= (u2 - 1.0) / (u2 + 1.0))
}

/// The NIS statistics of a window-1 pass over the record's start with process σ
/// `sigma`.
fn pass(
    model: &Arc<Model>,
    options: &EstimateOptions,
    record: &Record,
    uncertainty: &Uncertainty,
    sigma: f64,
) -> Result<Nis> {
    let mut u = uncertainty.clone();
    u.process = sigma;
    let eg = graph_with(model, options.coordinates, record, &u)?;
    let mut est = Estimator::new(model.clone(), eg, 1, options.settings, false)?;
    for readings in record.steps.iter().take(PASS_STEPS) {
        est.update(reading_factors(model, readings)?)?;
    }
    Ok(est.nis.clone())
}
