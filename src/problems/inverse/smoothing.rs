//! Smoothing of measured samples of the prescribed coordinates, for inverse dynamics
//! from measured motion (`mbfg inverse --sample-sigma`).
//!
//! Each prescribed coordinate z is smoothed on its own: its samples are readings
//! y_k = z(t_k) + v_k, v_k ~ N(0, σ²), and its motion prior makes the fourth
//! derivative white noise of intensity q (the state x = (z, ż, z̈, z⃛) an integrated
//! Wiener process). Between samples h apart that prior is exact:
//! x_{k+1} = F x_k + w_k, w_k ~ N(0, q Q_h), with F = exp(h·shift) and
//! (Q_h)_{ij} = h^{a+b+1} / ((a+b+1) a! b!), a = 3 − i, b = 3 − j. Being exact, it has
//! no step-to-step mode (the trapezoidal rule's (−1)^k acceleration is invisible to
//! its samples; here every mode of q̈ costs its jerk and snap).
//!
//! The batch least-squares problem is linear: its normal equations are block
//! tridiagonal (4 × 4 blocks), factored once per q; the marginal covariance of every
//! sample's state is the diagonal blocks of their inverse (selected inversion).
//!
//! q is chosen by maximum marginal likelihood (the "generalized maximum likelihood"
//! of smoothing splines), with constants dropped:
//! −2 log p(y | q, σ) = r + log det H + (N − 1) log det(q Q_h) + Σ_k log σ_k²,
//! r the whitened cost at the estimate and H its normal matrix. With σ unknown
//! ([`SampleSigma::FromData`]) its scale is profiled out, σ̂² = r₁ / (N − 4) with r₁
//! the cost at unit σ: the samples' own scatter about the smooth motion sets σ. Two
//! shapes of σ_k then compete by that likelihood: the same for every sample, or
//! proportional to each sample's rounding step (samples written to a fixed number of
//! significant digits, whose rounding error is ten times smaller below each power of
//! ten).

use crate::error::{Error, Result};
use crate::linalg::banded::{BandedCholesky, BlockTridiagonal};

/// The state's size: z, ż, z̈ and z⃛.
const D: usize = 4;

/// How noisy the prescribed samples are taken to be.
#[derive(Debug, Clone, PartialEq)]
pub enum SampleSigma {
    /// σ of each prescribed coordinate's samples, in the prescription's column order.
    Given(Vec<f64>),
    /// σ of each coordinate chosen from its samples by maximum marginal likelihood.
    FromData,
}

impl SampleSigma {
    /// The σ's named per prescribed column (`given[c]` for `columns[c]`), or why not:
    /// the columns left without one.
    pub fn per_column(
        columns: &[&str],
        given: Vec<Option<f64>>,
    ) -> std::result::Result<Self, String> {
        let missing: Vec<&str> = columns
            .iter()
            .zip(&given)
            .filter(|(_, g)| g.is_none())
            .map(|(c, _)| *c)
            .collect();
        if !missing.is_empty() {
            return Err(format!(
                "no σ for {} (name every prescribed coordinate, or give one σ for all)",
                missing.join(", ")
            ));
        }
        Ok(SampleSigma::Given(given.into_iter().flatten().collect()))
    }
}

/// What the smoothing found for one prescribed coordinate.
#[derive(Debug, Clone, PartialEq)]
pub struct ColumnFit {
    /// σ of the samples: the one given, or the one chosen from the data.
    pub sigma: f64,
    /// Whether `sigma` was chosen from the data.
    pub from_data: bool,
    /// Intensity q of the prior's white fourth derivative (unit²/s⁷).
    pub intensity: f64,
    /// RMS of the samples' difference from the smoothed motion.
    pub residual_rms: f64,
    /// The largest difference of a sample from the smoothed motion in units of that
    /// sample's σ, and the sample's index: far beyond a few σ it is a glitch, an angle
    /// written wrapped, or a σ given too small.
    pub worst_residual: (f64, usize),
    /// How σ varies from sample to sample.
    pub noise: NoiseShape,
}

/// The shape of the samples' noise.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum NoiseShape {
    /// The same σ for every sample.
    Uniform,
    /// σ proportional to each sample's rounding step, the samples written to
    /// `digits` significant digits; [`ColumnFit::sigma`] is the σ of the samples
    /// with the largest step.
    Rounding { digits: usize },
}

/// The smoothed prescribed motion: values, first and second derivatives
/// (row-major samples × prescribed coordinates) and their covariance.
#[derive(Debug, Clone, PartialEq)]
pub struct Smoothed {
    pub values: Vec<f64>,
    pub rates: Vec<f64>,
    pub accelerations: Vec<f64>,
    /// Per sample k and coordinate c, the 3 × 3 covariance of (z, ż, z̈), row-major,
    /// at `(k * p + c) * 9`.
    pub covariances: Vec<f64>,
    pub columns: Vec<ColumnFit>,
}

/// Smooths every column of `values` (row-major `steps` × p) sampled every `dt`, or,
/// with `times`, sampled at those times (increasing, `steps` of them): the smoothed
/// motion is then given on the uniform grid t₀ + k·dt, k < `steps`, t₀ the first
/// sample's time and dt their mean interval, each grid time interpolated between the
/// samples around it.
pub fn smooth(
    values: &[f64],
    steps: usize,
    dt: f64,
    times: Option<&[f64]>,
    sigma: &SampleSigma,
    names: &[&str],
) -> Result<Smoothed> {
    let p = names.len();
    if let SampleSigma::Given(s) = sigma {
        if s.len() != p {
            return Err(Error::InvalidArgument(format!(
                "{} sample σ's for {p} prescribed coordinates",
                s.len()
            )));
        }
        if let Some((c, v)) = s
            .iter()
            .enumerate()
            .find(|(_, v)| !(v.is_finite() && **v > 0.0))
        {
            return Err(Error::InvalidArgument(format!(
                "the sample σ of `{}` must be a positive number, got {v}",
                names[c]
            )));
        }
    }
    if steps <= D {
        return Err(Error::InvalidArgument(format!(
            "{steps} samples are too few to smooth (more than {D} are needed)"
        )));
    }
    let mut out = Smoothed {
        values: vec![0.0; steps * p],
        rates: vec![0.0; steps * p],
        accelerations: vec![0.0; steps * p],
        covariances: vec![0.0; steps * p * 9],
        columns: Vec::with_capacity(p),
    };
    let mut smoother = ColumnSmoother::new(steps);
    if let Some(times) = times {
        if times.len() != steps {
            return Err(Error::InvalidArgument(format!(
                "{} sample times for {steps} samples",
                times.len()
            )));
        }
        // Positions in steps of dt from the first sample: the scaled problem's time.
        smoother.at = times.iter().map(|t| (t - times[0]) / dt).collect();
    }
    let mut y = vec![0.0; steps];
    for c in 0..p {
        for (k, v) in y.iter_mut().enumerate() {
            *v = values[k * p + c];
        }
        let given = match sigma {
            SampleSigma::Given(s) => Some(s[c]),
            SampleSigma::FromData => None,
        };
        if let Some(s) = given {
            check_given(s, &y).map_err(|m| {
                Error::InvalidArgument(format!("the sample σ of `{}` ({s:e}) {m}", names[c]))
            })?;
        }
        let fit = smoother.fit(&y, dt, given);
        let fit = fit.map_err(|e| {
            Error::InvalidArgument(format!("smoothing the samples of `{}`: {e}", names[c]))
        })?;
        for k in 0..steps {
            let (x, cov) = (&smoother.x[k * D..(k + 1) * D], &smoother.cov[k]);
            out.values[k * p + c] = x[0];
            out.rates[k * p + c] = x[1];
            out.accelerations[k * p + c] = x[2];
            let at = (k * p + c) * 9;
            for i in 0..3 {
                for j in 0..3 {
                    out.covariances[at + i * 3 + j] = cov[i * D + j];
                }
            }
        }
        out.columns.push(fit);
    }
    Ok(out)
}

/// A given σ within what double precision can tell apart: not below 1e-15 of the
/// samples' size (their round-off), not above 1e6 times their spread (where no sample
/// carries information).
fn check_given(sigma: f64, y: &[f64]) -> std::result::Result<(), String> {
    let size = y.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    let (lo, hi) = y
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| {
            (a.min(*v), b.max(*v))
        });
    let spread = (hi - lo).max(1e-15 * size).max(1e-150);
    if sigma < 1e-15 * size {
        return Err(format!(
            "is below the samples' round-off (1e-15 of their size {size:.3e}): give at least {:.3e}",
            1e-15 * size
        ));
    }
    if sigma > 1e6 * spread {
        return Err(format!(
            "exceeds 1e6 times the samples' spread ({spread:.3e}): such samples carry no information"
        ));
    }
    Ok(())
}

/// Most refinements of a smoothing solve (two or three suffice).
const REFINEMENTS: usize = 6;

/// An interval's F, W, WF and FᵀWF.
type Weights = ([[f64; D]; D], [[f64; D]; D], [[f64; D]; D], [[f64; D]; D]);

/// The prior's [`Weights`] of every interval at one λ: one set on the uniform grid,
/// one per interval off it; the buffer kept from trial to trial.
#[derive(Debug, Default)]
struct Intervals {
    table: Vec<Weights>,
    uniform: bool,
}

impl Intervals {
    /// For samples at `at` (in steps; empty: the uniform grid) and intensity λ.
    fn fill(&mut self, w1: &[[f64; D]; D], at: &[f64], lambda: f64) {
        self.uniform = at.is_empty();
        self.table.clear();
        if self.uniform {
            self.table.push(interval_weights(w1, 1.0, lambda));
        } else {
            self.table.extend(
                at.windows(2)
                    .map(|p| interval_weights(w1, p[1] - p[0], lambda)),
            );
        }
    }

    /// The weights of the interval ending at step k ≥ 1.
    fn ending_at(&self, k: usize) -> &Weights {
        &self.table[if self.uniform { 0 } else { k - 1 }]
    }
}

/// The prior's misfit over one interval, x_k − F x_{k−1}, from the two states
/// (x_{k−1} then x_k).
fn misfit(f: &[[f64; D]; D], states: &[f64]) -> [f64; D] {
    let (before, x) = states.split_at(D);
    std::array::from_fn(|i| x[i] - (0..D).map(|j| f[i][j] * before[j]).sum::<f64>())
}

/// 0!, …, 7!.
const FACTORIAL: [f64; 8] = [1.0, 1.0, 2.0, 6.0, 24.0, 120.0, 720.0, 5040.0];

/// The transition over h: F(h)_{ij} = h^{j−i} / (j − i)!.
fn transition(h: f64) -> [[f64; D]; D] {
    let mut f = [[0.0; D]; D];
    for i in 0..D {
        for j in i..D {
            f[i][j] = h.powi((j - i) as i32) / FACTORIAL[j - i];
        }
    }
    f
}

/// The prior's covariance over h at unit intensity: Q(h)_{ij} = h^{a+b+1} / ((a+b+1) a! b!).
fn process(h: f64) -> [[f64; D]; D] {
    let mut q = [[0.0; D]; D];
    for i in 0..D {
        for j in 0..D {
            let (a, b) = (D - 1 - i, D - 1 - j);
            q[i][j] =
                h.powi((a + b + 1) as i32) / ((a + b + 1) as f64 * FACTORIAL[a] * FACTORIAL[b]);
        }
    }
    q
}

fn product(a: &[[f64; D]; D], b: &[[f64; D]; D]) -> [[f64; D]; D] {
    std::array::from_fn(|i| std::array::from_fn(|j| (0..D).map(|l| a[i][l] * b[l][j]).sum()))
}

fn transpose(a: &[[f64; D]; D]) -> [[f64; D]; D] {
    std::array::from_fn(|i| std::array::from_fn(|j| a[j][i]))
}

/// Per interval h (in steps) at intensity λ: W = Q(h)⁻¹/λ, WF and FᵀWF, with
/// Q(h)⁻¹ = S⁻¹ Q_1⁻¹ S⁻¹, S = diag(h^{a+1/2}) (Q(h) = S Q_1 S, so no small
/// entry of Q(h) is inverted directly).
fn interval_weights(w1: &[[f64; D]; D], h: f64, lambda: f64) -> Weights {
    let f = transition(h);
    let s: [f64; D] = std::array::from_fn(|i| h.powf((D - 1 - i) as f64 + 0.5));
    let w: [[f64; D]; D] =
        std::array::from_fn(|i| std::array::from_fn(|j| w1[i][j] / (s[i] * s[j] * lambda)));
    let wf = product(&w, &f);
    let ftwf = product(&transpose(&f), &wf);
    (f, w, wf, ftwf)
}

/// The prior's Q_1⁻¹ and log det Q_1 (one step, time in steps).
fn unit_prior() -> ([[f64; D]; D], f64) {
    let q = nalgebra::Matrix4::from_fn(|i, j| process(1.0)[i][j]);
    let log_det = q.determinant().ln();
    let inv = q.try_inverse().expect("Q_1 is positive definite");
    (
        std::array::from_fn(|i| std::array::from_fn(|j| inv[(i, j)])),
        log_det,
    )
}

/// One coordinate's smoother: the normal equations and their factor, reused for every
/// q tried; the last fit's state (x in physical units) and marginal covariances.
struct ColumnSmoother {
    h: BlockTridiagonal,
    chol: BandedCholesky,
    rhs: Vec<f64>,
    x: Vec<f64>,
    cov: Vec<Vec<f64>>,
    /// Σ_{k,k−1}, the covariance of neighbouring samples' states (interpolation).
    cov_lower: Vec<Vec<f64>>,
    /// The samples' positions in steps of dt, where they are not 0, 1, 2, … (empty
    /// on the uniform grid); the result is then interpolated to the grid.
    at: Vec<f64>,
    intervals: Intervals,
    w1: [[f64; D]; D],
    log_det_q1: f64,
}

/// The whitened cost and −2 log-likelihood (constants dropped) of one q.
#[derive(Debug, Clone, Copy)]
struct Trial {
    cost: f64,
    nll: f64,
}

impl ColumnSmoother {
    fn new(steps: usize) -> Self {
        let (w1, log_det_q1) = unit_prior();
        ColumnSmoother {
            h: BlockTridiagonal::new(steps, D),
            chol: BandedCholesky::new(steps, D),
            rhs: vec![0.0; steps * D],
            x: vec![0.0; steps * D],
            cov: Vec::new(),
            cov_lower: Vec::new(),
            at: Vec::new(),
            intervals: Intervals::default(),
            w1,
            log_det_q1,
        }
    }

    /// The whitened cost at `self.x`: the samples' misfits and the prior's.
    fn cost(&self, y: &[f64], weights: &[f64]) -> f64 {
        let x = &self.x;
        let mut cost = 0.0;
        for k in 0..y.len() {
            cost += weights[k] * (x[k * D] - y[k]).powi(2);
            if k > 0 {
                let (f, w, _, _) = self.intervals.ending_at(k);
                let d = misfit(f, &x[(k - 1) * D..(k + 1) * D]);
                for i in 0..D {
                    for j in 0..D {
                        cost += d[i] * w[i][j] * d[j];
                    }
                }
            }
        }
        cost
    }

    /// b − Hx at `self.x` into `self.rhs`: minus half the cost's gradient, summed
    /// factor by factor.
    fn negative_gradient(&mut self, y: &[f64], weights: &[f64]) {
        let (x, r, intervals) = (&self.x, &mut self.rhs, &self.intervals);
        r.fill(0.0);
        for k in 0..y.len() {
            r[k * D] = weights[k] * (y[k] - x[k * D]);
        }
        for k in 1..y.len() {
            let (f, w, _, _) = intervals.ending_at(k);
            let d = misfit(f, &x[(k - 1) * D..(k + 1) * D]);
            let g: [f64; D] = std::array::from_fn(|i| (0..D).map(|j| w[i][j] * d[j]).sum());
            for i in 0..D {
                r[k * D + i] -= g[i];
                r[(k - 1) * D + i] += (0..D).map(|j| f[j][i] * g[j]).sum::<f64>();
            }
        }
    }

    /// Solves for the state at prior intensity λ (in units of the scaled problem: time
    /// in steps, values in units of the unit σ): returns its cost and likelihood, the
    /// state in `self.x` (scaled). None where the normal equations are not positive
    /// definite in floating point (an extreme λ).
    fn trial(&mut self, y: &[f64], weights: &[f64], lambda: f64, profile: bool) -> Option<Trial> {
        let n = y.len();
        // W = Q(h)⁻¹/λ per interval; per step k ≥ 1: H_kk += W, H_{k−1,k−1} += FᵀWF,
        // H_{k,k−1} −= WF. On the uniform grid one set serves every interval.
        self.intervals.fill(&self.w1, &self.at, lambda);
        self.h.reset(n);
        for k in 0..n {
            self.h.diag_mut(k)[0] += weights[k];
        }
        for k in 1..n {
            let (_, w, wf, ftwf) = self.intervals.ending_at(k);
            let diag = self.h.diag_mut(k);
            for i in 0..D {
                for j in 0..D {
                    diag[i * D + j] += w[i][j];
                }
            }
            let before = self.h.diag_mut(k - 1);
            for i in 0..D {
                for j in 0..D {
                    before[i * D + j] += ftwf[i][j];
                }
            }
            let lower = self.h.lower_mut(k);
            for i in 0..D {
                for j in 0..D {
                    lower[i * D + j] = -wf[i][j];
                }
            }
        }
        self.chol.factor(&self.h, &[]).ok()?;
        self.rhs.fill(0.0);
        for (k, v) in y.iter().enumerate() {
            self.rhs[k * D] = *v * weights[k];
        }
        self.chol.solve(&mut self.rhs);
        std::mem::swap(&mut self.x, &mut self.rhs);
        // The normal equations' condition grows as 1/λ (the prior's weight against
        // the samples'), and the solution's error with it times the samples' size in
        // σ's (1e4 and more): at the likeliest λ the first solve's cost can be
        // several times the least one. Refined with the residual of the normal
        // equations formed factor by factor (b − Hx = −gradient, each interval's
        // misfit d_k = x_k − F x_{k−1} taken directly), the solution converges in
        // two or three solves to the least cost.
        let mut cost = self.cost(y, weights);
        for _ in 0..REFINEMENTS {
            self.negative_gradient(y, weights);
            self.chol.solve(&mut self.rhs);
            for (x, dx) in self.x.iter_mut().zip(&self.rhs) {
                *x += dx;
            }
            let refined = self.cost(y, weights);
            let gain = cost - refined;
            cost = refined;
            if !(gain > 1e-12 * cost) {
                break;
            }
        }
        // log det Q(h) = log det Q_1 + 16 log h (det S² = h^{2·(3.5+2.5+1.5+0.5)}).
        let log_intervals: f64 = self.at.windows(2).map(|p| 16.0 * (p[1] - p[0]).ln()).sum();
        let log_det_prior =
            (n - 1) as f64 * (D as f64 * lambda.ln() + self.log_det_q1) + log_intervals;
        let log_det_h = self.chol.log_determinant();
        // The noise's own normalizer, Σ log ρ_k² with ρ_k² = 1/weight_k (0 for
        // equal weights): what makes two noise shapes' likelihoods comparable.
        let log_det_noise: f64 = -weights.iter().map(|w| w.ln()).sum::<f64>();
        let nll = if profile {
            let s2 = cost / (n - D) as f64;
            (n - D) as f64 * s2.ln() + log_det_h + log_det_prior + log_det_noise
        } else {
            cost + log_det_h + log_det_prior + log_det_noise
        };
        (cost.is_finite() && nll.is_finite()).then_some(Trial { cost, nll })
    }

    /// The λ of least −2 log-likelihood for samples `ys` (scaled) and `weights`:
    /// a grid of decades, refined by golden section; None if no λ gives positive
    /// definite normal equations.
    fn search(&mut self, ys: &[f64], weights: &[f64], profile: bool) -> Option<(f64, f64)> {
        let mut eval = |log10: f64| {
            self.trial(ys, weights, 10f64.powf(log10), profile)
                .map_or(f64::INFINITY, |t| t.nll)
        };
        // Decades from 1e-30 to 1e12 (λ = q h⁷/σ²: the prior's snap over a step
        // against the samples' noise). Beyond 1e12 the normal equations' condition
        // (about λ) leaves too few digits: samples exact to round-off come out with
        // the σ of λ = 1e12, about 1e-13 of a motion of order 1, not smaller.
        let (mut centre, mut best) = (f64::NAN, f64::INFINITY);
        for e in -30..=12 {
            let v = eval(e as f64);
            if v < best {
                (centre, best) = (e as f64, v);
            }
        }
        if !best.is_finite() {
            return None;
        }
        let g = 0.5 * (5f64.sqrt() - 1.0);
        let (mut a, mut b) = (centre - 1.0, centre + 1.0);
        let (mut c, mut d) = (b - g * (b - a), a + g * (b - a));
        let (mut fc, mut fd) = (eval(c), eval(d));
        while b - a > 1e-3 {
            if fc < fd {
                (b, d, fd) = (d, c, fc);
                c = b - g * (b - a);
                fc = eval(c);
            } else {
                (a, c, fc) = (c, d, fd);
                d = a + g * (b - a);
                fd = eval(d);
            }
        }
        let (x, v) = if fc < fd { (c, fc) } else { (d, fd) };
        Some(if v < best { (x, v) } else { (centre, best) })
    }

    /// Replaces the states and covariances at the samples (positions `at`, scaled
    /// units, prior intensity λ) by those at the grid 0, 1, …, n − 1. Between samples
    /// k and k + 1 (h apart, the grid point τ after k) the prior is a Gauss–Markov
    /// bridge: given both ends, x(τ) = A x_k + B x_{k+1} + e with
    /// B = Q(τ)F(h−τ)ᵀQ(h)⁻¹, A = F(τ) − B F(h), and e of covariance
    /// λ(Q(τ) − B F(h−τ) Q(τ)), independent of the samples given the ends. So the
    /// mean is A x̂_k + B x̂_{k+1} and the covariance [A B] Σ_{k:k+1} [A B]ᵀ + Cov e,
    /// exactly.
    fn interpolate_to_grid(&mut self, lambda: f64) {
        let n = self.at.len();
        let mut x = vec![0.0; n * D];
        let mut cov = vec![vec![0.0; D * D]; n];
        let mut k = 0;
        for g in 0..n {
            let t = g as f64;
            while k + 2 < n && self.at[k + 1] <= t {
                k += 1;
            }
            let h = self.at[k + 1] - self.at[k];
            let tau = (t - self.at[k]).clamp(0.0, h);
            let q_tau = process(tau);
            let f_rest = transition(h - tau);
            let s: [f64; D] = std::array::from_fn(|i| h.powf((D - 1 - i) as f64 + 0.5));
            let q_h_inv: [[f64; D]; D] =
                std::array::from_fn(|i| std::array::from_fn(|j| self.w1[i][j] / (s[i] * s[j])));
            let b = product(&product(&q_tau, &transpose(&f_rest)), &q_h_inv);
            let bf = product(&b, &transition(h));
            let f_tau = transition(tau);
            let a: [[f64; D]; D] =
                std::array::from_fn(|i| std::array::from_fn(|j| f_tau[i][j] - bf[i][j]));
            let bridge = product(&product(&b, &f_rest), &q_tau);
            let (xk, xn) = (
                &self.x[k * D..(k + 1) * D],
                &self.x[(k + 1) * D..(k + 2) * D],
            );
            for i in 0..D {
                x[g * D + i] = (0..D).map(|j| a[i][j] * xk[j] + b[i][j] * xn[j]).sum();
            }
            // [A B] Σ [A B]ᵀ over the two ends: Σ_kk, Σ_{k+1,k+1}, Σ_{k+1,k} = lower.
            let (pk, pn, pl) = (&self.cov[k], &self.cov[k + 1], &self.cov_lower[k + 1]);
            let entry = |m: &[f64], i: usize, j: usize| m[i * D + j];
            let out = &mut cov[g];
            for i in 0..D {
                for j in 0..D {
                    let mut v = lambda * (q_tau[i][j] - bridge[i][j]);
                    for l in 0..D {
                        for m in 0..D {
                            v += a[i][l] * entry(pk, l, m) * a[j][m]
                                + b[i][l] * entry(pn, l, m) * b[j][m]
                                + b[i][l] * entry(pl, l, m) * a[j][m]
                                + a[i][l] * entry(pl, m, l) * b[j][m];
                        }
                    }
                    out[i * D + j] = v;
                }
            }
            for i in 0..D {
                for j in 0..i {
                    let v = 0.5 * (out[i * D + j] + out[j * D + i]);
                    out[i * D + j] = v;
                    out[j * D + i] = v;
                }
            }
        }
        self.x = x;
        self.cov = cov;
    }

    /// Fits one coordinate's samples `y` (spacing `dt`), σ given or from the data,
    /// and leaves the state and its covariances at the best λ in physical units.
    fn fit(
        &mut self,
        y: &[f64],
        dt: f64,
        sigma: Option<f64>,
    ) -> std::result::Result<ColumnFit, String> {
        let n = y.len();
        // The unit of the scaled problem: σ, or the scatter of the fourth differences
        // (Var Δ⁴v = 70 σ² for white v), which the profile then corrects.
        let scale = y.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        let unit = match sigma {
            Some(s) => s,
            None => {
                let d4: f64 = (0..n - 4)
                    .map(|k| {
                        (y[k] - 4.0 * y[k + 1] + 6.0 * y[k + 2] - 4.0 * y[k + 3] + y[k + 4]).powi(2)
                    })
                    .sum::<f64>()
                    / ((n - 4) as f64 * 70.0);
                d4.sqrt().max(1e-15 * scale).max(1e-150)
            }
        };
        let ys: Vec<f64> = y.iter().map(|v| v / unit).collect();
        let profile = sigma.is_none();
        let uniform = vec![1.0; n];
        let fail = || "no prior intensity gives positive definite normal equations".to_string();
        let (mut log10, nll) = self.search(&ys, &uniform, profile).ok_or_else(fail)?;
        let mut noise = NoiseShape::Uniform;
        let mut weights = uniform;
        // From the data, the rounding of the printed digits competes: σ_k ∝ the
        // rounding step of sample k, when the samples were written to a fixed number
        // of significant digits; the likelier shape wins.
        if profile {
            if let Some((digits, rounding)) = rounding_weights(y) {
                if let Some((l, v)) = self.search(&ys, &rounding, true) {
                    if v < nll {
                        (log10, noise, weights) = (l, NoiseShape::Rounding { digits }, rounding);
                    }
                }
            }
        }
        let lambda = 10f64.powf(log10);
        let trial = self
            .trial(&ys, &weights, lambda, profile)
            .ok_or("the chosen prior intensity lost positive definiteness")?;
        // σ in units of `unit`: 1 when given, the profile's estimate otherwise.
        let s = if profile {
            (trial.cost / (n - D) as f64).sqrt()
        } else {
            1.0
        };
        // Samples on a cubic to round-off (a coordinate held still, a ramp) have no
        // scatter to measure: σ is then the round-off level of the samples.
        let floor = 1e-13 * scale.max(1.0);
        if profile && !(s * unit > floor) {
            let mut fit = self.fit(y, dt, Some(floor))?;
            fit.from_data = true;
            return Ok(fit);
        }
        if !s.is_finite() {
            return Err("the samples' scatter is not a finite number".into());
        }
        let mut residual = 0.0;
        let mut worst = (0.0f64, 0);
        for k in 0..n {
            let r = (self.x[k * D] - ys[k]) * unit;
            residual += r * r;
            // σ_k = σ ρ_k = unit · s / √weight_k.
            let z = r.abs() * weights[k].sqrt() / (unit * s);
            if z > worst.0 {
                worst = (z, k);
            }
        }
        if self.at.is_empty() {
            self.chol.inverse_diagonal_blocks(&mut self.cov);
        } else {
            self.chol
                .inverse_tridiagonal_blocks(&mut self.cov, &mut self.cov_lower);
            self.interpolate_to_grid(lambda);
        }
        // Back to physical units: x_i · unit / dt^i, covariances alike, times s².
        let to_physical: [f64; D] = std::array::from_fn(|i| unit / dt.powi(i as i32));
        for k in 0..n {
            for (i, f) in to_physical.iter().enumerate() {
                self.x[k * D + i] *= f;
            }
            let cov = &mut self.cov[k];
            for i in 0..D {
                for j in 0..D {
                    cov[i * D + j] *= to_physical[i] * to_physical[j] * s * s;
                }
            }
        }
        let sigma = unit * s;
        Ok(ColumnFit {
            sigma,
            from_data: profile,
            noise,
            intensity: lambda * sigma * sigma / dt.powi(7),
            residual_rms: (residual / n as f64).sqrt(),
            worst_residual: worst,
        })
    }
}

/// Samples written to a fixed number of significant digits: that number and the
/// weights 1/ρ_k², ρ_k the rounding step of sample k relative to the largest
/// (10^(e_k + 1 − digits), e_k the sample's decimal exponent), kept within 1e-4 of it
/// so that the smallest samples do not dominate. None for samples with 15 digits or
/// more (not visibly rounded) or without a nonzero sample.
fn rounding_weights(y: &[f64]) -> Option<(usize, Vec<f64>)> {
    let digits = y.iter().map(|v| significant_digits(*v)).max()?;
    if digits == 0 || digits >= 15 {
        return None;
    }
    let step = |v: f64| 10f64.powi(v.abs().log10().floor() as i32 + 1 - digits as i32);
    let largest = y
        .iter()
        .filter(|v| **v != 0.0)
        .map(|v| step(*v))
        .fold(0.0f64, f64::max);
    let weights = y
        .iter()
        .map(|v| {
            let rho = if *v == 0.0 {
                1e-4
            } else {
                (step(*v) / largest).max(1e-4)
            };
            1.0 / (rho * rho)
        })
        .collect();
    Some((digits, weights))
}

/// Significant digits of the shortest decimal that reads back as `v` (0 for 0).
fn significant_digits(v: f64) -> usize {
    if v == 0.0 || !v.is_finite() {
        return 0;
    }
    let text = format!("{:e}", v.abs());
    let mantissa = text.split('e').next().unwrap_or("");
    mantissa.chars().filter(|c| c.is_ascii_digit()).count()
}
