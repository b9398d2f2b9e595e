//! The factor graph of an estimate ([`EstimationGraph`]): the forward graph's
//! motion model with the dynamics soft at the process noise, soft priors on a
//! start known roughly, the unknown inputs as random walks, and the readings at
//! the steps they were taken. In dependent coordinates (DC) the process noise acts
//! on every q̈; in independent ones (IC) on z̈, the motion's own degrees of freedom.

use super::options::{Uncertainty, INPUT_INITIAL_SIGMA};
use crate::coordinates::Coordinates;
use crate::dynamics;
use crate::error::{Error, Result};
use crate::factors::*;
use crate::graph::{ChainGraph, ChainGraphBuilder, Factor, Layout, Noise, VarKind};
use crate::model::{Model, State};
use crate::problems::prediction::taylor_step;
use std::sync::Arc;

/// σ of the weak link between consecutive steps' q in IC: it only keeps the
/// assembly branch the motion is on (as in a forward IC graph).
const BRANCH_LINK_SIGMA: f64 = 10.0;

/// The graph, its layout's sizes and the start its priors hold.
pub struct EstimationGraph {
    pub graph: ChainGraph,
    pub coordinates: Coordinates,
    pub n: usize,
    /// The independent coordinates (IC; indices into q), empty in DC.
    pub independent: Vec<usize>,
    /// Unknown inputs (generalized forces on chosen coordinates).
    pub inputs: Vec<usize>,
    pub start: State,
    /// Where the first solve begins, if not at `start` ([`super::start`]).
    pub guess: Option<State>,
}

impl EstimationGraph {
    /// The graph of `model` in `coordinates` at step `dt` from `start`, with
    /// `uncertainty`; the readings are added as they come
    /// ([`ChainGraph::add_soft_at`]).
    pub fn new(
        model: Arc<Model>,
        coordinates: Coordinates,
        integrator: Integrator,
        uncertainty: &Uncertainty,
        dt: f64,
        start: State,
    ) -> Result<Self> {
        if integrator == Integrator::Euler {
            return Err(Error::InvalidArgument(
                "an estimate integrates with the trapezoidal rule or hermite-simpson, not \
                 euler"
                    .into(),
            ));
        }
        let n = model.n();
        let inputs: Vec<usize> = uncertainty.inputs.iter().map(|&(c, _)| c).collect();
        let f = inputs.len();
        let independent = match coordinates {
            Coordinates::Dependent => Vec::new(),
            Coordinates::Independent if model.independent.is_empty() => {
                return Err(Error::InvalidArgument(
                    "an estimate in independent coordinates needs the scene to declare them \
                     (`independent:`)"
                        .into(),
                ))
            }
            Coordinates::Independent if model.parameters.is_some() => {
                return Err(Error::InvalidArgument(
                    "parameters (`estimation: parameters:`) are identified in dependent \
                     coordinates only: use --coords dc"
                        .into(),
                ))
            }
            Coordinates::Independent if f > 0 => {
                return Err(Error::InvalidArgument(
                    "unknown inputs (`estimation: inputs:`) are estimated in dependent \
                     coordinates only: use --coords dc"
                        .into(),
                ))
            }
            Coordinates::Independent => model.independent.clone(),
        };
        let z = independent.len();
        let mut vars = vec![(VarKind::Q, n), (VarKind::Dq, n), (VarKind::Ddq, n)];
        if z > 0 {
            vars.extend([(VarKind::Z, z), (VarKind::Dz, z), (VarKind::Ddz, z)]);
        }
        if f > 0 {
            vars.push((VarKind::Force, f));
        }
        if let Some(p) = &model.parameters {
            vars.push((VarKind::Param, p.len()));
        }
        let builder = ChainGraph::builder(Layout::new(&vars), dt, 0.0);
        let builder = match coordinates {
            Coordinates::Dependent => {
                dependent(builder, &model, integrator, uncertainty, &inputs, dt)
            }
            Coordinates::Independent => {
                independent_graph(builder, &model, integrator, uncertainty, &independent, dt)
            }
        };
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
            coordinates,
            n,
            independent,
            inputs,
            start,
            guess: None,
        })
    }

    /// Unknowns per step.
    pub fn size(&self) -> usize {
        self.graph.layout().size()
    }

    /// Where the unknown inputs sit in a step's block.
    pub fn inputs_at(&self) -> usize {
        self.graph
            .layout()
            .slot(VarKind::Force)
            .map_or(self.size(), |(o, _)| o)
    }

    /// The index among the graph's step terms of the dynamics factor (soft at the
    /// process noise): the first soft one, after the constraints.
    pub fn dynamics_term(&self) -> usize {
        self.graph
            .step_terms()
            .iter()
            .position(|t| !t.is_constraint())
            .expect("an estimation graph has a dynamics factor")
    }

    /// Where the identified parameters sit in a step's block, and how many there are.
    pub fn parameters_at(&self) -> Option<(usize, usize)> {
        self.graph.layout().slot(VarKind::Param)
    }

    /// The guess of step 0: the start and its accelerations, no input, the
    /// parameters' file values.
    pub fn initial_block(&self, model: &Model) -> Result<Vec<f64>> {
        let s = self.guess.as_ref().unwrap_or(&self.start);
        let ddq = dynamics::accelerations_guess(model, &s.q, &s.dq, self.graph.t0())?;
        let mut block = Vec::with_capacity(self.size());
        block.extend_from_slice(s.q.as_slice());
        block.extend_from_slice(s.dq.as_slice());
        block.extend_from_slice(ddq.as_slice());
        for v in [s.q.as_slice(), s.dq.as_slice(), ddq.as_slice()] {
            block.extend(self.independent.iter().map(|&i| v[i]));
        }
        block.resize(self.size(), 0.0);
        if let (Some((at, _)), Some(p)) = (self.parameters_at(), &model.parameters) {
            block[at..at + p.len()].copy_from_slice(&p.values);
        }
        Ok(block)
    }

    /// The guess of step k from the two before: a Taylor step of (q, q̇, q̈) and
    /// (z, ż, z̈) ([`crate::problems::prediction::taylor_step`]); the inputs held.
    pub fn predict(&self, values: &mut [f64], k: usize) {
        let (n, s) = (self.n, self.size());
        let z = self.independent.len();
        taylor_step(values, k, s, self.graph.dt(), &[(0, n), (3 * n, z)]);
        let held = 3 * (n + z);
        values.copy_within((k - 1) * s + held..k * s, k * s + held);
    }
}

/// The DC graph's step factors: the constraints held, f_dyn soft at the process
/// noise (with the inputs a variable), the integrators, the inputs' random walk.
fn dependent(
    builder: ChainGraphBuilder,
    model: &Arc<Model>,
    integrator: Integrator,
    uncertainty: &Uncertainty,
    inputs: &[usize],
    dt: f64,
) -> ChainGraphBuilder {
    let f = inputs.len();
    let dynamics = || -> Box<dyn Factor> {
        match ParametricDynamics::new(model.clone(), inputs.to_vec()) {
            Some(d) => Box::new(d),
            None if f > 0 => Box::new(Dynamics::inverse_on(model.clone(), inputs.to_vec())),
            None => Box::new(Dynamics::new(model.clone())),
        }
    };
    let mut builder = builder
        .step_constraint(Box::new(PositionConstraints::new(model.clone())))
        .step_constraint(Box::new(VelocityConstraints::new(model.clone())))
        .step_soft(dynamics(), Noise::Isotropic(uncertainty.process));
    // Projected on the constraints' tangent space: the full integrators ask 2m more
    // equations a step than the motion has free directions, a compromise whose
    // minimum is ill-determined along slow directions (see `factors::tangent`).
    // Hermite–Simpson's stage sees the dynamics factor's own variables (the
    // identified parameters, the unknown inputs).
    let integrators = integrator.factors_through(model, Form::Tangent, dt, dynamics());
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
    if let Some(p) = &model.parameters {
        // Constant over the record: consecutive copies held equal to a small fraction of
        // each prior's σ (a walk of 1e-6 σ a step drifts by 1e-6 σ √steps).
        let sigmas = &uncertainty.parameters;
        builder = builder
            .step_soft(
                Box::new(Equality::new(VarKind::Param, p.len())),
                Noise::Diagonal(sigmas.iter().map(|s| s * PARAMETER_LINK).collect()),
            )
            .initial_soft(
                Box::new(Prior::new(VarKind::Param, p.values.clone())),
                Noise::Diagonal(sigmas.clone()),
            );
    }
    builder
}

/// The link between consecutive copies of the identified parameters, as a fraction
/// of their prior's σ: tight enough that the drift it allows (4.5e-5 σ over 2000
/// steps) stays below what the readings determine of a well-seen parameter (a
/// friction coefficient to 1.8e-4 σ), loose enough that the first steps' pivots,
/// which hold the prior alone against the link's weight (10¹² times it), keep their
/// digits (at 1e-8 the start's information matrix is no longer positive definite).
const PARAMETER_LINK: f64 = 1e-6;

/// The IC graph's step factors: q, q̇, q̈ held to z, ż, z̈ by the constraints, f^i_dyn
/// soft at the process noise on z̈, the integrators of z, the weak link that keeps
/// the assembly branch.
fn independent_graph(
    builder: ChainGraphBuilder,
    model: &Arc<Model>,
    integrator: Integrator,
    uncertainty: &Uncertainty,
    independent: &[usize],
    dt: f64,
) -> ChainGraphBuilder {
    let set = independent.to_vec();
    let mut builder = builder
        .step_constraint(Box::new(IndependentPosition::with(
            model.clone(),
            set.clone(),
        )))
        .step_constraint(Box::new(IndependentVelocity::with(
            model.clone(),
            set.clone(),
        )))
        .step_constraint(Box::new(IndependentAcceleration::with(
            model.clone(),
            set.clone(),
        )))
        .step_soft(
            Box::new(IndependentDynamics::with(model.clone(), set.clone())),
            Noise::Isotropic(uncertainty.process),
        );
    let integrators = integrator.factors(model, Form::Independent(independent), dt);
    for (factor, sigma) in integrators.into_iter().zip(uncertainty.integrators(dt)) {
        builder = builder.step_soft(factor, Noise::Isotropic(sigma));
    }
    builder.step_soft(
        Box::new(Equality::new(VarKind::Q, model.n())),
        Noise::Isotropic(BRANCH_LINK_SIGMA),
    )
}
