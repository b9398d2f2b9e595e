//! How the solution of one step of inverse dynamics moves with its prescribed motion:
//! the Jacobian of x = (q, q̇, q̈, τ) with respect to y = (z, ż, z̈), the prescribed
//! coordinates' values, rates and accelerations, by implicit differentiation of the
//! step's equations G(x, y) = 0:
//!
//! Φ(q) = 0, Φ_q q̇ = 0, q_P − z = 0, q̇_P − ż = 0, q̈_P − z̈ = 0,
//! q̈(q, q̇, t; Q_scene + Pτ) − q̈ = 0 (f^d_idyn),
//!
//! so ∂x/∂y = −G_x⁻¹ G_y = G_x⁻¹ [0; 0; I; 0]. G_x is the closed-form Jacobians of the
//! factors that the inverse graph holds (each tested against finite differences), and
//! the smoothing's covariance Σ_y then gives Σ_x ≈ (∂x/∂y) Σ_y (∂x/∂y)ᵀ to first order.
//! Redundant constraint rows make G_x rank-deficient but consistent: the rows found
//! redundant at the initial state are left out and the square rest solved by LU;
//! where that fails (redundancy elsewhere along the motion), by least squares (SVD).

use crate::error::{Error, Result};
use crate::factors::{Dynamics, PositionConstraints, VelocityConstraints};
use crate::graph::{Factor, VarKind, Workspace};
use crate::model::Model;
use nalgebra::DMatrix;
use std::sync::Arc;

/// The factors of a step's equations and their scratch, reused along the run.
pub struct Sensitivity {
    n: usize,
    m: usize,
    idx: Vec<usize>,
    redundant: Vec<usize>,
    factors: Vec<Box<dyn Factor>>,
    ws: Workspace,
}

impl Sensitivity {
    /// For the coordinates `idx` of `model` prescribed (and actuated).
    pub fn new(model: Arc<Model>, idx: Vec<usize>) -> Self {
        let factors: Vec<Box<dyn Factor>> = vec![
            Box::new(PositionConstraints::new(model.clone())),
            Box::new(VelocityConstraints::new(model.clone())),
            Box::new(Dynamics::inverse_on(model.clone(), idx.clone())),
        ];
        let req = factors
            .iter()
            .fold(faer::dyn_stack::StackReq::EMPTY, |r, f| r.or(f.scratch()));
        Sensitivity {
            n: model.n(),
            m: model.m(),
            redundant: model.redundant.clone(),
            idx,
            factors,
            ws: Workspace::new(req),
        }
    }

    /// ∂x/∂y at time `t` and the step's solution x = (q, q̇, q̈, τ): a (3n + p) × 3p
    /// matrix, y = (z, ż, z̈) ordered as the prescription's columns in each part.
    pub fn jacobian(&mut self, t: f64, x: &[f64]) -> Result<DMatrix<f64>> {
        let (n, p) = (self.n, self.idx.len());
        let size = 3 * n + p;
        let offset = |kind: VarKind| match kind {
            VarKind::Q => 0,
            VarKind::Dq => n,
            VarKind::Ddq => 2 * n,
            _ => 3 * n,
        };
        let mut rows: Vec<Vec<f64>> = Vec::new();
        let mut selected_at = 0;
        for (which, f) in self.factors.iter().enumerate() {
            if which == 2 {
                // The prescribed motion's rows come before the dynamics'.
                selected_at = rows.len();
                for part in 0..3 {
                    for &i in &self.idx {
                        let mut row = vec![0.0; size];
                        row[part * n + i] = 1.0;
                        rows.push(row);
                    }
                }
            }
            let keys = f.keys().to_vec();
            let inputs: Vec<&[f64]> = keys
                .iter()
                .map(|k| {
                    let at = offset(k.kind);
                    let len = if k.kind == VarKind::Force { p } else { n };
                    &x[at..at + len]
                })
                .collect();
            let dim = f.dim();
            let mut r = vec![0.0; dim];
            let mut jac: Vec<Vec<f64>> = keys
                .iter()
                .enumerate()
                .map(|(a, _)| vec![0.0; dim * f.size(a)])
                .collect();
            f.evaluate(t, &inputs, &mut r, Some(&mut jac), &mut self.ws)?;
            for i in 0..dim {
                let mut row = vec![0.0; size];
                for (a, k) in keys.iter().enumerate() {
                    let (at, len) = (offset(k.kind), f.size(a));
                    for j in 0..len {
                        row[at + j] += jac[a][i * len + j];
                    }
                }
                rows.push(row);
            }
        }
        let g = DMatrix::from_fn(rows.len(), size, |i, j| rows[i][j]);
        let mut e = DMatrix::<f64>::zeros(rows.len(), 3 * p);
        for c in 0..3 * p {
            e[(selected_at + c, c)] = 1.0;
        }
        let m = self.m;
        let kept: Vec<usize> = (0..rows.len())
            .filter(|&i| !(i < 2 * m && self.redundant.contains(&(i % m))))
            .collect();
        if kept.len() == size {
            let gk = g.select_rows(&kept);
            let ek = e.select_rows(&kept);
            if let Some(j) = gk.lu().solve(&ek) {
                // Accepted where it also solves the rows left out (consistent).
                let scale = g.amax() * j.amax().max(1.0);
                if j.iter().all(|v| v.is_finite()) && (&g * &j - &e).amax() <= 1e-9 * scale {
                    return Ok(j);
                }
            }
        }
        let svd = g.svd(true, true);
        let tol = 1e-12 * svd.singular_values.max();
        svd.solve(&e, tol).map_err(|m| {
            Error::singular(format!(
                "the sensitivity of the step at t = {t} to its prescribed motion: {m}"
            ))
        })
    }
}
