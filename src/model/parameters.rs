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

use super::forces::{Force, Load};
use super::{mass, Model, PointSlot, Slot};
use crate::error::{Error, Result};

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
    /// Gravity, if the scene has it: its index in `Model::forces`, its vector in the
    /// file and the vector's ∂/∂p (x and y).
    gravity: Option<(usize, [f64; 2], [Vec<f64>; 2])>,
    /// Forces linear in two constants (springs and dampers, a DC motor's stall
    /// torque): (index into `Model::forces`, ∂/∂p of each constant).
    springs: Vec<(usize, Vec<f64>, Vec<f64>)>,
    /// Torques and forces whose values use the parameters, any way the expression
    /// does: (index into `Model::forces`, which of its [`Force::value_loads`]).
    loads: Vec<(usize, usize)>,
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
            loads: Vec::new(),
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
                    out.gravity = Some((*e, *vector, [a.clone(), b.clone()]));
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
        for (e, force) in model.forces.iter().enumerate() {
            for (k, slot) in force.value_loads().into_iter().enumerate() {
                if let Some((_, load)) = slot.filter(|(_, l)| l.uses_parameters()) {
                    load.parameter_indices().for_each(|j| touched[j] = true);
                    out.loads.push((e, k));
                }
            }
        }
        // A sensor's expression (an offset, a scale) determines its parameters through
        // the readings alone.
        for sensor in &model.sensors {
            sensor
                .parameter_indices()
                .into_iter()
                .for_each(|j| touched[j] = true);
        }
        if out.gravity.is_none() {
            out.gravity = model.forces.iter().enumerate().find_map(|(e, f)| match f {
                Force::Gravity { vector, .. } => Some((e, *vector, [vec![0.0; p], vec![0.0; p]])),
                _ => None,
            });
        }
        // A mass moves gravity's force only where there is gravity.
        if let Some((_, g, _)) = out.gravity {
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
                 gravity, spring, damper, motor, torque, force or sensor of the scene uses it",
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

    /// Σⱼ gⱼ (pⱼ − p₀ⱼ): how far a constant whose derivative is g moves from the
    /// file's p₀ to p.
    fn change(&self, g: &[f64], p: &[f64]) -> f64 {
        g.iter()
            .zip(p)
            .zip(&self.values)
            .map(|((g, p), v)| g * (p - v))
            .sum()
    }

    /// Gravity's vector at p, if the scene has gravity.
    fn gravity_at(&self, p: &[f64]) -> Option<[f64; 2]> {
        let (_, g0, [gx, gy]) = self.gravity.as_ref()?;
        Some([g0[0] + self.change(gx, p), g0[1] + self.change(gy, p)])
    }

    /// M(p) into `out` (row-major n × n).
    pub fn mass_at(&self, model: &Model, p: &[f64], out: &mut [f64]) {
        let n = model.n();
        for (k, o) in out[..n * n].iter_mut().enumerate() {
            *o = model.mass[(k / n, k % n)];
        }
        for (mj, j) in self.mass.iter().zip(0..) {
            let dpj = p[j] - self.values[j];
            if dpj != 0.0 {
                out.iter_mut().zip(mj).for_each(|(a, b)| *a += dpj * b);
            }
        }
    }

    /// Q(p) − Q(p₀) at (q, q̇, t) into `out` (length n; overwritten).
    pub fn force(
        &self,
        model: &Model,
        p: &[f64],
        (q, dq, t): (&[f64], &[f64], f64),
        out: &mut [f64],
    ) -> Result<()> {
        out.fill(0.0);
        if let (Some(g), Some((e, ..))) = (self.gravity_at(p), &self.gravity) {
            let scene = &model.scene;
            let body = |b: usize| scene.bodies[b].mass + self.change(&self.body_mass[b], p);
            let point = |i: usize| scene.points[i].mass + self.change(&self.point_mass[i], p);
            Self::add_gravity(model, &body, &point, g, out);
            // Less the file's gravity, which the model's own force holds.
            if let Force::Gravity { entries, .. } = &model.forces[*e] {
                entries.iter().for_each(|&(i, v)| out[i] -= v);
            }
        }
        for (e, dk, dc) in &self.springs {
            let f = model.forces[*e].with_constants(self.change(dk, p), self.change(dc, p));
            if let Some(f) = f {
                f.add_to(model, q, dq, t, out)?;
            }
        }
        for (row, load) in self.loads(model) {
            out[row] += load.value_at(model, q, dq, (t, Some(p)))?
                - load.value_at(model, q, dq, (t, None))?;
        }
        Ok(())
    }

    /// The torques' and forces' loads that use the parameters, with their rows of Q.
    fn loads<'a>(&'a self, model: &'a Model) -> impl Iterator<Item = (usize, &'a Load)> + 'a {
        self.loads
            .iter()
            .filter_map(move |&(e, k)| model.forces[e].value_loads()[k])
    }

    /// ∂/∂q and ∂/∂q̇ of [`Parameters::force`] added to `kq`, `kv` (n × n), and
    /// ∂(Q(p) − M(p) q̈)/∂p at the accelerations `ddq` written to `kp` (n × P), all
    /// row-major; `col` (length n) is scratch.
    #[allow(clippy::too_many_arguments)]
    pub fn jacobians(
        &self,
        model: &Model,
        p: &[f64],
        (q, dq, ddq, t): (&[f64], &[f64], &[f64], f64),
        kq: &mut [f64],
        kv: &mut [f64],
        kp: &mut [f64],
        col: &mut [f64],
    ) -> Result<()> {
        let (n, np) = (model.n(), self.len());
        for (e, dk, dc) in &self.springs {
            let f = model.forces[*e].with_constants(self.change(dk, p), self.change(dc, p));
            if let Some(f) = f {
                f.add_jacobians(model, (q, dq, t), kq, kv)?;
            }
        }
        for (row, load) in self.loads(model) {
            load.add_gradient_at(model, (q, dq, t), (Some(p), 1.0), row, kq, kv)?;
            load.add_gradient_at(model, (q, dq, t), (None, -1.0), row, kq, kv)?;
        }
        let scene = &model.scene;
        let g = self.gravity_at(p);
        for j in 0..np {
            col.fill(0.0);
            if let (Some(g), Some((_, _, [gx, gy]))) = (g, &self.gravity) {
                // Bilinear in the masses and the vector: each moved alone.
                let dbody = |b: usize| self.body_mass[b][j];
                let dpoint = |i: usize| self.point_mass[i][j];
                Self::add_gravity(model, &dbody, &dpoint, g, col);
                let body = |b: usize| scene.bodies[b].mass + self.change(&self.body_mass[b], p);
                let point = |i: usize| scene.points[i].mass + self.change(&self.point_mass[i], p);
                Self::add_gravity(model, &body, &point, [gx[j], gy[j]], col);
            }
            for (e, dk, dc) in &self.springs {
                if let Some(f) = model.forces[*e].with_constants(dk[j], dc[j]) {
                    f.add_to(model, q, dq, t, col)?;
                }
            }
            let mj = &self.mass[j];
            for r in 0..n {
                kp[r * np + j] = col[r] - Self::dot(&mj[r * n..(r + 1) * n], ddq);
            }
        }
        for (row, load) in self.loads(model) {
            load.add_parameter_gradient(
                model,
                (q, dq, t),
                p,
                1.0,
                &mut kp[row * np..(row + 1) * np],
            )?;
        }
        Ok(())
    }

    fn dot(a: &[f64], b: &[f64]) -> f64 {
        a.iter().zip(b).map(|(x, y)| x * y).sum()
    }
}
