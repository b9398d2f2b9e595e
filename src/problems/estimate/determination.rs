//! Which coordinates the readings leave undetermined ([`Determination`]): no sensor
//! observes them, directly or through the model, so their σ stays of the order of
//! the prior's on the start over most of the run (of the default prior's, where the
//! start is known better: a σ the readings hold is far below it, one the model
//! carries from the start grows to it). Their estimates are the prior's guess
//! carried along by the model, not a measurement.

use super::options::DEFAULT_INITIAL_SIGMA;

/// The coordinates whose σ an estimate watches (for undetermined coordinates, and
/// for when a growing window's oldest step has caught up): the motion's own degrees
/// of freedom where the scene names them (`independent:`), else every q.
pub fn watched_coordinates(model: &crate::model::Model) -> Vec<usize> {
    if model.independent.is_empty() {
        (0..model.n()).collect()
    } else {
        model.independent.clone()
    }
}

/// A coordinate's σ counts as undetermined above this fraction of its prior's.
pub const UNDETERMINED_FRACTION: f64 = 0.1;

/// A coordinate the readings leave undetermined.
#[derive(Debug, Clone, PartialEq)]
pub struct Undetermined {
    /// Its index in q.
    pub coordinate: usize,
    /// Its σ averaged over the run's final estimates.
    pub mean_sd: f64,
    /// σ of the prior on its start.
    pub prior: f64,
    /// The σ it was judged against: the prior's, or the default prior's where the
    /// start is known better.
    pub against: f64,
}

/// The watch over the final estimates of the coordinates `watched` (indices into q).
#[derive(Debug, Clone, Default)]
pub struct Determination {
    watched: Vec<(usize, f64)>,
    above: Vec<usize>,
    sums: Vec<f64>,
    steps: usize,
}

impl Determination {
    /// Watches `coordinates`, whose start priors have σ `priors` (indexed by q).
    pub fn new(coordinates: &[usize], priors: &[f64]) -> Self {
        Determination {
            watched: coordinates.iter().map(|&c| (c, priors[c])).collect(),
            above: vec![0; coordinates.len()],
            sums: vec![0.0; coordinates.len()],
            steps: 0,
        }
    }

    /// One final estimate: its covariance, row-major over the step's `size`
    /// variables (q first).
    pub fn add(&mut self, covariance: &[f64], size: usize) {
        self.steps += 1;
        for (w, &(c, prior)) in self.watched.iter().enumerate() {
            let sd = covariance[c * size + c].max(0.0).sqrt();
            self.sums[w] += sd;
            if sd > UNDETERMINED_FRACTION * prior.max(DEFAULT_INITIAL_SIGMA) {
                self.above[w] += 1;
            }
        }
    }

    /// The coordinates whose σ stayed above [`UNDETERMINED_FRACTION`] of the prior's
    /// (at least the default prior's) at more than half the steps.
    pub fn undetermined(&self) -> Vec<Undetermined> {
        self.watched
            .iter()
            .enumerate()
            .filter(|&(w, _)| 2 * self.above[w] > self.steps)
            .map(|(w, &(coordinate, prior))| Undetermined {
                coordinate,
                mean_sd: self.sums[w] / self.steps as f64,
                prior,
                against: prior.max(DEFAULT_INITIAL_SIGMA),
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_sigma_near_its_prior_over_most_steps_is_undetermined() {
        // Two coordinates of a 2-variable step, priors 1 and 0.5.
        let mut d = Determination::new(&[0, 1], &[1.0, 0.5]);
        let cov = |a: f64, b: f64| vec![a * a, 0.0, 0.0, b * b];
        for _ in 0..6 {
            d.add(&cov(0.4, 0.01), 2);
        }
        for _ in 0..4 {
            d.add(&cov(0.01, 0.01), 2);
        }
        let u = d.undetermined();
        assert_eq!(u.len(), 1);
        assert_eq!(u[0].coordinate, 0);
        assert!((u[0].mean_sd - (6.0 * 0.4 + 4.0 * 0.01) / 10.0).abs() < 1e-12);
        assert_eq!(u[0].prior, 1.0);
        assert_eq!(u[0].against, 1.0);
        // Above the fraction at exactly half the steps: determined.
        let mut d = Determination::new(&[0], &[1.0]);
        d.add(&[0.04], 1);
        d.add(&[1e-6], 1);
        assert!(d.undetermined().is_empty());
    }

    #[test]
    fn a_start_known_better_than_the_default_is_judged_against_the_default() {
        // The start's prior 1e-6: a σ the readings hold (1e-4, growing toward the
        // run's end as a chaotic motion's does) is determined; one near the default
        // prior's over most of the run is not, and is named against the default.
        let held = |k: usize| 1e-6 + 1e-4 * (k as f64 / 200.0).powi(3);
        let carried = |k: usize| 1e-6 + 0.5 * (k as f64 / 20.0).min(1.0);
        for (sd, undetermined) in [(&held as &dyn Fn(usize) -> f64, false), (&carried, true)] {
            let mut d = Determination::new(&[0], &[1e-6]);
            for k in 0..200 {
                d.add(&[sd(k) * sd(k)], 1);
            }
            let u = d.undetermined();
            assert_eq!(u.len(), usize::from(undetermined));
            if let Some(u) = u.first() {
                assert_eq!((u.prior, u.against), (1e-6, DEFAULT_INITIAL_SIGMA));
            }
        }
    }
}
