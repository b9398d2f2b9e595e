//! Block-tridiagonal symmetric systems: the normal equations of a graph whose factors
//! join only consecutive time steps. Ordering the unknowns by time step is already
//! fill-free for such a chain (its Cholesky factor stays block-bidiagonal), so the
//! "symbolic factorization" is the band itself, fixed per window size; each LM
//! iteration only refills and refactors the blocks, in O(steps · s³) and without
//! allocating.
//!
//! Each block k has an active size d_k ≤ s (the unknowns left after a step's hard
//! equations are eliminated); the work is O(Σ d_k³), and storage is packed: block k's
//! H[k][k] is d_k × d_k (row stride d_k) and H[k][k−1] d_k × d_{k−1} (row stride
//! d_{k−1}), one after the other, so a long horizon with d_k well below s touches
//! Σ d_k² numbers instead of blocks·s² (the capacity, allocated once and left
//! untouched past what is used).

use super::dense::{self, DenseError, Summation};

/// H = block tridiagonal with `blocks` diagonal blocks; only the lower blocks
/// H[k][k−1] are stored. Block k uses d_k unknowns.
#[derive(Debug, Clone)]
pub struct BlockTridiagonal {
    s: usize,
    blocks: usize,
    dims: Vec<usize>,
    /// Where H[k][k] and H[k][k−1] start in `diag` and `lower`.
    diag_at: Vec<usize>,
    lower_at: Vec<usize>,
    diag: Vec<f64>,
    lower: Vec<f64>,
    summation: Summation,
}

/// Grows `v` (within its reserved capacity: storage is touched only as far as it
/// is used) to at least `len` entries.
fn ensure(v: &mut Vec<f64>, len: usize) {
    if v.len() < len {
        v.resize(len, 0.0);
    }
}

/// Offsets of packed blocks: block k at Σ_{j<k} size(j).
fn pack(dims: &[usize], diag_at: &mut [usize], lower_at: &mut [usize], k: usize) {
    if k == 0 {
        diag_at[0] = 0;
        lower_at[0] = 0;
    } else {
        let (d, dp) = (dims[k - 1], if k >= 2 { dims[k - 2] } else { 0 });
        diag_at[k] = diag_at[k - 1] + d * d;
        lower_at[k] = lower_at[k - 1] + d * dp;
    }
}

impl BlockTridiagonal {
    /// Storage for up to `capacity` blocks of size s.
    pub fn new(capacity: usize, s: usize) -> Self {
        let mut h = BlockTridiagonal {
            s,
            blocks: capacity,
            dims: vec![s; capacity],
            diag_at: vec![0; capacity],
            lower_at: vec![0; capacity],
            diag: Vec::with_capacity(capacity * s * s),
            lower: Vec::with_capacity(capacity * s * s),
            summation: Summation::Sequential,
        };
        for k in 0..capacity {
            pack(&h.dims, &mut h.diag_at, &mut h.lower_at, k);
        }
        h
    }

    /// How products are summed in [`BlockTridiagonal::multiply`] (sequential by
    /// default).
    pub fn set_summation(&mut self, how: Summation) {
        self.summation = how;
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
        let s = self.s;
        self.reset_active(blocks, |_| s);
    }

    /// Uses the first `blocks` blocks with active sizes `dim(k)` and zeroes them.
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

    /// Gives block k the active size d and zeroes H[k][k] and H[k][k−1]; blocks are
    /// packed, so they are reset in order (block k − 1 first).
    pub fn reset_block(&mut self, k: usize, d: usize) {
        assert!(d <= self.s, "an active size beyond the block");
        self.dims[k] = d;
        pack(&self.dims, &mut self.diag_at, &mut self.lower_at, k);
        let dp = if k > 0 { self.dims[k - 1] } else { 0 };
        let (a, b) = (self.diag_at[k], self.lower_at[k]);
        ensure(&mut self.diag, a + d * d);
        ensure(&mut self.lower, b + d * dp);
        self.diag[a..a + d * d].fill(0.0);
        self.lower[b..b + d * dp].fill(0.0);
    }

    pub fn dim(&self, k: usize) -> usize {
        self.dims[k]
    }

    /// H[k][k], row-major d_k × d_k.
    pub fn diag_mut(&mut self, k: usize) -> &mut [f64] {
        let (a, d) = (self.diag_at[k], self.dims[k]);
        &mut self.diag[a..a + d * d]
    }

    pub fn diag(&self, k: usize) -> &[f64] {
        let (a, d) = (self.diag_at[k], self.dims[k]);
        &self.diag[a..a + d * d]
    }

    /// H[k][k−1], row-major d_k × d_{k−1} (k ≥ 1).
    pub fn lower_mut(&mut self, k: usize) -> &mut [f64] {
        let (b, n) = (self.lower_at[k], self.dims[k] * self.dims[k - 1]);
        &mut self.lower[b..b + n]
    }

    pub fn lower(&self, k: usize) -> &[f64] {
        let (b, n) = (self.lower_at[k], self.dims[k] * self.dims[k - 1]);
        &self.lower[b..b + n]
    }

    /// y = H x over the used blocks and their active parts (x and y with stride s per
    /// block; other entries of y: 0).
    pub fn multiply(&self, x: &[f64], y: &mut [f64]) {
        let s = self.s;
        y[..self.blocks * s].fill(0.0);
        for k in 0..self.blocks {
            let dk = self.dims[k];
            let d = self.diag(k);
            for i in 0..dk {
                let row = &d[i * dk..(i + 1) * dk];
                y[k * s + i] += dense::dot(row, &x[k * s..k * s + dk], self.summation);
            }
            if k > 0 {
                let dp = self.dims[k - 1];
                let b = self.lower(k);
                for i in 0..dk {
                    for j in 0..dp {
                        // H[k][k−1] and its transpose H[k−1][k].
                        y[k * s + i] += b[i * dp + j] * x[(k - 1) * s + j];
                        y[(k - 1) * s + j] += b[i * dp + j] * x[k * s + i];
                    }
                }
            }
        }
    }
}

/// The Cholesky factor of a block-tridiagonal matrix: diagonal blocks L_k and
/// sub-diagonal blocks C_k = H[k][k−1] L_{k−1}⁻ᵀ, packed like H.
#[derive(Debug, Clone)]
pub struct BandedCholesky {
    s: usize,
    blocks: usize,
    dims: Vec<usize>,
    diag_at: Vec<usize>,
    lower_at: Vec<usize>,
    l: Vec<f64>,
    c: Vec<f64>,
    summation: Summation,
    /// One block's Cᵀ (s × s), for the factorization in lanes.
    scratch: Vec<f64>,
    /// What [`BandedCholesky::inverse_diagonal_blocks`] and
    /// [`BandedCholesky::inverse_end_blocks`] work in.
    inverse_scratch: Vec<f64>,
}

impl BandedCholesky {
    pub fn new(capacity: usize, s: usize) -> Self {
        BandedCholesky {
            s,
            blocks: 0,
            dims: vec![s; capacity],
            diag_at: vec![0; capacity],
            lower_at: vec![0; capacity],
            l: Vec::with_capacity(capacity * s * s),
            c: Vec::with_capacity(capacity * s * s),
            summation: Summation::Sequential,
            scratch: vec![0.0; s * s],
            inverse_scratch: Vec::new(),
        }
    }

    /// How the factorization's and the solve's products are summed (sequential by
    /// default).
    pub fn set_summation(&mut self, how: Summation) {
        self.summation = how;
    }

    /// Factors H + diag(damping) (damping has s entries per block, of which the
    /// first d_k are read, or is empty). On failure, returns the block and row where
    /// positive definiteness was lost.
    pub fn factor(
        &mut self,
        h: &BlockTridiagonal,
        damping: &[f64],
    ) -> Result<(), (usize, DenseError)> {
        let s = self.s;
        self.blocks = h.blocks();
        self.dims[..self.blocks].copy_from_slice(&h.dims[..self.blocks]);
        self.diag_at[..self.blocks].copy_from_slice(&h.diag_at[..self.blocks]);
        self.lower_at[..self.blocks].copy_from_slice(&h.lower_at[..self.blocks]);
        if let Some(last) = self.blocks.checked_sub(1) {
            let d = self.dims[last];
            ensure(&mut self.l, self.diag_at[last] + d * d);
            let dp = if last > 0 { self.dims[last - 1] } else { 0 };
            ensure(&mut self.c, self.lower_at[last] + d * dp);
        }
        for k in 0..self.blocks {
            let dk = self.dims[k];
            let at = self.diag_at[k];
            let (before, rest) = self.l.split_at_mut(at);
            let lk = &mut rest[..dk * dk];
            lk.copy_from_slice(h.diag(k));
            if !damping.is_empty() {
                for i in 0..dk {
                    lk[i * dk + i] += damping[k * s + i];
                }
            }
            if k > 0 {
                let dp = self.dims[k - 1];
                let pa = self.diag_at[k - 1];
                let lprev = &before[pa..pa + dp * dp];
                let ca = self.lower_at[k];
                let ck = &mut self.c[ca..ca + dk * dp];
                match self.summation {
                    Summation::Sequential => {
                        ck.copy_from_slice(h.lower(k));
                        for r in 0..dk {
                            dense::solve_lower_strided(
                                lprev,
                                dp,
                                dp,
                                &mut ck[r * dp..(r + 1) * dp],
                            );
                        }
                        for i in 0..dk {
                            for j in 0..=i {
                                let a = &ck[i * dp..(i + 1) * dp];
                                let b = &ck[j * dp..(j + 1) * dp];
                                lk[i * dk + j] -= a.iter().zip(b).map(|(x, y)| x * y).sum::<f64>();
                            }
                        }
                    }
                    Summation::Lanes if dk > 0 && dp > 0 => {
                        // All of C_k's rows at once: Cᵀ = L⁻¹ H[k][k−1]ᵀ by forward
                        // substitution on rows of length d_k, and L_k L_kᵀ −= C Cᵀ
                        // as a sum of outer products, so the inner loops run along
                        // contiguous rows without a running sum to wait on.
                        let ct = &mut self.scratch[..dp * dk];
                        let hl = h.lower(k);
                        for r in 0..dk {
                            for i in 0..dp {
                                ct[i * dk + r] = hl[r * dp + i];
                            }
                        }
                        for i in 0..dp {
                            let (done, rest) = ct.split_at_mut(i * dk);
                            let row = &mut rest[..dk];
                            for (l, prev) in
                                lprev[i * dp..i * dp + i].iter().zip(done.chunks_exact(dk))
                            {
                                if *l != 0.0 {
                                    for (x, p) in row.iter_mut().zip(prev) {
                                        *x -= l * p;
                                    }
                                }
                            }
                            let d = lprev[i * dp + i];
                            for x in row.iter_mut() {
                                *x /= d;
                            }
                        }
                        for l in 0..dp {
                            let cl = &ct[l * dk..(l + 1) * dk];
                            for (i, &ci) in cl.iter().enumerate() {
                                if ci == 0.0 {
                                    continue;
                                }
                                for (o, &cj) in lk[i * dk..i * dk + i + 1].iter_mut().zip(cl) {
                                    *o -= ci * cj;
                                }
                            }
                        }
                        for r in 0..dk {
                            for i in 0..dp {
                                ck[r * dp + i] = ct[i * dk + r];
                            }
                        }
                    }
                    Summation::Lanes => {}
                }
            }
            dense::cholesky_strided_with(lk, dk, dk, self.summation).map_err(|e| (k, e))?;
        }
        Ok(())
    }

    /// The square of the ratio of the smallest to the largest diagonal entry of the
    /// last factor L: a cheap lower bound on 1/cond(H) (1 without blocks).
    pub fn pivot_ratio(&self) -> f64 {
        let (mut lo, mut hi) = (f64::INFINITY, 0.0f64);
        for k in 0..self.blocks {
            let (dk, at) = (self.dims[k], self.diag_at[k]);
            for i in 0..dk {
                let v = self.l[at + i * dk + i].abs();
                lo = lo.min(v);
                hi = hi.max(v);
            }
        }
        if hi > 0.0 {
            (lo / hi).powi(2)
        } else {
            1.0
        }
    }

    /// log det H = 2 Σ log L_ii of the last factor H = LLᵀ (what a Gaussian model's
    /// marginal likelihood needs).
    pub fn log_determinant(&self) -> f64 {
        let mut sum = 0.0;
        for k in 0..self.blocks {
            let (dk, at) = (self.dims[k], self.diag_at[k]);
            for i in 0..dk {
                sum += self.l[at + i * dk + i].ln();
            }
        }
        2.0 * sum
    }

    /// Solves H x = b in place (b with stride s per block; entries outside the active
    /// parts come out 0).
    pub fn solve(&self, b: &mut [f64]) {
        let s = self.s;
        for k in 0..self.blocks {
            let dk = self.dims[k];
            b[k * s + dk..(k + 1) * s].fill(0.0);
            if k > 0 {
                let dp = self.dims[k - 1];
                let ca = self.lower_at[k];
                let ck = &self.c[ca..ca + dk * dp];
                let (prev, cur) = b.split_at_mut(k * s);
                let yprev = &prev[(k - 1) * s..(k - 1) * s + dp];
                for i in 0..dk {
                    let row = &ck[i * dp..(i + 1) * dp];
                    cur[i] -= dense::dot(row, yprev, self.summation);
                }
            }
            let at = self.diag_at[k];
            dense::solve_lower_strided_with(
                &self.l[at..at + dk * dk],
                dk,
                dk,
                &mut b[k * s..k * s + dk],
                self.summation,
            );
        }
        for k in (0..self.blocks).rev() {
            let dk = self.dims[k];
            if k + 1 < self.blocks {
                let dn = self.dims[k + 1];
                let ca = self.lower_at[k + 1];
                let cn = &self.c[ca..ca + dn * dk];
                let (cur, next) = b.split_at_mut((k + 1) * s);
                let xnext = &next[..dn];
                let cur = &mut cur[k * s..];
                for i in 0..dn {
                    let row = &cn[i * dk..(i + 1) * dk];
                    let xi = xnext[i];
                    for (c, r) in cur[..dk].iter_mut().zip(row) {
                        *c -= r * xi;
                    }
                }
            }
            let at = self.diag_at[k];
            dense::solve_lower_transpose_strided(
                &self.l[at..at + dk * dk],
                dk,
                dk,
                &mut b[k * s..k * s + dk],
            );
        }
    }
}

impl BandedCholesky {
    /// The diagonal blocks of H⁻¹ from the factor H = LLᵀ, by the recursion along
    /// the band (selected inversion): Σ_T = L_T⁻ᵀL_T⁻¹ for the last block and
    /// Σ_k = L_k⁻ᵀ(I + C_{k+1}ᵀ Σ_{k+1} C_{k+1})L_k⁻¹ before it, C_{k+1} = L[k+1][k].
    /// A marginal covariance per block in O(Σ d_k³), never the whole inverse.
    /// `out[k]` is row-major d_k × d_k.
    pub fn inverse_diagonal_blocks(&mut self, out: &mut Vec<Vec<f64>>) {
        self.selected_inverse(out, None);
    }

    /// The diagonal blocks of H⁻¹ as [`Self::inverse_diagonal_blocks`], and in
    /// `lower[k]` (k ≥ 1) the block Σ_{k,k−1} below the diagonal, d_k × d_{k−1}
    /// row-major (`lower[0]` empty): from Σ L = L⁻ᵀ, whose blocks below the diagonal
    /// vanish, Σ_{k+1,k} = −Σ_{k+1} C_{k+1} L_k⁻¹. What a covariance between
    /// neighbouring blocks needs (an interpolation between them).
    pub fn inverse_tridiagonal_blocks(
        &mut self,
        diagonal: &mut Vec<Vec<f64>>,
        lower: &mut Vec<Vec<f64>>,
    ) {
        self.selected_inverse(diagonal, Some(lower));
    }

    fn selected_inverse(&mut self, out: &mut Vec<Vec<f64>>, mut lower: Option<&mut Vec<Vec<f64>>>) {
        out.resize_with(self.blocks, Vec::new);
        if let Some(lower) = lower.as_deref_mut() {
            lower.resize_with(self.blocks, Vec::new);
            if let Some(first) = lower.first_mut() {
                first.clear();
            }
        }
        let s = self.s;
        // M (d_k²), SC (d_{k+1} × d_k), Y (d_k²), one column (d_k): reused, as the
        // blocks are (an estimator asks for them every step).
        self.inverse_scratch.resize(3 * s * s + s, 0.0);
        for k in (0..self.blocks).rev() {
            let dk = self.dims[k];
            let (m, rest) = self.inverse_scratch.split_at_mut(s * s);
            let (sc, rest) = rest.split_at_mut(s * s);
            let (y, col) = rest.split_at_mut(s * s);
            let (m, y, col) = (&mut m[..dk * dk], &mut y[..dk * dk], &mut col[..dk]);
            // M = I + C_{k+1}ᵀ Σ_{k+1} C_{k+1} (d_k × d_k).
            m.fill(0.0);
            for i in 0..dk {
                m[i * dk + i] = 1.0;
            }
            let (done, later) = out.split_at_mut(k + 1);
            if k + 1 < self.blocks {
                let dn = self.dims[k + 1];
                let ca = self.lower_at[k + 1];
                let c = &self.c[ca..ca + dn * dk];
                let next = &later[0];
                // SC = Σ_{k+1} C (dn × dk), then M += Cᵀ SC.
                let sc = &mut sc[..dn * dk];
                sc.fill(0.0);
                for i in 0..dn {
                    for l in 0..dn {
                        let a = next[i * dn + l];
                        if a != 0.0 {
                            for j in 0..dk {
                                sc[i * dk + j] += a * c[l * dk + j];
                            }
                        }
                    }
                }
                for l in 0..dn {
                    for i in 0..dk {
                        let a = c[l * dk + i];
                        if a != 0.0 {
                            for j in 0..dk {
                                m[i * dk + j] += a * sc[l * dk + j];
                            }
                        }
                    }
                }
            }
            // Σ_k = L⁻ᵀ M L⁻¹: Y = L⁻ᵀ M column by column (M is symmetric), then
            // Σ = Y L⁻¹ = (L⁻ᵀ Yᵀ)ᵀ, written by its columns.
            let at = self.diag_at[k];
            let l = &self.l[at..at + dk * dk];
            // Σ_{k+1,k} = −SC L_k⁻¹, row by row: x L_k = −sc ⇔ L_kᵀ xᵀ = −scᵀ.
            if let (Some(lower), true) = (lower.as_deref_mut(), k + 1 < self.blocks) {
                let dn = self.dims[k + 1];
                let block = &mut lower[k + 1];
                block.clear();
                block.resize(dn * dk, 0.0);
                for i in 0..dn {
                    for j in 0..dk {
                        col[j] = -sc[i * dk + j];
                    }
                    dense::solve_lower_transpose_strided(l, dk, dk, col);
                    block[i * dk..(i + 1) * dk].copy_from_slice(col);
                }
            }
            for j in 0..dk {
                for i in 0..dk {
                    col[i] = m[i * dk + j];
                }
                dense::solve_lower_transpose_strided(l, dk, dk, col);
                for i in 0..dk {
                    y[i * dk + j] = col[i];
                }
            }
            let sigma = &mut done[k];
            sigma.clear();
            sigma.resize(dk * dk, 0.0);
            for j in 0..dk {
                col.copy_from_slice(&y[j * dk..(j + 1) * dk]);
                dense::solve_lower_transpose_strided(l, dk, dk, col);
                for i in 0..dk {
                    sigma[i * dk + j] = col[i];
                }
            }
            // Symmetric up to round-off: keep it exactly so.
            for i in 0..dk {
                for j in 0..i {
                    let v = 0.5 * (sigma[i * dk + j] + sigma[j * dk + i]);
                    sigma[i * dk + j] = v;
                    sigma[j * dk + i] = v;
                }
            }
        }
    }
}

impl BandedCholesky {
    /// The first and last diagonal blocks of H⁻¹ only (`out[0]` and `out[last]`; the
    /// others left empty): the last is L_T⁻ᵀL_T⁻¹, the first ZᵀZ with Z = L⁻¹E₀, the
    /// forward solve of the first block's unit columns, Z_0 = L_0⁻¹ and
    /// Z_k = −L_k⁻¹C_k Z_{k−1}. A fixed-lag estimator asks for these two every step;
    /// the forward recursion costs about two thirds of the selected inversion and
    /// writes no middle block.
    pub fn inverse_end_blocks(&mut self, out: &mut Vec<Vec<f64>>) {
        out.resize_with(self.blocks, Vec::new);
        if self.blocks == 0 {
            return;
        }
        let s = self.s;
        self.inverse_scratch.resize(2 * s * s, 0.0);
        let (z, w) = self.inverse_scratch.split_at_mut(s * s);
        let d0 = self.dims[0];
        let last = self.blocks - 1;
        let sigma0 = &mut out[0];
        sigma0.clear();
        sigma0.resize(d0 * d0, 0.0);
        // Z_0 = L_0⁻¹.
        lower_inverse(&self.l[..d0 * d0], d0, &mut z[..d0 * d0]);
        add_gram(&z[..d0 * d0], d0, d0, sigma0);
        for k in 1..self.blocks {
            let (dk, dp) = (self.dims[k], self.dims[k - 1]);
            let ca = self.lower_at[k];
            let c = &self.c[ca..ca + dk * dp];
            // W = C_k Z_{k−1} (dk × d0), then Z_k = L_k⁻¹ W (the sign drops out of ZᵀZ).
            let w = &mut w[..dk * d0];
            w.fill(0.0);
            for i in 0..dk {
                for l in 0..dp {
                    let a = c[i * dp + l];
                    if a != 0.0 {
                        for (o, zv) in w[i * d0..(i + 1) * d0]
                            .iter_mut()
                            .zip(&z[l * d0..(l + 1) * d0])
                        {
                            *o += a * zv;
                        }
                    }
                }
            }
            let at = self.diag_at[k];
            forward_rows(&self.l[at..at + dk * dk], dk, w, d0);
            z[..dk * d0].copy_from_slice(w);
            add_gram(&z[..dk * d0], dk, d0, &mut out[0]);
        }
        if last > 0 {
            let dk = self.dims[last];
            let at = self.diag_at[last];
            let z = &mut z[..dk * dk];
            lower_inverse(&self.l[at..at + dk * dk], dk, z);
            let sigma = &mut out[last];
            sigma.clear();
            sigma.resize(dk * dk, 0.0);
            add_gram(z, dk, dk, sigma);
        }
        for sigma in &mut out[1..last.max(1)] {
            sigma.clear();
        }
    }
}

/// L⁻¹ into `z` (d × d) for L lower triangular d × d: the identity's rows solved
/// forward.
fn lower_inverse(l: &[f64], d: usize, z: &mut [f64]) {
    z.fill(0.0);
    for i in 0..d {
        z[i * d + i] = 1.0;
    }
    forward_rows(l, d, z, d);
}

/// Solves L X = B in place for the rows × cols matrix B (row-major), L lower
/// triangular rows × rows.
fn forward_rows(l: &[f64], rows: usize, b: &mut [f64], cols: usize) {
    for i in 0..rows {
        let (done, rest) = b.split_at_mut(i * cols);
        let row = &mut rest[..cols];
        for (k, prev) in done.chunks_exact(cols).enumerate() {
            let a = l[i * rows + k];
            if a != 0.0 {
                for (x, p) in row.iter_mut().zip(prev) {
                    *x -= a * p;
                }
            }
        }
        let d = l[i * rows + i];
        for x in row.iter_mut() {
            *x /= d;
        }
    }
}

/// out += ZᵀZ for the rows × cols matrix Z (row-major); out is cols × cols and
/// stays exactly symmetric.
fn add_gram(z: &[f64], rows: usize, cols: usize, out: &mut [f64]) {
    for r in 0..rows {
        let zr = &z[r * cols..(r + 1) * cols];
        for i in 0..cols {
            let a = zr[i];
            if a == 0.0 {
                continue;
            }
            for j in 0..=i {
                out[i * cols + j] += a * zr[j];
            }
        }
    }
    for i in 0..cols {
        for j in 0..i {
            out[j * cols + i] = out[i * cols + j];
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
        // Active sizes below s: the same as the dense system of the active unknowns
        // (blocks packed: refilled after the sizes are set).
        let dims = [5, 3, 0, 4, 2, 5];
        h.reset_active(blocks, |k| dims[k]);
        for k in 0..blocks {
            let (d, dp) = (dims[k], if k > 0 { dims[k - 1] } else { 0 });
            for a in 0..d {
                for b in 0..d {
                    h.diag_mut(k)[a * d + b] = dense[(k * s + a, k * s + b)];
                }
                for b in 0..dp {
                    h.lower_mut(k)[a * dp + b] = dense[(k * s + a, (k - 1) * s + b)];
                }
            }
        }
        let active: Vec<usize> = (0..n).filter(|&i| i % s < dims[i / s]).collect();
        let sub = DMatrix::from_fn(active.len(), active.len(), |a, b| {
            dense[(active[a], active[b])]
        });
        let rhs = DVector::from_fn(active.len(), |a, _| b[active[a]]);
        let expect = sub.cholesky().unwrap().solve(&rhs);
        for how in [Summation::Sequential, Summation::Lanes] {
            f.set_summation(how);
            h.set_summation(how);
            f.factor(&h, &[]).unwrap();
            let mut x = b.as_slice().to_vec();
            f.solve(&mut x);
            for i in 0..n {
                let want = active
                    .iter()
                    .position(|&a| a == i)
                    .map_or(0.0, |a| expect[a]);
                assert!(
                    (x[i] - want).abs() < 1e-12,
                    "{how:?} {i}: {} vs {want}",
                    x[i]
                );
            }
            let mut y = vec![0.0; n];
            h.multiply(&x, &mut y);
            for &i in &active {
                assert!((y[i] - b[i]).abs() < 1e-12, "{how:?}: H x = b");
            }
        }
    }

    #[test]
    fn inverse_diagonal_blocks_are_those_of_the_dense_inverse() {
        // Active sizes that differ from block to block (as reduced unknowns do).
        let dims = [3, 5, 2, 4, 4, 1];
        let s = 5;
        let offsets: Vec<usize> = dims
            .iter()
            .scan(0, |o, &d| {
                let at = *o;
                *o += d;
                Some(at)
            })
            .collect();
        let n: usize = dims.iter().sum();
        let mut seed = 11u64;
        let mut rnd = || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((seed >> 11) as f64 / (1u64 << 53) as f64) - 0.5
        };
        let mut j = DMatrix::zeros(3 * n, n);
        for (k, (&d, &o)) in dims.iter().zip(&offsets).enumerate() {
            let lo = if k > 0 { offsets[k - 1] } else { o };
            for r in 0..3 * d {
                for c in lo..o + d {
                    j[(3 * o + r, c)] = rnd();
                }
            }
        }
        let dense = j.transpose() * &j + DMatrix::identity(n, n) * 0.1;
        let mut h = BlockTridiagonal::new(8, s);
        h.set_blocks(dims.len());
        for (k, (&d, &o)) in dims.iter().zip(&offsets).enumerate() {
            h.reset_block(k, d);
            for a in 0..d {
                for b in 0..d {
                    h.diag_mut(k)[a * d + b] = dense[(o + a, o + b)];
                }
                if k > 0 {
                    let (dp, op) = (dims[k - 1], offsets[k - 1]);
                    for b in 0..dp {
                        h.lower_mut(k)[a * dp + b] = dense[(o + a, op + b)];
                    }
                }
            }
        }
        let mut f = BandedCholesky::new(8, s);
        f.factor(&h, &[]).unwrap();
        let mut blocks = Vec::new();
        f.inverse_diagonal_blocks(&mut blocks);
        let (mut diagonal, mut lower) = (Vec::new(), Vec::new());
        f.inverse_tridiagonal_blocks(&mut diagonal, &mut lower);
        assert_eq!(diagonal, blocks);
        let inverse = dense.clone().try_inverse().unwrap();
        assert!(lower[0].is_empty());
        for k in 1..dims.len() {
            let (d, o, dp, op) = (dims[k], offsets[k], dims[k - 1], offsets[k - 1]);
            assert_eq!(lower[k].len(), d * dp);
            for a in 0..d {
                for b in 0..dp {
                    let (got, want) = (lower[k][a * dp + b], inverse[(o + a, op + b)]);
                    assert!(
                        (got - want).abs() < 1e-10 * (1.0 + want.abs()),
                        "lower block {k} ({a}, {b}): {got} vs {want}"
                    );
                }
            }
        }
        let mut ends = Vec::new();
        f.inverse_end_blocks(&mut ends);
        let inverse = dense.try_inverse().unwrap();
        let last = dims.len() - 1;
        assert_eq!(ends.len(), dims.len());
        assert!(ends[1..last].iter().all(Vec::is_empty));
        for k in [0, last] {
            for (a, (got, want)) in ends[k].iter().zip(&blocks[k]).enumerate() {
                assert!(
                    (got - want).abs() < 1e-10 * (1.0 + want.abs()),
                    "end block {k} entry {a}: {got} vs {want}"
                );
            }
        }
        assert_eq!(blocks.len(), dims.len());
        for (k, (&d, &o)) in dims.iter().zip(&offsets).enumerate() {
            for a in 0..d {
                for b in 0..d {
                    let (got, want) = (blocks[k][a * d + b], inverse[(o + a, o + b)]);
                    assert!(
                        (got - want).abs() < 1e-10 * (1.0 + want.abs()),
                        "block {k} ({a}, {b}): {got} vs {want}"
                    );
                }
            }
        }
    }
}
