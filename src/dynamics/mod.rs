//! Classical forward dynamics, used by the factors and as a check on them:
//! q̈ from the augmented (KKT) system with Lagrange multipliers, and z̈ by the
//! R-matrix method (paper, section 2); and the allocation-free [`DynamicsKernel`]
//! with exact Jacobians on which the dynamics factors build (`kernel`, evaluated
//! in `augmented`, its singularity measure in `regularization`, its directional
//! products in `along`; a large mechanism's KKT system factored sparse in
//! `sparse_kkt`).

mod along;
mod augmented;
mod kernel;
mod regularization;
mod sparse_kkt;

pub use augmented::KernelScratch;
pub use kernel::DynamicsKernel;
pub use sparse_kkt::{KktStructure, SPARSE_KKT_FROM};

use crate::error::{Error, Result};
use crate::kinematics::{s_and_r, well_conditioned};
use crate::model::Model;
use nalgebra::{DMatrix, DVector};

/// Accelerations and the multipliers of the independent (non-redundant) constraints.
#[derive(Debug, Clone, PartialEq)]
pub struct LagrangeSolution {
    pub ddq: DVector<f64>,
    /// One multiplier per entry of `Model::active`.
    pub lambda: DVector<f64>,
}

/// Solves [M Φ_qᵀ; Φ_q 0] [q̈; λ] = [Q; c] (paper, eq. "qDynSys"), with c = −Φ̇_q q̇
/// and the redundant constraints left out so that the system is regular.
pub fn lagrange(
    model: &Model,
    q: &DVector<f64>,
    dq: &DVector<f64>,
    t: f64,
) -> Result<LagrangeSolution> {
    if let Some(structure) = KktStructure::for_model(model) {
        return lagrange_sparse(model, &structure, q, dq, t);
    }
    let n = model.n();
    let rows = &model.active;
    let m = rows.len();
    let jac = model.jacobian(q);
    let c = model.acceleration_rhs(q, dq);
    let force = model.generalized_forces(q, dq, t)?;
    // Equilibrated: M scaled by its largest entry and Φ_q by its, so that the pivot
    // test below reads the same for a 1 g and a 30 t pendulum, for mm and m links.
    let mu_m = model.mass.amax();
    let mu_j = rows
        .iter()
        .flat_map(|&k| jac.row(k).iter().map(|v| v.abs()).collect::<Vec<_>>())
        .fold(0.0f64, f64::max);
    if !(mu_m > 0.0 && mu_m.is_finite()) || (m > 0 && !(mu_j > 0.0 && mu_j.is_finite())) {
        return Err(Error::singular(
            "the mass matrix or the constraint Jacobian is zero or not finite at this configuration",
        ));
    }
    let mu_j = if m > 0 { mu_j } else { 1.0 };
    let mut kkt = DMatrix::zeros(n + m, n + m);
    kkt.view_mut((0, 0), (n, n))
        .copy_from(&(&model.mass / mu_m));
    let mut rhs = DVector::zeros(n + m);
    rhs.rows_mut(0, n).copy_from(&(&force / mu_m));
    for (r, &k) in rows.iter().enumerate() {
        for j in 0..n {
            kkt[(n + r, j)] = jac[(k, j)] / mu_j;
            kkt[(j, n + r)] = jac[(k, j)] / mu_j;
        }
        rhs[n + r] = c[k] / mu_j;
    }
    if !rhs.iter().all(|v| v.is_finite()) {
        return Err(Error::singular(
            "the generalized forces or the constraints' acceleration terms are not finite at this state",
        ));
    }
    let lu = kkt.full_piv_lu();
    if !well_conditioned(lu.u().diagonal().as_slice()) {
        return Err(Error::singular(
            "the augmented (KKT) system is singular at this configuration: the constraints are dependent here or the mass matrix does not cover the free motion",
        ));
    }
    let x = lu
        .solve(&rhs)
        .ok_or_else(|| Error::singular("augmented (KKT) system"))?;
    Ok(LagrangeSolution {
        ddq: x.rows(0, n).into_owned(),
        lambda: x.rows(n, m) * (mu_m / mu_j),
    })
}

/// The condition number of the augmented system above which it is taken as singular
/// (the dense LU's pivot test reads its pivots' ratio against 1e-13).
const KKT_CONDITION_LIMIT: f64 = 1e13;

/// [`lagrange`] for a mechanism whose augmented system is factored sparse
/// ([`SPARSE_KKT_FROM`] unknowns on): the dense full-pivot LU costs (n + m)³ (38 s
/// for a 2,000-point chain), the sparse one about its nonzeros. Its partial pivots do
/// not reveal a singular system, so a solve of a probe right-hand side bounds
/// ‖K⁻¹‖ from below: past [`KKT_CONDITION_LIMIT`] of 1/‖K‖, K is singular.
fn lagrange_sparse(
    model: &Model,
    structure: &KktStructure,
    q: &DVector<f64>,
    dq: &DVector<f64>,
    t: f64,
) -> Result<LagrangeSolution> {
    let (n, m) = (model.n(), model.m());
    let ma = model.active.len();
    let big = n + ma;
    let mut jac = vec![0.0; m * n];
    model.jacobian_into(q.as_slice(), &mut jac);
    let c = model.acceleration_rhs(q, dq);
    let force = model.generalized_forces(q, dq, t)?;
    let norm = model
        .mass
        .amax()
        .max(jac.iter().fold(0.0f64, |a, v| a.max(v.abs())));
    if !(norm > 0.0 && norm.is_finite()) {
        return Err(Error::singular(
            "the mass matrix or the constraint Jacobian is zero or not finite at this configuration",
        ));
    }
    // Two right-hand sides, row-major: [Q; c] and the probe of alternating signs.
    let mut b = vec![0.0; 2 * big];
    for i in 0..n {
        b[2 * i] = force[i];
    }
    for (r, &k) in model.active.iter().enumerate() {
        b[2 * (n + r)] = c[k];
    }
    for (i, probe) in b.iter_mut().skip(1).step_by(2).enumerate() {
        *probe = if i % 2 == 0 { 1.0 } else { -1.0 };
    }
    if !b.iter().all(|v| v.is_finite()) {
        return Err(Error::singular(
            "the generalized forces or the constraints' acceleration terms are not finite at this state",
        ));
    }
    let singular = || {
        Error::singular(
            "the augmented (KKT) system is singular at this configuration: the constraints are dependent here or the mass matrix does not cover the free motion",
        )
    };
    let lu = structure
        .factor(model, &jac, None)
        .map_err(|_| singular())?;
    lu.solve_many(&mut b, 2).map_err(|_| singular())?;
    let inverse = b
        .iter()
        .skip(1)
        .step_by(2)
        .fold(0.0f64, |a, v| a.max(v.abs()));
    if !(inverse * norm < KKT_CONDITION_LIMIT) {
        return Err(singular());
    }
    Ok(LagrangeSolution {
        ddq: DVector::from_iterator(n, (0..n).map(|i| b[2 * i])),
        lambda: DVector::from_iterator(ma, (0..ma).map(|r| b[2 * (n + r)])),
    })
}

/// q̈ at (q, q̇, t) as a starting guess: for a mechanism whose augmented system is
/// factored sparse ([`SPARSE_KKT_FROM`] unknowns on) by its sparse LU, else (and
/// where that fails) by [`lagrange`], whose pivot test names a singular
/// configuration.
pub fn accelerations_guess(
    model: &Model,
    q: &DVector<f64>,
    dq: &DVector<f64>,
    t: f64,
) -> Result<DVector<f64>> {
    let sparse = || -> Option<DVector<f64>> {
        let structure = KktStructure::for_model(model)?;
        let (n, m) = (model.n(), model.m());
        let mut jac = vec![0.0; m * n];
        model.jacobian_into(q.as_slice(), &mut jac);
        let lu = structure.factor(model, &jac, None).ok()?;
        let c = model.acceleration_rhs(q, dq);
        let mut rhs: Vec<f64> = model
            .generalized_forces(q, dq, t)
            .ok()?
            .iter()
            .copied()
            .collect();
        rhs.extend(model.active.iter().map(|&k| c[k]));
        lu.solve_many(&mut rhs, 1).ok()?;
        Some(DVector::from_column_slice(&rhs[..n]))
    };
    match sparse() {
        Some(ddq) => Ok(ddq),
        None => Ok(lagrange(model, q, dq, t)?.ddq),
    }
}

/// Accelerations in independent coordinates by the R-matrix method.
#[derive(Debug, Clone, PartialEq)]
pub struct RMatrixSolution {
    /// z̈ = M̄⁻¹ Q̄, with M̄ = RᵀMR and Q̄ = Rᵀ(Q − M S c).
    pub ddz: DVector<f64>,
    /// q̈ = S c + R z̈.
    pub ddq: DVector<f64>,
}

/// z̈ for the coordinates `independent` (indices in q) (paper, eq. "zDynSys").
pub fn r_matrix(
    model: &Model,
    q: &DVector<f64>,
    dq: &DVector<f64>,
    t: f64,
    independent: &[usize],
) -> Result<RMatrixSolution> {
    let (s, r) = s_and_r(model, q, independent)?;
    let c_all = model.acceleration_rhs(q, dq);
    let c = DVector::from_iterator(model.active.len(), model.active.iter().map(|&k| c_all[k]));
    let force = model.generalized_forces(q, dq, t)?;
    let sc = &s * &c;
    let m_bar = r.transpose() * &model.mass * &r;
    let q_bar = r.transpose() * (force - &model.mass * &sc);
    let chol = m_bar
        .cholesky()
        .ok_or_else(|| Error::singular("the reduced mass matrix RᵀMR is not positive definite"))?;
    let ddz = chol.solve(&q_bar);
    let ddq = sc + &r * &ddz;
    Ok(RMatrixSolution { ddz, ddq })
}

/// Classical inverse dynamics: the actuator forces Q_a on the coordinates `actuated`
/// (one generalized force per listed coordinate, zero elsewhere) that, with the
/// scene's forces, produce the consistent motion (q, q̇, q̈). Solves
/// M q̈ + Φ_qᵀλ − E Q_a = Q_scene for (λ, Q_a) in the least-squares sense, so
/// redundant constraints are harmless. Returns the full n-vector of actuator forces.
pub fn actuator_forces(
    model: &Model,
    q: &DVector<f64>,
    dq: &DVector<f64>,
    ddq: &DVector<f64>,
    t: f64,
    actuated: &[usize],
) -> Result<DVector<f64>> {
    let n = model.n();
    let m = model.m();
    let jac = model.jacobian(q);
    let rhs = model.generalized_forces(q, dq, t)? - &model.mass * ddq;
    let mut a = DMatrix::zeros(n, m + actuated.len());
    a.view_mut((0, 0), (n, m)).copy_from(&jac.transpose());
    for (c, &i) in actuated.iter().enumerate() {
        a[(i, m + c)] = -1.0;
    }
    if !(a.iter().chain(rhs.iter()).all(|v| v.is_finite())) {
        return Err(Error::singular(format!(
            "inverse dynamics at t = {t}: the state gives non-finite constraint forces"
        )));
    }
    let svd = a.svd(true, true);
    let x = svd
        .solve(&rhs, 1e-12 * svd.singular_values.max())
        .map_err(|e| Error::singular(format!("inverse dynamics: {e}")))?;
    let mut out = DVector::zeros(n);
    for (c, &i) in actuated.iter().enumerate() {
        out[i] = x[m + c];
    }
    Ok(out)
}
