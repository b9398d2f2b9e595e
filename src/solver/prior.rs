//! The Gaussian prior a step leaves on the next as it leaves a fixed-lag window, and
//! the products the solver takes with it: its value and gradient, and its share of
//! a window's reduced normal equations.
//!
//! A prior projected on the tangent space of its step's hard equations has rank d
//! (the null space's dimension) and is N̄CN̄ᵀ with N̄ the s × d basis. Written out
//! s × s it costs O(s²) memory passes to form and O(s²) per product; kept as N̄
//! (sparse rows) and C (d × d) every product goes through the basis' nonzeros.

use crate::linalg::dense;
use crate::linalg::nullspace::NullSpace;

/// Unknowns per step from which a projected prior is kept as N̄CN̄ᵀ rather than
/// written out s × s. Below it the written-out form is as cheap, and the results
/// of small mechanisms stay those of the products they were measured with.
pub const TANGENT_FORM_FROM: usize = 64;

/// A Gaussian prior on one step's block left by marginalization, in information
/// form: c + ηᵀδ + ½ δᵀΛδ with δ = x − x̄. With the hard equations eliminated
/// exactly, Λ holds only soft information (no 1/σ_hard² next to 1/σ_soft²), so the
/// information form loses nothing that a square-root form would keep.
#[derive(Debug, Clone, PartialEq)]
pub struct LinearPrior {
    pub information: Information,
    pub eta: Vec<f64>,
    /// The cost at δ = 0 (what the marginalized factors leave behind).
    pub constant: f64,
    pub xbar: Vec<f64>,
    /// Set by [`WindowSolver::project_prior`]: the reduction of step `step`'s hard
    /// equations it made, which a one-step solve of that step reuses while the
    /// solver has linearized nothing since and the step's values are the ones
    /// reduced (x + p = x̄ to the bit).
    pub projection: Option<Projection>,
}

/// Λ of a [`LinearPrior`].
#[derive(Debug, Clone, PartialEq)]
pub enum Information {
    /// Row-major s × s.
    Dense(Vec<f64>),
    /// N̄CN̄ᵀ on the tangent space of the step's hard equations, with η = N̄γ.
    Tangent(TangentInformation),
}

/// Λ = N̄CN̄ᵀ, η = N̄γ: N̄ (s × d, orthonormal columns) by its rows' nonzero spans,
/// C symmetric d × d.
#[derive(Debug, Clone, PartialEq)]
pub struct TangentInformation {
    /// Row i of N̄ holds columns start[i].. with the entries
    /// values[offset[i]..offset[i + 1]]; the rest of the row is 0.
    start: Vec<usize>,
    offset: Vec<usize>,
    values: Vec<f64>,
    /// Row-major d × d.
    core: Vec<f64>,
    gamma: Vec<f64>,
}

/// Which linearization of a step's hard equations a projected prior was made on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Projection {
    pub(super) step: usize,
    pub(super) generation: u64,
}

impl TangentInformation {
    /// C (row-major d × d, symmetric) and γ on the basis of `reduction`.
    pub fn new(reduction: &NullSpace, core: Vec<f64>, gamma: Vec<f64>) -> Self {
        let s = reduction.particular.len();
        let (mut start, mut offset, mut values) =
            (Vec::with_capacity(s), Vec::with_capacity(s + 1), Vec::new());
        offset.push(0);
        for i in 0..s {
            let (first, row) = reduction.row(i);
            start.push(first);
            values.extend_from_slice(row);
            offset.push(values.len());
        }
        debug_assert_eq!(core.len(), reduction.dim * reduction.dim);
        TangentInformation {
            start,
            offset,
            values,
            core,
            gamma,
        }
    }

    /// d, the dimension of the tangent space.
    pub fn dim(&self) -> usize {
        self.gamma.len()
    }

    /// C, row-major d × d.
    pub fn core(&self) -> &[f64] {
        &self.core
    }

    /// γ, with η = N̄γ.
    pub fn gamma(&self) -> &[f64] {
        &self.gamma
    }

    /// Row i of N̄ where it may be nonzero: (first column, entries).
    fn row(&self, i: usize) -> (usize, &[f64]) {
        (
            self.start[i],
            &self.values[self.offset[i]..self.offset[i + 1]],
        )
    }

    /// z = N̄ᵀv (d).
    fn reduce(&self, v: &[f64], z: &mut [f64]) {
        z.fill(0.0);
        for (i, &vi) in v.iter().enumerate() {
            let (first, row) = self.row(i);
            for (o, n) in z[first..].iter_mut().zip(row) {
                *o += n * vi;
            }
        }
    }

    /// v = N̄z (s).
    pub(super) fn lift(&self, z: &[f64], v: &mut [f64]) {
        for (i, out) in v.iter_mut().enumerate() {
            let (first, row) = self.row(i);
            *out = row.iter().zip(&z[first..]).map(|(a, b)| a * b).sum();
        }
    }

    /// Cz (d).
    fn core_times(&self, z: &[f64], out: &mut [f64]) {
        let d = self.dim();
        for (a, o) in out.iter_mut().enumerate() {
            *o = self.core[a * d..(a + 1) * d]
                .iter()
                .zip(z)
                .map(|(c, v)| c * v)
                .sum();
        }
    }
}

impl LinearPrior {
    /// Unknowns of the step it is on.
    pub fn size(&self) -> usize {
        self.xbar.len()
    }

    /// Λ written out, row-major s × s.
    pub fn dense_information(&self) -> Vec<f64> {
        let s = self.size();
        match &self.information {
            Information::Dense(lambda) => lambda.clone(),
            Information::Tangent(t) => {
                let d = t.dim();
                let mut lambda = vec![0.0; s * s];
                // N̄C row by row, then its products with N̄'s rows.
                let mut nc = vec![0.0; s * d];
                for i in 0..s {
                    let (first, row) = t.row(i);
                    for (a, &n) in row.iter().enumerate() {
                        let c = &t.core[(first + a) * d..(first + a + 1) * d];
                        for (o, cv) in nc[i * d..(i + 1) * d].iter_mut().zip(c) {
                            *o += n * cv;
                        }
                    }
                }
                for i in 0..s {
                    for j in 0..s {
                        let (first, row) = t.row(j);
                        lambda[i * s + j] = row
                            .iter()
                            .zip(&nc[i * d + first..])
                            .map(|(a, b)| a * b)
                            .sum();
                    }
                }
                lambda
            }
        }
    }

    /// grad = Λδ + η with δ = x − x̄ (into `delta`); returns the prior's cost
    /// c + ηᵀδ + ½δᵀΛδ. `work` holds 2d values (the tangent form's N̄ᵀδ and CN̄ᵀδ).
    pub(super) fn gradient(
        &self,
        x: &[f64],
        delta: &mut [f64],
        grad: &mut [f64],
        work: &mut [f64],
    ) -> f64 {
        let s = self.size();
        for i in 0..s {
            delta[i] = x[i] - self.xbar[i];
        }
        let lin: f64 = self.eta.iter().zip(delta.iter()).map(|(a, b)| a * b).sum();
        let quad = match &self.information {
            Information::Dense(lambda) => {
                let mut quad = 0.0;
                for i in 0..s {
                    let row = &lambda[i * s..(i + 1) * s];
                    let ld: f64 = row.iter().zip(delta.iter()).map(|(a, b)| a * b).sum();
                    quad += delta[i] * ld;
                    grad[i] = ld + self.eta[i];
                }
                quad
            }
            Information::Tangent(t) => {
                let d = t.dim();
                let (z, cz) = work[..2 * d].split_at_mut(d);
                t.reduce(delta, z);
                t.core_times(z, cz);
                let quad = z.iter().zip(cz.iter()).map(|(a, b)| a * b).sum();
                for (c, g) in cz.iter_mut().zip(&t.gamma) {
                    *c += g;
                }
                t.lift(cz, grad);
                quad
            }
        };
        self.constant + lin + 0.5 * quad
    }

    /// out += Λv; `work` holds 2d values.
    pub(super) fn add_information_times(&self, v: &[f64], out: &mut [f64], work: &mut [f64]) {
        let s = self.size();
        match &self.information {
            Information::Dense(lambda) => {
                for (i, o) in out.iter_mut().enumerate() {
                    let row = &lambda[i * s..(i + 1) * s];
                    *o += row.iter().zip(v).map(|(a, b)| a * b).sum::<f64>();
                }
            }
            Information::Tangent(t) => {
                let d = t.dim();
                let (z, cz) = work[..2 * d].split_at_mut(d);
                t.reduce(v, z);
                t.core_times(z, cz);
                for (i, o) in out.iter_mut().enumerate() {
                    let (first, row) = t.row(i);
                    *o += row
                        .iter()
                        .zip(&cz[first..])
                        .map(|(a, b)| a * b)
                        .sum::<f64>();
                }
            }
        }
    }

    /// A window's first block in the coordinates of `red` (δ = p + Ny): h (dim × dim)
    /// += NᵀΛN and g += Nᵀ`grad`. `scratch` holds at least 2·s² values.
    pub(super) fn add_reduced(
        &self,
        red: &NullSpace,
        grad: &[f64],
        h: &mut [f64],
        g: &mut [f64],
        scratch: &mut [f64],
    ) {
        let s = self.size();
        let dim = red.dim;
        let blocked = match &self.information {
            Information::Dense(lambda) => add_dense_reduced(lambda, s, red, h, scratch),
            Information::Tangent(t) => {
                add_tangent_reduced(t, red, h, scratch);
                false
            }
        };
        if blocked {
            // N written out after ΛN in the scratch.
            let nb = &scratch[s * dim..2 * s * dim];
            for (a, ga) in g[..dim].iter_mut().enumerate() {
                *ga += (0..s).map(|k| nb[k * dim + a] * grad[k]).sum::<f64>();
            }
            return;
        }
        for (k, &gk) in grad.iter().enumerate() {
            let (start, nrow) = red.row(k);
            for (a, &na) in nrow.iter().enumerate() {
                if na != 0.0 {
                    g[start + a] += na * gk;
                }
            }
        }
    }
}

/// h += NᵀΛN for a written-out Λ (s × s), over N's nonzeros: its first q columns on
/// the rows `free`, then one unit column per untouched unknown (each sum over rows
/// in order), or dense by faer's blocked kernels where N has many dense columns
/// (then true, with N written out after ΛN in the scratch).
fn add_dense_reduced(
    lambda: &[f64],
    s: usize,
    red: &NullSpace,
    h: &mut [f64],
    scratch: &mut [f64],
) -> bool {
    let dim = red.dim;
    let (free, untouched) = red.structure();
    let q = dim - untouched.len();
    let (ln, nb) = scratch.split_at_mut(s * dim);
    if dense::blocked_products(s, q) {
        red.basis_into(nb);
        let nv = dense::rows(nb, s, dim, dim);
        let lambda = dense::rows(lambda, s, s, s);
        dense::multiply(dense::rows_mut(ln, s, dim, dim), false, lambda, nv);
        let lnv = dense::rows(ln, s, dim, dim);
        dense::multiply(dense::rows_mut(h, dim, dim, dim), true, nv.transpose(), lnv);
        return true;
    }
    for i in 0..s {
        let row = &lambda[i * s..(i + 1) * s];
        let out = &mut ln[i * dim..(i + 1) * dim];
        // Row by row of N (contiguous), each entry still summed over `free` in order
        // from 0.
        out[..q].fill(0.0);
        for &k in free {
            let rk = row[k];
            for (o, nk) in out[..q].iter_mut().zip(red.free_row(k)) {
                *o += rk * nk;
            }
        }
        for (o, &k) in out[q..].iter_mut().zip(untouched) {
            *o = 0.0 + row[k];
        }
    }
    for k in 0..s {
        let (start, nrow) = red.row(k);
        let lrow = &ln[k * dim..(k + 1) * dim];
        for (a, &na) in nrow.iter().enumerate() {
            if na == 0.0 {
                continue;
            }
            let a = start + a;
            for (o, lv) in h[a * dim..(a + 1) * dim].iter_mut().zip(lrow) {
                *o += na * lv;
            }
        }
    }
    false
}

/// h += NᵀN̄CN̄ᵀN = MᵀCM with M = N̄ᵀN (d̄ × dim, from the rows where both bases may be
/// nonzero): N and N̄ reduce the same equations, often at the same point, so M is
/// mostly the untouched unknowns' unit entries and its products go over its
/// nonzeros; a denser M by faer's blocked kernels.
fn add_tangent_reduced(
    t: &TangentInformation,
    red: &NullSpace,
    h: &mut [f64],
    scratch: &mut [f64],
) {
    let (db, dim) = (t.dim(), red.dim);
    let (m, rest) = scratch.split_at_mut(db * dim);
    let u = &mut rest[..db * dim];
    m.fill(0.0);
    for i in 0..t.start.len() {
        let (first, row) = t.row(i);
        if row.is_empty() {
            continue;
        }
        let (start, nrow) = red.row(i);
        for (a, &na) in row.iter().enumerate() {
            let out = &mut m[(first + a) * dim + start..(first + a) * dim + start + nrow.len()];
            for (o, nb) in out.iter_mut().zip(nrow) {
                *o += na * nb;
            }
        }
    }
    let nonzeros = m.iter().filter(|v| **v != 0.0).count();
    if 4 * nonzeros > db * dim {
        // U = CM (d̄ × dim), h += MᵀU.
        let (mv, cv) = (
            dense::rows(m, db, dim, dim),
            dense::rows(&t.core, db, db, db),
        );
        dense::multiply(dense::rows_mut(u, db, dim, dim), false, cv, mv);
        let uv = dense::rows(u, db, dim, dim);
        dense::multiply(dense::rows_mut(h, dim, dim, dim), true, mv.transpose(), uv);
        return;
    }
    // U = MᵀC (dim × d̄) row by row over M's nonzeros, then h += UM likewise.
    u.fill(0.0);
    for a in 0..db {
        let c = &t.core[a * db..(a + 1) * db];
        for b in 0..dim {
            let mab = m[a * dim + b];
            if mab != 0.0 {
                for (o, cv) in u[b * db..(b + 1) * db].iter_mut().zip(c) {
                    *o += mab * cv;
                }
            }
        }
    }
    for a in 0..db {
        for b in 0..dim {
            let mab = m[a * dim + b];
            if mab != 0.0 {
                for r in 0..dim {
                    h[r * dim + b] += u[r * db + a] * mab;
                }
            }
        }
    }
}
