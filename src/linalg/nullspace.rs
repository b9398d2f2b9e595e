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
//! Equations that are kept but nearly dependent (a pivot far below the largest, as
//! near a singular configuration, where the position and velocity constraints lose a
//! rank together and the step's pivot falls like the square of the distance) are
//! satisfied with a damped correction: correcting them exactly would divide the
//! round-off in their residual by that pivot and move the state along the direction
//! they barely fix by that much, every iteration (see [`NullSpace::CORRECTION_TOLERANCE`]).

/// Scratch and results of one reduction, sized once for `s` unknowns and up to
/// `max_rows` equations.
#[derive(Debug, Clone)]
pub struct NullSpace {
    s: usize,
    max_rows: usize,
    /// The equations of the last reduction, row-major rows × s (for `solve`).
    c: Vec<f64>,
    rows: usize,
    /// Per unknown: the unit equation fixing it, if any.
    fixed: Vec<Option<usize>>,
    /// Unknowns neither fixed by unit equations nor untouched by the others (those
    /// the QR sees), the other equations, and the unknowns no equation touches.
    free: Vec<usize>,
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
    /// s × s row-major; columns 0..dim hold an orthonormal null-space basis, the rest 0.
    pub basis: Vec<f64>,
    /// Per row of the basis, the columns [start, end) outside which it is 0 (fixed
    /// unknowns: none; untouched ones: their unit column; the rest: the QR's columns).
    span: Vec<(usize, usize)>,
    /// The least-norm solution of the independent equations (exact on fixed unknowns).
    pub particular: Vec<f64>,
    /// Dimension of the null space.
    pub dim: usize,
    /// Rank of C.
    pub rank: usize,
}

impl NullSpace {
    /// Relative size below which a pivot counts as zero (rank-deficient direction).
    pub const RANK_TOLERANCE: f64 = 1e-10;

    /// Relative size μ (to the largest pivot) below which a kept pivot R gets a
    /// damped correction: the component w = b/R of the least-norm solution becomes
    /// b/(R(1 + (μ/R)¹⁶)), which is b/R to round-off for R ≥ 10μ (exactly b/R is
    /// used there) and below 0.8 b/μ everywhere. Near a singular configuration the
    /// pivot of a step's position and velocity constraints together falls like the
    /// square of the distance to it; an exact correction there divides the round-off
    /// in the residual by the pivot and, in the parallelogram, moves the state along
    /// the anti-parallelogram velocity by up to 1e-7 per iteration, so the window
    /// solves stall on that noise. The residual a damped correction leaves in that
    /// equation is of the order of its round-off. Regular motion stays above 10μ:
    /// the smallest pivot in the scene suite is 2.9e-5 (the four-bar in independent
    /// coordinates, whose acceleration rows scale with q̇); μ from 1e-7 to 1e-6 lets
    /// the parallelogram pass in dependent coordinates at every Δt and phase tried.
    pub const CORRECTION_TOLERANCE: f64 = 3e-7;

    pub fn new(s: usize, max_rows: usize) -> Self {
        let mut ns = NullSpace {
            s,
            max_rows,
            c: vec![0.0; s * max_rows],
            rows: 0,
            fixed: vec![None; s],
            free: Vec::with_capacity(s),
            others: Vec::with_capacity(max_rows),
            untouched: Vec::with_capacity(s),
            pinned: Vec::with_capacity(s),
            a: vec![0.0; s * max_rows],
            rdiag: vec![0.0; s.min(max_rows)],
            beta: vec![0.0; s.min(max_rows)],
            perm: vec![0; max_rows],
            norms: vec![0.0; 2 * max_rows],
            w: vec![0.0; s],
            rhs: vec![0.0; max_rows],
            basis: vec![0.0; s * s],
            span: vec![(0, 0); s],
            particular: vec![0.0; s],
            dim: s,
            rank: 0,
        };
        ns.set_unconstrained();
        ns
    }

    /// No equations: N = I, p = 0.
    pub fn set_unconstrained(&mut self) {
        let s = self.s;
        self.basis.fill(0.0);
        for i in 0..s {
            self.basis[i * s + i] = 1.0;
            self.span[i] = (i, i + 1);
        }
        self.particular.fill(0.0);
        self.fixed.fill(None);
        self.free.clear();
        self.others.clear();
        self.untouched.clear();
        self.untouched.extend(0..s);
        self.pinned.clear();
        self.rows = 0;
        self.dim = s;
        self.rank = 0;
    }

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
        self.c[..rows * s].copy_from_slice(&c[..rows * s]);
        // Unit equations fix their unknown; a second one on the same unknown is
        // redundant.
        self.fixed.fill(None);
        self.others.clear();
        for j in 0..rows {
            let row = &c[j * s..(j + 1) * s];
            let mut nonzero = row.iter().enumerate().filter(|(_, v)| **v != 0.0);
            match (nonzero.next(), nonzero.next()) {
                (Some((i, _)), None) => {
                    if self.fixed[i].is_none() {
                        self.fixed[i] = Some(j);
                    }
                }
                (None, None) => {}
                _ => self.others.push(j),
            }
        }
        self.free.clear();
        self.untouched.clear();
        self.pinned.clear();
        for i in 0..s {
            if self.fixed[i].is_some() {
                self.pinned.push(i);
                continue;
            }
            if self.others.iter().any(|&j| c[j * s + i] != 0.0) {
                self.free.push(i);
            } else {
                self.untouched.push(i);
            }
        }
        let sf = self.free.len();
        let m = self.others.len();
        // A = Cᵀ[free, others]: column k is equation others[k] on the free unknowns.
        for (k, &j) in self.others.iter().enumerate() {
            for (a, &i) in self.free.iter().enumerate() {
                self.a[k * sf + a] = c[j * s + i];
            }
        }
        let rank = householder_pivoted(
            &mut self.a,
            sf,
            m,
            &mut self.rdiag,
            &mut self.beta,
            &mut self.perm,
            &mut self.norms,
        );
        let fixed_count = s - sf - self.untouched.len();
        // Columns that may hold a basis vector from before (past them all is 0).
        let stale = self.dim;
        self.rank = fixed_count + rank;
        self.dim = sf - rank + self.untouched.len();
        let mut p = std::mem::take(&mut self.particular);
        self.solve(b, &mut p);
        self.particular = p;
        // Null-space basis: Q e_j (j = rank..sf) on the free unknowns, 0 on fixed ones,
        // then a unit vector per untouched unknown.
        let width = stale.max(self.dim);
        for row in self.basis.chunks_exact_mut(s) {
            row[..width].fill(0.0);
        }
        for j in rank..sf {
            self.w[..sf].fill(0.0);
            self.w[j] = 1.0;
            apply_q(&self.a, &self.beta, sf, rank, &mut self.w[..sf]);
            for (a, &i) in self.free.iter().enumerate() {
                self.basis[i * s + (j - rank)] = self.w[a];
            }
        }
        self.span.fill((0, 0));
        for &i in &self.free {
            self.span[i] = (0, sf - rank);
        }
        for (u, &i) in self.untouched.iter().enumerate() {
            let col = sf - rank + u;
            self.basis[i * s + col] = 1.0;
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
        (start, &self.basis[i * self.s + start..i * self.s + end])
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
                x[i] = b[j] / self.c[j * s + i];
            }
        }
        let sf = self.free.len();
        let rank = self.rank - (s - sf - self.untouched.len());
        // The other equations on the free unknowns: b − C[:, fixed] x_fixed.
        for (k, &j) in self.others.iter().enumerate() {
            let row = &self.c[j * s..(j + 1) * s];
            let mut v = b[j];
            for &i in &self.pinned {
                v -= row[i] * x[i];
            }
            self.rhs[k] = v;
        }
        // The selected equations read R₁ᵀ Q₁ᵀ x_free = b_sel: R₁ᵀ w = b_sel, x = Q₁ w,
        // with a damped division by pivots below 10 μ (CORRECTION_TOLERANCE).
        let mu = Self::CORRECTION_TOLERANCE * self.rdiag.first().map_or(0.0, |r| r.abs());
        for i in 0..rank {
            let mut acc = self.rhs[self.perm[i]];
            for l in 0..i {
                acc -= self.a[i * sf + l] * self.w[l];
            }
            let r = self.rdiag[i];
            self.w[i] = if r.abs() >= 10.0 * mu {
                acc / r
            } else {
                let x = (mu / r).powi(2).powi(2).powi(2).powi(2);
                acc / (r * (1.0 + x))
            };
        }
        self.w[rank..sf].fill(0.0);
        apply_q(&self.a, &self.beta, sf, rank, &mut self.w[..sf]);
        for (a, &i) in self.free.iter().enumerate() {
            x[i] = self.w[a];
        }
    }
}

/// Householder QR with column pivoting of the column-major `s` × `m` matrix `a`,
/// stopping at the first pivot below [`NullSpace::RANK_TOLERANCE`] relative to the
/// largest column; returns the rank. Reflectors stay below the diagonal, R above it
/// with its diagonal in `rdiag`; `perm[k]` is the original column now at k. Column
/// norms are downdated, and recomputed when cancellation has eaten most of them.
fn householder_pivoted(
    a: &mut [f64],
    s: usize,
    m: usize,
    rdiag: &mut [f64],
    beta: &mut [f64],
    perm: &mut [usize],
    norms: &mut [f64],
) -> usize {
    if m == 0 || s == 0 {
        return 0;
    }
    let (partial, reference) = norms.split_at_mut(m);
    let mut largest = 0.0f64;
    for j in 0..m {
        perm[j] = j;
        let n2: f64 = a[j * s..(j + 1) * s].iter().map(|v| v * v).sum();
        partial[j] = n2;
        reference[j] = n2;
        largest = largest.max(n2);
    }
    let tol2 = (NullSpace::RANK_TOLERANCE * largest.sqrt()).powi(2);
    let mut rank = 0;
    for k in 0..s.min(m) {
        let mut best = k;
        for j in k + 1..m {
            if partial[j] > partial[best] {
                best = j;
            }
        }
        if partial[best] <= tol2 {
            // Confirm with exact norms before declaring the rest dependent.
            let exact: f64 = a[best * s + k..(best + 1) * s].iter().map(|v| v * v).sum();
            if exact <= tol2 {
                break;
            }
            partial[best] = exact;
        }
        if best != k {
            for i in 0..s {
                a.swap(k * s + i, best * s + i);
            }
            perm.swap(k, best);
            partial.swap(k, best);
            reference.swap(k, best);
        }
        let col = &mut a[k * s + k..(k + 1) * s];
        let norm = col.iter().map(|v| v * v).sum::<f64>().sqrt();
        let alpha = if col[0] > 0.0 { -norm } else { norm };
        col[0] -= alpha;
        let vnorm2: f64 = col.iter().map(|v| v * v).sum();
        let b = if vnorm2 > 0.0 { 2.0 / vnorm2 } else { 0.0 };
        rdiag[k] = alpha;
        beta[k] = b;
        let (left, right) = a.split_at_mut((k + 1) * s);
        let v = &left[k * s + k..(k + 1) * s];
        for (jj, y) in right.chunks_exact_mut(s).take(m - k - 1).enumerate() {
            let y = &mut y[k..];
            let dot: f64 = v.iter().zip(y.iter()).map(|(a, b)| a * b).sum();
            let f = b * dot;
            for (yi, vi) in y.iter_mut().zip(v) {
                *yi -= f * vi;
            }
            // Downdate the partial norm of rows k+1.. of this column.
            let j = k + 1 + jj;
            partial[j] -= y[0] * y[0];
            if partial[j] < 1e-4 * reference[j] {
                partial[j] = y[1..].iter().map(|v| v * v).sum();
                reference[j] = partial[j];
            }
        }
        rank += 1;
    }
    rank
}

/// x ← H₀ H₁ … H_{r−1} x with the reflectors stored below the diagonal of `a`.
fn apply_q(a: &[f64], beta: &[f64], s: usize, rank: usize, x: &mut [f64]) {
    for k in (0..rank).rev() {
        let v = &a[k * s + k..(k + 1) * s];
        let y = &mut x[k..s];
        let dot: f64 = v.iter().zip(y.iter()).map(|(a, b)| a * b).sum();
        let f = beta[k] * dot;
        for (yi, vi) in y.iter_mut().zip(v) {
            *yi -= f * vi;
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
            let n = DMatrix::from_row_slice(s, s, &ns.basis)
                .columns(0, ns.dim)
                .into_owned();
            let p = DMatrix::from_column_slice(s, 1, &ns.particular);
            assert!((&c * &n).amax() < 1e-12, "C N = 0");
            for i in 0..s {
                let (start, row) = ns.row(i);
                for j in 0..s {
                    let inside = j >= start && j < start + row.len();
                    let v = if inside { row[j - start] } else { 0.0 };
                    assert_eq!(v, ns.basis[i * s + j], "row {i} of N outside its span");
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
            let n = DMatrix::from_row_slice(s, s, &ns.basis)
                .columns(0, ns.dim)
                .into_owned();
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
            assert_eq!(ns.basis[2 * 3], 1.0, "the untouched unknown stays free");
        }
    }

    #[test]
    fn no_equations_leave_every_direction_free() {
        let mut ns = NullSpace::new(3, 2);
        ns.reduce(&[], &[], 0);
        assert_eq!(ns.dim, 3);
        assert_eq!(ns.basis, vec![1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]);
    }
}
