//! A classical reference integrator, independent of the factor graphs: the equations
//! of motion in independent coordinates, z̈ = M̄⁻¹Q̄ (R-matrix method), integrated by
//! classical fourth-order Runge-Kutta with a fine fixed step, q recovered at every
//! stage by the position and velocity problems. Used to check the graphs until the
//! external references (IDA, exudyn, Pinocchio) are in place.

use crate::dynamics;
use crate::error::{Error, Result};
use crate::kinematics;
use crate::model::Model;
use crate::trajectory::Trajectory;
use nalgebra::DVector;

/// Integrates from the model's initial state with internal step `h`, sampling every
/// `dt` (a multiple of h) up to `t_end`.
pub fn minimal_coordinates_rk4(
    model: &Model,
    independent: &[usize],
    dt: f64,
    t_end: f64,
    h: f64,
) -> Result<Trajectory> {
    let sub = (dt / h).round() as usize;
    if sub == 0 || ((sub as f64) * h - dt).abs() > 1e-12 * dt {
        return Err(Error::InvalidArgument(format!(
            "dt = {dt} is not a multiple of h = {h}"
        )));
    }
    let f = independent.len();
    let samples = (t_end / dt).round() as usize + 1;
    let mut q = model.initial.q.clone();
    let z0: Vec<f64> = independent.iter().map(|&i| q[i]).collect();
    let dz0: Vec<f64> = independent.iter().map(|&i| model.initial.dq[i]).collect();
    let mut y = DVector::from_iterator(2 * f, z0.into_iter().chain(dz0));
    let mut tr = Trajectory {
        names: model.names.clone(),
        t: Vec::with_capacity(samples),
        q: Vec::with_capacity(samples * model.n()),
        dq: Vec::with_capacity(samples * model.n()),
        ddq: Vec::with_capacity(samples * model.n()),
    };
    // State derivative [ż; z̈] at (t, y); q is kept as the Newton start (the branch).
    let rhs = |t: f64,
               y: &DVector<f64>,
               q: &mut DVector<f64>|
     -> Result<(DVector<f64>, DVector<f64>, DVector<f64>)> {
        for (k, &i) in independent.iter().enumerate() {
            q[i] = y[k];
        }
        kinematics::solve_position(model, q, independent)?;
        let dz: Vec<f64> = (0..f).map(|k| y[f + k]).collect();
        let dq = kinematics::solve_velocity(model, q, independent, &dz)?;
        let s = dynamics::r_matrix(model, q, &dq, t, independent)?;
        let mut d = DVector::zeros(2 * f);
        for k in 0..f {
            d[k] = dz[k];
            d[f + k] = s.ddz[k];
        }
        Ok((d, dq, s.ddq))
    };
    let mut t = 0.0;
    for sample in 0..samples {
        let (_, dq, ddq) = rhs(t, &y, &mut q)?;
        tr.t.push(sample as f64 * dt);
        tr.q.extend_from_slice(q.as_slice());
        tr.dq.extend_from_slice(dq.as_slice());
        tr.ddq.extend_from_slice(ddq.as_slice());
        if sample + 1 == samples {
            break;
        }
        for _ in 0..sub {
            let mut qs = q.clone();
            let k1 = rhs(t, &y, &mut qs)?.0;
            let k2 = rhs(t + 0.5 * h, &(&y + &k1 * (0.5 * h)), &mut qs)?.0;
            let k3 = rhs(t + 0.5 * h, &(&y + &k2 * (0.5 * h)), &mut qs)?.0;
            let k4 = rhs(t + h, &(&y + &k3 * h), &mut qs)?.0;
            y += (k1 + k2 * 2.0 + k3 * 2.0 + k4) * (h / 6.0);
            t += h;
        }
        t = (sample + 1) as f64 * dt;
    }
    Ok(tr)
}

/// The paper's RMSE: over all samples and over the x, y of the named points, the
/// root mean square of the difference between two trajectories sampled alike.
pub fn rmse_points(a: &Trajectory, b: &Trajectory, coordinates: &[usize]) -> f64 {
    let samples = a.len().min(b.len());
    let (na, nb) = (a.n(), b.n());
    let mut sum = 0.0;
    for k in 0..samples {
        for &c in coordinates {
            let d = a.q[k * na + c] - b.q[k * nb + c];
            sum += d * d;
        }
    }
    (sum / (samples * coordinates.len()).max(1) as f64).sqrt()
}
