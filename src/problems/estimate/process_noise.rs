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
//!
//! Where the scene identifies parameters, they carry the bias, and a batch estimate
//! lowers the σ once they are estimated ([`DynamicsUse`], covariance matching on the
//! dynamics): the default's σ leaves the dynamics too loose to tie the parameters to
//! the motion, and the batch shows how much of that σ the motion needs.

use super::consistency::{step_rows, Nis, Whiteness};
use super::graph::EstimationGraph;
use super::online::Estimator;
use super::options::{carries_its_error, EstimateOptions, Uncertainty};
use super::record::Record;
use super::run::{graph_with, reading_factors};
use crate::error::Result;
use crate::graph::{Term, Workspace};
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
    /// Chosen from the readings: the default (`default`, at the run's step) left the
    /// pass's mean NIS at `nis`, outside `bounds`.
    Readings {
        nis: f64,
        bounds: (f64, f64),
        default: f64,
    },
    /// The default, whose pass's mean NIS `nis` was outside its bounds, kept: at
    /// the σ `tried` the pass's mean NIS was still `then` (it does not come from
    /// the process noise).
    Unresponsive { nis: f64, tried: f64, then: f64 },
    /// The default, whose pass's mean NIS `nis` was below its bounds, kept: at the
    /// smaller σ `tried`, where the mean NIS was inside them, the innovations'
    /// lag-one autocorrelation was `lag_one`, too far from white ones'.
    Correlated { nis: f64, tried: f64, lag_one: f64 },
    /// Lowered from `from` (the default) by a batch estimate that identifies
    /// parameters: at `from` its dynamics residuals used `used` of their expected χ²
    /// (see [`DynamicsUse`]).
    Identified { from: f64, used: f64 },
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
    if carries_its_error(model) {
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
            default: sigma0,
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
    let eg = graph_with(model, options.motion(model), record, &u)?;
    let mut est = Estimator::new(model.clone(), eg, 1, options.settings, false)?;
    for readings in record.steps.iter().take(PASS_STEPS) {
        est.update(reading_factors(model, readings)?)?;
    }
    Ok(est.nis.clone())
}

/// How much of its process noise a smoothed estimate uses, from its dynamics
/// residuals: at the optimum of a model whose σ's are right, each whitened residual
/// row ρ_i = r_i/σ_i has E[ρ_i²] = 1 − h_i P h_iᵀ (h_i the row's whitened Jacobian,
/// P the step's posterior covariance), the part of the row the estimate does not
/// absorb. `chi2` sums the ρ_i², `dof` their expectations; a `chi2` below `dof`
/// says the motion leaves the model by less than σ, and σ·√(chi2/dof) is the σ the
/// residuals show (covariance matching, whose fixed point is where the likelihood
/// of the readings is largest in σ). Rows the readings do not reach (a direction
/// the constraints fix) add about 0 to both.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DynamicsUse {
    pub chi2: f64,
    pub dof: f64,
}

impl DynamicsUse {
    /// chi2 / dof: 1 where the σ is what the residuals show.
    pub fn ratio(&self) -> f64 {
        self.chi2 / self.dof
    }

    /// The dynamics residuals of the steps of `values` (step-major, every step of
    /// `eg`'s graph) against their posterior covariances (row-major s × s, one per
    /// step). `None` where a residual cannot be evaluated or there are no rows.
    pub fn of(
        eg: &EstimationGraph,
        values: &[f64],
        covariances: &[Vec<f64>],
        ws: &mut Workspace,
    ) -> Option<DynamicsUse> {
        let graph = &eg.graph;
        let layout = graph.layout();
        let s = layout.size();
        let Term::Soft(factor, noise) = &graph.step_terms()[eg.dynamics_term()] else {
            return None;
        };
        let mut h = vec![0.0; s];
        let (mut chi2, mut dof) = (0.0, 0.0);
        for (k, p) in covariances.iter().enumerate() {
            let x = &values[k * s..(k + 1) * s];
            let (r, rows) = step_rows(layout, factor.as_ref(), graph.run_time(k), x, ws)?;
            for (i, ri) in r.iter().enumerate() {
                // The row whitened by its σ.
                let w = noise.weight(i);
                for (hc, jc) in h.iter_mut().zip(&rows[i * s..(i + 1) * s]) {
                    *hc = w * jc;
                }
                let hph: f64 = (0..s)
                    .map(|a| h[a] * (0..s).map(|b| p[a * s + b] * h[b]).sum::<f64>())
                    .sum();
                chi2 += (w * ri).powi(2);
                dof += (1.0 - hph).clamp(0.0, 1.0);
            }
        }
        (dof > 0.0 && chi2.is_finite()).then_some(DynamicsUse { chi2, dof })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::coordinates::Coordinates;
    use crate::factors::Integrator;
    use crate::scene::Scene;
    use std::path::Path;

    fn graph() -> (Arc<Model>, EstimationGraph) {
        let path = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("scenes/identification/fourbar-mass-bad.yaml");
        let model = Arc::new(Model::new(&Scene::load(path).unwrap()).unwrap());
        let u = Uncertainty::of(&model, 0.005);
        let start = model.initial.clone();
        let eg = EstimationGraph::new(
            model.clone(),
            Coordinates::Dependent,
            Integrator::Trapezoidal,
            &u,
            0.005,
            start,
        )
        .unwrap();
        (model, eg)
    }

    #[test]
    fn the_dynamics_use_counts_whitened_residuals_against_what_the_estimate_absorbs() {
        let (model, eg) = graph();
        let (n, s, steps) = (model.n(), eg.size(), 3);
        let sigma = Uncertainty::of(&model, 0.005).process;
        let block = eg.initial_block(&model).unwrap();
        let mut values: Vec<f64> = (0..steps).flat_map(|_| block.clone()).collect();
        let mut ws = eg.graph.workspace();
        let zero = vec![vec![0.0; s * s]; steps];
        // The start's accelerations are the model's: no residual; with no posterior
        // uncertainty, every row counts whole.
        let at_model = DynamicsUse::of(&eg, &values, &zero, &mut ws).unwrap();
        assert!(at_model.chi2 < 1e-16, "{at_model:?}");
        assert_eq!(at_model.dof, (steps * n) as f64);
        // Each step's q̈ of one coordinate 2σ off the model's: 4 per step.
        for k in 0..steps {
            values[k * s + 2 * n + n - 1] += 2.0 * sigma;
        }
        let off = DynamicsUse::of(&eg, &values, &zero, &mut ws).unwrap();
        assert!((off.chi2 - 4.0 * steps as f64).abs() < 1e-9, "{off:?}");
        assert!((off.ratio() - 4.0 / n as f64).abs() < 1e-9);
        // A posterior as wide as the prior on q̈ absorbs every row.
        let mut wide = zero.clone();
        for p in &mut wide {
            for i in 2 * n..3 * n {
                p[i * s + i] = sigma * sigma;
            }
        }
        // (None: no row left to count.)
        let absorbed = DynamicsUse::of(&eg, &values, &wide, &mut ws);
        assert!(absorbed.is_none_or(|u| u.dof < 1e-9), "{absorbed:?}");
    }
}
