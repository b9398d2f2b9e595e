//! How the model depends on the parameters an estimate identifies ([`Parameters`]).
//! The scene reader lets them into masses, inertias, gravity and spring and damper
//! constants, each linearly (`scene::Identified`), so M(p) and Q(q, q̇, t; p) are
//! exact at every p from the file's model and the constants' derivatives: M is
//! linear in the masses and inertias, a spring's force in its stiffness and
//! damping, gravity's force bilinear in the masses and the vector.
//!
//! The dynamics factor solves M(p) q̈ + Φ_qᵀλ = Q(p) with M(p) ([`Parameters::mass_at`])
//! in its augmented system and Q(p) as the file's Q plus the force the parameters
//! add ([`Parameters::force`]): its residual stays an acceleration at every p, so
//! that the process noise means the same whatever masses the estimate tries.

use super::forces::Force;
use super::{mass, Model, PointSlot, Slot};
use crate::error::{Error, Result};

/// The masses of the bodies and the points, and gravity's vector, at some p.
struct Masses {
    bodies: Vec<f64>,
    points: Vec<f64>,
    g: [f64; 2],
}

/// The identified parameters, their values in the file, and the derivatives of the
/// model's constants.
#[derive(Debug, Clone)]
pub struct Parameters {
    pub names: Vec<String>,
    /// The file's values, the priors' means.
    pub values: Vec<f64>,
    /// ∂M/∂pⱼ, row-major n × n each.
    mass: Vec<Vec<f64>>,
    /// ∂mass/∂p of every body (zeros where it does not depend on them).
    body_mass: Vec<Vec<f64>>,
    /// ∂mass/∂p of every point (zeros where it does not depend on them).
    point_mass: Vec<Vec<f64>>,
    /// Gravity's vector in the file and its ∂/∂p (x and y), if the scene has gravity.
    gravity: Option<([f64; 2], [Vec<f64>; 2])>,
    /// Forces linear in two constants (springs and dampers, a DC motor's stall
    /// torque): (index into `Model::forces`, ∂/∂p of each constant).
    springs: Vec<(usize, Vec<f64>, Vec<f64>)>,
}

impl Parameters {
    /// The scene's identified parameters, or `None` where it identifies none. A
    /// parameter that nothing in the model depends on is refused: its estimate would
    /// be its prior.
    pub(super) fn of(model: &Model) -> Result<Option<Parameters>> {
        let id = &model.scene.identified;
        if id.is_empty() {
            return Ok(None);
        }
        let (n, p) = (model.n(), id.names.len());
        let mut out = Parameters {
            names: id.names.clone(),
            values: id.values.clone(),
            mass: vec![vec![0.0; n * n]; p],
            body_mass: vec![vec![0.0; p]; model.scene.bodies.len()],
            point_mass: vec![vec![0.0; p]; model.scene.points.len()],
            gravity: None,
            springs: Vec::new(),
        };
        let mut touched = vec![false; p];
        for (b, dm, di0) in &id.bodies {
            let body = &model.scene.bodies[*b];
            let slots = model.slots(&body.points[..2], None);
            for j in 0..p {
                if dm[j] == 0.0 && di0[j] == 0.0 {
                    continue;
                }
                touched[j] = true;
                let mb = mass::inertia_matrix(body, dm[j], di0[j]);
                for (a, sa) in slots.iter().enumerate() {
                    for (c, sc) in slots.iter().enumerate() {
                        if let (Slot::Q(r), Slot::Q(k)) = (sa, sc) {
                            out.mass[j][r * n + k] += mb[a][c];
                        }
                    }
                }
            }
            out.body_mass[*b] = dm.clone();
        }
        for (pt, dm) in &id.points {
            if let PointSlot::Free(i) = model.points[*pt] {
                for j in (0..p).filter(|&j| dm[j] != 0.0) {
                    touched[j] = true;
                    out.mass[j][i * n + i] += dm[j];
                    out.mass[j][(i + 1) * n + i + 1] += dm[j];
                }
            }
            out.point_mass[*pt] = dm.clone();
        }
        for (e, [a, b]) in &id.effects {
            let changed = |j: usize| a[j] != 0.0 || b[j] != 0.0;
            (0..p)
                .filter(|&j| changed(j))
                .for_each(|j| touched[j] = true);
            match &model.forces[*e] {
                Force::Gravity { vector, .. } => {
                    out.gravity = Some((*vector, [a.clone(), b.clone()]));
                }
                f if f.with_constants(0.0, 0.0).is_some() => {
                    out.springs.push((*e, a.clone(), b.clone()));
                }
                _ => {
                    return Err(Error::InvalidArgument(format!(
                        "effect {} cannot depend on an identified parameter",
                        model.scene.effects[*e].describe(&model.scene)
                    )))
                }
            }
        }
        if out.gravity.is_none() {
            out.gravity = model.forces.iter().find_map(|f| match f {
                Force::Gravity { vector, .. } => Some((*vector, [vec![0.0; p], vec![0.0; p]])),
                _ => None,
            });
        }
        // A mass moves gravity's force only where there is gravity.
        if let Some((g, _)) = out.gravity {
            if g != [0.0, 0.0] {
                let masses = id.bodies.iter().map(|(_, dm, _)| dm);
                for dm in masses.chain(id.points.iter().map(|(_, dm)| dm)) {
                    (0..p)
                        .filter(|&j| dm[j] != 0.0)
                        .for_each(|j| touched[j] = true);
                }
            }
        }
        if let Some(j) = touched.iter().position(|t| !t) {
            return Err(Error::InvalidArgument(format!(
                "the identified parameter '{}' changes nothing in the model: no mass, inertia, \
                 gravity, spring, damper or motor of the scene uses it",
                out.names[j]
            )));
        }
        Ok(Some(out))
    }

    pub fn len(&self) -> usize {
        self.names.len()
    }

    pub fn is_empty(&self) -> bool {
        self.names.is_empty()
    }

    /// Gravity's generalized force with the bodies' masses `mass(b)`, the points'
    /// masses `point(p)` and the vector `g`, added to `out`.
    fn add_gravity(
        model: &Model,
        mass: &dyn Fn(usize) -> f64,
        point: &dyn Fn(usize) -> f64,
        g: [f64; 2],
        out: &mut [f64],
    ) {
        for (b, body) in model.scene.bodies.iter().enumerate() {
            let m = mass(b);
            if m == 0.0 {
                continue;
            }
            let f = mass::gravity_force(body, m, g);
            for (k, &pt) in body.points[..2].iter().enumerate() {
                if let PointSlot::Free(i) = model.points[pt] {
                    out[i] += f[2 * k];
                    out[i + 1] += f[2 * k + 1];
                }
            }
        }
        for pt in 0..model.scene.points.len() {
            if let PointSlot::Free(i) = model.points[pt] {
                let m = point(pt);
                out[i] += m * g[0];
                out[i + 1] += m * g[1];
            }
        }
    }

    fn shift(&self, p: &[f64]) -> Vec<f64> {
        p.iter().zip(&self.values).map(|(a, b)| a - b).collect()
    }

    fn dot(a: &[f64], b: &[f64]) -> f64 {
        a.iter().zip(b).map(|(x, y)| x * y).sum()
    }

    /// The bodies' and the points' masses and gravity's vector at p.
    fn gravity_at(&self, model: &Model, dp: &[f64]) -> Option<Masses> {
        let (g0, [gx, gy]) = self.gravity.as_ref()?;
        let scene = &model.scene;
        let at = |m: f64, dm: &[f64]| m + Self::dot(dm, dp);
        Some(Masses {
            bodies: scene
                .bodies
                .iter()
                .zip(&self.body_mass)
                .map(|(b, dm)| at(b.mass, dm))
                .collect(),
            points: scene
                .points
                .iter()
                .zip(&self.point_mass)
                .map(|(p, dm)| at(p.mass, dm))
                .collect(),
            g: [g0[0] + Self::dot(gx, dp), g0[1] + Self::dot(gy, dp)],
        })
    }

    /// M(p), row-major n × n.
    pub fn mass_at(&self, model: &Model, p: &[f64]) -> Vec<f64> {
        let n = model.n();
        let dp = self.shift(p);
        let mut m: Vec<f64> = (0..n * n).map(|k| model.mass[(k / n, k % n)]).collect();
        for (j, mj) in self.mass.iter().enumerate() {
            if dp[j] != 0.0 {
                m.iter_mut().zip(mj).for_each(|(a, b)| *a += dp[j] * b);
            }
        }
        m
    }

    /// Q(p) − Q(p₀) at (q, q̇, t) into `out` (length n; overwritten).
    pub fn force(
        &self,
        model: &Model,
        p: &[f64],
        (q, dq, t): (&[f64], &[f64], f64),
        out: &mut [f64],
    ) -> Result<()> {
        let n = model.n();
        let dp = self.shift(p);
        out.fill(0.0);
        if let Some(at) = self.gravity_at(model, &dp) {
            let g0 = self.gravity.as_ref().map_or([0.0; 2], |(g0, _)| *g0);
            Self::add_gravity(model, &|b| at.bodies[b], &|p| at.points[p], at.g, out);
            let mut base = vec![0.0; n];
            let scene = &model.scene;
            let body0 = |b: usize| scene.bodies[b].mass;
            let point0 = |p: usize| scene.points[p].mass;
            Self::add_gravity(model, &body0, &point0, g0, &mut base);
            out.iter_mut().zip(&base).for_each(|(o, b)| *o -= b);
        }
        for (e, dk, dc) in &self.springs {
            let f = model.forces[*e].with_constants(Self::dot(dk, &dp), Self::dot(dc, &dp));
            if let Some(f) = f {
                f.add_to(model, q, dq, t, out)?;
            }
        }
        Ok(())
    }

    /// ∂/∂q and ∂/∂q̇ of [`Parameters::force`] added to `kq`, `kv` (n × n), and
    /// ∂(Q(p) − M(p) q̈)/∂p at the accelerations `ddq` written to `kp` (n × P), all
    /// row-major.
    pub fn jacobians(
        &self,
        model: &Model,
        p: &[f64],
        (q, dq, ddq, t): (&[f64], &[f64], &[f64], f64),
        kq: &mut [f64],
        kv: &mut [f64],
        kp: &mut [f64],
    ) -> Result<()> {
        let (n, np) = (model.n(), self.len());
        let dp = self.shift(p);
        for (e, dk, dc) in &self.springs {
            if let Some(f) = model.forces[*e].with_constants(Self::dot(dk, &dp), Self::dot(dc, &dp))
            {
                f.add_jacobians(model, (q, dq, t), kq, kv)?;
            }
        }
        kp.fill(0.0);
        let mut col = vec![0.0; n];
        let at = self.gravity_at(model, &dp);
        for j in 0..np {
            col.fill(0.0);
            if let (Some(at), Some((_, [gx, gy]))) = (&at, &self.gravity) {
                let dbody = |b: usize| self.body_mass[b][j];
                let dpoint = |p: usize| self.point_mass[p][j];
                Self::add_gravity(model, &dbody, &dpoint, at.g, &mut col);
                let body = |b: usize| at.bodies[b];
                let point = |p: usize| at.points[p];
                Self::add_gravity(model, &body, &point, [gx[j], gy[j]], &mut col);
            }
            for (e, dk, dc) in &self.springs {
                if let Some(f) = model.forces[*e].with_constants(dk[j], dc[j]) {
                    f.add_to(model, q, dq, t, &mut col)?;
                }
            }
            let mj = &self.mass[j];
            for r in 0..n {
                col[r] -= Self::dot(&mj[r * n..(r + 1) * n], ddq);
            }
            for r in 0..n {
                kp[r * np + j] = col[r];
            }
        }
        Ok(())
    }
}
