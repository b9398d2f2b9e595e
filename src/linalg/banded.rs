//! Block-tridiagonal symmetric systems: the normal equations of a graph whose factors
//! join only consecutive time steps. Ordering the unknowns by time step is already
//! fill-free for such a chain (its Cholesky factor stays block-bidiagonal), so the
//! "symbolic factorization" is the band itself, fixed per window size; each LM
//! iteration only refills and refactors the blocks, in O(steps · s³) and without
//! allocating.

use super::dense::{self, DenseError};

/// H = block tridiagonal with `blocks` diagonal blocks of size s×s; only the lower
/// blocks H[k][k−1] are stored (row-major).
#[derive(Debug, Clone)]
pub struct BlockTridiagonal {
    s: usize,
    blocks: usize,
    diag: Vec<f64>,
    lower: Vec<f64>,
}

impl BlockTridiagonal {
    /// Storage for up to `capacity` blocks of size s.
    pub fn new(capacity: usize, s: usize) -> Self {
        BlockTridiagonal {
            s,
            blocks: capacity,
            diag: vec![0.0; capacity * s * s],
            lower: vec![0.0; capacity * s * s],
        }
    }

    pub fn block_size(&self) -> usize {
        self.s
    }

    pub fn blocks(&self) -> usize {
        self.blocks
    }

    pub fn capacity(&self) -> usize {
        self.diag.len() / (self.s * self.s).max(1)
    }

    /// Uses the first `blocks` blocks (≤ capacity) and zeroes them.
    pub fn reset(&mut self, blocks: usize) {
        assert!(blocks <= self.capacity(), "more blocks than allocated");
        self.blocks = blocks;
        let len = blocks * self.s * self.s;
        self.diag[..len].fill(0.0);
        self.lower[..len].fill(0.0);
    }

    /// H[k][k], row-major s×s.
    pub fn diag_mut(&mut self, k: usize) -> &mut [f64] {
        let ss = self.s * self.s;
        &mut self.diag[k * ss..(k + 1) * ss]
    }

    pub fn diag(&self, k: usize) -> &[f64] {
        let ss = self.s * self.s;
        &self.diag[k * ss..(k + 1) * ss]
    }

    /// H[k][k−1], row-major s×s (k ≥ 1).
    pub fn lower_mut(&mut self, k: usize) -> &mut [f64] {
        let ss = self.s * self.s;
        &mut self.lower[k * ss..(k + 1) * ss]
    }

    pub fn lower(&self, k: usize) -> &[f64] {
        let ss = self.s * self.s;
        &self.lower[k * ss..(k + 1) * ss]
    }

    /// y = H x over the used blocks.
    pub fn multiply(&self, x: &[f64], y: &mut [f64]) {
        let s = self.s;
        y[..self.blocks * s].fill(0.0);
        for k in 0..self.blocks {
            let d = self.diag(k);
            for i in 0..s {
                let mut acc = 0.0;
                for j in 0..s {
                    acc += d[i * s + j] * x[k * s + j];
                }
                y[k * s + i] += acc;
            }
            if k > 0 {
                let b = self.lower(k);
                for i in 0..s {
                    for j in 0..s {
                        // H[k][k−1] and its transpose H[k−1][k].
                        y[k * s + i] += b[i * s + j] * x[(k - 1) * s + j];
                        y[(k - 1) * s + j] += b[i * s + j] * x[k * s + i];
                    }
                }
            }
        }
    }
}

/// The Cholesky factor of a block-tridiagonal matrix: diagonal blocks L_k and
/// sub-diagonal blocks C_k = H[k][k−1] L_{k−1}⁻ᵀ.
#[derive(Debug, Clone)]
pub struct BandedCholesky {
    s: usize,
    blocks: usize,
    l: Vec<f64>,
    c: Vec<f64>,
}

impl BandedCholesky {
    pub fn new(capacity: usize, s: usize) -> Self {
        BandedCholesky {
            s,
            blocks: 0,
            l: vec![0.0; capacity * s * s],
            c: vec![0.0; capacity * s * s],
        }
    }

    /// Factors H + diag(damping) (damping has one entry per unknown, or is empty).
    /// On failure, returns the block and row where positive definiteness was lost.
    pub fn factor(
        &mut self,
        h: &BlockTridiagonal,
        damping: &[f64],
    ) -> Result<(), (usize, DenseError)> {
        let s = self.s;
        let ss = s * s;
        self.blocks = h.blocks();
        for k in 0..self.blocks {
            let (before, rest) = self.l.split_at_mut(k * ss);
            let lk = &mut rest[..ss];
            lk.copy_from_slice(h.diag(k));
            if !damping.is_empty() {
                for i in 0..s {
                    lk[i * s + i] += damping[k * s + i];
                }
            }
            if k > 0 {
                let lprev = &before[(k - 1) * ss..k * ss];
                let ck = &mut self.c[k * ss..(k + 1) * ss];
                ck.copy_from_slice(h.lower(k));
                for r in 0..s {
                    dense::solve_lower(lprev, s, &mut ck[r * s..(r + 1) * s]);
                }
                for i in 0..s {
                    for j in 0..=i {
                        let mut acc = 0.0;
                        for t in 0..s {
                            acc += ck[i * s + t] * ck[j * s + t];
                        }
                        lk[i * s + j] -= acc;
                    }
                }
            }
            dense::cholesky(lk, s).map_err(|e| (k, e))?;
        }
        Ok(())
    }

    /// Solves H x = b in place.
    pub fn solve(&self, b: &mut [f64]) {
        let s = self.s;
        let ss = s * s;
        for k in 0..self.blocks {
            if k > 0 {
                let ck = &self.c[k * ss..(k + 1) * ss];
                let (prev, cur) = b.split_at_mut(k * s);
                let yprev = &prev[(k - 1) * s..];
                for i in 0..s {
                    let mut acc = 0.0;
                    for t in 0..s {
                        acc += ck[i * s + t] * yprev[t];
                    }
                    cur[i] -= acc;
                }
            }
            dense::solve_lower(&self.l[k * ss..(k + 1) * ss], s, &mut b[k * s..(k + 1) * s]);
        }
        for k in (0..self.blocks).rev() {
            if k + 1 < self.blocks {
                let cn = &self.c[(k + 1) * ss..(k + 2) * ss];
                let (cur, next) = b.split_at_mut((k + 1) * s);
                let xnext = &next[..s];
                let cur = &mut cur[k * s..];
                for j in 0..s {
                    let mut acc = 0.0;
                    for i in 0..s {
                        acc += cn[i * s + j] * xnext[i];
                    }
                    cur[j] -= acc;
                }
            }
            dense::solve_lower_transpose(
                &self.l[k * ss..(k + 1) * ss],
                s,
                &mut b[k * s..(k + 1) * s],
            );
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{DMatrix, DVector};

    #[test]
    fn solves_like_a_dense_cholesky() {
        let (blocks, s) = (6, 5);
        let n = blocks * s;
        let mut seed = 3u64;
        let mut rnd = || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((seed >> 11) as f64 / (1u64 << 53) as f64) - 0.5
        };
        // A banded J (rows touch two consecutive blocks), H = JᵀJ + I.
        let mut j = DMatrix::zeros(2 * n, n);
        for r in 0..2 * n {
            let k = (r / 2) / s;
            for c in k.saturating_sub(1) * s..((k + 1) * s).min(n) {
                j[(r, c)] = rnd();
            }
        }
        let dense = j.transpose() * &j + DMatrix::identity(n, n);
        let mut h = BlockTridiagonal::new(8, s);
        h.reset(blocks);
        for k in 0..blocks {
            for a in 0..s {
                for b in 0..s {
                    h.diag_mut(k)[a * s + b] = dense[(k * s + a, k * s + b)];
                    if k > 0 {
                        h.lower_mut(k)[a * s + b] = dense[(k * s + a, (k - 1) * s + b)];
                    }
                }
            }
        }
        // Nothing outside the band.
        for r in 0..n {
            for c in 0..n {
                if (r / s).abs_diff(c / s) > 1 {
                    assert_eq!(dense[(r, c)], 0.0);
                }
            }
        }
        let b = DVector::from_fn(n, |i, _| (i as f64).cos());
        let mut f = BandedCholesky::new(8, s);
        f.factor(&h, &[]).unwrap();
        let mut x = b.as_slice().to_vec();
        f.solve(&mut x);
        let expect = dense.clone().cholesky().unwrap().solve(&b);
        for i in 0..n {
            assert!(
                (x[i] - expect[i]).abs() < 1e-12,
                "{i}: {} vs {}",
                x[i],
                expect[i]
            );
        }
        let mut y = vec![0.0; n];
        h.multiply(expect.as_slice(), &mut y);
        for i in 0..n {
            assert!((y[i] - b[i]).abs() < 1e-12);
        }
    }
}
