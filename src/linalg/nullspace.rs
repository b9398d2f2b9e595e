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
    w: Vec<f64>,
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
    /// in that equation is of the order of its round-off. μ = 5e-5 lets the
    /// parallelogram pass its flat configurations in dependent coordinates at
    /// Δt = 1, 0.1 and 0.01 ms, and the N four-bars (N up to 40) at every Δt and
    /// window of the robustness matrix; the range that does is narrow: at 3e-5 the
    /// parallelogram diverges at 0.01 ms, at 1e-4 the 10 four-bar at 20 ms.
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
            w: vec![0.0; s],
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
        for j in 0..rows {
            let row = &c[j * s..(j + 1) * s];
            let mut nonzero = row
                .iter()
                .enumerate()
                .filter(|(_, v)| **v != 0.0)
                .map(|(i, _)| i);
            match (nonzero.next(), nonzero.next()) {
                (Some(i), None) => {
                    if self.fixed[i].is_none() {
                        self.fixed[i] = Some(j);
                    }
                }
                (None, None) => {}
                (Some(i0), Some(i1)) => {
                    self.others.push(j);
                    touched[i0] = true;
                    touched[i1] = true;
                    for i in nonzero {
                        touched[i] = true;
                    }
                }
                (None, Some(_)) => unreachable!("a second nonzero without a first"),
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
        // A = Cᵀ[free, others]: column k is equation others[k] on the free unknowns;
        // its group is the segment of the last of them it touches.
        for (k, &j) in self.others.iter().enumerate() {
            let col = &mut self.a[k * sf..(k + 1) * sf];
            for (o, &i) in col.iter_mut().zip(&self.qr_rows) {
                *o = c[j * s + i];
            }
            self.group[k] = col
                .iter()
                .rposition(|v| *v != 0.0)
                .map_or(0, |a| self.segment[self.qr_rows[a]]);
            // Its size on the unknowns of its own segment, those its pivot is taken
            // from: an acceleration row's coefficients on q and q̇ grow like q̇², its
            // pivot on q̈ does not.
            let g = self.group[k];
            let norm = col
                .iter()
                .zip(&self.qr_rows)
                .filter(|(_, &i)| self.segment[i] == g)
                .map(|(v, _)| v * v)
                .sum::<f64>()
                .sqrt();
            let scale = if norm > 0.0 { 1.0 / norm } else { 1.0 };
            self.row_scale[k] = scale;
            for o in col.iter_mut() {
                *o *= scale;
            }
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
        for j in rank..sf {
            self.w[..sf].fill(0.0);
            self.w[j] = 1.0;
            apply_q(
                &self.a,
                &self.beta,
                &self.rend,
                &self.made,
                sf,
                &mut self.w[..sf],
                self.summation,
            );
            for a in 0..sf {
                self.dense[a * q + (j - rank)] = self.w[a];
            }
        }
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
        let dim = self.dim;
        let mut n = vec![0.0; self.s * dim];
        for i in 0..self.s {
            let (start, row) = self.row(i);
            n[i * dim + start..i * dim + start + row.len()].copy_from_slice(row);
        }
        n
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
                        for l in 0..i {
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
        apply_q(
            &self.a,
            &self.beta,
            &self.rend,
            &self.made,
            sf,
            &mut self.w[..sf],
            self.summation,
        );
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

/// Marks a column of the QR found dependent.
const DROPPED: usize = usize::MAX;

/// How the columns of a grouped QR are grouped: per column its group (a segment),
/// per segment the end of its rows; filled in, per reflector the end of its rows,
/// and per group the reflectors it made and whether it stands apart (see
/// [`householder_grouped`]).
struct Grouping<'a> {
    group: &'a mut [usize],
    seg_end: &'a [usize],
    rend: &'a mut [usize],
    made: &'a mut Vec<GroupReflectors>,
}

/// The reflectors ks..ke of one group; `apart` when they span exactly its segment's
/// rows (nothing left of earlier segments, the segment fully determined): they were
/// not applied to the later groups' columns, whose rows there keep C's coefficients.
#[derive(Debug, Clone, Copy)]
struct GroupReflectors {
    ks: usize,
    ke: usize,
    apart: bool,
}

// Kept hand-written although faer's column-pivoted QR is faster on one dense segment
// from s ≈ 16 on (`benches/linalg.rs`, group `nullspace`: faer/hand 1.3–1.8 at s ≤ 8,
// 0.9 at 16–32, 0.3 at 70–120): faer pivots over all columns and blocks its
// reflectors, so it cannot pivot segment by segment, stop a reflector at its
// segment's rows or leave a group apart, which the solver's reductions rely on.
/// Householder QR with column pivoting of the column-major `s` × `m` matrix `a`,
/// group by group: the pivot is the column of largest remaining norm in the current
/// group, whose columns are 0 past their segment's rows, so its reflectors and their
/// updates stop there. A group ends at its first pivot below
/// [`NullSpace::RANK_TOLERANCE`] relative to the largest column (its other columns
/// are dependent). A group's reflectors reach the later groups' columns only when
/// they must: when the group leaves rows of its segment (or found rows of earlier
/// ones) for the later groups; when it determines exactly its segment's rows, the
/// later columns keep C's coefficients there, and [`NullSpace::solve`] substitutes
/// the segment's solution into them instead. Returns the rank. With one group this
/// is the plain pivoted QR, operation for operation. Reflectors stay below the
/// diagonal, R above it with its diagonal in `rdiag`; `perm[k]` is the original
/// column now at k. Column norms are downdated, and recomputed when cancellation has
/// eaten most of them.
#[allow(clippy::too_many_arguments)]
fn householder_grouped(
    a: &mut [f64],
    s: usize,
    m: usize,
    grouping: Grouping,
    how: Summation,
    rdiag: &mut [f64],
    beta: &mut [f64],
    perm: &mut [usize],
    norms: &mut [f64],
) -> usize {
    let Grouping {
        group,
        seg_end,
        rend,
        made,
    } = grouping;
    made.clear();
    if m == 0 || s == 0 {
        return 0;
    }
    let (partial, reference) = norms.split_at_mut(m);
    let mut largest = 0.0f64;
    for j in 0..m {
        perm[j] = j;
        let col = &a[j * s..(j + 1) * s];
        let n2 = dot(col, col, how);
        partial[j] = n2;
        reference[j] = n2;
        largest = largest.max(n2);
    }
    let tol2 = (NullSpace::RANK_TOLERANCE * largest.sqrt()).powi(2);
    let groups = seg_end.len();
    let mut k = 0;
    for g in 0..groups {
        let end = seg_end[g];
        let start = if g > 0 { seg_end[g - 1] } else { 0 };
        let ks = k;
        if groups > 1 {
            // Norms over the live rows (earlier groups' reflectors may not have
            // reached these columns).
            for j in k..m {
                if group[j] == g {
                    let live = &a[j * s + k..j * s + end];
                    partial[j] = dot(live, live, how);
                    reference[j] = partial[j];
                }
            }
        }
        while k < s.min(m) {
            let mut best = None;
            for j in k..m {
                if group[j] == g && best.is_none_or(|b| partial[j] > partial[b]) {
                    best = Some(j);
                }
            }
            let exhausted = match best {
                None => true,
                Some(b) if partial[b] <= tol2 => {
                    // Confirm with exact norms before declaring the rest dependent.
                    let live = &a[b * s + k..b * s + end];
                    let exact = dot(live, live, how);
                    if exact <= tol2 {
                        true
                    } else {
                        partial[b] = exact;
                        false
                    }
                }
                Some(_) => false,
            };
            if exhausted {
                for gj in group[k..m].iter_mut().filter(|gj| **gj == g) {
                    *gj = DROPPED;
                }
                break;
            }
            let best = best.expect("a column of the group");
            if best != k {
                for i in 0..s {
                    a.swap(k * s + i, best * s + i);
                }
                perm.swap(k, best);
                partial.swap(k, best);
                reference.swap(k, best);
                group.swap(k, best);
            }
            let col = &mut a[k * s + k..k * s + end];
            let norm = dot(col, col, how).sqrt();
            let alpha = if col[0] > 0.0 { -norm } else { norm };
            col[0] -= alpha;
            let vnorm2 = dot(col, col, how);
            let b = if vnorm2 > 0.0 { 2.0 / vnorm2 } else { 0.0 };
            rdiag[k] = alpha;
            beta[k] = b;
            rend[k] = end;
            let (left, right) = a.split_at_mut((k + 1) * s);
            let v = &left[k * s + k..k * s + end];
            for (jj, y) in right.chunks_exact_mut(s).take(m - k - 1).enumerate() {
                let j = k + 1 + jj;
                // This group's columns now; the later ones below, if at all.
                if group[j] != g {
                    continue;
                }
                let live = &mut y[k..end];
                let f = b * dot(v, live, how);
                for (yi, vi) in live.iter_mut().zip(v) {
                    *yi -= f * vi;
                }
                // Downdate the partial norm of rows k+1.. of this column.
                partial[j] -= live[0] * live[0];
                if partial[j] < 1e-4 * reference[j] {
                    partial[j] = dot(&y[k + 1..], &y[k + 1..], how);
                    reference[j] = partial[j];
                }
            }
            k += 1;
        }
        let apart = ks == start && k == end;
        if !apart && g + 1 < groups {
            // The later groups' columns see this group's reflectors, in order.
            for r in ks..k {
                let (left, right) = a.split_at_mut((r + 1) * s);
                let v = &left[r * s + r..r * s + end];
                for (jj, y) in right.chunks_exact_mut(s).take(m - r - 1).enumerate() {
                    let j = r + 1 + jj;
                    if group[j] == DROPPED || group[j] <= g {
                        continue;
                    }
                    let live = &mut y[r..end];
                    let f = beta[r] * dot(v, live, how);
                    for (yi, vi) in live.iter_mut().zip(v) {
                        *yi -= f * vi;
                    }
                }
            }
        }
        made.push(GroupReflectors { ks, ke: k, apart });
        if k == s.min(m) {
            break;
        }
    }
    k
}

/// x ← H₀ H₁ … H_{r−1} x with the reflectors stored below the diagonal of `a`
/// (reflector k nonzero on rows k..rend[k]), leaving out the groups apart (their
/// rows are 0 in the null-space vectors, and `solve` applies them itself).
#[allow(clippy::too_many_arguments)]
fn apply_q(
    a: &[f64],
    beta: &[f64],
    rend: &[usize],
    made: &[GroupReflectors],
    s: usize,
    x: &mut [f64],
    how: Summation,
) {
    for g in made.iter().rev().filter(|g| !g.apart) {
        for k in (g.ks..g.ke).rev() {
            let end = rend[k];
            let v = &a[k * s + k..k * s + end];
            let y = &mut x[k..end];
            let f = beta[k] * dot(v, y, how);
            for (yi, vi) in y.iter_mut().zip(v) {
                *yi -= f * vi;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::DMatrix;

    fn pseudo_random(seed: &mut u64) -> f64 {
        *seed = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((*seed >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0
    }

    /// C = A B with A rows × rank and B rank × s has rank `rank`.
    fn low_rank(rows: usize, s: usize, rank: usize, seed: &mut u64) -> DMatrix<f64> {
        let a = DMatrix::from_fn(rows, rank, |_, _| pseudo_random(seed));
        let b = DMatrix::from_fn(rank, s, |_, _| pseudo_random(seed));
        a * b
    }

    #[test]
    fn basis_spans_the_null_space_and_particular_solution_is_least_norm() {
        let mut seed = 7;
        for &(rows, s, rank) in &[
            (3, 5, 3),
            (6, 12, 4),
            (8, 6, 6),
            (7, 7, 5),
            (1, 3, 1),
            (5, 9, 0),
        ] {
            let c = low_rank(rows, s, rank, &mut seed);
            let x_true = DMatrix::from_fn(s, 1, |_, _| pseudo_random(&mut seed));
            let b = &c * &x_true; // consistent right-hand side
            let row_major: Vec<f64> = c.transpose().iter().copied().collect();
            let mut ns = NullSpace::new(s, rows);
            ns.reduce(&row_major, b.as_slice(), rows);
            assert_eq!(ns.rank, rank, "rank of a {rows}×{s} matrix");
            assert_eq!(ns.dim, s - rank);
            let n = DMatrix::from_row_slice(s, ns.dim, &ns.basis());
            let p = DMatrix::from_column_slice(s, 1, &ns.particular);
            assert!((&c * &n).amax() < 1e-12, "C N = 0");
            for i in 0..s {
                let (start, row) = ns.row(i);
                for j in 0..ns.dim {
                    let inside = j >= start && j < start + row.len();
                    let v = if inside { row[j - start] } else { 0.0 };
                    assert_eq!(
                        v,
                        ns.basis()[i * ns.dim + j],
                        "row {i} of N outside its span"
                    );
                }
            }
            let ntn = n.transpose() * &n;
            assert!(
                (ntn - DMatrix::identity(ns.dim, ns.dim)).amax() < 1e-12,
                "NᵀN = I"
            );
            assert!((&c * &p - &b).amax() < 1e-10, "C p = b");
            assert!((n.transpose() * &p).amax() < 1e-12, "p ⟂ null(C)");
            let b2 = &c * DMatrix::from_fn(s, 1, |_, _| pseudo_random(&mut seed));
            let mut x = vec![0.0; s];
            ns.solve(b2.as_slice(), &mut x);
            let x = DMatrix::from_column_slice(s, 1, &x);
            assert!((&c * &x - &b2).amax() < 1e-10, "C x = b for another b");
        }
    }

    #[test]
    fn unit_equations_fix_their_unknowns_and_the_rest_reduce_as_before() {
        let mut seed = 11;
        let (s, rows) = (9, 7);
        for trial in 0..5 {
            // Rows 0..3 unit rows on unknowns 2, 5, 5 (a redundant duplicate), the
            // rest dense and rank-deficient.
            let mut c = DMatrix::zeros(rows, s);
            c[(0, 2)] = 2.0;
            c[(1, 5)] = -0.5;
            c[(2, 5)] = 1.5;
            let dense = low_rank(rows - 3, s, 2 + trial % 2, &mut seed);
            c.view_mut((3, 0), (rows - 3, s)).copy_from(&dense);
            let x_true = DMatrix::from_fn(s, 1, |_, _| pseudo_random(&mut seed));
            let b = &c * &x_true;
            let row_major: Vec<f64> = c.transpose().iter().copied().collect();
            let mut ns = NullSpace::new(s, rows);
            ns.reduce(&row_major, b.as_slice(), rows);
            let rank = c.clone().svd(false, false).rank(1e-9);
            assert_eq!(ns.rank, rank, "trial {trial}");
            let n = DMatrix::from_row_slice(s, ns.dim, &ns.basis());
            let p = DMatrix::from_column_slice(s, 1, &ns.particular);
            assert!((&c * &n).amax() < 1e-12);
            assert!((n.transpose() * &n - DMatrix::identity(ns.dim, ns.dim)).amax() < 1e-12);
            assert!((&c * &p - &b).amax() < 1e-10);
            assert!((p[2] - x_true[2]).abs() < 1e-14 && (p[5] - x_true[5]).abs() < 1e-14);
            assert!(n.row(2).amax() == 0.0 && n.row(5).amax() == 0.0);
        }
    }

    /// A kept equation whose pivot is far below the largest (RANK_TOLERANCE <
    /// R/R₀ < CORRECTION_TOLERANCE) is corrected with a damped step: the least-norm
    /// solution stays below b/μ instead of b/R, the equation pivoted first still
    /// holds, and well above μ the solution is the exact one.
    #[test]
    fn nearly_dependent_equations_get_a_damped_correction() {
        // Rows (1, 1, 0) and (1, 1 + δ, 0): the second pivot is about δ/2 of the first.
        for (delta, damped) in [(1e-9, true), (1e-3, false)] {
            let c = [1.0, 1.0, 0.0, 1.0, 1.0 + delta, 0.0];
            let b = [0.0, 1e-12];
            let mut ns = NullSpace::new(3, 2);
            ns.reduce(&c, &b, 2);
            assert_eq!(ns.rank, 2, "δ = {delta}: the equation is kept");
            assert_eq!(ns.dim, 1);
            let p = &ns.particular;
            let (r0, r1) = (p[0] + p[1], p[0] + (1.0 + delta) * p[1] - 1e-12);
            assert!(
                r0.abs().min(r1.abs()) < 1e-15 && r0.abs().max(r1.abs()) <= 1e-12,
                "δ = {delta}: the equation pivoted first holds, the other is left at most \
                 its residual (residuals {r0:e}, {r1:e})"
            );
            if damped {
                let mu = NullSpace::CORRECTION_TOLERANCE;
                assert!(
                    p[1].abs() <= 1e-12 / mu,
                    "δ = {delta}: correction {:e} not damped",
                    p[1]
                );
            } else {
                let exact = 1e-12 / delta;
                assert!(
                    (p[1] - exact).abs() <= 1e-12 * exact,
                    "δ = {delta}: {:e} instead of the exact {exact:e}",
                    p[1]
                );
            }
            assert_eq!(
                ns.basis()[2 * ns.dim],
                1.0,
                "the untouched unknown stays free"
            );
        }
    }

    /// The damping is for round-off only: a nearly dependent equation whose residual
    /// stands far above the round-off its noise declares is corrected exactly (the
    /// velocity constraints of a 10-loop chain a few 1e-6 from its flat configuration,
    /// left 4e-8 off by the damping, stalled its solves), one at its round-off is still
    /// damped, and without declared noise every one is.
    #[test]
    fn a_residual_above_its_round_off_is_corrected_exactly() {
        let delta = 1e-7;
        let c = [1.0, 1.0, 0.0, 1.0, 1.0 + delta, 0.0];
        let exact = |b: f64| b / delta;
        for (b1, noise, exact_expected) in [
            (1e-8, Some(1e-16), true),
            (1e-14, Some(1e-16), false),
            (1e-8, None, false),
        ] {
            let mut ns = NullSpace::new(3, 2);
            if let Some(e) = noise {
                ns.set_noise(&[e, e]);
            }
            ns.reduce(&c, &[0.0, b1], 2);
            let p1 = ns.particular[1];
            if exact_expected {
                assert!(
                    (p1 - exact(b1)).abs() <= 1e-6 * exact(b1),
                    "b = {b1:e}: {p1:e} instead of {:e}",
                    exact(b1)
                );
            } else {
                assert!(
                    p1.abs() <= b1 / NullSpace::CORRECTION_TOLERANCE,
                    "b = {b1:e}, noise {noise:?}: correction {p1:e} not damped"
                );
            }
        }
    }

    /// Equations of very different sizes are independent all the same: the
    /// reduction's rank, particular solution and multipliers do not change when one
    /// equation is scaled by 1e-8 (as the damping would, were the pivots compared
    /// with the largest equation's).
    #[test]
    fn equations_of_very_different_sizes_are_solved_exactly() {
        let c = [2.0, 1.0, 0.0, 0.0, 1.0, 3.0];
        let b = [1.0, 2.0];
        let mut plain = NullSpace::new(3, 2);
        plain.reduce(&c, &b, 2);
        for scale in [1e-8, 1e8] {
            let cs = [2.0, 1.0, 0.0, 0.0, scale, 3.0 * scale];
            let bs = [1.0, 2.0 * scale];
            let mut ns = NullSpace::new(3, 2);
            ns.reduce(&cs, &bs, 2);
            assert_eq!(ns.rank, 2, "scale {scale:e}");
            for (p, q) in ns.particular.iter().zip(&plain.particular) {
                assert!(
                    (p - q).abs() <= 1e-12,
                    "scale {scale:e}: {p:e} against {q:e}"
                );
            }
            let g = [0.3, -0.7, 1.1];
            let (mut l, mut lp) = ([0.0; 2], [0.0; 2]);
            ns.multipliers(&g, &mut l);
            plain.multipliers(&g, &mut lp);
            assert!(
                (l[0] - lp[0]).abs() <= 1e-12
                    && (l[1] * scale - lp[1]).abs() <= 1e-9 * lp[1].abs().max(1.0),
                "scale {scale:e}: multipliers {l:?} against {lp:?}"
            );
        }
    }

    #[test]
    fn transposed_solve_is_exact_for_consistent_systems() {
        let mut seed = 23;
        let (s, rows) = (8, 9);
        for trial in 0..4 {
            // Unit rows on unknowns 1 and 6, the rest dense (rank-deficient on odd
            // trials, so some equations are dependent).
            let mut c = DMatrix::zeros(rows, s);
            c[(0, 1)] = 1.5;
            c[(1, 6)] = -2.0;
            let dense = low_rank(rows - 2, s, 5 + trial % 2, &mut seed);
            c.view_mut((2, 0), (rows - 2, s)).copy_from(&dense);
            let mu_true = DMatrix::from_fn(rows, 1, |_, _| pseudo_random(&mut seed));
            let r = c.transpose() * &mu_true; // consistent
            let row_major: Vec<f64> = c.transpose().iter().copied().collect();
            let mut ns = NullSpace::new(s, rows);
            ns.reduce(&row_major, &vec![0.0; rows], rows);
            let mut mu = vec![0.0; rows];
            ns.solve_transpose(r.as_slice(), &mut mu);
            let back = c.transpose() * DMatrix::from_column_slice(rows, 1, &mu);
            assert!((back - &r).amax() < 1e-10, "trial {trial}: Cᵀμ = r");
        }
    }

    #[test]
    fn segments_give_the_same_reduction_and_zeros_where_earlier_ones_fix() {
        // Block-triangular equations on (x, v, a), 4 unknowns each: A x = ·,
        // B x + A v = ·, with A rank 3 (one redundant row in each block), one unit
        // row on x; a untouched.
        let mut seed = 5;
        let (s, rows) = (12, 9);
        for trial in 0..4 {
            let a = low_rank(4, 4, 3, &mut seed);
            let b = DMatrix::from_fn(4, 4, |_, _| pseudo_random(&mut seed));
            let mut c = DMatrix::zeros(rows, s);
            c.view_mut((0, 0), (4, 4)).copy_from(&a);
            c.view_mut((4, 0), (4, 4)).copy_from(&b);
            c.view_mut((4, 4), (4, 4)).copy_from(&a);
            c[(8, trial % 4)] = 1.0;
            let x_true = DMatrix::from_fn(s, 1, |_, _| pseudo_random(&mut seed));
            let rhs = &c * &x_true;
            let row_major: Vec<f64> = c.transpose().iter().copied().collect();
            let mut plain = NullSpace::new(s, rows);
            plain.reduce(&row_major, rhs.as_slice(), rows);
            let mut seg = NullSpace::new(s, rows);
            seg.set_segments(&[0, 0, 0, 0, 1, 1, 1, 1, 2, 2, 2, 2]);
            seg.reduce(&row_major, rhs.as_slice(), rows);
            assert_eq!(
                (seg.rank, seg.dim),
                (plain.rank, plain.dim),
                "trial {trial}"
            );
            let n = DMatrix::from_row_slice(s, seg.dim, &seg.basis());
            let n0 = DMatrix::from_row_slice(s, plain.dim, &plain.basis());
            assert!((&c * &n).amax() < 1e-12, "C N = 0");
            assert!((n.transpose() * &n - DMatrix::identity(seg.dim, seg.dim)).amax() < 1e-12);
            // The same space: N₀ N₀ᵀ N = N.
            assert!((&n0 * (n0.transpose() * &n) - &n).amax() < 1e-12);
            for i in 0..s {
                assert!((seg.particular[i] - plain.particular[i]).abs() < 1e-12);
                let (start, row) = seg.row(i);
                for j in 0..seg.dim {
                    let inside = j >= start && j < start + row.len();
                    let v = if inside { row[j - start] } else { 0.0 };
                    assert_eq!(
                        v,
                        seg.basis()[i * seg.dim + j],
                        "row {i} of N outside its span"
                    );
                }
            }
            let b2 = &c * DMatrix::from_fn(s, 1, |_, _| pseudo_random(&mut seed));
            let (mut x1, mut x2) = (vec![0.0; s], vec![0.0; s]);
            plain.solve(b2.as_slice(), &mut x1);
            seg.solve(b2.as_slice(), &mut x2);
            assert!(x1.iter().zip(&x2).all(|(a, b)| (a - b).abs() < 1e-12));
            let mu_true = DMatrix::from_fn(rows, 1, |_, _| pseudo_random(&mut seed));
            let r = c.transpose() * &mu_true;
            let mut mu = vec![0.0; rows];
            seg.solve_transpose(r.as_slice(), &mut mu);
            let back = c.transpose() * DMatrix::from_column_slice(rows, 1, &mu);
            assert!((back - &r).amax() < 1e-10, "Cᵀμ = r");
        }
        // x fully fixed (A regular): the basis is exactly 0 on x.
        let a = DMatrix::from_fn(4, 4, |_, _| pseudo_random(&mut seed));
        let b = DMatrix::from_fn(3, 4, |_, _| pseudo_random(&mut seed));
        let mut c = DMatrix::zeros(7, 12);
        c.view_mut((0, 0), (4, 4)).copy_from(&a);
        c.view_mut((4, 0), (3, 4)).copy_from(&b);
        c.view_mut((4, 4), (3, 4)).copy_from(&a.rows(0, 3));
        let row_major: Vec<f64> = c.transpose().iter().copied().collect();
        let rhs: Vec<f64> = (0..7).map(|_| pseudo_random(&mut seed)).collect();
        let mut plain = NullSpace::new(12, 7);
        plain.reduce(&row_major, &rhs, 7);
        for how in [Summation::Sequential, Summation::Lanes] {
            let mut seg = NullSpace::new(12, 7);
            seg.set_segments(&[0, 0, 0, 0, 1, 1, 1, 1, 2, 2, 2, 2]);
            seg.set_summation(how);
            seg.reduce(&row_major, &rhs, 7);
            assert_eq!(seg.dim, 5);
            // The positions' group stands apart: its reflectors never reach the
            // velocity equations, whose solution reads the positions' instead.
            assert!(seg.made[0].apart && !seg.made[1].apart);
            for i in 0..4 {
                assert!(seg.row(i).1.is_empty(), "row {i} of N");
            }
            for i in 0..12 {
                assert!((seg.particular[i] - plain.particular[i]).abs() < 1e-12);
            }
            let n = DMatrix::from_row_slice(12, seg.dim, &seg.basis());
            assert!((&c * &n).amax() < 1e-12, "C N = 0");
            assert!((n.transpose() * &n - DMatrix::identity(seg.dim, seg.dim)).amax() < 1e-12);
            let b2 = &c * DMatrix::from_fn(12, 1, |_, _| pseudo_random(&mut seed));
            let (mut x1, mut x2) = (vec![0.0; 12], vec![0.0; 12]);
            plain.solve(b2.as_slice(), &mut x1);
            seg.solve(b2.as_slice(), &mut x2);
            assert!(x1.iter().zip(&x2).all(|(a, b)| (a - b).abs() < 1e-12));
            let mu_true = DMatrix::from_fn(7, 1, |_, _| pseudo_random(&mut seed));
            let r = c.transpose() * &mu_true;
            let mut mu = vec![0.0; 7];
            seg.solve_transpose(r.as_slice(), &mut mu);
            let back = c.transpose() * DMatrix::from_column_slice(7, 1, &mu);
            assert!((back - &r).amax() < 1e-10, "Cᵀμ = r");
        }
    }

    #[test]
    fn multipliers_solve_the_least_squares_problem() {
        // Dense rank-deficient equations, and unit rows (one of them a duplicate)
        // next to them: C(Cᵀλ + g) = 0 is the least-squares condition.
        let mut seed = 5;
        for &(rows, s, rank, units) in &[(3, 6, 3, 0), (6, 12, 4, 0), (7, 9, 3, 3), (5, 5, 4, 2)] {
            let mut c = DMatrix::zeros(rows, s);
            let dense = low_rank(rows - units, s, rank, &mut seed);
            c.view_mut((units, 0), (rows - units, s)).copy_from(&dense);
            for u in 0..units {
                c[(u, 1 + (u % 2) * 2)] = 1.5 + u as f64;
            }
            let g = DMatrix::from_fn(s, 1, |_, _| pseudo_random(&mut seed));
            let row_major: Vec<f64> = c.transpose().iter().copied().collect();
            let mut ns = NullSpace::new(s, rows);
            ns.reduce(&row_major, &vec![0.0; rows], rows);
            let mut lambda = vec![0.0; rows];
            ns.multipliers(g.as_slice(), &mut lambda);
            let l = DMatrix::from_column_slice(rows, 1, &lambda);
            let residual = c.transpose() * l + &g;
            assert!(
                (&c * &residual).amax() < 1e-12,
                "C(Cᵀλ + g) = {:e} for a {rows}×{s} system of rank {rank}",
                (&c * &residual).amax()
            );
        }
    }

    #[test]
    fn no_equations_leave_every_direction_free() {
        let mut ns = NullSpace::new(3, 2);
        ns.reduce(&[], &[], 0);
        assert_eq!(ns.dim, 3);
        assert_eq!(
            ns.basis(),
            vec![1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
        );
    }
}
