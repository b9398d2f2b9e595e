//! Whether a step may be taken as a square system: the dynamics kernel's distance
//! to a rank loss of Φ_q, s = (tr G⁻¹)^(−1/2), from G's sparse Cholesky factor by
//! selected inversion, with G's pattern analysed once per mechanism.

use crate::dynamics::DynamicsKernel;
use crate::linalg::sparse::InverseTrace;
use crate::model::{Model, MAX_LOCAL};

/// s must pass [`DynamicsKernel::REGULAR_ABOVE`] by this factor: the kernel
/// computes it densely, in another order of rounding.
const REGULAR_MARGIN: f64 = 1.001;

/// G's structure over a mechanism's active constraints.
#[derive(Clone)]
pub(in crate::problems::forward) struct Regularity {
    /// The lower triangle of G = ÂÂᵀ: per entry the pair of active rows (i, j ≤ i)
    /// and the pairs of their local coordinates that are one coordinate of q.
    entries: Vec<GramEntry>,
}

/// The scratch of the regularity test: the rows' gradients, G and tr G⁻¹.
pub(in crate::problems::forward) struct GramWork {
    /// Each active row's gradient, the entries of AAᵀ and the row norms.
    gradients: Vec<[f64; MAX_LOCAL]>,
    dots: Vec<f64>,
    norms: Vec<f64>,
    /// G's lower triangle, entry by entry as in `entries`.
    values: Vec<f64>,
    trace: InverseTrace,
}

impl Regularity {
    /// G's pattern for `model`.
    pub(in crate::problems::forward) fn new(model: &Model) -> Regularity {
        Regularity {
            entries: gram_entries(model),
        }
    }

    /// The scratch of [`Regularity::regular`] for `model`, with G's symbolic
    /// analysis; `None` where that fails.
    pub(in crate::problems::forward) fn work(&self, model: &Model) -> Option<GramWork> {
        let ma = model.active.len();
        let lower: Vec<(usize, usize)> = self.entries.iter().map(|e| (e.0, e.1)).collect();
        Some(GramWork {
            gradients: vec![[0.0; MAX_LOCAL]; ma],
            dots: vec![0.0; self.entries.len()],
            norms: vec![0.0; ma],
            values: vec![0.0; self.entries.len()],
            trace: InverseTrace::new(ma, &lower)?,
        })
    }

    /// Whether the active rows of Φ_q at q are far enough from a rank loss that the
    /// dynamics kernel uses the plain augmented system: its measure
    /// s = (tr G⁻¹)^(−1/2) at least [`DynamicsKernel::REGULAR_ABOVE`] (with a
    /// margin for rounding), tr G⁻¹ from the sparse Cholesky factor of G.
    pub(super) fn regular(&self, model: &Model, q: &[f64], gram: &mut GramWork) -> bool {
        self.distance_to_rank_loss(model, q, gram) >= REGULAR_MARGIN * DynamicsKernel::REGULAR_ABOVE
    }

    /// The dynamics kernel's s at q (0 where G does not factor).
    pub(in crate::problems::forward) fn distance_to_rank_loss(
        &self,
        model: &Model,
        q: &[f64],
        gram: &mut GramWork,
    ) -> f64 {
        self.measure(model, q, gram, |trace, _| trace.recip().sqrt())
    }

    /// The distance to a rank loss of the rows nearest one, (max (G⁻¹)ᵢᵢ)^(−1/2) at q
    /// (0 where G does not factor): the distance of one row to the span of the others.
    /// s sums G⁻¹ over every row, so that it falls with the number of loops losing a
    /// rank at once; this one does not add up rows on disjoint parts (on a chain of
    /// loops sharing bodies it still falls, more slowly).
    pub(in crate::problems::forward) fn nearest_rank_loss(
        &self,
        model: &Model,
        q: &[f64],
        gram: &mut GramWork,
    ) -> f64 {
        self.measure(model, q, gram, |_, inverse| {
            inverse.largest_diagonal().recip().sqrt()
        })
    }

    /// A distance to a rank loss at q from tr G⁻¹ and G's inverse (∞ without active
    /// rows, 0 where G does not factor).
    fn measure(
        &self,
        model: &Model,
        q: &[f64],
        gram: &mut GramWork,
        distance: impl Fn(f64, &InverseTrace) -> f64,
    ) -> f64 {
        if model.active.is_empty() {
            return f64::INFINITY;
        }
        match self.inverse_trace(model, q, gram) {
            Some(trace) => distance(trace, &gram.trace),
            None => 0.0,
        }
    }

    /// The norm of each active row's gradient at q, |∇Φᵢ(q)| (a coordinate a row
    /// holds twice adds up), in the order of `model.active`.
    pub(super) fn row_norms<'a>(
        &self,
        model: &Model,
        q: &[f64],
        gram: &'a mut GramWork,
    ) -> &'a [f64] {
        self.rows(model, q, gram);
        &gram.norms
    }

    /// tr G⁻¹ at q, G's inverse left in `gram`; `None` where G does not factor.
    fn inverse_trace(&self, model: &Model, q: &[f64], gram: &mut GramWork) -> Option<f64> {
        if !self.rows(model, q, gram) {
            return None;
        }
        for ((value, (i, j, _)), dot) in gram.values.iter_mut().zip(&self.entries).zip(&gram.dots) {
            *value = dot / (gram.norms[*i] * gram.norms[*j]);
        }
        gram.trace.trace(&gram.values)
    }

    /// The active rows' gradients at q, the entries of AAᵀ and the row norms, into
    /// `gram`; whether every norm is positive and finite.
    fn rows(&self, model: &Model, q: &[f64], gram: &mut GramWork) -> bool {
        let GramWork {
            gradients,
            dots,
            norms,
            ..
        } = gram;
        let mut u = [0.0; MAX_LOCAL];
        for (row, &k) in model.active.iter().enumerate() {
            let c = &model.constraints[k];
            c.gather(q, &mut u);
            c.equation.gradient(&u, &mut gradients[row]);
        }
        // AAᵀ over the shared coordinates (a coordinate a row holds twice adds up),
        // the row norms from its diagonal, then G.
        for ((i, j, shared), dot) in self.entries.iter().zip(dots.iter_mut()) {
            *dot = shared
                .iter()
                .map(|&(p, s)| gradients[*i][p] * gradients[*j][s])
                .sum();
        }
        for ((i, j, _), dot) in self.entries.iter().zip(dots.iter()) {
            if i == j {
                norms[*i] = dot.sqrt();
            }
        }
        norms.iter().all(|v| *v > 0.0 && v.is_finite())
    }
}

/// The most steps between two measures of s.
const REFRESH: usize = 8;

/// When s, measured along a run, is measured again: where it may have come near a
/// rank loss since it was last (carried on at four times its last change a step),
/// and every [`REFRESH`] steps; between, far from any, the last measure stands.
#[derive(Debug, Clone, Copy, Default)]
pub(in crate::problems::forward) struct Remeasure {
    /// The last s measured (0 before any: measure) and its change a step since
    /// the measure before.
    measured: f64,
    change: f64,
    /// Steps since.
    skipped: usize,
}

impl Remeasure {
    /// s far enough from a rank loss that it need not be measured every step.
    pub(in crate::problems::forward) const FAR: f64 = 1e-2;

    /// The last measure, where it stands for this step (counted as skipped);
    /// `None` where s is to be measured.
    pub(in crate::problems::forward) fn standing(&mut self) -> Option<f64> {
        if self.least() > Remeasure::FAR && self.skipped < REFRESH {
            self.skipped += 1;
            Some(self.measured)
        } else {
            None
        }
    }

    /// The least s the next step may reach: the last measure carried on at four
    /// times its last change a step (0 before any measure).
    pub(in crate::problems::forward) fn least(&self) -> f64 {
        self.measured - 4.0 * self.change.abs() * (self.skipped + 1) as f64
    }

    /// The last measure where it was taken at the step before (`None` where it
    /// was not, or there is none).
    pub(in crate::problems::forward) fn fresh(&self) -> Option<f64> {
        (self.skipped == 0 && self.measured > 0.0).then_some(self.measured)
    }

    /// Records s as measured at this step.
    pub(in crate::problems::forward) fn measured(&mut self, s: f64) {
        let steps = (self.skipped + 1) as f64;
        self.change = (s - self.measured) / steps;
        self.measured = s;
        self.skipped = 0;
    }

    /// The last measure and its change a step.
    pub(in crate::problems::forward) fn last(&self) -> (f64, f64) {
        (self.measured, self.change)
    }
}

/// An entry of G's lower triangle: rows (i, j ≤ i) and the pairs of their local
/// coordinates that are one coordinate of q.
type GramEntry = (usize, usize, Vec<(usize, usize)>);

/// The lower triangle of G = ÂÂᵀ over the active rows: (i, j ≤ i, the local
/// coordinate pairs of rows j and i that are one coordinate of q).
fn gram_entries(model: &Model) -> Vec<GramEntry> {
    let ma = model.active.len();
    let mut rows_of = vec![Vec::new(); model.n()];
    for (row, &k) in model.active.iter().enumerate() {
        for (p, ip) in model.constraints[k].local_index().iter().enumerate() {
            if let Some(ip) = *ip {
                rows_of[ip].push((row, p));
            }
        }
    }
    let mut pairs: Vec<(usize, usize, usize, usize)> = Vec::new();
    for list in &rows_of {
        for &(i, p) in list {
            for &(j, s) in list {
                if j <= i {
                    pairs.push((i, j, p, s));
                }
            }
        }
    }
    pairs.sort_unstable();
    let mut entries: Vec<GramEntry> = Vec::new();
    for (i, j, p, s) in pairs {
        match entries.last_mut() {
            Some(last) if last.0 == i && last.1 == j => last.2.push((p, s)),
            _ => entries.push((i, j, vec![(p, s)])),
        }
    }
    // Every row's diagonal, even one whose gradient touches no free coordinate.
    let mut diagonal = vec![false; ma];
    for e in &entries {
        diagonal[e.0] |= e.0 == e.1;
    }
    for (i, _) in diagonal.iter().enumerate().filter(|(_, d)| !**d) {
        entries.push((i, i, Vec::new()));
    }
    entries
}
