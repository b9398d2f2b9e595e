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

    /// `independent` names as many coordinates as the mechanism has degrees of
    /// freedom: the error when it does not, naming what locks a mechanism that cannot
    /// move, and the points on no body whose x, y add freedoms.
    fn independent_count_error(&self, q: &DVector<f64>) -> Error {
        let (k, f) = (self.independent.len(), self.dof());
        let named = self.scene.independent.join(", ");
        let message = if f == 0 {
            let culprit = match super::locking_constraint(self, q) {
                Some(c) => format!(
                    "; constraint '{}' takes its last degree of freedom",
                    self.constraints[c].name
                ),
                None => String::new(),
            };
            format!(
                "the mechanism cannot move: its {} constraint(s) leave none of its {} \
                 coordinate(s) free (0 degrees of freedom){culprit}, and `independent` \
                 names {k} [{named}]",
                self.m(),
                self.n()
            )
        } else {
            let massless = crate::model::plausibility::massless_points(self);
            let why = match massless.is_empty() {
                true => String::new(),
                false => format!(
                    " (point(s) {} on no body and without mass: their x, y move freely; \
                     put them on a body, or name their coordinates)",
                    massless.join(", ")
                ),
            };
            format!(
                "names {k} coordinate(s) [{named}], but the mechanism has {f} degree(s) of \
                 freedom{why}: name {f}"
            )
        };
        Error::Scene(crate::error::SceneError {
            file: self.scene.file.clone(),
            line: self.scene.independent_line,
            key: "independent".into(),
            message,
        })
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
        if !self.independent.is_empty() && self.independent.len() != self.dof() {
            return Err(self.independent_count_error(&q));
        }
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
