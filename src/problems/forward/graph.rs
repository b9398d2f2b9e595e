//! The factor graph of a forward run ([`ForwardGraph`]): its variables and factors
//! in dependent or independent coordinates, the initial guess and the prediction of
//! each step, and the conversions between its variables and a [`Trajectory`].

use super::options::{ForwardOptions, NoiseModels};
use super::plan::Plan;
use super::start::Start;
use crate::coordinates::Coordinates;
use crate::dynamics;
use crate::error::Result;
use crate::factors::*;
use crate::graph::{ChainGraph, Layout, Noise, VarKind};
use crate::model::Model;
use crate::problems::prediction::taylor_step;
use crate::trajectory::Trajectory;
use std::sync::Arc;

/// The graph of a forward problem, with its layout.
pub struct ForwardGraph {
    pub graph: ChainGraph,
    pub coordinates: Coordinates,
    pub(super) n: usize,
    pub(super) f: usize,
    /// The state its initial priors hold, and its independent coordinates (IC).
    pub(super) start: Start,
}

impl ForwardGraph {
    /// Builds the DC or IC graph for `model` from the scene's start ([`Start::of`]:
    /// initial priors from its initial state, its declared independent coordinates).
    pub fn new(model: Arc<Model>, options: &ForwardOptions) -> Result<Self> {
        let plan = Plan::new(&model, options)?;
        let start = Start::of(&model);
        ForwardGraph::planned(model, &plan, &options.noise, start)
    }

    /// The graph of `plan` for `model`, with the noise models `noise`, from `start`:
    /// its initial priors hold `start.state`, and in IC its z are
    /// `start.independent`.
    pub fn planned(
        model: Arc<Model>,
        plan: &Plan,
        noise: &NoiseModels,
        start: Start,
    ) -> Result<Self> {
        let independent = &start.independent;
        let (n, f) = (model.n(), independent.len());
        let nm = *noise;
        let dt = plan.dt;
        let init = &start.state;
        // The position and velocity integrators of each coordinate set, soft with
        // these σ. Tangent DC integrators leave one soft equation per unknown: the
        // solution has a zero residual and does not depend on the σ's, only the
        // conditioning of its normal equations does. Their σ are scaled by Δt (their
        // residuals over Δt are a velocity and an acceleration), so that f_dyn's rows
        // do not swamp them at a small Δt or on small links (docs/accuracy.md,
        // "Tangent integrators are weighted per unit of time").
        let sigma = [nm.integrator_position, nm.integrator_velocity];
        let dc_sigma = if plan.tangent_dc() {
            [sigma[0] * dt, sigma[1] * dt]
        } else {
            sigma
        };
        let form = match plan.coordinates {
            Coordinates::Dependent if plan.tangent_dc() => Form::Tangent,
            Coordinates::Dependent => Form::Full,
            Coordinates::Independent => Form::Independent(independent),
        };
        let integrators = plan.integrator.factors(&model, form, dt);
        let graph = match plan.coordinates {
            Coordinates::Dependent => {
                let layout = Layout::new(&[(VarKind::Q, n), (VarKind::Dq, n), (VarKind::Ddq, n)]);
                let mut builder = ChainGraph::builder(layout, dt, 0.0)
                    .step_constraint(Box::new(PositionConstraints::new(model.clone())))
                    .step_constraint(Box::new(VelocityConstraints::new(model.clone())))
                    .step_soft(
                        Box::new(Dynamics::new(model.clone())),
                        Noise::Isotropic(nm.dynamics),
                    );
                for (factor, sigma) in integrators.into_iter().zip(dc_sigma) {
                    builder = builder.step_soft(factor, Noise::Isotropic(sigma));
                }
                builder
                    .initial_constraint(Box::new(Prior::new(
                        VarKind::Q,
                        init.q.as_slice().to_vec(),
                    )))
                    .initial_constraint(Box::new(Prior::new(
                        VarKind::Dq,
                        init.dq.as_slice().to_vec(),
                    )))
                    .build()?
            }
            Coordinates::Independent => {
                let z0: Vec<f64> = independent.iter().map(|&i| init.q[i]).collect();
                let dz0: Vec<f64> = independent.iter().map(|&i| init.dq[i]).collect();
                // Table 2: covariance 1 on the dependent entries, 10⁻³ on those in z.
                let mut sig = vec![nm.initial_q; n];
                for &i in independent {
                    sig[i] = 1e-3f64.sqrt() * nm.initial_q;
                }
                let layout = Layout::new(&[
                    (VarKind::Q, n),
                    (VarKind::Dq, n),
                    (VarKind::Ddq, n),
                    (VarKind::Z, f),
                    (VarKind::Dz, f),
                    (VarKind::Ddz, f),
                ]);
                let mut builder = ChainGraph::builder(layout, dt, 0.0)
                    .step_constraint(Box::new(IndependentPosition::with(
                        model.clone(),
                        independent.clone(),
                    )))
                    .step_constraint(Box::new(IndependentVelocity::with(
                        model.clone(),
                        independent.clone(),
                    )))
                    .step_constraint(Box::new(IndependentAcceleration::with(
                        model.clone(),
                        independent.clone(),
                    )))
                    .step_soft(
                        Box::new(IndependentDynamics::with(
                            model.clone(),
                            independent.clone(),
                        )),
                        Noise::Isotropic(nm.dynamics),
                    );
                for (factor, sigma) in integrators.into_iter().zip(sigma) {
                    builder = builder.step_soft(factor, Noise::Isotropic(sigma));
                }
                builder
                    .step_soft(
                        Box::new(Equality::new(VarKind::Q, n)),
                        Noise::Isotropic(nm.equality),
                    )
                    .initial_constraint(Box::new(Prior::new(VarKind::Z, z0)))
                    .initial_constraint(Box::new(Prior::new(VarKind::Dz, dz0)))
                    .initial_soft(
                        Box::new(Prior::new(VarKind::Q, init.q.as_slice().to_vec())),
                        Noise::Diagonal(sig),
                    )
                    .build()?
            }
        };
        Ok(ForwardGraph {
            graph,
            coordinates: plan.coordinates,
            n,
            f,
            start,
        })
    }

    /// The initial guess of step 0: the graph's start state and its accelerations.
    pub(super) fn initial_block(&self, model: &Model) -> Result<Vec<f64>> {
        let init = &self.start.state;
        let ddq = dynamics::accelerations_guess(model, &init.q, &init.dq, self.graph.t0())?;
        let mut block = Vec::with_capacity(self.graph.layout().size());
        block.extend_from_slice(init.q.as_slice());
        block.extend_from_slice(init.dq.as_slice());
        block.extend_from_slice(ddq.as_slice());
        if self.coordinates == Coordinates::Independent {
            for v in [&init.q, &init.dq, &ddq] {
                block.extend(self.start.independent.iter().map(|&i| v[i]));
            }
        }
        Ok(block)
    }

    /// Guess of step k from the steps before: a Taylor step of (q, q̇, q̈) and, in IC,
    /// of (z, ż, z̈) ([`crate::problems::prediction::taylor_step`]).
    pub(super) fn predict(&self, values: &mut [f64], k: usize) {
        let s = self.graph.layout().size();
        let triples: &[(usize, usize)] = if self.coordinates == Coordinates::Independent {
            &[(0, self.n), (3 * self.n, self.f)]
        } else {
            &[(0, self.n)]
        };
        taylor_step(values, k, s, self.graph.dt(), triples);
    }
}

impl ForwardGraph {
    /// The graph's variables (step-major) filled from a trajectory of the same model:
    /// a starting point for a solve, or the state a benchmark linearizes at. (The
    /// graph knows its own coordinates: `_model` is kept for the callers.)
    pub fn fill_from_trajectory(&self, _model: &Model, tr: &Trajectory, values: &mut [f64]) {
        let n = self.n;
        for k in 0..tr.len() {
            let row = k * n..(k + 1) * n;
            let (q, dq, ddq) = (&tr.q[row.clone()], &tr.dq[row.clone()], &tr.ddq[row]);
            self.fill_step(q, dq, ddq, k, values);
        }
    }

    /// Step k of the graph's variables (step-major) filled from a state q, q̇, q̈ of
    /// the same model, as [`ForwardGraph::fill_from_trajectory`] fills each step.
    pub(super) fn fill_step(
        &self,
        q: &[f64],
        dq: &[f64],
        ddq: &[f64],
        k: usize,
        values: &mut [f64],
    ) {
        let (n, s) = (self.n, self.graph.layout().size());
        let block = &mut values[k * s..(k + 1) * s];
        block[..n].copy_from_slice(q);
        block[n..2 * n].copy_from_slice(dq);
        block[2 * n..3 * n].copy_from_slice(ddq);
        if self.coordinates == Coordinates::Independent {
            for (j, src) in [q, dq, ddq].iter().enumerate() {
                for (i, &c) in self.start.independent.iter().enumerate() {
                    block[3 * n + j * self.f + i] = src[c];
                }
            }
        }
    }
}
