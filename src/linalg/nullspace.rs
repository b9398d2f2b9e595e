//! Exact linear equality constraints C δ = b on a step's unknowns: a basis N of the
//! null space of C and the least-norm solution p, so that every solution reads
//! δ = p + N y. The solver eliminates hard factors this way instead of weighting them,
//! which keeps the normal equations' condition number that of the soft factors alone.
//!
//! Householder QR with column pivoting of Cᵀ (one column per equation) reveals the
//! rank, so redundant equations (over-constrained mechanisms, or the initial priors
//! together with the constraints they already satisfy) are dropped, not divided by 0.

/// Scratch and results of one reduction, sized once for `s` unknowns and up to
/// `max_rows` equations.
#[derive(Debug, Clone)]
pub struct NullSpace {
    s: usize,
    max_rows: usize,
    /// Cᵀ column-major (column j = equation j), overwritten by the QR factors.
    a: Vec<f64>,
    rdiag: Vec<f64>,
    beta: Vec<f64>,
    perm: Vec<usize>,
    norms: Vec<f64>,
    w: Vec<f64>,
    /// s × s row-major; columns 0..dim hold an orthonormal null-space basis, the rest 0.
    pub basis: Vec<f64>,
    /// The least-norm solution of the independent equations.
    pub particular: Vec<f64>,
    /// Dimension of the null space.
    pub dim: usize,
    /// Rank of C.
    pub rank: usize,
}

impl NullSpace {
    /// Relative size below which a pivot counts as zero (rank-deficient direction).
    pub const RANK_TOLERANCE: f64 = 1e-10;

    pub fn new(s: usize, max_rows: usize) -> Self {
        let mut ns = NullSpace {
            s,
            max_rows,
            a: vec![0.0; s * max_rows],
            rdiag: vec![0.0; s.min(max_rows)],
            beta: vec![0.0; s.min(max_rows)],
            perm: vec![0; max_rows],
            norms: vec![0.0; max_rows],
            w: vec![0.0; s],
            basis: vec![0.0; s * s],
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
        }
        self.particular.fill(0.0);
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
        // Column j of Cᵀ is row j of C: the row-major C is Cᵀ column-major.
        self.a[..rows * s].copy_from_slice(&c[..rows * s]);
        let mut largest = 0.0f64;
        for j in 0..rows {
            self.perm[j] = j;
            self.norms[j] = self.a[j * s..(j + 1) * s].iter().map(|v| v * v).sum();
            largest = largest.max(self.norms[j]);
        }
        let tol = Self::RANK_TOLERANCE * largest.sqrt();
        let steps = s.min(rows);
        let mut rank = 0;
        for k in 0..steps {
            // Pivot: the remaining column of largest norm below row k (recomputed, not
            // downdated, so no cancellation creeps in).
            let mut best = k;
            let mut best_norm = -1.0;
            for j in k..rows {
                let col = &self.a[j * s + k..(j + 1) * s];
                let nrm: f64 = col.iter().map(|v| v * v).sum();
                self.norms[j] = nrm;
                if nrm > best_norm {
                    best_norm = nrm;
                    best = j;
                }
            }
            if best_norm.sqrt() <= tol {
                break;
            }
            if best != k {
                for i in 0..s {
                    self.a.swap(k * s + i, best * s + i);
                }
                self.perm.swap(k, best);
            }
            // Householder reflector H = I − β v vᵀ taking column k (rows k..s) to α e_k.
            let col = &mut self.a[k * s + k..(k + 1) * s];
            let norm = best_norm.sqrt();
            let alpha = if col[0] > 0.0 { -norm } else { norm };
            col[0] -= alpha;
            let vnorm2: f64 = col.iter().map(|v| v * v).sum();
            let beta = if vnorm2 > 0.0 { 2.0 / vnorm2 } else { 0.0 };
            self.rdiag[k] = alpha;
            self.beta[k] = beta;
            let (left, right) = self.a.split_at_mut((k + 1) * s);
            let v = &left[k * s + k..(k + 1) * s];
            for j in 0..rows - k - 1 {
                let y = &mut right[j * s + k..(j + 1) * s];
                let dot: f64 = v.iter().zip(y.iter()).map(|(a, b)| a * b).sum();
                let f = beta * dot;
                for (yi, vi) in y.iter_mut().zip(v) {
                    *yi -= f * vi;
                }
            }
            rank += 1;
        }
        self.rank = rank;
        self.dim = s - rank;
        let mut p = std::mem::take(&mut self.particular);
        self.solve(b, &mut p);
        self.particular = p;
        // Null-space basis: Q e_j for j = rank..s.
        self.basis.fill(0.0);
        for j in rank..s {
            self.w.fill(0.0);
            self.w[j] = 1.0;
            apply_q(&self.a, &self.beta, s, rank, &mut self.w);
            for i in 0..s {
                self.basis[i * s + (j - rank)] = self.w[i];
            }
        }
    }
}

impl NullSpace {
    /// The least-norm solution x (length s) of the independent equations of the last
    /// [`NullSpace::reduce`] for another right-hand side b: a second-order correction
    /// reuses the factors of C.
    pub fn solve(&mut self, b: &[f64], x: &mut [f64]) {
        let (s, rank) = (self.s, self.rank);
        // The selected equations read R₁ᵀ Q₁ᵀ x = b_sel: solve R₁ᵀ w = b_sel, x = Q₁ w.
        for i in 0..rank {
            let mut acc = b[self.perm[i]];
            for l in 0..i {
                acc -= self.a[i * s + l] * self.w[l];
            }
            self.w[i] = acc / self.rdiag[i];
        }
        x.fill(0.0);
        x[..rank].copy_from_slice(&self.w[..rank]);
        apply_q(&self.a, &self.beta, s, rank, x);
    }
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
    fn no_equations_leave_every_direction_free() {
        let mut ns = NullSpace::new(3, 2);
        ns.reduce(&[], &[], 0);
        assert_eq!(ns.dim, 3);
        assert_eq!(ns.basis, vec![1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]);
    }
}
