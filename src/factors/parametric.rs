//! The dynamics factor of an estimate that identifies parameters, f^d_par
//! ([`ParametricDynamics`]): f^d_dyn with the parameters p a variable (and, where the
//! scene declares them, unknown input forces), on the [`DynamicsKernel`].
//!
//! e = q̈(q, q̇, t; p, u) − q̈_t, q̈ from the augmented system with M(p) and the forces
//! Q_scene + F, F = Q(p) − Q(p₀) + u ([`Parameters::force`], the inputs u). With
//! G = ∂q̈/∂Q (the first n rows of K(p)⁻¹ on [I; 0]):
//!   ∂e/∂q = ∂q̈/∂q|_F + G ∂F/∂q,  ∂e/∂q̇ = ∂q̈/∂q̇|_F + G ∂F/∂q̇,  ∂e/∂q̈_t = −I,
//!   ∂e/∂pⱼ = G (∂Q/∂pⱼ − ∂M/∂pⱼ q̈),  ∂e/∂u = G (its columns).

use super::shared::key_accessor;
use crate::dynamics::{DynamicsKernel, KernelScratch};
use crate::error::Result;
use crate::graph::{zeros, Factor, Key, StackReq, VarKind, Workspace};
use crate::model::parameters::Parameters;
use crate::model::Model;
use std::sync::Arc;

pub struct ParametricDynamics {
    model: Arc<Model>,
    parameters: Arc<Parameters>,
    keys: Vec<Key>,
    /// The coordinates the unknown inputs act on (one entry of the Force variable
    /// each), empty without inputs.
    inputs: Vec<usize>,
    /// 0..n: G's columns, the forces on every coordinate.
    all: Vec<usize>,
}

impl ParametricDynamics {
    /// f^d_par of `model`'s identified parameters, with unknown inputs on the
    /// coordinates `inputs` (none: no Force key). `None` when the model identifies
    /// no parameter.
    pub fn new(model: Arc<Model>, inputs: Vec<usize>) -> Option<Self> {
        let parameters = model.parameters.clone()?;
        let mut keys = vec![
            Key::now(VarKind::Q),
            Key::now(VarKind::Dq),
            Key::now(VarKind::Ddq),
            Key::now(VarKind::Param),
        ];
        if !inputs.is_empty() {
            keys.push(Key::now(VarKind::Force));
        }
        Some(ParametricDynamics {
            all: (0..model.n()).collect(),
            model,
            parameters,
            keys,
            inputs,
        })
    }
}

impl Factor for ParametricDynamics {
    fn name(&self) -> &str {
        "f^d_par"
    }
    key_accessor!();
    fn size(&self, key: usize) -> usize {
        match key {
            3 => self.parameters.len(),
            4 => self.inputs.len(),
            _ => self.model.n(),
        }
    }
    fn dim(&self) -> usize {
        self.model.n()
    }
    /// The kernel's, and M(p), the forces, q̈(p), G and ∂F/∂(q, q̇, p) with a column.
    fn scratch(&self) -> StackReq {
        let (n, np) = (self.model.n(), self.parameters.len());
        DynamicsKernel::scratch(&self.model).and(StackReq::new::<f64>(4 * n * n + 3 * n + n * np))
    }
    fn evaluate(
        &self,
        t: f64,
        x: &[&[f64]],
        r: &mut [f64],
        jac: Option<&mut [Vec<f64>]>,
        ws: &mut Workspace,
    ) -> Result<()> {
        let model = &*self.model;
        let (n, np) = (model.n(), self.parameters.len());
        let (force, stack) = zeros(ws.stack(), n);
        self.parameters.force(model, x[3], (x[0], x[1], t), force)?;
        for (k, &c) in self.inputs.iter().enumerate() {
            force[c] += x[4][k];
        }
        // M(p) in a dense K (a large mechanism's sparse K holds the file's M).
        let (mass, stack) = zeros(stack, n * n);
        self.parameters.mass_at(model, x[3], mass);
        let mass: &[f64] = mass;
        let (kernel, stack) = KernelScratch::new(model, None, stack);
        let mut kernel = kernel.with_mass(mass);
        let Some(j) = jac else {
            DynamicsKernel::evaluate(model, x[0], x[1], t, Some(force), r, None, &mut kernel)?;
            r.iter_mut().zip(x[2]).for_each(|(e, a)| *e -= a);
            return Ok(());
        };
        let (jq, rest) = j.split_at_mut(1);
        let (jv, rest) = rest.split_at_mut(1);
        let (ja, rest) = rest.split_at_mut(1);
        let (jp, ju) = rest.split_at_mut(1);
        DynamicsKernel::evaluate(
            model,
            x[0],
            x[1],
            t,
            Some(force),
            r,
            Some((&mut jq[0], &mut jv[0])),
            &mut kernel,
        )?;
        let (acceleration, stack) = zeros(stack, n);
        acceleration.copy_from_slice(r);
        r.iter_mut().zip(x[2]).for_each(|(e, a)| *e -= a);
        let (g, stack) = zeros(stack, n * n);
        DynamicsKernel::force_jacobian(model, &self.all, g, &mut kernel)?;
        let (fq, stack) = zeros(stack, n * n);
        let (fv, stack) = zeros(stack, n * n);
        let (fp, stack) = zeros(stack, n * np);
        let (col, _) = zeros(stack, n);
        self.parameters
            .jacobians(model, x[3], (x[0], x[1], acceleration, t), fq, fv, fp, col)?;
        // out += G · B for a row-major n × w block B.
        let add_product = |out: &mut [f64], b: &[f64], w: usize| {
            for i in 0..n {
                for k in 0..n {
                    let gik = g[i * n + k];
                    if gik == 0.0 {
                        continue;
                    }
                    for c in 0..w {
                        out[i * w + c] += gik * b[k * w + c];
                    }
                }
            }
        };
        add_product(&mut jq[0], fq, n);
        add_product(&mut jv[0], fv, n);
        super::shared::identity(&mut ja[0], n, -1.0);
        let jp = &mut jp[0];
        jp.fill(0.0);
        add_product(jp, fp, np);
        if let Some(ju) = ju.first_mut() {
            let w = self.inputs.len();
            for i in 0..n {
                for (c, &k) in self.inputs.iter().enumerate() {
                    ju[i * w + c] = g[i * n + k];
                }
            }
        }
        Ok(())
    }
}
