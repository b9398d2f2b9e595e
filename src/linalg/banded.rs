//! Block-tridiagonal symmetric systems: the normal equations of a graph whose factors
//! join only consecutive time steps. Ordering the unknowns by time step is already
//! fill-free for such a chain (its Cholesky factor stays block-bidiagonal), so the
//! "symbolic factorization" is the band itself, fixed per window size; each LM
//! iteration only refills and refactors the blocks, in O(steps · s³) and without
//! allocating.
//!
//! Each block k has an active size d_k ≤ s (the unknowns left after a step's hard
//! equations are eliminated); storage keeps stride s, the work is O(Σ d_k³).

use super::dense::{self, DenseError};

/// H = block tridiagonal with `blocks` diagonal blocks of size s×s; only the lower
/// blocks H[k][k−1] are stored (row-major, stride s). Block k uses its leading
/// d_k rows and columns.
#[derive(Debug, Clone)]
pub struct BlockTridiagonal {
    s: usize,
    blocks: usize,
    dims: Vec<usize>,
    diag: Vec<f64>,
    lower: Vec<f64>,
}

impl BlockTridiagonal {
    /// Storage for up to `capacity` blocks of size s.
    pub fn new(capacity: usize, s: usize) -> Self {
        BlockTridiagonal {
            s,
            blocks: capacity,
            dims: vec![s; capacity],
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
        self.dims.len()
    }

    /// Uses the first `blocks` blocks (≤ capacity), zeroes them and makes every one
    /// fully active.
    pub fn reset(&mut self, blocks: usize) {
        assert!(blocks <= self.capacity(), "more blocks than allocated");
        self.blocks = blocks;
        let len = blocks * self.s * self.s;
        self.diag[..len].fill(0.0);
        self.lower[..len].fill(0.0);
        self.dims[..blocks].fill(self.s);
    }

    /// Uses the first `blocks` blocks with active sizes `dim(k)` and zeroes their
    /// active parts only: with d_k well below s (many unknowns fixed by hard
    /// equations) the rest of the storage is never read.
    pub fn reset_active(&mut self, blocks: usize, dim: impl Fn(usize) -> usize) {
        self.set_blocks(blocks);
        for k in 0..blocks {
            self.reset_block(k, dim(k));
        }
    }

    /// Uses the first `blocks` blocks (≤ capacity); their contents are set block by
    /// block with [`BlockTridiagonal::reset_block`], in order.
    pub fn set_blocks(&mut self, blocks: usize) {
        assert!(blocks <= self.capacity(), "more blocks than allocated");
        self.blocks = blocks;
    }

    /// Gives block k the active size d and zeroes its active parts (H[k][k] and
    /// H[k][k−1], whose width is block k − 1's size: set that one first).
    pub fn reset_block(&mut self, k: usize, d: usize) {
        let s = self.s;
        assert!(d <= s, "an active size beyond the block");
        self.dims[k] = d;
        let dp = if k > 0 { self.dims[k - 1] } else { 0 };
        let (diag, lower) = (
            &mut self.diag[k * s * s..(k + 1) * s * s],
            &mut self.lower[k * s * s..(k + 1) * s * s],
        );
        for i in 0..d {
            diag[i * s..i * s + d].fill(0.0);
            lower[i * s..i * s + dp].fill(0.0);
        }
    }

    /// Sets the active size of block k (its unknowns past d are absent: zero).
    pub fn set_dim(&mut self, k: usize, d: usize) {
        assert!(d <= self.s, "an active size beyond the block");
        self.dims[k] = d;
    }

    pub fn dim(&self, k: usize) -> usize {
        self.dims[k]
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

    /// y = H x over the used blocks and their active parts (other entries of y: 0).
    pub fn multiply(&self, x: &[f64], y: &mut [f64]) {
        let s = self.s;
        y[..self.blocks * s].fill(0.0);
        for k in 0..self.blocks {
            let dk = self.dims[k];
            let d = self.diag(k);
            for i in 0..dk {
                let row = &d[i * s..i * s + dk];
                y[k * s + i] += row
                    .iter()
                    .zip(&x[k * s..k * s + dk])
                    .map(|(a, b)| a * b)
                    .sum::<f64>();
            }
            if k > 0 {
                let dp = self.dims[k - 1];
                let b = self.lower(k);
                for i in 0..dk {
                    for j in 0..dp {
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
    dims: Vec<usize>,
    l: Vec<f64>,
    c: Vec<f64>,
}

impl BandedCholesky {
    pub fn new(capacity: usize, s: usize) -> Self {
        BandedCholesky {
            s,
            blocks: 0,
            dims: vec![s; capacity],
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
        self.dims[..self.blocks].copy_from_slice(&h.dims[..self.blocks]);
        for k in 0..self.blocks {
            let dk = self.dims[k];
            let (before, rest) = self.l.split_at_mut(k * ss);
            let lk = &mut rest[..ss];
            // Active parts only (the rest is never read).
            for i in 0..dk {
                lk[i * s..i * s + dk].copy_from_slice(&h.diag(k)[i * s..i * s + dk]);
            }
            if !damping.is_empty() {
                for i in 0..dk {
                    lk[i * s + i] += damping[k * s + i];
                }
            }
            if k > 0 {
                let dp = self.dims[k - 1];
                let lprev = &before[(k - 1) * ss..k * ss];
                let ck = &mut self.c[k * ss..(k + 1) * ss];
                for i in 0..dk {
                    ck[i * s..i * s + dp].copy_from_slice(&h.lower(k)[i * s..i * s + dp]);
                }
                for r in 0..dk {
                    dense::solve_lower_strided(lprev, dp, s, &mut ck[r * s..r * s + dp]);
                }
                for i in 0..dk {
                    for j in 0..=i {
                        let a = &ck[i * s..i * s + dp];
                        let b = &ck[j * s..j * s + dp];
                        lk[i * s + j] -= a.iter().zip(b).map(|(x, y)| x * y).sum::<f64>();
                    }
                }
            }
            dense::cholesky_strided(lk, dk, s).map_err(|e| (k, e))?;
        }
        Ok(())
    }

    /// Solves H x = b in place (entries outside the active parts come out 0).
    pub fn solve(&self, b: &mut [f64]) {
        let s = self.s;
        let ss = s * s;
        for k in 0..self.blocks {
            let dk = self.dims[k];
            b[k * s + dk..(k + 1) * s].fill(0.0);
            if k > 0 {
                let dp = self.dims[k - 1];
                let ck = &self.c[k * ss..(k + 1) * ss];
                let (prev, cur) = b.split_at_mut(k * s);
                let yprev = &prev[(k - 1) * s..(k - 1) * s + dp];
                for i in 0..dk {
                    let row = &ck[i * s..i * s + dp];
                    cur[i] -= row.iter().zip(yprev).map(|(x, y)| x * y).sum::<f64>();
                }
            }
            dense::solve_lower_strided(
                &self.l[k * ss..(k + 1) * ss],
                dk,
                s,
                &mut b[k * s..k * s + dk],
            );
        }
        for k in (0..self.blocks).rev() {
            let dk = self.dims[k];
            if k + 1 < self.blocks {
                let dn = self.dims[k + 1];
                let cn = &self.c[(k + 1) * ss..(k + 2) * ss];
                let (cur, next) = b.split_at_mut((k + 1) * s);
                let xnext = &next[..dn];
                let cur = &mut cur[k * s..];
                for i in 0..dn {
                    let row = &cn[i * s..i * s + dk];
                    let xi = xnext[i];
                    for (c, r) in cur[..dk].iter_mut().zip(row) {
                        *c -= r * xi;
                    }
                }
            }
            dense::solve_lower_transpose_strided(
                &self.l[k * ss..(k + 1) * ss],
                dk,
                s,
                &mut b[k * s..k * s + dk],
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
        // Active sizes below s: the same as the dense system of the active unknowns.
        let dims = [5, 3, 0, 4, 2, 5];
        for (k, &d) in dims.iter().enumerate() {
            h.set_dim(k, d);
        }
        let active: Vec<usize> = (0..n).filter(|&i| i % s < dims[i / s]).collect();
        let sub = DMatrix::from_fn(active.len(), active.len(), |a, b| {
            dense[(active[a], active[b])]
        });
        let rhs = DVector::from_fn(active.len(), |a, _| b[active[a]]);
        let expect = sub.cholesky().unwrap().solve(&rhs);
        f.factor(&h, &[]).unwrap();
        let mut x = b.as_slice().to_vec();
        f.solve(&mut x);
        for i in 0..n {
            let want = active
                .iter()
                .position(|&a| a == i)
                .map_or(0.0, |a| expect[a]);
            assert!((x[i] - want).abs() < 1e-12, "{i}: {} vs {want}", x[i]);
        }
    }
}
