//! How well the constraints determine the coordinates near a configuration: the
//! distance to rank loss of Φ_q restricted to the dependent coordinates
//! ([`Determinacy`], which a run in independent coordinates watches to switch sets or
//! stop ahead of a singular configuration), and the scale-free σ_r/σ₁ of Φ_q itself
//! (`constraint_conditioning`) that a failure message quotes.

use crate::linalg::dense;
use crate::linalg::sparse::InverseTrace;
use crate::model::{Model, PointSlot, MAX_LOCAL};

/// Active constraints from which s is taken from G's sparse Cholesky factor by
/// selected inversion (linear in a chain's length) instead of the dense factor and
/// inverse (cubic). The trace is the same to rounding.
const SPARSE_DISTANCE_FROM: usize = 48;

/// A configuration ahead where the independent coordinates z stop determining the
/// other coordinates' velocities: Φ_q restricted to the dependent coordinates
/// (square, m_active × (n − f)) loses a rank, so the matrix R of q̇ = R ż does not
/// exist there and the graph in independent coordinates is ill-posed. Found from its
/// distance to rank loss s ([`Determinacy`]) falling below
/// [`Determinacy::STOP_BELOW`].
#[derive(Debug, Clone, PartialEq)]
pub struct SingularConfiguration {
    /// Where s extrapolates to 0, linearly from this step and the one before (this
    /// step's time where s was not falling).
    pub t_singular: f64,
    /// s at the step where the run stopped.
    pub distance: f64,
    /// The rank the dependent block keeps there (singular values of its normalized
    /// rows above 10 s) and its full rank (the number of dependent coordinates).
    pub rank: usize,
    pub full_rank: usize,
    pub independent: Vec<String>,
    pub dependent: Vec<String>,
}

/// How well the independent coordinates determine the others at q, without
/// allocating: the distance to rank loss s = (tr G⁻¹)^(−1/2) of Φ_q restricted to
/// the dependent coordinates, G = D̂D̂ᵀ with D̂ its active rows normalized.
/// √(λ_min(G)/m) ≤ s ≤ √λ_min(G): s is the smallest singular value of D̂ to within a
/// factor √m, and 0 where a rank is lost.
pub struct Determinacy {
    /// The independent coordinates in use, and the others.
    independent: Vec<usize>,
    dependent: Vec<usize>,
    jac: Vec<f64>,
    column_norms: Vec<f64>,
    rows: Vec<f64>,
    chol: Vec<f64>,
    /// One column of L⁻¹ at a time (see [`dense::inverse_trace`]).
    column: Vec<f64>,
    /// Per row of `rows`, the columns [start, end) outside which it is 0; per row
    /// of L, its first nonzero column.
    spans: Vec<[usize; 2]>,
    first: Vec<usize>,
    /// G's lower triangle, for the sparse route: its entries (rows i ≥ j) and their
    /// values, and tr G⁻¹ with the symbolic analysis of the entries it was made for
    /// (the same until the dependent columns change).
    lower: Vec<(usize, usize)>,
    values: Vec<f64>,
    trace: Option<(Vec<(usize, usize)>, InverseTrace)>,
    /// The sparse route's dependent columns, and per column the (active row,
    /// normalized value) of its nonzeros.
    mask: Vec<bool>,
    incidence: Vec<Vec<(usize, f64)>>,
}

impl Determinacy {
    /// Where the coordinates in use determine the others less well than this and
    /// worse from step to step (or will at the next step, extrapolated), a run in
    /// independent coordinates looks for a better set (`docs/accuracy.md`,
    /// "Independent coordinates that re-select themselves").
    pub const SEARCH_BELOW: f64 = 5e-3;

    /// A run switches to the best set where it determines the others this many times
    /// better than the set in use (so that it does not switch back at once).
    pub const SWITCH_GAIN: f64 = 1.5;

    /// A solve in independent coordinates that fails while s, falling, extrapolates
    /// to 0 within this many steps, and no set of coordinates does materially better
    /// ([`Determinacy::SWITCH_GAIN`]), is reported as the singular configuration
    /// ahead: solves fail some steps before the flat point, above
    /// [`Determinacy::STOP_BELOW`]. A failure where s is already below
    /// [`Determinacy::SEARCH_BELOW`] is attributed whatever the number of steps: at
    /// fine steps, steps are no measure of the distance (`docs/dc-stall.md`,
    /// "8. Independent coordinates that stop determining the others").
    pub const ATTRIBUTE_WITHIN: f64 = 20.0;

    /// ... and only where s is below this: a violent transient at a coarse step makes
    /// s fall fast in a mechanism that has no singular configuration, and the
    /// extrapolation alone would name one.
    pub const ATTRIBUTE_BELOW: f64 = 0.05;

    /// A run in independent coordinates stops where even the best set's s falls
    /// below this: Φ_q itself is about to lose a rank, and no choice of coordinates
    /// helps. It is crossed before the solves start to fail, a step or two ahead of
    /// the flat point; at coarse steps, where s falls past it in one step, the run
    /// stops where s's linear extrapolation crosses 0 within the next step.
    pub const STOP_BELOW: f64 = 2.5e-3;

    /// How well `independent` (indices into q) determines the other coordinates,
    /// with the coordinates' scales taken at the configuration `q0` (the start of
    /// the run or segment that uses them).
    pub fn new(model: &Model, independent: &[usize], q0: &[f64]) -> Self {
        let dependent = complement(model.n(), independent);
        let ma = model.active.len();
        let mut det = Determinacy {
            jac: vec![0.0; model.m() * model.n()],
            column_norms: vec![1.0; model.n()],
            rows: vec![0.0; ma * dependent.len()],
            chol: vec![0.0; ma * ma],
            column: vec![0.0; ma],
            spans: vec![[0, 0]; ma],
            first: vec![0; ma],
            lower: Vec::new(),
            values: Vec::new(),
            trace: None,
            mask: vec![false; model.n()],
            incidence: vec![Vec::new(); model.n()],
            independent: independent.to_vec(),
            dependent,
        };
        det.set_column_scales(model, q0);
        det
    }

    /// s at q: 0 where the dependent block has lost a rank (or is not square).
    /// From [`SPARSE_DISTANCE_FROM`] active constraints over each constraint's own
    /// coordinates, in time linear in a chain's length.
    pub fn distance(&mut self, model: &Model, q: &[f64]) -> f64 {
        if model.active.len() >= SPARSE_DISTANCE_FROM {
            let dependent = std::mem::take(&mut self.dependent);
            let s = self.sparse_distance(model, q, &dependent);
            self.dependent = dependent;
            return s;
        }
        self.dense_distance(model, q)
    }

    /// [`Determinacy::distance`] from the dense Φ_q, leaving the scaled dependent
    /// block in `rows`.
    fn dense_distance(&mut self, model: &Model, q: &[f64]) -> f64 {
        self.jacobian(model, q);
        let dependent = std::mem::take(&mut self.dependent);
        let s = self.distance_over(model, &dependent);
        self.dependent = dependent;
        s
    }

    /// The most sets [`Determinacy::best`] evaluates in one search.
    pub const SEARCH_SETS: usize = 2000;

    /// What [`Determinacy::best`] may spend in one search, in multiply-adds (each set
    /// costs about ma³/2): a few seconds. Unbounded, a long chain's search of
    /// one-coordinate swaps runs for hours.
    pub const SEARCH_WORK: f64 = 5e9;

    /// The set of independent coordinates that determines the others best at q, and
    /// its distance to rank loss s: over every set where there are at most
    /// [`Determinacy::SEARCH_SETS`], else by swaps of one coordinate from the current
    /// set while s improves, within the same number of sets and
    /// [`Determinacy::SEARCH_WORK`] (the best found so far where a large mechanism
    /// runs out). Where even the best s is small, Φ_q itself is close to losing a
    /// rank.
    pub fn best(&mut self, model: &Model, q: &[f64]) -> (f64, Vec<usize>) {
        let (n, f) = (model.n(), self.independent.len());
        // Each set's s by the sparse route from SPARSE_DISTANCE_FROM rows (the same
        // sets within the same budget: only faster), else from the dense Φ_q.
        let sparse = model.active.len() >= SPARSE_DISTANCE_FROM;
        if !sparse {
            self.jacobian(model, q);
        }
        let distance_of = |det: &mut Determinacy, dependent: &[usize]| {
            if sparse {
                det.sparse_distance(model, q, dependent)
            } else {
                det.distance_over(model, dependent)
            }
        };
        let current = self.independent.clone();
        let mut best = (distance_of(self, &complement(n, &current)), current);
        let ma = model.active.len() as f64;
        let affordable = (Self::SEARCH_WORK / (0.5 * ma * ma * ma).max(1.0)) as usize;
        let mut budget = Self::SEARCH_SETS.min(affordable.max(1));
        // Every set looked at, for the preference among the good ones below.
        let mut seen = vec![best.clone()];
        let mut consider = |det: &mut Determinacy, set: &[usize], best: &mut (f64, Vec<usize>)| {
            if budget == 0 {
                return false;
            }
            budget -= 1;
            let s = distance_of(det, &complement(n, set));
            seen.push((s, set.to_vec()));
            if s > best.0 {
                *best = (s, set.to_vec());
            }
            true
        };
        if binomial(n, f) <= Self::SEARCH_SETS {
            let mut set: Vec<usize> = (0..f).collect();
            loop {
                if !consider(self, &set, &mut best) {
                    break;
                }
                // The next f-subset of 0..n in lexicographic order.
                let Some(i) = (0..f).rev().find(|&i| set[i] < n - f + i) else {
                    break;
                };
                set[i] += 1;
                for j in i + 1..f {
                    set[j] = set[j - 1] + 1;
                }
            }
        } else {
            loop {
                let before = best.0;
                let current = best.1.clone();
                let mut exhausted = false;
                'swaps: for i in 0..f {
                    for c in (0..n).filter(|c| !current.contains(c)) {
                        let mut set = current.clone();
                        set[i] = c;
                        set.sort_unstable();
                        if !consider(self, &set, &mut best) {
                            exhausted = true;
                            break 'swaps;
                        }
                    }
                }
                if best.0 <= before || exhausted {
                    break;
                }
            }
        }
        // Among the sets within PREFER_ANGLES_WITHIN of the best, the one with the most
        // angles: a body's angle follows it through whole turns, where a point's x or
        // y loses rank twice a turn (docs/dc-stall.md, "8. Independent coordinates
        // that stop determining the others").
        let angles = |set: &[usize]| set.iter().filter(|&&i| model.is_angle(i)).count();
        let floor = Self::PREFER_ANGLES_WITHIN * best.0;
        seen.into_iter()
            .filter(|(s, _)| *s >= floor)
            .max_by(|a, b| angles(&a.1).cmp(&angles(&b.1)).then(a.0.total_cmp(&b.0)))
            .unwrap_or(best)
    }

    /// Sets of independent coordinates within this fraction of the best distance to
    /// rank loss are ranked by how many angles they hold ([`Determinacy::best`]).
    pub const PREFER_ANGLES_WITHIN: f64 = 0.5;

    fn jacobian(&mut self, model: &Model, q: &[f64]) {
        model.jacobian_into(q, &mut self.jac);
    }

    /// The norms of Φ_q's columns over the active rows at q (1 for a column without
    /// entries): the coordinates' scales, taken once at the initial configuration so
    /// that a column that shrinks towards a singular configuration is not rescaled.
    ///
    /// A point's x and y columns are scaled by no less than the root mean square of
    /// the two: a point placed level with its neighbour has an x column as small as
    /// that link (2·length from its distance equation alone) and a y column of 1 (its
    /// angle equation's): scaled apart, a small link's turn reads as a rank loss
    /// closer than it is.
    fn set_column_scales(&mut self, model: &Model, q: &[f64]) {
        self.jacobian(model, q);
        let n = model.n();
        let squares: Vec<f64> = (0..n)
            .map(|c| {
                model
                    .active
                    .iter()
                    .map(|&k| self.jac[k * n + c].powi(2))
                    .sum()
            })
            .collect();
        let mut scale = squares.clone();
        for slot in &model.points {
            if let PointSlot::Free(x) = *slot {
                let both = 0.5 * (squares[x] + squares[x + 1]);
                scale[x] = squares[x].max(both);
                scale[x + 1] = squares[x + 1].max(both);
            }
        }
        for (norm, sq) in self.column_norms.iter_mut().zip(scale) {
            *norm = if sq > 0.0 { sq.sqrt() } else { 1.0 };
        }
    }

    /// s of Φ_q at q restricted to the columns `dependent`, each row of Φ_q formed
    /// over its constraint's coordinates and G over the pairs of rows that share a
    /// dependent column: the same scaling and G as [`Determinacy::distance_over`].
    fn sparse_distance(&mut self, model: &Model, q: &[f64], dependent: &[usize]) -> f64 {
        let ma = model.active.len();
        if ma != dependent.len() {
            return 0.0;
        }
        if ma == 0 {
            return f64::INFINITY;
        }
        self.mask.fill(false);
        for &c in dependent {
            self.mask[c] = true;
        }
        self.incidence.iter_mut().for_each(Vec::clear);
        let (mut u, mut gradient) = ([0.0; MAX_LOCAL], [0.0; MAX_LOCAL]);
        for (row, &k) in model.active.iter().enumerate() {
            let c = &model.constraints[k];
            c.gather(q, &mut u);
            c.equation.gradient(&u, &mut gradient);
            // The row's nonzeros by column (a column the constraint holds twice adds
            // up), scaled by the columns' norms.
            let mut entries = [(0usize, 0.0f64); MAX_LOCAL];
            let mut len = 0;
            for (p, ip) in c.local_index().iter().enumerate() {
                let Some(ip) = *ip else { continue };
                match entries[..len].iter_mut().find(|e| e.0 == ip) {
                    Some(e) => e.1 += gradient[p],
                    None => {
                        entries[len] = (ip, gradient[p]);
                        len += 1;
                    }
                }
            }
            let entries = &mut entries[..len];
            entries.sort_unstable_by_key(|e| e.0);
            let mut norm = 0.0;
            for e in entries.iter_mut() {
                e.1 /= self.column_norms[e.0];
                norm += e.1 * e.1;
            }
            let norm = norm.sqrt();
            if !(norm > 0.0) {
                return 0.0;
            }
            // (Zeros too: G's pattern, and its analysis, stay those of the columns.)
            let mut held = false;
            for &(col, v) in entries.iter().filter(|e| self.mask[e.0]) {
                self.incidence[col].push((row, v / norm));
                held |= v != 0.0;
            }
            if !held {
                // An equation without a dependent coordinate determines none.
                return 0.0;
            }
        }
        self.lower.clear();
        self.values.clear();
        for list in &self.incidence {
            // Rows in ascending order: (i, j ≤ i) pairs of rows sharing this column.
            for (a, &(i, vi)) in list.iter().enumerate() {
                for &(j, vj) in &list[..=a] {
                    self.lower.push((i, j));
                    self.values.push(vi * vj);
                }
            }
        }
        if self
            .trace
            .as_ref()
            .is_none_or(|(lower, _)| *lower != self.lower)
        {
            self.trace = InverseTrace::new(ma, &self.lower).map(|t| (self.lower.clone(), t));
        }
        self.trace
            .as_mut()
            .and_then(|(_, trace)| trace.trace(&self.values))
            .map_or(0.0, |trace| trace.recip().sqrt())
    }

    /// s of Φ_q (in `self.jac`) restricted to the columns `dependent`, from the dense
    /// Gram matrix (a large mechanism's s is [`Determinacy::sparse_distance`]'s; this
    /// route serves it only for the scaled block in `rows`).
    fn distance_over(&mut self, model: &Model, dependent: &[usize]) -> f64 {
        let (n, ma, d) = (model.n(), model.active.len(), dependent.len());
        if ma != d {
            return 0.0;
        }
        if ma == 0 {
            return f64::INFINITY;
        }
        for (r, &k) in model.active.iter().enumerate() {
            let row = &mut self.rows[r * d..(r + 1) * d];
            for (o, &c) in row.iter_mut().zip(dependent) {
                *o = self.jac[k * n + c];
            }
            // Columns scaled by the coordinates' scales (mixed units and sizes: a
            // 7 mm crank's angle column is 100× smaller than its points'), rows by
            // their whole scaled row: an equation whose dependent part vanishes (a
            // point on a crank at the top of its circle, with its y independent) no
            // longer determines them, whatever the size of that part.
            for (o, &c) in row.iter_mut().zip(dependent) {
                *o /= self.column_norms[c];
            }
            let norm = (0..n)
                .map(|c| (self.jac[k * n + c] / self.column_norms[c]).powi(2))
                .sum::<f64>()
                .sqrt();
            if !(norm > 0.0) {
                return 0.0;
            }
            row.iter_mut().for_each(|v| *v /= norm);
        }
        let (rows, g) = (&self.rows, &mut self.chol);
        dense::sparse_gram(
            ma,
            |i| &rows[i * d..(i + 1) * d],
            &mut self.spans,
            &mut self.first,
            g,
        );
        if dense::cholesky(g, ma).is_err() {
            return 0.0;
        }
        dense::inverse_trace(g, ma, &mut self.column, &mut self.first, None)
            .recip()
            .sqrt()
    }

    /// The report of a run stopped at q (time t, distance s) with the step before
    /// at q0 (t0, s0): where s extrapolates to 0, and the rank kept there.
    ///
    /// The rank is what is left where the scaled dependent block's singular values,
    /// each extrapolated linearly from q0 and q to that time, have not fallen to a
    /// tenth of their value at q: a chain of N loops loses N ranks together at its
    /// flat configuration, whose singular values fall at different rates, so a count
    /// of those already small at the stop sees too few. Where s is not falling
    /// (no time to extrapolate to), those below 10 s at q are counted as lost.
    pub(crate) fn singular_configuration(
        &mut self,
        model: &Model,
        q0: &[f64],
        q: &[f64],
        (t0, s0): (f64, f64),
        (t, s): (f64, f64),
    ) -> SingularConfiguration {
        let t_singular = if s0 > s {
            t + s * (t - t0) / (s0 - s)
        } else {
            t
        };
        let d = self.dependent.len();
        let singular_values = |det: &mut Self, at: &[f64]| -> Option<Vec<f64>> {
            det.dense_distance(model, at);
            let rows = nalgebra::DMatrix::from_row_slice(model.active.len(), d, &det.rows);
            // nalgebra's SVD does not return on a non-finite matrix.
            rows.iter().all(|v| v.is_finite()).then(|| {
                let mut sv: Vec<f64> = rows.singular_values().iter().copied().collect();
                sv.sort_by(|a, b| b.total_cmp(a));
                sv
            })
        };
        let before = singular_values(self, q0);
        let now = singular_values(self, q);
        let rank = match (before, now) {
            (Some(before), Some(now)) if t_singular > t && t > t0 => {
                let ahead = (t_singular - t) / (t - t0);
                let lost = now
                    .iter()
                    .zip(&before)
                    .filter(|(&v, &v0)| v + (v - v0) * ahead <= 0.1 * v)
                    .count();
                d - lost.max(1)
            }
            (_, Some(now)) => now.iter().filter(|&&v| v > 10.0 * s).count(),
            _ => 0,
        };
        let names = |idx: &mut dyn Iterator<Item = usize>| -> Vec<String> {
            idx.map(|i| model.names[i].clone()).collect()
        };
        SingularConfiguration {
            t_singular,
            distance: s,
            rank,
            full_rank: d,
            independent: names(&mut self.independent.iter().copied()),
            dependent: names(&mut self.dependent.iter().copied()),
        }
    }
}

/// The coordinates of 0..n not in `set`.
fn complement(n: usize, set: &[usize]) -> Vec<usize> {
    (0..n).filter(|i| !set.contains(i)).collect()
}

/// n choose k, saturating.
fn binomial(n: usize, k: usize) -> usize {
    (0..k.min(n)).fold(1usize, |acc, i| acc.saturating_mul(n - i) / (i + 1))
}

/// σ_r/σ₁ of Φ_q(q), r = the number of independent constraints at the start, scale-free:
/// its active rows, columns scaled by their norms at the start configuration q0 (the
/// coordinates' scales: mm-size links and angles in radians weigh alike), each row
/// then normalized, so that a well-conditioned mechanism with a small crank reads so.
pub(crate) fn constraint_conditioning(model: &Model, q0: &[f64], q: &[f64]) -> f64 {
    let r = model.active.len();
    if r == 0 {
        return 1.0;
    }
    let active = |q: &[f64]| {
        let jac = model.jacobian(&nalgebra::DVector::from_column_slice(q));
        nalgebra::DMatrix::from_fn(r, model.n(), |i, c| jac[(model.active[i], c)])
    };
    let initial = active(q0);
    let mut a = active(q);
    for (c, scale) in initial.column_iter().map(|col| col.norm()).enumerate() {
        if scale > 0.0 {
            a.column_mut(c).unscale_mut(scale);
        }
    }
    for mut row in a.row_iter_mut() {
        let norm = row.norm();
        if norm > 0.0 {
            row.unscale_mut(norm);
        }
    }
    if !a.iter().all(|v| v.is_finite()) {
        // Not a configuration (nalgebra's SVD would not return on it).
        return 0.0;
    }
    let mut sv: Vec<f64> = a.singular_values().iter().copied().collect();
    sv.sort_by(|a, b| b.total_cmp(a));
    if sv[0] > 0.0 {
        sv.get(r - 1).copied().unwrap_or(0.0) / sv[0]
    } else {
        0.0
    }
}

/// What a [`Watch`] makes of a step.
#[derive(Debug, Clone, PartialEq)]
pub enum Watched {
    /// The coordinates in use determine the others well enough: go on.
    Continue,
    /// They approach a configuration where they stop determining the others while
    /// Φ_q keeps its rank: go on from this step with these independent coordinates.
    Reselect(Vec<usize>),
    /// Φ_q itself approaches a rank loss (the problem is ill-posed there): stop
    /// before this step, which is named with the configuration ahead.
    Stop(SingularConfiguration),
}

/// A run in independent coordinates watching, step by step, how well its
/// coordinates determine the others ([`Determinacy::distance`], s): it switches to a
/// better set where s falls while another set's stays high, and stops ahead of a
/// configuration where every set's falls.
pub struct Watch {
    determinacy: Determinacy,
    /// The last two converged steps' (t, s).
    before: (f64, f64),
    older: (f64, f64),
    /// s at the segment's first step: a long chain reads s well below the
    /// thresholds from its start (about 0.6/k for k links) with no better set, and
    /// is judged by how far s has fallen from there.
    origin: f64,
}

impl Watch {
    /// The watch of a run or segment in the independent coordinates `independent`
    /// that starts at the configuration `q0` (see [`Determinacy::new`]).
    pub fn new(model: &Model, independent: &[usize], q0: &[f64]) -> Watch {
        let far = (0.0, f64::INFINITY);
        Watch {
            determinacy: Determinacy::new(model, independent, q0),
            before: far,
            older: far,
            origin: f64::INFINITY,
        }
    }

    /// After a converged step j of the segment (j = 0 its first) at time t with
    /// positions q, those of step j − 1 being `q_before`.
    pub fn observe(
        &mut self,
        model: &Model,
        j: usize,
        t: f64,
        q_before: &[f64],
        q: &[f64],
    ) -> Watched {
        let before = self.before;
        let now = (t, self.determinacy.distance(model, q));
        // At coarse steps s can fall from well above the thresholds to beyond the
        // singular point in one step: judge by the lower of s and its linear
        // extrapolation to the next step.
        let ahead = if before.1.is_finite() {
            now.1.min(2.0 * now.1 - before.1).max(0.0)
        } else {
            now.1
        };
        let falling = now.1 < before.1;
        // No switch at a segment's first step (its start is unknown there).
        if j > 0 && falling && ahead < Determinacy::SEARCH_BELOW && ahead <= 0.5 * self.origin {
            let (best, set) = self.determinacy.best(model, q);
            if best >= Determinacy::SWITCH_GAIN * now.1 {
                return Watched::Reselect(set);
            }
        }
        // The stop on the extrapolation only where it crosses 0 within the step: a
        // regular dip seen at coarse steps must not stop the run.
        let crossing = before.1.is_finite() && 2.0 * now.1 <= before.1;
        if !before.1.is_finite() {
            self.origin = now.1;
        }
        let low = now.1 < Determinacy::STOP_BELOW && now.1 <= 0.5 * self.origin;
        if falling && (low || crossing) {
            let singular = self
                .determinacy
                .singular_configuration(model, q_before, q, before, now);
            return Watched::Stop(singular);
        }
        self.older = before;
        self.before = now;
        Watched::Continue
    }

    /// After step j's solve failed: the singular configuration it fails because of,
    /// where z and every other set of coordinates approach a rank loss, located from
    /// the last two converged steps (`q_older`, `q_before`). `too_coarse`: a body
    /// turned so far over the step that s moving fast says nothing on its own.
    pub fn attribute(
        &mut self,
        model: &Model,
        j: usize,
        dt: f64,
        (q_older, q_before): (&[f64], &[f64]),
        too_coarse: bool,
    ) -> Option<SingularConfiguration> {
        let (before, older) = (self.before, self.older);
        let rate = (older.1 - before.1) / (before.0 - older.0);
        let steps_to_rank_loss = before.1 / (rate * dt);
        let near = (steps_to_rank_loss <= Determinacy::ATTRIBUTE_WITHIN
            && before.1 < Determinacy::ATTRIBUTE_BELOW
            && !too_coarse)
            || before.1 < Determinacy::SEARCH_BELOW;
        if j < 2 || rate <= 0.0 || !near {
            return None;
        }
        let (best, _) = self.determinacy.best(model, q_before);
        (best < Determinacy::SWITCH_GAIN * before.1).then(|| {
            self.determinacy
                .singular_configuration(model, q_older, q_before, older, before)
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::Scene;
    use std::sync::Arc;

    /// The sparse route gives the dense one's s, on a chain of 40 loops and a
    /// 32-link pendulum (angle coordinates), at the start and moved off it.
    #[test]
    fn sparse_distance_is_the_dense_one() {
        for scene in ["benchmarks/n-fourbar-40.yaml", "scale/n-pendulum-32.yaml"] {
            let path = format!("{}/scenes/{scene}", env!("CARGO_MANIFEST_DIR"));
            let model = Arc::new(Model::new(&Scene::load(&path).unwrap()).unwrap());
            assert!(model.active.len() >= SPARSE_DISTANCE_FROM);
            let mut det = Determinacy::new(&model, &model.independent, model.initial.q.as_slice());
            let dependent = complement(model.n(), &model.independent);
            for shift in [0.0, 0.02, 0.2] {
                let q: Vec<f64> = (0..model.n())
                    .map(|i| model.initial.q[i] + shift * ((i as f64 * 0.618).fract() - 0.5))
                    .collect();
                det.jacobian(&model, &q);
                let dense = det.distance_over(&model, &dependent);
                let by_rows = det.sparse_distance(&model, &q, &dependent);
                assert!(
                    (by_rows - dense).abs() <= 1e-10 * dense,
                    "{scene} shifted by {shift}: s = {by_rows} by rows, {dense} dense"
                );
            }
        }
    }
}
