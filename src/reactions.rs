//! Joint forces: the force the rest of the mechanism exerts on each body at each of
//! its points, in newtons, global axes.
//!
//! In natural coordinates a body's points are its coordinates, so the forces at its
//! points are generalized forces on them, and the body's own equation of motion reads
//! M_b a_b + Σ_k Φ_k,rᵀ λ_k = Q_b + F_b, the sum over the constraints that belong to
//! the body (its rigidity, and the angle coordinates measured along it: those carry a
//! motor's torque onto it). The multipliers λ come from the whole mechanism,
//! Φ_qᵀ λ = Q − M q̈, so F_b = M_b a_b − Q_b + Σ_k Φ_k,rᵀ λ_k is the force at each
//! point where bodies meet, as the Newton–Euler equations of all bodies together
//! give it. Loads at points (point masses, springs, forces) and sliders act on the
//! point, not on a body: they are in the balance of the point, not in F_b.

use crate::error::{Error, Result};
use crate::model::{mass, Model, MAX_LOCAL};
use crate::scene::{ConstraintKind, Effect, RelativeKind};
use nalgebra::{DMatrix, DVector};

/// For every body, in scene order, the force on it at each of its points, in the order
/// of `body.points`: `[[fx, fy], …]`.
pub type JointForces = Vec<Vec<[f64; 2]>>;

/// The joint forces at the state (q, q̇, q̈) at time t, q̈ consistent with the motion
/// (a forward or inverse result). `extra` adds generalized forces that are not the
/// scene's (the actuator forces of an inverse solve).
pub fn joint_forces(
    model: &Model,
    q: &[f64],
    dq: &[f64],
    ddq: &[f64],
    t: f64,
    extra: Option<&[f64]>,
) -> Result<JointForces> {
    let scene = &model.scene;
    let lambda = multipliers(model, q, dq, ddq, t, extra)?;
    let gravity = scene.effects.iter().find_map(|e| match e {
        Effect::Gravity { vector } => Some(*vector),
        _ => None,
    });
    let accel = |p: usize| model.point_velocity(ddq, p);
    let owner = owners(model);
    let mut out: JointForces = scene
        .bodies
        .iter()
        .map(|b| vec![[0.0; 2]; b.points.len()])
        .collect();
    // Inertia and gravity on the first two points, where a body's mass is.
    for (bi, body) in scene.bodies.iter().enumerate() {
        let mb = mass::body_mass_matrix(body);
        let (a1, a2) = (accel(body.points[0]), accel(body.points[1]));
        let a = [a1[0], a1[1], a2[0], a2[1]];
        let g = gravity.map_or([0.0; 4], |g| mass::body_gravity_force(body, g));
        for r in 0..4 {
            let inertia: f64 = (0..4).map(|c| mb[r][c] * a[c]).sum();
            out[bi][r / 2][r % 2] += inertia - g[r];
        }
    }
    // The constraints that belong to a body, point by point.
    let mut u = [0.0; MAX_LOCAL];
    let mut grad = [0.0; MAX_LOCAL];
    for (r, &k) in model.active.iter().enumerate() {
        let c = &model.constraints[k];
        c.gather(q, &mut u);
        grad.fill(0.0);
        c.equation.gradient(&u[..c.equation.len()], &mut grad);
        for (j, &p) in c.points.iter().enumerate() {
            let Some(bi) = owner[k][j] else { continue };
            let slot = scene.bodies[bi]
                .points
                .iter()
                .position(|&bp| bp == p)
                .expect("an owner body holds the point");
            out[bi][slot][0] += grad[2 * j] * lambda[r];
            out[bi][slot][1] += grad[2 * j + 1] * lambda[r];
        }
    }
    if out.iter().flatten().flatten().any(|v| !v.is_finite()) {
        return Err(Error::singular(format!(
            "joint forces at t = {t} s are not finite"
        )));
    }
    Ok(out)
}

/// The force each of the scene's `constraints` carries at the state (q, q̇, q̈) at time
/// t, in the order listed, N. With the equations' multipliers λ (M q̈ + Φ_qᵀ λ = Q):
///
/// - a `distance` between A and B: its tension T = 2 |r_B − r_A| λ, positive when it
///   pulls A and B together (the force on B is −T (r_B − r_A)/|r_B − r_A|);
/// - a `fixed_slider` or `mobile_slider` of P on the line A→B: the normal force N on P
///   along the line's left normal n (A→B turned 90° counter-clockwise), N = −|r_B − r_A| λ;
///   the guide takes −N n at P (on a moving guide, that force and its moment about A,
///   −N s with s the distance of P from A along the line, act on the guide's body).
///
/// A redundant constraint is left out of the dynamics: it carries none (0).
pub fn constraint_forces(
    model: &Model,
    q: &[f64],
    dq: &[f64],
    ddq: &[f64],
    t: f64,
    extra: Option<&[f64]>,
) -> Result<Vec<f64>> {
    let lambda = multipliers(model, q, dq, ddq, t, extra)?;
    let length = |a: usize, b: usize| {
        let (ra, rb) = (model.point_position(q, a), model.point_position(q, b));
        (rb[0] - ra[0]).hypot(rb[1] - ra[1])
    };
    let out: Vec<f64> = model
        .scene
        .constraints
        .iter()
        .map(|c| {
            let row = model
                .active
                .iter()
                .position(|&k| model.constraints[k].name == c.name);
            let Some(r) = row else { return 0.0 };
            match c.kind {
                ConstraintKind::Distance { points, .. } => {
                    2.0 * length(points[0], points[1]) * lambda[r]
                }
                ConstraintKind::FixedSlider { line, .. }
                | ConstraintKind::MobileSlider { line, .. } => {
                    -length(line[0], line[1]) * lambda[r]
                }
            }
        })
        .collect();
    if out.iter().any(|v| !v.is_finite()) {
        return Err(Error::singular(format!(
            "constraint forces at t = {t} s are not finite"
        )));
    }
    Ok(out)
}

/// λ over the active constraints from Φ_qᵀ λ = Q − M q̈ (least squares: exact for a
/// consistent state).
fn multipliers(
    model: &Model,
    q: &[f64],
    dq: &[f64],
    ddq: &[f64],
    t: f64,
    extra: Option<&[f64]>,
) -> Result<DVector<f64>> {
    let n = model.n();
    let (qv, dqv) = (
        DVector::from_column_slice(q),
        DVector::from_column_slice(dq),
    );
    let mut rhs =
        model.generalized_forces(&qv, &dqv, t)? - &model.mass * DVector::from_column_slice(ddq);
    if let Some(f) = extra {
        rhs += DVector::from_column_slice(f);
    }
    let jac = model.jacobian(&qv);
    let active = &model.active;
    let a = DMatrix::from_fn(n, active.len(), |i, r| jac[(active[r], i)]);
    if !(a.iter().chain(rhs.iter()).all(|v| v.is_finite())) {
        return Err(Error::singular(format!(
            "joint forces at t = {t} s: the state is not finite"
        )));
    }
    if active.is_empty() {
        return Ok(DVector::zeros(0));
    }
    let svd = a.svd(true, true);
    let eps = 1e-12 * svd.singular_values.max();
    svd.solve(&rhs, eps)
        .map_err(|e| Error::singular(format!("joint forces at t = {t} s: {e}")))
}

/// For each constraint and each of its points, the body the constraint's force there
/// acts on: a body's rigidity on that body; an angle coordinate along a body's segment
/// on that body (a motor's torque acts on the body, not on its pins); anything else on
/// the point itself (None).
fn owners(model: &Model) -> Vec<Vec<Option<usize>>> {
    let scene = &model.scene;
    let body_of = |a: usize, b: usize| {
        scene
            .bodies
            .iter()
            .position(|body| body.points.contains(&a) && body.points.contains(&b))
    };
    model
        .constraints
        .iter()
        .map(|c| {
            if let Some(b) = c.body {
                return vec![Some(b); c.points.len()];
            }
            match c.coordinate.map(|i| &scene.coordinates[i].kind) {
                Some(RelativeKind::AbsoluteAngle { from, to }) => {
                    vec![body_of(*from, *to); 2]
                }
                Some(RelativeKind::RelativeAngle { a, b }) => {
                    let (ba, bb) = (body_of(a[0], a[1]), body_of(b[0], b[1]));
                    vec![ba, ba, bb, bb]
                }
                _ => vec![None; c.points.len()],
            }
        })
        .collect()
}
