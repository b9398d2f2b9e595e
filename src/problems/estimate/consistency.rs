//! Whether the reported uncertainty is honest: the normalized innovation squared
//! (NIS) of every reading, against the χ² bounds its mean must fall within.

use crate::graph::{ChainGraph, Factor, Key, Layout, Term, Workspace};
use nalgebra::{DMatrix, DVector};
use std::collections::HashMap;

/// Running NIS statistics of a run.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Nis {
    /// Σ NIS over the readings' steps.
    pub sum: f64,
    /// Steps with readings counted.
    pub count: usize,
    /// Σ of the readings' dimensions (the χ² degrees of freedom of `sum`).
    pub dof: usize,
    /// Whether the innovations are white, as a consistent estimator's are.
    pub whiteness: Whiteness,
}

/// The lag-one autocorrelation of each sensor's normalized innovations, pooled over
/// the sensors: near zero for a model whose errors the process noise describes, and
/// far above its bound where the readings keep disagreeing the same way step after
/// step (a bias, in the dynamics or in a sensor's model).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Whiteness {
    /// Each sensor's last normalized innovation, by its factor's name.
    last: HashMap<String, Vec<f64>>,
    /// Σ eₖ·eₖ₋₁, Σ eₖ₋₁², Σ eₖ² over the pairs of successive readings of a sensor.
    products: f64,
    before: f64,
    after: f64,
    /// The pairs counted.
    pub pairs: usize,
}

impl Whiteness {
    fn add(&mut self, sensor: &str, e: Vec<f64>) {
        let Some(prev) = self.last.get_mut(sensor) else {
            self.last.insert(sensor.to_string(), e);
            return;
        };
        if prev.len() == e.len() {
            for (a, b) in prev.iter().zip(&e) {
                self.products += a * b;
                self.before += a * a;
                self.after += b * b;
                self.pairs += 1;
            }
        }
        *prev = e;
    }

    /// The pooled lag-one autocorrelation, if any pair was counted.
    pub fn lag_one(&self) -> Option<f64> {
        let d = (self.before * self.after).sqrt();
        (self.pairs > 0 && d > 0.0).then(|| self.products / d)
    }

    /// The 95 % bound of |lag-one autocorrelation| of white innovations.
    pub fn bound(&self) -> f64 {
        1.959964 / (self.pairs.max(1) as f64).sqrt()
    }
}

impl Nis {
    /// The mean NIS per step with readings.
    pub fn mean(&self) -> f64 {
        if self.count == 0 {
            f64::NAN
        } else {
            self.sum / self.count as f64
        }
    }

    /// The mean a consistent estimator's NIS has: the readings' mean dimension.
    pub fn expected(&self) -> f64 {
        self.dof as f64 / self.count.max(1) as f64
    }

    /// The 95 % two-sided bounds of the mean NIS of a consistent estimator: Σ NIS is
    /// χ² with `dof` degrees of freedom (Wilson–Hilferty's normal approximation of
    /// its quantiles, accurate to a fraction of a percent from a few degrees of
    /// freedom on).
    pub fn bounds(&self) -> (f64, f64) {
        let k = self.dof as f64;
        let c = self.count.max(1) as f64;
        let q = |z: f64| {
            let a = 2.0 / (9.0 * k);
            k * (1.0 - a + z * a.sqrt()).powi(3).max(0.0)
        };
        (q(-1.959964) / c, q(1.959964) / c)
    }

    /// Whether the mean NIS is within its 95 % bounds.
    pub fn consistent(&self) -> bool {
        let (lo, hi) = self.bounds();
        let m = self.mean();
        self.count > 0 && m >= lo && m <= hi
    }

    /// The NIS of the readings `terms` at a step whose estimate `x` (its block) has
    /// the filtered covariance `p` (s × s, row-major), added to the statistics: with
    /// the residual r = h(x̂) − y after the update, r = R S⁻¹ ν, so that
    /// νᵀS⁻¹ν = rᵀ(R − HPHᵀ)⁻¹r. Returns it, or `None` where R − HPHᵀ is not
    /// positive definite (the readings are explained beyond their noise).
    pub fn add(
        &mut self,
        layout: &Layout,
        terms: &[(usize, Term)],
        x: &[f64],
        p: &[f64],
        t: f64,
        ws: &mut Workspace,
    ) -> Option<f64> {
        let s = layout.size();
        let mut rows: Vec<(f64, f64, Vec<f64>)> = Vec::new();
        let mut sensors: Vec<(&str, usize)> = Vec::new();
        for (_, term) in terms {
            let (Term::Soft(factor, noise), true) =
                (term, term.factor().keys().iter().all(|k| k.lag == 0))
            else {
                continue;
            };
            let (r, h) = step_rows(layout, factor.as_ref(), t, x, ws)?;
            sensors.push((factor.name(), r.len()));
            for (i, ri) in r.iter().enumerate() {
                rows.push((*ri, 1.0 / noise.weight(i), h[i * s..(i + 1) * s].to_vec()));
            }
        }
        if rows.is_empty() {
            return None;
        }
        let m = rows.len();
        let h = DMatrix::from_fn(m, s, |i, j| rows[i].2[j]);
        let pm = DMatrix::from_row_slice(s, s, p);
        let mut post = -(&h * pm * h.transpose());
        for (i, row) in rows.iter().enumerate() {
            post[(i, i)] += row.1 * row.1;
        }
        let r = DVector::from_fn(m, |i, _| rows[i].0);
        let diagonal = post.diagonal();
        let chol = post.cholesky()?;
        let nis = r.dot(&chol.solve(&r));
        if !nis.is_finite() {
            return None;
        }
        self.sum += nis;
        self.count += 1;
        self.dof += m;
        let mut i = 0;
        for (name, dim) in sensors {
            let e = (i..i + dim)
                .map(|j| r[j] / diagonal[j].max(f64::MIN_POSITIVE).sqrt())
                .collect();
            self.whiteness.add(name, e);
            i += dim;
        }
        Some(nis)
    }
}

/// A factor of one step (its keys all at lag 0) at the step's state `x`: its
/// residual, and its Jacobian on the step's unknowns (dim × `layout.size()`,
/// row-major). `None` where it cannot be evaluated there.
pub(super) fn step_rows(
    layout: &Layout,
    factor: &dyn Factor,
    t: f64,
    x: &[f64],
    ws: &mut Workspace,
) -> Option<(Vec<f64>, Vec<f64>)> {
    let (s, dim, keys) = (layout.size(), factor.dim(), factor.keys());
    let slot = |k: &Key| layout.slot(k.kind).unwrap_or((0, 0));
    let inputs: Vec<&[f64]> = keys
        .iter()
        .map(|k| {
            let (o, d) = slot(k);
            &x[o..o + d]
        })
        .collect();
    let mut r = vec![0.0; dim];
    let mut jac: Vec<Vec<f64>> = (0..keys.len())
        .map(|a| vec![0.0; dim * factor.size(a)])
        .collect();
    factor
        .evaluate(t, &inputs, &mut r, Some(&mut jac), ws)
        .ok()?;
    let mut h = vec![0.0; dim * s];
    for (a, k) in keys.iter().enumerate() {
        let (o, d) = slot(k);
        for i in 0..dim {
            for c in 0..d {
                h[i * s + o + c] += jac[a][i * d + c];
            }
        }
    }
    Some((r, h))
}

/// The NIS of the readings at run step `run_step` of `graph` (see [`Nis::add`]).
pub fn readings_at(graph: &ChainGraph, run_step: usize) -> &[(usize, Term)] {
    graph.terms_at(run_step)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bounds_hold_the_chi_square_mean() {
        // 1000 scalar readings: Σ NIS ~ χ²(1000), mean 1 ± 1.96·√(2/1000).
        let nis = Nis {
            sum: 1000.0,
            count: 1000,
            dof: 1000,
            ..Nis::default()
        };
        let (lo, hi) = nis.bounds();
        assert!((lo - 0.91426).abs() < 1e-3, "{lo}");
        assert!((hi - 1.08953).abs() < 1e-3, "{hi}");
        assert!(nis.consistent());
        let off = Nis { sum: 1200.0, ..nis };
        assert!(!off.consistent());
    }

    #[test]
    fn whiteness_tells_white_innovations_from_correlated_ones() {
        // A reproducible white sequence (a hashed counter, uniform in [−1, 1]) and
        // the same through a first-order filter (autocorrelation 0.8), read by two
        // sensors, one of them every other step.
        let white_at = |k: u64| {
            let mut x = k.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ 0xD1B5_4A32_D192_ED03;
            x ^= x >> 31;
            x = x.wrapping_mul(0xBF58_476D_1CE4_E5B9);
            x ^= x >> 29;
            (x >> 11) as f64 / (1u64 << 52) as f64 - 1.0
        };
        let (mut white, mut correlated) = (Whiteness::default(), Whiteness::default());
        let mut ar = 0.0;
        for k in 0..4000u64 {
            ar = 0.8 * ar + white_at(k);
            white.add("a", vec![white_at(k)]);
            correlated.add("a", vec![ar]);
            if k % 2 == 0 {
                white.add("b", vec![white_at(k + 10_000), white_at(k + 20_000)]);
            }
        }
        let r = white.lag_one().unwrap();
        assert!(r.abs() <= white.bound(), "{r} against ±{}", white.bound());
        assert_eq!(white.pairs, 3999 + 2 * 1999);
        let r = correlated.lag_one().unwrap();
        assert!((r - 0.8).abs() < 0.05, "{r}");
    }
}
