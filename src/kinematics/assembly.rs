//! The assembly of a model: [`Model::new`] builds the model of a scene and makes its
//! initial state consistent by the position and velocity problems, finding the
//! redundant constraints on the way. It lives with the kinematics it calls, so that
//! the model itself does not depend on them.

use super::{assembly_tolerance, constraint_rank, solve_position_within, solve_velocity};
use crate::error::{Error, Result};
use crate::model::{Model, State};
use crate::scene::Scene;
use nalgebra::DVector;

impl Model {
    /// Assembles a validated scene.
    pub fn new(scene: &Scene) -> Result<Model> {
        let mut model = Model::unassembled(scene)?;
        model.assemble_initial_state()?;
        let (n, init) = (model.n(), &model.initial);
        if let Some(i) = (0..n).find(|&i| !(init.q[i].is_finite() && init.dq[i].is_finite())) {
            return Err(Error::singular(format!(
                "{}: the initial state is not finite at coordinate `{}` (q = {}, q̇ = {})",
                scene.file, model.names[i], init.q[i], init.dq[i]
            )));
        }
        Ok(model)
    }

    /// The scene's approximate positions made consistent (keeping the independent
    /// coordinates), the redundant constraints found there, and the velocities from
    /// the independent ones (at rest when the scene gives none).
    fn assemble_initial_state(&mut self) -> Result<()> {
        let mut q = self.approximate_positions();
        let tol = assembly_tolerance(self, &q);
        solve_position_within(self, &mut q, &self.independent.clone(), tol)?;
        let rank = constraint_rank(self, &q);
        self.redundant = rank.redundant;
        self.active = (0..self.m())
            .filter(|k| !self.redundant.contains(k))
            .collect();
        let dq = if self.independent.is_empty() {
            DVector::zeros(self.n())
        } else {
            let dz: Vec<f64> = self
                .scene
                .independent
                .iter()
                .map(|name| {
                    self.scene
                        .initial_velocities
                        .iter()
                        .find(|(n, _)| n == name)
                        .map_or(0.0, |(_, v)| *v)
                })
                .collect();
            solve_velocity(self, &q, &self.independent, &dz)?
        };
        self.initial = State { q, dq };
        Ok(())
    }
}
