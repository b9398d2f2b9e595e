//! The constraint factors of dependent coordinates: f^d_pc ([`PositionConstraints`])
//! and f^d_vc ([`VelocityConstraints`]).

use super::shared::{key_accessor, mat_vec};
use crate::error::Result;
use crate::graph::{zeros, Factor, Key, StackReq, VarKind, Workspace};
use crate::model::Model;
use std::sync::Arc;

/// f^d_pc: e = Φ(q).
pub struct PositionConstraints {
    model: Arc<Model>,
    keys: [Key; 1],
}

impl PositionConstraints {
    pub fn new(model: Arc<Model>) -> Self {
        PositionConstraints {
            model,
            keys: [Key::now(VarKind::Q)],
        }
    }
}

impl Factor for PositionConstraints {
    fn name(&self) -> &str {
        "f^d_pc"
    }
    key_accessor!();
    fn size(&self, _key: usize) -> usize {
        self.model.n()
    }
    fn dim(&self) -> usize {
        self.model.m()
    }
    fn evaluate(
        &self,
        _t: f64,
        x: &[&[f64]],
        r: &mut [f64],
        jac: Option<&mut [Vec<f64>]>,
        _ws: &mut Workspace,
    ) -> Result<()> {
        self.model.phi_into(x[0], r);
        if let Some(j) = jac {
            self.model.jacobian_into(x[0], &mut j[0]);
        }
        Ok(())
    }
}

/// f^d_vc: e = Φ_q(q) q̇, with ∂e/∂q = Φ_qq q̇ = Φ̇_q and ∂e/∂q̇ = Φ_q.
pub struct VelocityConstraints {
    model: Arc<Model>,
    keys: [Key; 2],
}

impl VelocityConstraints {
    pub fn new(model: Arc<Model>) -> Self {
        VelocityConstraints {
            model,
            keys: [Key::now(VarKind::Q), Key::now(VarKind::Dq)],
        }
    }
}

impl Factor for VelocityConstraints {
    fn name(&self) -> &str {
        "f^d_vc"
    }
    key_accessor!();
    fn size(&self, _key: usize) -> usize {
        self.model.n()
    }
    fn dim(&self) -> usize {
        self.model.m()
    }
    fn scratch(&self) -> StackReq {
        StackReq::new::<f64>(self.model.m() * self.model.n())
    }
    fn evaluate(
        &self,
        _t: f64,
        x: &[&[f64]],
        r: &mut [f64],
        jac: Option<&mut [Vec<f64>]>,
        ws: &mut Workspace,
    ) -> Result<()> {
        let (m, n) = (self.model.m(), self.model.n());
        let (a, _) = zeros(ws.stack(), m * n);
        let a = &mut a[..];
        self.model.jacobian_into(x[0], a);
        mat_vec(a, m, n, x[1], r);
        if let Some(j) = jac {
            self.model.jacobian_derivative_into(x[0], x[1], &mut j[0]);
            j[1].copy_from_slice(a);
        }
        Ok(())
    }
}
