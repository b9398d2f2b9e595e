//! The factor graph of an estimate ([`EstimationGraph`]): the forward graph's
//! motion model with the dynamics soft at the process noise, soft priors on a
//! start known roughly, the unknown inputs as random walks, and the readings at
//! the steps they were taken.

use super::options::{Uncertainty, INPUT_INITIAL_SIGMA};
use crate::dynamics;
use crate::error::Result;
use crate::factors::*;
use crate::graph::{ChainGraph, Factor, Layout, Noise, VarKind};
use crate::model::{Model, State};
use std::sync::Arc;

/// The graph, its layout's sizes and the start its priors hold.
pub struct EstimationGraph {
    pub graph: ChainGraph,
    pub n: usize,
    /// Unknown inputs (generalized forces on chosen coordinates).
    pub inputs: Vec<usize>,
    pub start: State,
}

impl EstimationGraph {
    /// The graph of `model` at step `dt` from `start`, with `uncertainty`; the readings
    /// are added as they come ([`ChainGraph::add_soft_at`]).
    pub fn new(
        model: Arc<Model>,
        uncertainty: &Uncertainty,
        dt: f64,
        start: State,
    ) -> Result<Self> {
        let n = model.n();
        let inputs: Vec<usize> = uncertainty.inputs.iter().map(|&(c, _)| c).collect();
        let f = inputs.len();
        let mut vars = vec![(VarKind::Q, n), (VarKind::Dq, n), (VarKind::Ddq, n)];
        if f > 0 {
            vars.push((VarKind::Force, f));
        }
        let dynamics: Box<dyn Factor> = if f > 0 {
            Box::new(Dynamics::inverse_on(model.clone(), inputs.clone()))
        } else {
            Box::new(Dynamics::new(model.clone()))
        };
        let mut builder = ChainGraph::builder(Layout::new(&vars), dt, 0.0)
            .step_constraint(Box::new(PositionConstraints::new(model.clone())))
            .step_constraint(Box::new(VelocityConstraints::new(model.clone())))
            .step_soft(dynamics, Noise::Isotropic(uncertainty.process));
        // Projected on the constraints' tangent space: the full integrators ask 2m more
        // equations a step than the motion has free directions, a compromise whose
        // minimum is ill-determined along slow directions (see `factors::tangent`).
        let integrators = Integrator::Trapezoidal.factors(&model, Form::Tangent, dt);
        for (factor, sigma) in integrators.into_iter().zip(uncertainty.integrators(dt)) {
            builder = builder.step_soft(factor, Noise::Isotropic(sigma));
        }
        if f > 0 {
            // A random walk: Q_k − Q_{k−1} ~ N(0, σ_rate² Δt).
            let walk = uncertainty
                .inputs
                .iter()
                .map(|&(_, rate)| rate * dt.sqrt())
                .collect();
            builder = builder
                .step_soft(
                    Box::new(Equality::new(VarKind::Force, f)),
                    Noise::Diagonal(walk),
                )
                .initial_soft(
                    Box::new(Prior::new(VarKind::Force, vec![0.0; f])),
                    Noise::Isotropic(INPUT_INITIAL_SIGMA),
                );
        }
        let graph = builder
            .initial_soft(
                Box::new(Prior::new(VarKind::Q, start.q.as_slice().to_vec())),
                Noise::Diagonal(uncertainty.initial_q.clone()),
            )
            .initial_soft(
                Box::new(Prior::new(VarKind::Dq, start.dq.as_slice().to_vec())),
                Noise::Diagonal(uncertainty.initial_dq.clone()),
            )
            .build()?;
        Ok(EstimationGraph {
            graph,
            n,
            inputs,
            start,
        })
    }

    /// Unknowns per step.
    pub fn size(&self) -> usize {
        self.graph.layout().size()
    }

    /// The guess of step 0: the start and its accelerations, no input.
    pub fn initial_block(&self, model: &Model) -> Result<Vec<f64>> {
        let s = &self.start;
        let ddq = dynamics::accelerations_guess(model, &s.q, &s.dq, self.graph.t0())?;
        let mut block = Vec::with_capacity(self.size());
        block.extend_from_slice(s.q.as_slice());
        block.extend_from_slice(s.dq.as_slice());
        block.extend_from_slice(ddq.as_slice());
        block.resize(self.size(), 0.0);
        Ok(block)
    }

    /// The guess of step k from the two before: a Taylor step of q, q̇, q̈ with the
    /// jerk of the last two accelerations; the inputs held.
    pub fn predict(&self, values: &mut [f64], k: usize) {
        let (n, s) = (self.n, self.size());
        let dt = self.graph.dt();
        let (prev, next) = values.split_at_mut(k * s);
        let older = (k >= 2).then(|| &prev[(k - 2) * s..(k - 1) * s]);
        let prev = &prev[(k - 1) * s..];
        let next = &mut next[..s];
        for i in 0..n {
            let (x, v, a) = (prev[i], prev[n + i], prev[2 * n + i]);
            let j = older.map_or(0.0, |o| (a - o[2 * n + i]) / dt);
            next[i] = x + dt * v + 0.5 * dt * dt * a + dt * dt * dt / 6.0 * j;
            next[n + i] = v + dt * a + 0.5 * dt * dt * j;
            next[2 * n + i] = a + dt * j;
        }
        next[3 * n..].copy_from_slice(&prev[3 * n..s]);
    }
}
