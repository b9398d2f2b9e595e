//! Which coordinates the readings leave undetermined ([`Determination`]): no sensor
//! observes them, directly or through the model, so their σ stays of the order of
//! the prior's on the start over most of the run, or, where the start is known
//! better than the readings could tell it, grows over the run as the model carries
//! the start's prior along. Their estimates are the prior's guess carried along by
//! the model, not a measurement.

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
/// Where the start's prior is tighter than the run's σ: the σ over the run's last
/// tenth, as a multiple of its median over the run, above which it grows (a σ the
/// readings hold stays level; one the model carries grows as a random walk's,
/// about 2.6 times by then).
const GROWS: f64 = 2.0;

/// A coordinate the readings leave undetermined.
#[derive(Debug, Clone, PartialEq)]
pub struct Undetermined {
    /// Its index in q.
    pub coordinate: usize,
    /// Its σ averaged over the run's final estimates.
    pub mean_sd: f64,
    /// σ of the prior on its start.
    pub prior: f64,
    /// Where its start is known better than its σ over the run: its σ at the end
    /// of the run (its σ grows from the start's prior).
    pub grows_to: Option<f64>,
}

/// The watch over the final estimates of the coordinates `watched` (indices into q).
#[derive(Debug, Clone, Default)]
pub struct Determination {
    watched: Vec<(usize, f64)>,
    above: Vec<usize>,
    sums: Vec<f64>,
    steps: usize,
    /// Every step's σ of each watched coordinate.
    sds: Vec<Vec<f64>>,
}

impl Determination {
    /// Watches `coordinates`, whose start priors have σ `priors` (indexed by q).
    pub fn new(coordinates: &[usize], priors: &[f64]) -> Self {
        Determination {
            watched: coordinates.iter().map(|&c| (c, priors[c])).collect(),
            above: vec![0; coordinates.len()],
            sums: vec![0.0; coordinates.len()],
            steps: 0,
            sds: vec![Vec::new(); coordinates.len()],
        }
    }

    /// One final estimate: its covariance, row-major over the step's `size`
    /// variables (q first).
    pub fn add(&mut self, covariance: &[f64], size: usize) {
        self.steps += 1;
        for (w, &(c, prior)) in self.watched.iter().enumerate() {
            let sd = covariance[c * size + c].max(0.0).sqrt();
            self.sums[w] += sd;
            self.sds[w].push(sd);
            if sd > UNDETERMINED_FRACTION * prior {
                self.above[w] += 1;
            }
        }
    }

    /// The coordinates whose σ stayed above [`UNDETERMINED_FRACTION`] of the prior's
    /// at more than half the steps; where that prior is tighter than their mean σ
    /// over the run, those whose σ also grows ([`GROWS`]).
    pub fn undetermined(&self) -> Vec<Undetermined> {
        self.watched
            .iter()
            .enumerate()
            .filter(|&(w, _)| 2 * self.above[w] > self.steps)
            .filter_map(|(w, &(coordinate, prior))| {
                let mean_sd = self.sums[w] / self.steps as f64;
                let grows_to = if mean_sd > prior {
                    Some(self.growth(&self.sds[w])?)
                } else {
                    None
                };
                Some(Undetermined {
                    coordinate,
                    mean_sd,
                    prior,
                    grows_to,
                })
            })
            .collect()
    }

    /// The σ at the end of the run where σ over its last tenth is [`GROWS`] times
    /// its median over the run or more.
    fn growth(&self, sds: &[f64]) -> Option<f64> {
        let last = &sds[sds.len() - sds.len().div_ceil(10)..];
        let mut sorted = sds.to_vec();
        sorted.sort_by(f64::total_cmp);
        let median = sorted[sorted.len() / 2];
        let end = last.iter().sum::<f64>() / last.len() as f64;
        (end >= GROWS * median).then(|| sds[sds.len() - 1])
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
        assert_eq!(u[0].grows_to, None);
        // Above the fraction at exactly half the steps: determined.
        let mut d = Determination::new(&[0], &[1.0]);
        d.add(&[0.04], 1);
        d.add(&[1e-6], 1);
        assert!(d.undetermined().is_empty());
    }

    #[test]
    fn a_start_known_better_than_the_run_counts_only_where_its_sigma_grows() {
        // The start's prior 1e-6, the run's σ far above it: level (the readings hold
        // it), determined; growing as t^1.5 (the model carries the start), not.
        let level = |k: usize| 1e-4 * (1.0 + 0.1 * (k as f64).sin());
        let walk = |k: usize| 1e-6 + 1e-5 * (k as f64).powf(1.5);
        for (sd, undetermined) in [(&level as &dyn Fn(usize) -> f64, false), (&walk, true)] {
            let mut d = Determination::new(&[0], &[1e-6]);
            for k in 0..200 {
                d.add(&[sd(k) * sd(k)], 1);
            }
            let u = d.undetermined();
            assert_eq!(u.len(), usize::from(undetermined));
            if let Some(u) = u.first() {
                assert!((u.grows_to.unwrap() - walk(199)).abs() < 1e-12);
            }
        }
    }
}
