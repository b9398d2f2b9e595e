//! Kinematics: the position, velocity and acceleration problems, the rank of Φ_q and
//! the choice of independent coordinates; the assembly of a model's initial state
//! ([`Model::new`], in `assembly`), and how well the coordinates are determined near
//! a configuration ([`determinacy`]).

mod assembly;
pub mod determinacy;

pub(crate) use determinacy::constraint_conditioning;
pub use determinacy::{Determinacy, SingularConfiguration, Watch, Watched};

use crate::error::{Error, Result};
use crate::linalg::nullspace::NullSpace;
use crate::model::Model;
use nalgebra::{DMatrix, DVector};

/// Relative tolerance on singular values when deciding rank.
const RANK_TOL: f64 = 1e-9;

/// Outcome of a converged position problem.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PositionSolution {
    pub iterations: usize,
    /// max |Φ| at the solution.
    pub residual: f64,
}

/// Tolerance on |Φ| for a model: its equations are quadratic in lengths, so scale
/// with the square of the mechanism's size.
pub fn position_tolerance(q: &DVector<f64>) -> f64 {
    position_tolerance_of(q.as_slice())
}

/// [`position_tolerance`] of a slice.
pub fn position_tolerance_of(q: &[f64]) -> f64 {
    let s = q.iter().fold(1.0f64, |m, v| m.max(v.abs()));
    1e-12 * s * s
}

/// Solves Φ(q) = 0 by damped Newton, moving every coordinate except those in `keep`.
/// Each step is the least-norm correction, so redundant constraints do no harm.
/// On failure, names the constraints left violated.
pub fn solve_position(
    model: &Model,
    q: &mut DVector<f64>,
    keep: &[usize],
) -> Result<PositionSolution> {
    let tol = position_tolerance(q);
    solve_position_within(model, q, keep, tol)
}

/// The tolerance of an assembly: [`position_tolerance`] of the points' coordinates
/// only. An angle is no length scale: a crank placed at 10⁸ rad would otherwise
/// accept a residual of 10⁴.
pub fn assembly_tolerance(model: &Model, q: &DVector<f64>) -> f64 {
    position_tolerance_of(&q.as_slice()[..model.relative_offset])
}

/// [`solve_position`] to the tolerance `tol` on max |Φ|.
pub fn solve_position_within(
    model: &Model,
    q: &mut DVector<f64>,
    keep: &[usize],
    tol: f64,
) -> Result<PositionSolution> {
    const MAX_ITERATIONS: usize = 100;
    let n = model.n();
    let free: Vec<usize> = (0..n).filter(|i| !keep.contains(i)).collect();
    let mut phi = model.phi(q);
    let mut iterations = 0;
    while !(phi.amax() <= tol) {
        if iterations == MAX_ITERATIONS || free.is_empty() || !phi.iter().all(|v| v.is_finite()) {
            return Err(violated(model, &phi, tol, iterations));
        }
        iterations += 1;
        let jac = model.jacobian(q);
        let jf = DMatrix::from_fn(model.m(), free.len(), |r, c| jac[(r, free[c])]);
        if !jf.iter().all(|v| v.is_finite()) {
            return Err(violated(model, &phi, tol, iterations));
        }
        let svd = jf.svd(true, true);
        let eps = RANK_TOL * svd.singular_values.max();
        let Ok(step) = svd.solve(&(-&phi), eps) else {
            return Err(violated(model, &phi, tol, iterations));
        };
        // Backtrack until |Φ| decreases.
        let norm0 = phi.norm();
        let mut alpha = 1.0;
        loop {
            let mut trial = q.clone();
            for (k, &i) in free.iter().enumerate() {
                trial[i] += alpha * step[k];
            }
            let phi_trial = model.phi(&trial);
            if phi_trial.norm() < norm0 {
                *q = trial;
                phi = phi_trial;
                break;
            }
            alpha *= 0.5;
            if alpha < 1e-6 {
                return Err(violated(model, &phi, tol, iterations));
            }
        }
    }
    Ok(PositionSolution {
        iterations,
        residual: phi.amax(),
    })
}

fn violated(model: &Model, phi: &DVector<f64>, tol: f64, iterations: usize) -> Error {
    let mut bad: Vec<(String, f64)> = phi
        .iter()
        .enumerate()
        .filter(|(_, v)| !(v.abs() <= tol))
        .map(|(k, v)| (model.constraints[k].name.clone(), v.abs()))
        .collect();
    bad.sort_by(|a, b| b.1.total_cmp(&a.1));
    Error::PositionProblem {
        violated: bad,
        iterations,
    }
}

/// Rank of Φ_q and the constraints that are linear combinations of earlier ones.
#[derive(Debug, Clone, PartialEq)]
pub struct RankInfo {
    pub rank: usize,
    /// Indices of redundant constraints; the others are independent.
    pub redundant: Vec<usize>,
}

/// Constraints from which [`constraint_rank`] first tries to certify full rank by a
/// sparse factorization: below, the scan's m²n operations cost less.
const SPARSE_RANK_FROM: usize = 48;

/// Coordinates from which the velocity and acceleration problems are solved with a
/// sparse LU (under its condition estimate): the size from which the dynamics factor
/// their KKT system sparse too (the 40 four-bar loops on).
const SPARSE_SOLVE_FROM: usize = 160;

/// Scans the rows of Φ_q in order, keeping those not in the span of the kept ones.
/// A large mechanism's rows are first certified independent, with a wide margin,
/// by the sparse Cholesky factor of their Gram matrix; only where that fails does
/// the scan run.
pub fn constraint_rank(model: &Model, q: &DVector<f64>) -> RankInfo {
    let jac = model.jacobian(q);
    let scale = (0..jac.nrows())
        .map(|r| jac.row(r).norm())
        .fold(0.0, f64::max);
    if jac.nrows() >= SPARSE_RANK_FROM && certainly_full_rank(&jac, scale) {
        return RankInfo {
            rank: jac.nrows(),
            redundant: Vec::new(),
        };
    }
    let mut basis: Vec<DVector<f64>> = Vec::new();
    let mut redundant = Vec::new();
    for r in 0..jac.nrows() {
        let row = jac.row(r).transpose();
        let residual = orthogonalize(&row, &basis);
        let norm = residual.norm();
        if norm > 1e-8 * row.norm().max(1e-300) && norm > 1e-14 * scale {
            basis.push(residual / norm);
        } else {
            redundant.push(r);
        }
    }
    RankInfo {
        rank: basis.len(),
        redundant,
    }
}

/// The constraint that takes a mechanism's last degree of freedom at q, when its
/// constraints leave none: the rows of Φ_q are scanned as in [`constraint_rank`], the
/// relative coordinates' definitions first (each adds an equation and a coordinate,
/// and locks nothing), then the others in scene order; the first row after which the
/// rank is n is named. None when the mechanism can move.
pub fn locking_constraint(model: &Model, q: &DVector<f64>) -> Option<usize> {
    let n = model.n();
    if n == 0 || model.dof() > 0 {
        return None;
    }
    let jac = model.jacobian(q);
    let scale = (0..jac.nrows())
        .map(|r| jac.row(r).norm())
        .fold(0.0, f64::max);
    let (defining, others): (Vec<usize>, Vec<usize>) =
        (0..model.m()).partition(|&k| model.constraints[k].coordinate.is_some());
    let mut basis: Vec<DVector<f64>> = Vec::new();
    for r in defining.into_iter().chain(others) {
        let row = jac.row(r).transpose();
        let residual = orthogonalize(&row, &basis);
        let norm = residual.norm();
        if norm > 1e-8 * row.norm().max(1e-300) && norm > 1e-14 * scale {
            basis.push(residual / norm);
            if basis.len() == n {
                return Some(r);
            }
        }
    }
    None
}

/// Whether no row of `jac` comes near the scan's redundancy test. The k-th pivot of
/// the Cholesky factor of the Gram matrix of the normalized rows, in their order, is
/// the part of row k outside the span of the rows before it, which the scan
/// measures. It is read through a squared quantity (rounding ~1e-16 relative), so a
/// pivot is trusted only from 1e-6 (1e-4 relative accuracy), a hundred times the
/// scan's threshold; below, the scan decides.
fn certainly_full_rank(jac: &DMatrix<f64>, scale: f64) -> bool {
    let (m, n) = (jac.nrows(), jac.ncols());
    let norms: Vec<f64> = (0..m).map(|r| jac.row(r).norm()).collect();
    if !norms.iter().all(|v| *v > 0.0 && v.is_finite()) {
        return false;
    }
    let mut lower = Vec::new();
    for j in 0..n {
        let rows: Vec<usize> = (0..m).filter(|&r| jac[(r, j)] != 0.0).collect();
        for (a, &i) in rows.iter().enumerate() {
            for &k in &rows[..=a] {
                lower.push((i, k, jac[(i, j)] * jac[(k, j)] / (norms[i] * norms[k])));
            }
        }
    }
    let Some(pivots) = crate::linalg::sparse::cholesky_pivots(m, &lower) else {
        return false;
    };
    pivots
        .iter()
        .zip(&norms)
        .all(|(p, norm)| *p >= 1e-6 && p * norm >= 1e-12 * scale)
}

/// Removes from v its components along an orthonormal basis (twice, for accuracy).
fn orthogonalize(v: &DVector<f64>, basis: &[DVector<f64>]) -> DVector<f64> {
    let mut r = v.clone();
    for _ in 0..2 {
        for b in basis {
            let c = b.dot(&r);
            r.axpy(-c, b, 1.0);
        }
    }
    r
}

/// Chooses f = n − rank independent coordinates that make [Φ_q; B] best conditioned
/// at q: at each step the coordinate whose unit vector lies farthest from the span of
/// the constraint rows and the coordinates already chosen.
pub fn choose_independent(model: &Model, q: &DVector<f64>) -> Vec<usize> {
    let jac = model.jacobian(q);
    let n = model.n();
    let mut basis: Vec<DVector<f64>> = Vec::new();
    for r in 0..jac.nrows() {
        let row = orthogonalize(&jac.row(r).transpose(), &basis);
        let norm = row.norm();
        if norm > 1e-8 * jac.row(r).norm().max(1e-300) {
            basis.push(row / norm);
        }
    }
    let mut chosen = Vec::new();
    while basis.len() < n {
        let (best, residual) = (0..n)
            .filter(|j| !chosen.contains(j))
            .map(|j| {
                (
                    j,
                    orthogonalize(&DVector::from_fn(n, |i, _| f64::from(i == j)), &basis),
                )
            })
            .max_by(|a, b| a.1.norm().total_cmp(&b.1.norm()))
            .expect("fewer basis vectors than coordinates leaves a candidate");
        let norm = residual.norm();
        chosen.push(best);
        basis.push(residual / norm);
    }
    chosen.sort_unstable();
    chosen
}

/// [Φ_q (independent rows); B], where B selects the coordinates in `independent`.
fn augmented(model: &Model, q: &DVector<f64>, independent: &[usize]) -> DMatrix<f64> {
    let jac = model.jacobian(q);
    let rows: Vec<usize> = model.active.clone();
    let (m, n) = (rows.len(), model.n());
    let mut a = DMatrix::zeros(m + independent.len(), n);
    for (r, &k) in rows.iter().enumerate() {
        a.row_mut(r).copy_from(&jac.row(k));
    }
    for (r, &j) in independent.iter().enumerate() {
        a[(m + r, j)] = 1.0;
    }
    a
}

fn names(model: &Model, idx: &[usize]) -> String {
    idx.iter()
        .map(|&i| model.names[i].as_str())
        .collect::<Vec<_>>()
        .join(", ")
}

/// Solves [Φ_q; B] x = [rhs; values] exactly, or says why it cannot.
fn solve_augmented(
    model: &Model,
    q: &DVector<f64>,
    independent: &[usize],
    rhs: &DVector<f64>,
    values: &[f64],
    what: &str,
) -> Result<DVector<f64>> {
    let n = model.n();
    let f = n - model.active.len();
    if independent.len() != f {
        return Err(Error::InvalidArgument(format!(
            "the {what} problem needs {f} independent coordinate(s) (the degrees of freedom), got {} [{}]",
            independent.len(),
            names(model, independent)
        )));
    }
    let a = augmented(model, q, independent);
    let mut b = DVector::zeros(a.nrows());
    for (r, &k) in model.active.iter().enumerate() {
        b[r] = rhs[k];
    }
    b.rows_mut(model.active.len(), values.len())
        .copy_from_slice(values);
    if n >= SPARSE_SOLVE_FROM {
        if let Some(x) = solve_sparse(&a, &b) {
            return Ok(x);
        }
    }
    let lu = a.full_piv_lu();
    if !well_conditioned(lu.u().diagonal().as_slice()) {
        return Err(Error::singular(format!(
            "the independent coordinates [{}] do not determine the {what} at this configuration",
            names(model, independent)
        )));
    }
    lu.solve(&b)
        .ok_or_else(|| Error::singular(format!("{what} problem")))
}

/// Largest condition number (1-norm estimate) at which [`solve_sparse`] trusts
/// its answer: a hundred times below where the dense pivot test (a pivot ratio
/// of 1e-13) calls the matrix singular; nearer, the dense test decides.
const SPARSE_TRUSTED_CONDITION: f64 = 1e11;

/// The solution of the square system A x = b by a sparse LU, when A is clearly
/// regular; `None` sends the caller to the dense factorization and its pivot test.
fn solve_sparse(a: &DMatrix<f64>, b: &DVector<f64>) -> Option<DVector<f64>> {
    let size = a.nrows();
    let triplets: Vec<(usize, usize, f64)> = (0..size)
        .flat_map(|c| (0..size).map(move |r| (r, c)))
        .filter(|&(r, c)| a[(r, c)] != 0.0)
        .map(|(r, c)| (r, c, a[(r, c)]))
        .collect();
    let mut x = b.as_slice().to_vec();
    let condition = crate::linalg::sparse::solve_square(size, &triplets, &mut x)?;
    (condition <= SPARSE_TRUSTED_CONDITION).then(|| DVector::from_vec(x))
}

/// Whether the pivots of an LU factorization show a regular matrix.
pub(crate) fn well_conditioned(pivots: &[f64]) -> bool {
    let max = pivots.iter().fold(0.0f64, |m, p| m.max(p.abs()));
    let min = pivots.iter().fold(f64::INFINITY, |m, p| m.min(p.abs()));
    max > 0.0 && min > 1e-13 * max
}

/// The velocity problem: q̇ with Φ_q q̇ = 0 and the given independent velocities.
pub fn solve_velocity(
    model: &Model,
    q: &DVector<f64>,
    independent: &[usize],
    dz: &[f64],
) -> Result<DVector<f64>> {
    let zero = DVector::zeros(model.m());
    solve_augmented(model, q, independent, &zero, dz, "velocity")
}

/// The acceleration problem: q̈ with Φ_q q̈ = −Φ̇_q q̇ and the given independent
/// accelerations.
pub fn solve_acceleration(
    model: &Model,
    q: &DVector<f64>,
    dq: &DVector<f64>,
    independent: &[usize],
    ddz: &[f64],
) -> Result<DVector<f64>> {
    let c = model.acceleration_rhs(q, dq);
    solve_augmented(model, q, independent, &c, ddz, "acceleration")
}

/// The augmented matrix's inverse split as [S R] (paper, eq. "dq = Sb + R ż").
pub fn s_and_r(
    model: &Model,
    q: &DVector<f64>,
    independent: &[usize],
) -> Result<(DMatrix<f64>, DMatrix<f64>)> {
    let n = model.n();
    let m = model.active.len();
    if independent.len() + m != n {
        return Err(Error::InvalidArgument(format!(
            "{} independent coordinate(s) given for {} degrees of freedom",
            independent.len(),
            n - m
        )));
    }
    let a = augmented(model, q, independent);
    let lu = a.full_piv_lu();
    if !well_conditioned(lu.u().diagonal().as_slice()) {
        return Err(Error::singular(format!(
            "the independent coordinates [{}] do not determine the motion at this configuration",
            names(model, independent)
        )));
    }
    let inv = lu
        .try_inverse()
        .ok_or_else(|| Error::singular("[Φ_q; B]"))?;
    Ok((
        inv.columns(0, m).into_owned(),
        inv.columns(m, n - m).into_owned(),
    ))
}

/// The position, velocity and acceleration problems with a fixed set of prescribed
/// coordinates, and the actuator forces on them, solved sample after sample along a
/// prescribed motion without allocating. Each Newton step of the position problem is
/// the least-norm correction from a rank-revealing QR of Φ_q on the other coordinates
/// (the [`NullSpace`] reduction of [Φ_q; Eᵀ], E the columns of I on the prescribed
/// coordinates), so redundant constraints do no harm; one more reduction at the
/// solution serves the velocity and acceleration problems (Φ_q q̇ = 0 and
/// Φ_q q̈ = −Φ̇_q q̇ with the prescribed components given) and, transposed, the
/// actuator forces (Φ_qᵀλ − E Q_a = Q − M q̈).
pub struct PrescribedKinematics {
    keep: Vec<usize>,
    n: usize,
    m: usize,
    /// [Φ_q; Eᵀ], row-major (m + p) × n.
    c: Vec<f64>,
    b: Vec<f64>,
    phi: Vec<f64>,
    trial: Vec<f64>,
    phi_trial: Vec<f64>,
    step: Vec<f64>,
    mu: Vec<f64>,
    ns: NullSpace,
}

impl PrescribedKinematics {
    /// For the coordinates `keep` prescribed (indices in q).
    pub fn new(model: &Model, keep: &[usize]) -> Self {
        let (n, m, p) = (model.n(), model.m(), keep.len());
        let mut c = vec![0.0; (m + p) * n];
        for (r, &i) in keep.iter().enumerate() {
            c[(m + r) * n + i] = 1.0;
        }
        PrescribedKinematics {
            keep: keep.to_vec(),
            n,
            m,
            c,
            b: vec![0.0; m + p],
            phi: vec![0.0; m],
            trial: vec![0.0; n],
            phi_trial: vec![0.0; m],
            step: vec![0.0; n],
            mu: vec![0.0; m + p],
            ns: {
                let mut ns = NullSpace::new(n, m + p);
                ns.set_summation(crate::linalg::dense::Summation::Lanes);
                ns
            },
        }
    }

    /// [Φ_q(q); Eᵀ] and its reduction (right-hand side in `b`).
    fn reduce_at(&mut self, model: &Model, q: &[f64]) {
        let (n, m) = (self.n, self.m);
        model.jacobian_into(q, &mut self.c[..m * n]);
        self.ns.reduce(&self.c, &self.b, m + self.keep.len());
    }

    /// Solves Φ(q) = 0 by damped Newton moving every coordinate but the prescribed
    /// ones, like [`solve_position`] (same tolerance, same backtracking, same errors).
    pub fn position(&mut self, model: &Model, q: &mut [f64]) -> Result<PositionSolution> {
        let tol = position_tolerance_of(q);
        self.position_within(model, q, tol)
    }

    /// [`PrescribedKinematics::position`] to |Φ| ≤ `tol` (a starting guess far from the
    /// solution should not set the tolerance).
    pub fn position_within(
        &mut self,
        model: &Model,
        q: &mut [f64],
        tol: f64,
    ) -> Result<PositionSolution> {
        const MAX_ITERATIONS: usize = 100;
        let (n, m) = (self.n, self.m);
        model.phi_into(q, &mut self.phi);
        let amax = |v: &[f64]| v.iter().fold(0.0f64, |a, x| a.max(x.abs()));
        let norm = |v: &[f64]| v.iter().map(|x| x * x).sum::<f64>().sqrt();
        let mut iterations = 0;
        while amax(&self.phi) > tol {
            if iterations == MAX_ITERATIONS || self.keep.len() == n {
                return Err(violated_slice(model, &self.phi, tol, iterations));
            }
            iterations += 1;
            for (b, p) in self.b[..m].iter_mut().zip(&self.phi) {
                *b = -p;
            }
            self.b[m..].fill(0.0);
            self.reduce_at(model, q);
            self.step.copy_from_slice(&self.ns.particular);
            if !self.step.iter().all(|v| v.is_finite()) {
                return Err(violated_slice(model, &self.phi, tol, iterations));
            }
            // Backtrack until |Φ| decreases.
            let norm0 = norm(&self.phi);
            let mut alpha = 1.0;
            loop {
                for ((t, x), d) in self.trial.iter_mut().zip(q.iter()).zip(&self.step) {
                    *t = x + alpha * d;
                }
                model.phi_into(&self.trial, &mut self.phi_trial);
                if norm(&self.phi_trial) < norm0 {
                    q.copy_from_slice(&self.trial);
                    std::mem::swap(&mut self.phi, &mut self.phi_trial);
                    break;
                }
                alpha *= 0.5;
                if alpha < 1e-6 {
                    return Err(violated_slice(model, &self.phi, tol, iterations));
                }
            }
        }
        Ok(PositionSolution {
            iterations,
            residual: amax(&self.phi),
        })
    }

    /// Factors [Φ_q(q); Eᵀ] at a solution of the position problem for
    /// [`PrescribedKinematics::velocity`], [`PrescribedKinematics::acceleration`] and
    /// [`PrescribedKinematics::forces`]; refuses a configuration where the prescribed
    /// coordinates do not determine the motion.
    pub fn factor(&mut self, model: &Model, q: &[f64]) -> Result<()> {
        let f = self.n - model.active.len();
        if self.keep.len() != f {
            return Err(Error::InvalidArgument(format!(
                "the velocity problem needs {f} independent coordinate(s) (the degrees of freedom), got {} [{}]",
                self.keep.len(),
                names(model, &self.keep)
            )));
        }
        self.b.fill(0.0);
        self.reduce_at(model, q);
        if self.ns.dim != 0 || self.ns.rank != self.n {
            return Err(Error::singular(format!(
                "the independent coordinates [{}] do not determine the velocity at this configuration",
                names(model, &self.keep)
            )));
        }
        Ok(())
    }

    /// q̇ with Φ_q q̇ = 0 and the prescribed components `v`, at the factored q.
    pub fn velocity(&mut self, v: &[f64], dq: &mut [f64]) {
        let m = self.m;
        self.b[..m].fill(0.0);
        self.b[m..].copy_from_slice(v);
        self.ns.solve(&self.b, dq);
    }

    /// q̈ with Φ_q q̈ = −Φ̇_q q̇ and the prescribed components `a`, at the factored q.
    pub fn acceleration(
        &mut self,
        model: &Model,
        q: &[f64],
        dq: &[f64],
        a: &[f64],
        ddq: &mut [f64],
    ) {
        let m = self.m;
        model.acceleration_rhs_into(q, dq, &mut self.b[..m]);
        self.b[m..].copy_from_slice(a);
        self.ns.solve(&self.b, ddq);
    }

    /// The actuator forces Q_a on the prescribed coordinates (one per coordinate, in
    /// their order) with M q̈ + Φ_qᵀλ − E Q_a = Q(q, q̇, t), at the factored q.
    pub fn forces(
        &mut self,
        model: &Model,
        q: &[f64],
        dq: &[f64],
        ddq: &[f64],
        t: f64,
        out: &mut [f64],
    ) -> Result<()> {
        let (n, m) = (self.n, self.m);
        let r = &mut self.trial;
        r.fill(0.0);
        for (i, f) in model.forces.iter().enumerate() {
            f.add_to(model, q, dq, t, r)
                .map_err(|e| model.effect_error(i, e))?;
        }
        for i in 0..n {
            r[i] -= (0..n).map(|j| model.mass[(i, j)] * ddq[j]).sum::<f64>();
        }
        self.ns.solve_transpose(r, &mut self.mu);
        for (o, mu) in out.iter_mut().zip(&self.mu[m..]) {
            *o = -mu;
        }
        Ok(())
    }
}

fn violated_slice(model: &Model, phi: &[f64], tol: f64, iterations: usize) -> Error {
    violated(model, &DVector::from_column_slice(phi), tol, iterations)
}
