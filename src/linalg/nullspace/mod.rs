//! Exact linear equality constraints C δ = b on a step's unknowns: a basis N of the
//! null space of C and the least-norm solution p, so that every solution reads
//! δ = p + N y. The solver eliminates hard factors this way instead of weighting them,
//! which keeps the normal equations' condition number that of the soft factors alone.
//!
//! Equations with a single nonzero (priors on components, prescribed values, forces
//! fixed at zero) fix their unknown outright and are taken out first; unknowns no
//! equation touches (the accelerations under position and velocity constraints) are
//! free outright, a unit basis vector each, and stay out of the QR. The rest go
//! through a Householder QR with column pivoting of Cᵀ restricted to the unknowns left
//! (one column per equation), which reveals the rank, so redundant equations
//! (over-constrained mechanisms, or the initial priors together with the constraints
//! they already satisfy) are dropped, not divided by 0.
//!
//! Unknowns may be split into ordered segments ([`NullSpace::set_segments`]; the
//! solver puts positions, velocities, accelerations and forces in segments 0–3).
//! Each equation then belongs to the segment of the last unknown it touches, and the
//! QR takes the equations segment by segment (pivoting within a segment), with the
//! QR's rows ordered by segment: the position equations' reflectors then touch the
//! position rows only, the velocity equations' the velocity rows and what the
//! position equations left, and so on. For the block-triangular hard equations of a
//! step ([Φ_q 0; ∂(Φ_q q̇)/∂q Φ_q] and their kin) this costs a fraction of a QR of
//! the whole, and the null-space basis comes out exactly 0 on the unknowns the
//! earlier segments fix (the positions, in inverse dynamics). The basis is another
//! orthonormal basis of the same space and the particular solution the same
//! least-norm one.
//!
//! The QR sees each equation normalized by its size on the unknowns of its own
//! segment, so that "nearly dependent" means nearly dependent: a pivot is compared
//! with its own equation's size, not with the largest equation's. A 7 mm crank's
//! constraint next to a 0.6 m rod's, or an acceleration row whose coefficients on q
//! and q̇ grow like q̇², would otherwise read as a rank loss and be damped or dropped.
//!
//! Equations that are kept but nearly dependent (a pivot far below the largest, as
//! near a singular configuration, where the position and velocity constraints lose a
//! rank together and the step's pivot falls like the square of the distance) are
//! satisfied with a damped correction: correcting them exactly would divide the
//! round-off in their residual by that pivot and move the state along the direction
//! they barely fix by that much, every iteration (see [`NullSpace::CORRECTION_TOLERANCE`]).
//! A residual the caller shows to stand far above its round-off ([`NullSpace::set_noise`])
//! is real, and is corrected exactly however small the pivot.

use super::dense::{dot, Summation};
use householder::{
    apply_q, apply_q_columns, householder_grouped, GroupReflectors, Grouping, Sparsity,
    TRACK_SUPPORT_FROM,
};

mod householder;
#[cfg(test)]
mod tests;

/// Scratch and results of one reduction, sized once for `s` unknowns and up to
/// `max_rows` equations.
#[derive(Debug, Clone)]
pub struct NullSpace {
    s: usize,
    max_rows: usize,
    rows: usize,
    /// −g for `multipliers`.
    scratch_g: Vec<f64>,
    /// What `solve` keeps of the equations: per fixed unknown its unit equation's
    /// coefficient, and the other equations' coefficients on the fixed unknowns
    /// (row-major others × pinned).
    /// Per unknown: the unit equation fixing it, if any; whether another equation
    /// touches it.
    fixed: Vec<Option<usize>>,
    touched: Vec<bool>,
    /// Each equation's nonzero unknowns, one equation after another, and where
    /// each equation's end; per unknown its position in `qr_rows` (usize::MAX if
    /// not free).
    nonzeros: Vec<usize>,
    nonzeros_end: Vec<usize>,
    qr_pos: Vec<usize>,
    /// One column's nonzero positions in `qr_rows`; every column's, one after
    /// another, and where each begins (for the QR's support).
    entries: Vec<usize>,
    column_rows: Vec<usize>,
    column_bounds: Vec<usize>,
    /// Unknowns neither fixed by unit equations nor untouched by the others (those
    /// the QR sees, ascending), the other equations, and the unknowns no equation
    /// touches.
    free: Vec<usize>,
    /// Per unknown, its segment; the number of segments.
    segment: Vec<usize>,
    segments: usize,
    /// The free unknowns in the QR's row order (by segment, then index), and per
    /// segment the end of its rows in that order.
    qr_rows: Vec<usize>,
    seg_end: Vec<usize>,
    /// Per column of the QR: its segment, or [`DROPPED`]; per reflector, the end of
    /// its rows (it is 0 past them).
    group: Vec<usize>,
    rend: Vec<usize>,
    /// Per group of the last QR, its reflectors.
    made: Vec<GroupReflectors>,
    others: Vec<usize>,
    untouched: Vec<usize>,
    /// The unknowns unit equations fix, ascending.
    pinned: Vec<usize>,
    /// Cᵀ[free, others] column-major (stride free.len()), overwritten by the QR.
    a: Vec<f64>,
    rdiag: Vec<f64>,
    beta: Vec<f64>,
    perm: Vec<usize>,
    norms: Vec<f64>,
    /// Per QR column, a superset of its nonzero rows (bits), and one reflector's;
    /// per column, the range of those rows.
    support: Vec<u64>,
    support_start: Vec<usize>,
    support_end: Vec<usize>,
    w: Vec<f64>,
    /// The per-column sums of [`apply_q_columns`].
    column_sums: Vec<f64>,
    rhs: Vec<f64>,
    /// Per QR column (an equation of `others`), 1/its norm on the free unknowns: the
    /// QR factors the equations normalized, so that its rank test and damping compare
    /// each pivot with its own equation's size, not with the largest equation's (a
    /// 7 mm crank's constraint next to a 0.6 m rod's, or a velocity row scaled by q̇).
    row_scale: Vec<f64>,
    pin_coef: Vec<f64>,
    others_pinned: Vec<f64>,
    /// The basis' dense part: the QR's null vectors on the free unknowns, row-major
    /// free × q in the QR's row order (q = dim − untouched); its other columns are
    /// the untouched unknowns' unit vectors, written nowhere.
    dense: Vec<f64>,
    /// Per unknown, its row in `dense` (free unknowns only).
    dense_row: Vec<usize>,
    /// How the QR's sums of products are taken.
    summation: Summation,
    /// Per row of the basis, the columns [start, end) outside which it is 0 (fixed
    /// unknowns: none; untouched ones: their unit column; the rest: the QR's columns).
    span: Vec<(usize, usize)>,
    /// The least-norm solution of the independent equations (exact on fixed unknowns).
    pub particular: Vec<f64>,
    /// Per equation, the round-off in its residual (∞: unknown, every nearly
    /// dependent equation is damped); see [`NullSpace::set_noise`].
    noise: Vec<f64>,
    /// The largest round-off of the last reduction's normalized residuals (of the
    /// equations the QR sees): what a pivot's division must stand above.
    noise_floor: f64,
    /// Dimension of the null space.
    pub dim: usize,
    /// Rank of C.
    pub rank: usize,
}

impl NullSpace {
    /// Becomes a copy of `other` (a reduction kept for a later solve), reusing this
    /// one's buffers.
    pub fn copy_from(&mut self, other: &NullSpace) {
        self.s.clone_from(&other.s);
        self.max_rows.clone_from(&other.max_rows);
        self.rows.clone_from(&other.rows);
        self.scratch_g.clone_from(&other.scratch_g);
        self.fixed.clone_from(&other.fixed);
        self.touched.clone_from(&other.touched);
        self.nonzeros.clone_from(&other.nonzeros);
        self.nonzeros_end.clone_from(&other.nonzeros_end);
        self.qr_pos.clone_from(&other.qr_pos);
        self.entries.clone_from(&other.entries);
        self.column_rows.clone_from(&other.column_rows);
        self.column_bounds.clone_from(&other.column_bounds);
        self.free.clone_from(&other.free);
        self.segment.clone_from(&other.segment);
        self.segments.clone_from(&other.segments);
        self.qr_rows.clone_from(&other.qr_rows);
        self.seg_end.clone_from(&other.seg_end);
        self.group.clone_from(&other.group);
        self.rend.clone_from(&other.rend);
        self.made.clone_from(&other.made);
        self.others.clone_from(&other.others);
        self.untouched.clone_from(&other.untouched);
        self.pinned.clone_from(&other.pinned);
        self.a.clone_from(&other.a);
        self.rdiag.clone_from(&other.rdiag);
        self.beta.clone_from(&other.beta);
        self.perm.clone_from(&other.perm);
        self.norms.clone_from(&other.norms);
        self.support.clone_from(&other.support);
        self.support_start.clone_from(&other.support_start);
        self.support_end.clone_from(&other.support_end);
        self.w.clone_from(&other.w);
        self.column_sums.clone_from(&other.column_sums);
        self.rhs.clone_from(&other.rhs);
        self.row_scale.clone_from(&other.row_scale);
        self.pin_coef.clone_from(&other.pin_coef);
        self.others_pinned.clone_from(&other.others_pinned);
        self.dense.clone_from(&other.dense);
        self.dense_row.clone_from(&other.dense_row);
        self.summation.clone_from(&other.summation);
        self.span.clone_from(&other.span);
        self.particular.clone_from(&other.particular);
        self.noise.clone_from(&other.noise);
        self.noise_floor.clone_from(&other.noise_floor);
        self.dim.clone_from(&other.dim);
        self.rank.clone_from(&other.rank);
    }
    /// Relative size below which a pivot counts as zero (rank-deficient direction).
    pub const RANK_TOLERANCE: f64 = 1e-10;

    /// Relative size μ (to the largest pivot; the equations are normalized) below
    /// which a kept pivot R gets a damped correction: the component w = b/R of the
    /// least-norm solution becomes b/(R(1 + (μ/R)¹⁶)), which is b/R to round-off for
    /// R ≥ 10μ (exactly b/R is used there) and below 0.8 b/μ everywhere. Near a
    /// singular configuration a step's position pivot, and its velocity pivot in
    /// the next segment, fall like the distance to it; an exact correction there
    /// divides the round-off in the residual by the pivot and, in the parallelogram,
    /// moves the state along the anti-parallelogram velocity every iteration, so the
    /// window solves stall on that noise. The residual a damped correction leaves
    /// in that equation is of the order of its round-off. The range of μ that passes
    /// the parallelogram's and the N four-bars' flat configurations is narrow
    /// (`docs/dc-stall.md`, "6. Equations of very different sizes").
    pub const CORRECTION_TOLERANCE: f64 = 5e-5;

    pub fn new(s: usize, max_rows: usize) -> Self {
        let mut ns = NullSpace {
            s,
            max_rows,
            scratch_g: Vec::with_capacity(s),
            pin_coef: vec![0.0; s],
            others_pinned: Vec::new(),
            rows: 0,
            fixed: vec![None; s],
            touched: vec![false; s],
            nonzeros: Vec::new(),
            nonzeros_end: Vec::with_capacity(max_rows),
            qr_pos: vec![usize::MAX; s],
            entries: Vec::new(),
            column_rows: Vec::new(),
            column_bounds: Vec::with_capacity(max_rows + 1),
            free: Vec::with_capacity(s),
            segment: vec![0; s],
            segments: 1,
            qr_rows: Vec::with_capacity(s),
            seg_end: vec![0; 1],
            group: vec![0; max_rows],
            rend: vec![0; s.min(max_rows)],
            made: Vec::with_capacity(4),
            others: Vec::with_capacity(max_rows),
            untouched: Vec::with_capacity(s),
            pinned: Vec::with_capacity(s),
            a: Vec::new(),
            rdiag: vec![0.0; s.min(max_rows)],
            beta: vec![0.0; s.min(max_rows)],
            perm: vec![0; max_rows],
            norms: vec![0.0; 2 * max_rows],
            support: Vec::new(),
            support_start: vec![0; max_rows],
            support_end: vec![0; max_rows],
            w: vec![0.0; s],
            column_sums: Vec::new(),
            rhs: vec![0.0; max_rows],
            row_scale: vec![1.0; max_rows],
            dense: Vec::new(),
            dense_row: vec![usize::MAX; s],
            summation: Summation::Sequential,
            span: vec![(0, 0); s],
            particular: vec![0.0; s],
            noise: vec![f64::INFINITY; max_rows],
            noise_floor: f64::INFINITY,
            dim: s,
            rank: 0,
        };
        // Unconstrained, with N = I not written out until it is asked for: the
        // solver's blocks are reduced before use, and their storage (allocated at
        // the first reduction, to its size) stays small when dim is.
        for i in 0..s {
            ns.span[i] = (i, i + 1);
        }
        ns.untouched.extend(0..s);
        ns
    }

    /// Grows `v` to at least `len` entries (allocating only when a reduction needs
    /// more than any before it).
    fn ensure(v: &mut Vec<f64>, len: usize) {
        if v.len() < len {
            v.resize(len, 0.0);
        }
    }

    /// Splits the unknowns into ordered segments (`segment[i]` for unknown i): the
    /// equations are reduced segment by segment (see the module's documentation).
    /// One segment (the default) is the plain pivoted QR.
    pub fn set_segments(&mut self, segment: &[usize]) {
        assert_eq!(segment.len(), self.s, "one segment per unknown");
        self.segment.copy_from_slice(segment);
        self.segments = segment.iter().max().map_or(1, |m| m + 1);
        self.seg_end = vec![0; self.segments];
    }

    /// w[..sf] ← Q w[..sf] with the last QR's reflectors (see [`apply_q`]).
    fn apply_q_to_w(&mut self, sf: usize) {
        apply_q(
            &self.a,
            &self.beta,
            &self.rend,
            &self.made,
            sf,
            &mut self.w[..sf],
            self.summation,
        );
    }

    /// The first row where column i of the last QR's R may be nonzero: the start
    /// of its tracked rows, 0 where the QR tracked none.
    fn r_start(&self, i: usize) -> usize {
        if self.free.len() >= TRACK_SUPPORT_FROM {
            self.support_start[i].min(i)
        } else {
            0
        }
    }

    /// w ← H_k w (reflector k of the last QR, on rows k..rend[k]).
    fn reflect(&mut self, k: usize, sf: usize) {
        let end = self.rend[k];
        let v = &self.a[k * sf + k..k * sf + end];
        let y = &mut self.w[k..end];
        let f = self.beta[k] * dot(v, y, self.summation);
        for (yi, vi) in y.iter_mut().zip(v) {
            *yi -= f * vi;
        }
    }

    /// How the QR's sums of products are taken (sequential by default).
    pub fn set_summation(&mut self, how: Summation) {
        self.summation = how;
    }

    /// No equations: N = I, p = 0.
    pub fn set_unconstrained(&mut self) {
        let s = self.s;
        for i in 0..s {
            self.span[i] = (i, i + 1);
        }
        self.dense_row.fill(usize::MAX);
        self.particular.fill(0.0);
        self.fixed.fill(None);
        self.free.clear();
        self.qr_rows.clear();
        self.made.clear();
        self.others.clear();
        self.untouched.clear();
        self.untouched.extend(0..s);
        self.pinned.clear();
        self.rows = 0;
        self.dim = s;
        self.rank = 0;
    }

    /// The round-off in each equation's residual (as many as the next reduction's
    /// equations): a nearly dependent equation whose residual stands above it by
    /// [`NullSpace::NOISE_MARGIN`] is corrected exactly, since the damping is there
    /// for round-off only. Without it (or with ∞) every one is damped.
    pub fn set_noise(&mut self, noise: &[f64]) {
        self.noise[..noise.len()].copy_from_slice(noise);
        self.noise[noise.len()..].fill(f64::INFINITY);
    }

    /// How far above its round-off a nearly dependent equation's residual must stand
    /// to be corrected exactly.
    pub const NOISE_MARGIN: f64 = 1e4;

    /// Reduces the `rows` equations C δ = b, C row-major rows × s.
    pub fn reduce(&mut self, c: &[f64], b: &[f64], rows: usize) {
        assert!(
            rows <= self.max_rows,
            "more equations than the reduction holds"
        );
        if rows == 0 {
            self.set_unconstrained();
            return;
        }
        let s = self.s;
        self.rows = rows;
        // Unit equations fix their unknown; a second one on the same unknown is
        // redundant.
        self.fixed.fill(None);
        self.others.clear();
        // One pass along the rows: unit equations, the others, and the unknowns the
        // others touch.
        let touched = &mut self.touched;
        touched.fill(false);
        self.nonzeros.clear();
        self.nonzeros_end.clear();
        for j in 0..rows {
            let row = &c[j * s..(j + 1) * s];
            let start = self.nonzeros.len();
            self.nonzeros.extend(
                row.iter()
                    .enumerate()
                    .filter(|(_, v)| **v != 0.0)
                    .map(|(i, _)| i),
            );
            self.nonzeros_end.push(self.nonzeros.len());
            match self.nonzeros[start..] {
                [i] => {
                    if self.fixed[i].is_none() {
                        self.fixed[i] = Some(j);
                    }
                }
                [] => {}
                ref several => {
                    self.others.push(j);
                    for &i in several {
                        touched[i] = true;
                    }
                }
            }
        }
        self.free.clear();
        self.untouched.clear();
        self.pinned.clear();
        for i in 0..s {
            if self.fixed[i].is_some() {
                self.pinned.push(i);
            } else if self.touched[i] {
                self.free.push(i);
            } else {
                self.untouched.push(i);
            }
        }
        let np = self.pinned.len();
        Self::ensure(&mut self.others_pinned, self.others.len() * np);
        for &i in &self.pinned {
            let j = self.fixed[i].expect("a pinned unknown has its unit equation");
            self.pin_coef[i] = c[j * s + i];
        }
        for (k, &j) in self.others.iter().enumerate() {
            for (o, &i) in self.others_pinned[k * np..(k + 1) * np]
                .iter_mut()
                .zip(&self.pinned)
            {
                *o = c[j * s + i];
            }
        }
        let sf = self.free.len();
        let m = self.others.len();
        // The QR's rows: the free unknowns by segment (ascending within one).
        self.qr_rows.clear();
        self.qr_rows.extend_from_slice(&self.free);
        if self.segments > 1 {
            let seg = &self.segment;
            self.qr_rows.sort_unstable_by_key(|&i| (seg[i], i));
        }
        self.seg_end.fill(0);
        for &i in &self.qr_rows {
            self.seg_end[self.segment[i]] += 1;
        }
        for g in 1..self.segments {
            self.seg_end[g] += self.seg_end[g - 1];
        }
        Self::ensure(&mut self.a, sf * m);
        if self.support.len() < (m + 1) * sf.div_ceil(64) {
            self.support.resize((m + 1) * sf.div_ceil(64), 0);
        }
        self.qr_pos.fill(usize::MAX);
        for (a, &i) in self.qr_rows.iter().enumerate() {
            self.qr_pos[i] = a;
        }
        // A = Cᵀ[free, others]: column k is equation others[k] on the free unknowns;
        // its group is the segment of the last of them it touches. Each column is
        // written, measured and scaled over its nonzeros (in the QR's row order, so
        // that its norm is the same sum as over the whole column).
        let entries = &mut self.entries;
        self.column_rows.clear();
        self.column_bounds.clear();
        self.column_bounds.push(0);
        for (k, &j) in self.others.iter().enumerate() {
            let col = &mut self.a[k * sf..(k + 1) * sf];
            col.fill(0.0);
            let start = if j > 0 { self.nonzeros_end[j - 1] } else { 0 };
            entries.clear();
            for &i in &self.nonzeros[start..self.nonzeros_end[j]] {
                let a = self.qr_pos[i];
                if a != usize::MAX {
                    col[a] = c[j * s + i];
                    entries.push(a);
                }
            }
            entries.sort_unstable();
            self.group[k] = entries.last().map_or(0, |&a| self.segment[self.qr_rows[a]]);
            // Its size on the unknowns of its own segment, those its pivot is taken
            // from: an acceleration row's coefficients on q and q̇ grow like q̇², its
            // pivot on q̈ does not.
            let g = self.group[k];
            let norm = entries
                .iter()
                .filter(|&&a| self.segment[self.qr_rows[a]] == g)
                .map(|&a| col[a] * col[a])
                .sum::<f64>()
                .sqrt();
            let scale = if norm > 0.0 { 1.0 / norm } else { 1.0 };
            self.row_scale[k] = scale;
            for &a in entries.iter() {
                col[a] *= scale;
            }
            self.column_rows.extend_from_slice(entries);
            self.column_bounds.push(self.column_rows.len());
        }
        let rank = householder_grouped(
            &mut self.a,
            sf,
            m,
            Grouping {
                group: &mut self.group[..m],
                seg_end: &self.seg_end,
                rend: &mut self.rend,
                made: &mut self.made,
            },
            self.summation,
            &mut self.rdiag,
            &mut self.beta,
            &mut self.perm,
            &mut self.norms,
            Sparsity {
                support: if sf >= TRACK_SUPPORT_FROM {
                    &mut self.support
                } else {
                    &mut []
                },
                starts: &mut self.support_start,
                ends: &mut self.support_end,
                order: true,
                nonzeros: Some((&self.column_rows, &self.column_bounds)),
            },
        );
        let fixed_count = s - sf - self.untouched.len();
        self.rank = fixed_count + rank;
        self.dim = sf - rank + self.untouched.len();
        let q = sf - rank;
        self.noise_floor = self
            .others
            .iter()
            .enumerate()
            .map(|(k, &j)| self.noise[j] * self.row_scale[k])
            .fold(0.0f64, f64::max);
        let mut p = std::mem::take(&mut self.particular);
        self.solve(b, &mut p);
        self.particular = p;
        // Null-space basis: Q e_j (j = rank..sf) on the free unknowns, 0 on fixed ones,
        // then a unit vector per untouched unknown (implicit).
        Self::ensure(&mut self.dense, sf * q);
        apply_q_columns(
            &self.a,
            &self.beta,
            &self.rend,
            &self.made,
            sf,
            rank,
            q,
            &mut self.dense,
            &mut self.column_sums,
            self.summation,
        );
        // Each row's span: its nonzeros (rows the earlier segments fix are 0).
        self.span.fill((0, 0));
        self.dense_row.fill(usize::MAX);
        for (a, &i) in self.qr_rows.iter().enumerate() {
            self.dense_row[i] = a;
            let row = &self.dense[a * q..(a + 1) * q];
            if let (Some(a), Some(b)) = (
                row.iter().position(|v| *v != 0.0),
                row.iter().rposition(|v| *v != 0.0),
            ) {
                self.span[i] = (a, b + 1);
            }
        }
        for (u, &i) in self.untouched.iter().enumerate() {
            let col = q + u;
            self.span[i] = (col, col + 1);
        }
    }

    /// The basis' structure: columns 0..q (q = dim − untouched.len()) are nonzero on
    /// the rows `free` only, column q + u is the unit vector of `untouched[u]`.
    /// Returns (free, untouched), both ascending.
    pub fn structure(&self) -> (&[usize], &[usize]) {
        (&self.free, &self.untouched)
    }

    /// Row i of the basis where it may be nonzero: (first column, entries). Products
    /// with N skip the rest, which is most of it (one entry per untouched unknown,
    /// none per fixed one).
    #[inline]
    pub fn row(&self, i: usize) -> (usize, &[f64]) {
        let (start, end) = self.span[i];
        match self.dense_row[i] {
            usize::MAX if end > start => (start, &[1.0]),
            usize::MAX => (start, &[]),
            a => {
                let q = self.dim - self.untouched.len();
                (start, &self.dense[a * q + start..a * q + end])
            }
        }
    }

    /// Row `i` of the basis' first q = dim − untouched columns (those of the QR's
    /// null vectors; i free, see [`NullSpace::structure`]).
    pub fn free_row(&self, i: usize) -> &[f64] {
        let q = self.dim - self.untouched.len();
        let a = self.dense_row[i];
        &self.dense[a * q..(a + 1) * q]
    }

    /// The null-space basis N written out, row-major s × dim, orthonormal columns.
    pub fn basis(&self) -> Vec<f64> {
        let mut n = vec![0.0; self.s * self.dim];
        self.basis_into(&mut n);
        n
    }

    /// [`NullSpace::basis`] into `n` (at least s × dim).
    pub fn basis_into(&self, n: &mut [f64]) {
        let dim = self.dim;
        n[..self.s * dim].fill(0.0);
        for i in 0..self.s {
            let (start, row) = self.row(i);
            n[i * dim + start..i * dim + start + row.len()].copy_from_slice(row);
        }
    }

    /// The least-norm solution x (length s) of the independent equations of the last
    /// [`NullSpace::reduce`] for another right-hand side b (damped along nearly
    /// dependent ones, see [`NullSpace::CORRECTION_TOLERANCE`]): a second-order
    /// correction reuses the factors of C.
    pub fn solve(&mut self, b: &[f64], x: &mut [f64]) {
        let s = self.s;
        x.fill(0.0);
        for &i in &self.pinned {
            if let Some(j) = self.fixed[i] {
                x[i] = b[j] / self.pin_coef[i];
            }
        }
        let sf = self.free.len();
        let rank = self.rank - (s - sf - self.untouched.len());
        // The other equations on the free unknowns: b − C[:, fixed] x_fixed.
        let np = self.pinned.len();
        for (k, &j) in self.others.iter().enumerate() {
            let row = &self.others_pinned[k * np..(k + 1) * np];
            let mut v = b[j];
            for (c, &i) in row.iter().zip(&self.pinned) {
                v -= c * x[i];
            }
            self.rhs[k] = v * self.row_scale[k];
        }
        // The selected equations read R₁ᵀ Q₁ᵀ x_free = b_sel: R₁ᵀ w = b_sel, x = Q₁ w,
        // with a damped division by pivots below 10 μ (CORRECTION_TOLERANCE).
        let mu = Self::CORRECTION_TOLERANCE
            * self.rdiag[..rank]
                .iter()
                .fold(0.0f64, |m, r| m.max(r.abs()));
        // A group apart is finished at once: its reflectors turn its w into x on its
        // rows, which the later equations (C's coefficients there) then read.
        for gi in 0..self.made.len() {
            let GroupReflectors { ks, ke, apart } = self.made[gi];
            for i in ks..ke {
                let mut acc = self.rhs[self.perm[i]];
                match self.summation {
                    Summation::Sequential => {
                        // R's column i is 0 above the rows its support tracking
                        // saw first (0 where nothing is tracked).
                        for l in self.r_start(i)..i {
                            acc -= self.a[i * sf + l] * self.w[l];
                        }
                    }
                    Summation::Lanes => {
                        acc -= dot(&self.a[i * sf..i * sf + i], &self.w[..i], self.summation)
                    }
                }
                let r = self.rdiag[i];
                self.w[i] =
                    if r.abs() >= 10.0 * mu || acc.abs() > Self::NOISE_MARGIN * self.noise_floor {
                        acc / r
                    } else {
                        let x = (mu / r).powi(2).powi(2).powi(2).powi(2);
                        acc / (r * (1.0 + x))
                    };
            }
            if apart {
                for k in (ks..ke).rev() {
                    self.reflect(k, sf);
                }
            }
        }
        self.w[rank..sf].fill(0.0);
        self.apply_q_to_w(sf);
        for (a, &i) in self.qr_rows.iter().enumerate() {
            x[i] = self.w[a];
        }
    }

    /// Least-squares multipliers of the last [`NullSpace::reduce`]'s equations for a
    /// gradient g (length s): λ (one per equation, 0 on dropped ones) minimizing
    /// ‖Cᵀλ + g‖, from the same factors. A unit equation takes all of g on its unknown;
    /// the others, through the QR, what is left on the free unknowns.
    pub fn multipliers(&mut self, g: &[f64], lambda: &mut [f64]) {
        // Cᵀλ = −g solved as `solve_transpose` does: least squares on the QR's
        // unknowns, exact on the unknowns unit equations fix.
        let mut minus = std::mem::take(&mut self.scratch_g);
        minus.clear();
        minus.extend(g.iter().map(|v| -v));
        self.solve_transpose(&minus, lambda);
        self.scratch_g = minus;
    }
}

impl NullSpace {
    /// A solution μ (one entry per equation of the last [`NullSpace::reduce`]) of
    /// Cᵀ μ = r (r of length s) that is exact whenever the system is consistent: on
    /// the QR's unknowns A μ_others = r_free with A = Cᵀ[free, others] = Q R Pᵀ, so
    /// μ = P R₁⁻¹ (Qᵀ r_free)₁..rank (the dependent equations get 0); then each
    /// unit equation takes what its unknown's row leaves, r_i − Σ C[j][i] μ_j over
    /// the others (a duplicate unit equation gets 0). Rows of untouched unknowns
    /// (0 = r_i) are not checked.
    pub fn solve_transpose(&mut self, r: &[f64], mu: &mut [f64]) {
        let s = self.s;
        mu[..self.rows].fill(0.0);
        let sf = self.free.len();
        let rank = self.rank - (s - sf - self.untouched.len());
        // w = Qᵀ r_free = H_{rank−1} ⋯ H₀ r_free, but for the groups apart (their rows
        // keep r until the later unknowns are known).
        for (a, &i) in self.qr_rows.iter().enumerate() {
            self.w[a] = r[i];
        }
        for gi in 0..self.made.len() {
            let GroupReflectors { ks, ke, apart } = self.made[gi];
            if !apart {
                for k in ks..ke {
                    self.reflect(k, sf);
                }
            }
        }
        // R₁ z = w₁..rank (R above the diagonal of `a`, column-major, its diagonal in
        // `rdiag`), group by group from the last; a group apart first takes the later
        // unknowns out of its rows (C's coefficients there) and then its Qᵀ.
        for gi in (0..self.made.len()).rev() {
            let GroupReflectors { ks, ke, apart } = self.made[gi];
            if apart {
                for i in ks..ke {
                    let mut acc = self.w[i];
                    for j in ke..rank {
                        acc -= self.a[j * sf + i] * self.w[j];
                    }
                    self.w[i] = acc;
                }
                for k in ks..ke {
                    self.reflect(k, sf);
                }
            }
            for i in (ks..ke).rev() {
                let mut acc = self.w[i];
                let upto = if apart { ke } else { rank };
                for j in i + 1..upto {
                    acc -= self.a[j * sf + i] * self.w[j];
                }
                self.w[i] = acc / self.rdiag[i];
            }
        }
        // The QR's multipliers are those of the normalized equations.
        for i in 0..rank {
            let k = self.perm[i];
            mu[self.others[k]] = self.w[i] * self.row_scale[k];
        }
        let np = self.pinned.len();
        for (t, &i) in self.pinned.iter().enumerate() {
            if let Some(j) = self.fixed[i] {
                let mut v = r[i];
                for (k, &o) in self.others.iter().enumerate() {
                    v -= self.others_pinned[k * np + t] * mu[o];
                }
                mu[j] = v / self.pin_coef[i];
            }
        }
    }
}
