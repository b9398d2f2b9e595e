//! The factors of independent coordinates: f^i_pc ([`IndependentPosition`]), f^i_vc
//! ([`IndependentVelocity`]), f^i_ac ([`IndependentAcceleration`]) and f^i_dyn
//! ([`IndependentDynamics`], with its inverse-dynamics form f^i_idyn).

use super::dynamics::ALONG_FROM;
use super::shared::{identity, key_accessor, mat_vec, nonzero_columns};
use crate::dynamics::DynamicsKernel;
use crate::dynamics::{KernelScratch, KktStructure};
use crate::error::Result;
use crate::graph::{carve, zeros, AlongDirections, Factor, Key, StackReq, VarKind, Workspace};
use crate::model::Model;
use std::sync::Arc;

/// f^i_pc: e = [Φ(q); q[idx] − z].
pub struct IndependentPosition {
    model: Arc<Model>,
    /// The independent coordinates z (indices into q), in z's order.
    independent: Vec<usize>,
    keys: [Key; 2],
}

impl IndependentPosition {
    /// The factor on the scene's independent coordinates.
    pub fn new(model: Arc<Model>) -> Self {
        let independent = model.independent.clone();
        IndependentPosition::with(model, independent)
    }

    /// The factor on the independent coordinates `independent` (indices into q).
    pub fn with(model: Arc<Model>, independent: Vec<usize>) -> Self {
        IndependentPosition {
            model,
            independent,
            keys: [Key::now(VarKind::Q), Key::now(VarKind::Z)],
        }
    }
}

/// Writes the selection rows q[idx] − z (n coordinates, idx = `independent`): I_idx
/// into `jq` rows m.., −I into `jz`.
fn selection_rows(
    (n, independent): (usize, &[usize]),
    m: usize,
    jq: &mut [f64],
    jz: Option<&mut [f64]>,
) {
    let f = independent.len();
    jq[m * n..(m + f) * n].fill(0.0);
    for (k, &i) in independent.iter().enumerate() {
        jq[(m + k) * n + i] = 1.0;
    }
    if let Some(jz) = jz {
        jz.fill(0.0);
        for k in 0..f {
            jz[(m + k) * f + k] = -1.0;
        }
    }
}

impl Factor for IndependentPosition {
    fn name(&self) -> &str {
        "f^i_pc"
    }
    key_accessor!();
    fn size(&self, key: usize) -> usize {
        // The last key is z's.
        if key + 1 == self.keys.len() {
            self.independent.len()
        } else {
            self.model.n()
        }
    }
    fn dim(&self) -> usize {
        self.model.m() + self.independent.len()
    }
    fn evaluate(
        &self,
        _t: f64,
        x: &[&[f64]],
        r: &mut [f64],
        jac: Option<&mut [Vec<f64>]>,
        _ws: &mut Workspace,
    ) -> Result<()> {
        let (m, n) = (self.model.m(), self.model.n());
        self.model.phi_into(x[0], &mut r[..m]);
        for (k, &i) in self.independent.iter().enumerate() {
            r[m + k] = x[0][i] - x[1][k];
        }
        if let Some(j) = jac {
            let (jq, jz) = j.split_at_mut(1);
            self.model.jacobian_into(x[0], &mut jq[0][..m * n]);
            selection_rows((n, &self.independent), m, &mut jq[0], Some(&mut jz[0]));
        }
        Ok(())
    }
}

/// f^i_vc: e = [Φ_q q̇; q̇[idx] − ż].
pub struct IndependentVelocity {
    model: Arc<Model>,
    /// The independent coordinates z (indices into q), in z's order.
    independent: Vec<usize>,
    keys: [Key; 3],
}

impl IndependentVelocity {
    /// The factor on the scene's independent coordinates.
    pub fn new(model: Arc<Model>) -> Self {
        let independent = model.independent.clone();
        IndependentVelocity::with(model, independent)
    }

    /// The factor on the independent coordinates `independent` (indices into q).
    pub fn with(model: Arc<Model>, independent: Vec<usize>) -> Self {
        IndependentVelocity {
            model,
            independent,
            keys: [
                Key::now(VarKind::Q),
                Key::now(VarKind::Dq),
                Key::now(VarKind::Dz),
            ],
        }
    }
}

impl Factor for IndependentVelocity {
    fn name(&self) -> &str {
        "f^i_vc"
    }
    key_accessor!();
    fn size(&self, key: usize) -> usize {
        // The last key is z's.
        if key + 1 == self.keys.len() {
            self.independent.len()
        } else {
            self.model.n()
        }
    }
    fn dim(&self) -> usize {
        self.model.m() + self.independent.len()
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
        mat_vec(a, m, n, x[1], &mut r[..m]);
        for (k, &i) in self.independent.iter().enumerate() {
            r[m + k] = x[1][i] - x[2][k];
        }
        if let Some(j) = jac {
            let (jq, rest) = j.split_at_mut(1);
            let (jv, jz) = rest.split_at_mut(1);
            self.model
                .jacobian_derivative_into(x[0], x[1], &mut jq[0][..m * n]);
            jq[0][m * n..].fill(0.0);
            jv[0][..m * n].copy_from_slice(a);
            selection_rows((n, &self.independent), m, &mut jv[0], Some(&mut jz[0]));
        }
        Ok(())
    }
}

/// f^i_ac: e = [Φ̇_q q̇ + Φ_q q̈; q̈[idx] − z̈].
pub struct IndependentAcceleration {
    model: Arc<Model>,
    /// The independent coordinates z (indices into q), in z's order.
    independent: Vec<usize>,
    keys: [Key; 4],
}

impl IndependentAcceleration {
    /// The factor on the scene's independent coordinates.
    pub fn new(model: Arc<Model>) -> Self {
        let independent = model.independent.clone();
        IndependentAcceleration::with(model, independent)
    }

    /// The factor on the independent coordinates `independent` (indices into q).
    pub fn with(model: Arc<Model>, independent: Vec<usize>) -> Self {
        IndependentAcceleration {
            model,
            independent,
            keys: [
                Key::now(VarKind::Q),
                Key::now(VarKind::Dq),
                Key::now(VarKind::Ddq),
                Key::now(VarKind::Ddz),
            ],
        }
    }
}

impl Factor for IndependentAcceleration {
    fn name(&self) -> &str {
        "f^i_ac"
    }
    key_accessor!();
    fn size(&self, key: usize) -> usize {
        // The last key is z's.
        if key + 1 == self.keys.len() {
            self.independent.len()
        } else {
            self.model.n()
        }
    }
    fn dim(&self) -> usize {
        self.model.m() + self.independent.len()
    }
    fn scratch(&self) -> StackReq {
        let (m, n) = (self.model.m(), self.model.n());
        StackReq::all_of(&[StackReq::new::<f64>(m * n), StackReq::new::<f64>(m)])
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
        let (q, dq, ddq, ddz) = (x[0], x[1], x[2], x[3]);
        let (a, stack) = zeros(ws.stack(), m * n);
        let (c, _) = zeros(stack, m);
        let (a, c) = (&mut a[..], &mut c[..]);
        self.model.jacobian_into(q, a);
        self.model.acceleration_rhs_into(q, dq, c);
        mat_vec(a, m, n, ddq, &mut r[..m]);
        for k in 0..m {
            r[k] -= c[k]; // Φ_q q̈ + Φ̇_q q̇ with Φ̇_q q̇ = −c
        }
        for (k, &i) in self.independent.iter().enumerate() {
            r[m + k] = ddq[i] - ddz[k];
        }
        if let Some(j) = jac {
            let (jq, rest) = j.split_at_mut(1);
            let (jv, rest) = rest.split_at_mut(1);
            let (ja, jz) = rest.split_at_mut(1);
            // ∂/∂q = ∂(Φ̇_q q̇)/∂q + Φ_qq q̈; ∂/∂q̇ = 2 Φ̇_q; ∂/∂q̈ = [Φ_q; I_idx].
            ja[0][..m * n].copy_from_slice(a);
            selection_rows((n, &self.independent), m, &mut ja[0], Some(&mut jz[0]));
            self.model.third_order_into(q, dq, &mut jq[0][..m * n]);
            self.model.jacobian_derivative_into(q, ddq, a);
            for (v, w) in jq[0][..m * n].iter_mut().zip(a.iter()) {
                *v += w;
            }
            jq[0][m * n..].fill(0.0);
            self.model
                .jacobian_derivative_into(q, dq, &mut jv[0][..m * n]);
            for v in &mut jv[0][..m * n] {
                *v *= 2.0;
            }
            jv[0][m * n..].fill(0.0);
        }
        Ok(())
    }
}

/// f^i_dyn: e = z̈(q, q̇, t) − z̈_t, with z̈ = q̈[idx] — the R-matrix result, computed
/// through the augmented system (the two agree to round-off; tested in `tests/model.rs`).
pub struct IndependentDynamics {
    model: Arc<Model>,
    /// The independent coordinates z (indices into q), in z's order.
    independent: Vec<usize>,
    keys: Vec<Key>,
    inverse: bool,
    /// Every coordinate, the columns of ∂q̈/∂Q (forces act on all of them).
    all: Vec<usize>,
    /// A large mechanism's KKT structure, analysed once.
    kkt: Option<KktStructure>,
}

impl IndependentDynamics {
    /// The factor on the scene's independent coordinates.
    pub fn new(model: Arc<Model>) -> Self {
        let independent = model.independent.clone();
        IndependentDynamics::with(model, independent)
    }

    /// The factor on the independent coordinates `independent` (indices into q).
    pub fn with(model: Arc<Model>, independent: Vec<usize>) -> Self {
        IndependentDynamics {
            independent,
            all: (0..model.n()).collect(),
            kkt: KktStructure::for_model(&model),
            model,
            keys: vec![
                Key::now(VarKind::Q),
                Key::now(VarKind::Dq),
                Key::now(VarKind::Ddz),
            ],
            inverse: false,
        }
    }

    /// f^i_idyn: e = z̈(q, q̇, t; Q_scene + Q) − z̈_t with the actuator forces Q a
    /// variable (fourth key); ∂e/∂Q is the independent rows of ∂q̈/∂Q.
    pub fn inverse(model: Arc<Model>) -> Self {
        let mut f = IndependentDynamics::new(model);
        f.keys.push(Key::now(VarKind::Force));
        f.inverse = true;
        f
    }
}

impl Factor for IndependentDynamics {
    fn name(&self) -> &str {
        if self.inverse {
            "f^i_idyn"
        } else {
            "f^i_dyn"
        }
    }
    key_accessor!();
    fn size(&self, key: usize) -> usize {
        // q, q̇, z̈ and (f^i_idyn) Q on every coordinate.
        if key == 2 {
            self.independent.len()
        } else {
            self.model.n()
        }
    }
    fn dim(&self) -> usize {
        self.independent.len()
    }
    /// The kernel's, q̈, then ∂q̈/∂q, ∂q̈/∂q̇ and ∂q̈/∂Q or (f^i_idyn along
    /// directions) [`DynamicsKernel::along`]'s.
    fn scratch(&self) -> StackReq {
        let n = self.model.n();
        let kernel = DynamicsKernel::scratch(&self.model).and(StackReq::new::<f64>(n));
        let jacobians = StackReq::new::<f64>(3 * n * n);
        match self.along_columns() {
            Some(max_cols) => {
                kernel.and(jacobians.or(DynamicsKernel::along_scratch(&self.model, max_cols)))
            }
            None => kernel.and(jacobians),
        }
    }
    /// f^i_idyn, and f^i_dyn of [`ALONG_FROM`] coordinates on.
    fn along(&self) -> Option<&dyn AlongDirections> {
        self.along_columns().map(|_| self as &dyn AlongDirections)
    }
    fn evaluate(
        &self,
        t: f64,
        x: &[&[f64]],
        r: &mut [f64],
        jac: Option<&mut [Vec<f64>]>,
        ws: &mut Workspace,
    ) -> Result<()> {
        let n = self.model.n();
        let f = self.independent.len();
        let (mut kernel, stack) = KernelScratch::new(&self.model, self.kkt.as_ref(), ws.stack());
        // Written whole before they are read (q̈ and the Jacobians by the kernel).
        let (ddq, stack) = carve(stack, n);
        let (jq, stack) = carve(stack, n * n);
        let (jv, stack) = carve(stack, n * n);
        let (jf, _) = carve(stack, n * n);
        let (ddq, jq, jv, jf) = (&mut ddq[..], &mut jq[..], &mut jv[..], &mut jf[..]);
        let want = jac.is_some();
        let force = if self.inverse { Some(x[3]) } else { None };
        DynamicsKernel::evaluate(
            &self.model,
            x[0],
            x[1],
            t,
            force,
            ddq,
            want.then_some((&mut *jq, &mut *jv)),
            &mut kernel,
        )?;
        for (k, &i) in self.independent.iter().enumerate() {
            r[k] = ddq[i] - x[2][k];
        }
        if let Some(j) = jac {
            for (k, &i) in self.independent.iter().enumerate() {
                j[0][k * n..(k + 1) * n].copy_from_slice(&jq[i * n..(i + 1) * n]);
                j[1][k * n..(k + 1) * n].copy_from_slice(&jv[i * n..(i + 1) * n]);
            }
            identity(&mut j[2], f, -1.0);
            if self.inverse {
                DynamicsKernel::force_jacobian(&self.model, &self.all, jf, &mut kernel)?;
                for (k, &i) in self.independent.iter().enumerate() {
                    j[3][k * n..(k + 1) * n].copy_from_slice(&jf[i * n..(i + 1) * n]);
                }
            }
        }
        Ok(())
    }
}

impl IndependentDynamics {
    /// The most directions it linearizes along (see [`IndependentDynamics::along`]):
    /// f^i_idyn's Jacobians take a solve per coordinate and force; f^i_dyn's one per
    /// coordinate twice, and more directions than n make them the cheaper.
    fn along_columns(&self) -> Option<usize> {
        let n = self.model.n();
        if self.inverse {
            Some(3 * n)
        } else {
            (n >= ALONG_FROM).then_some(n)
        }
    }
}

impl AlongDirections for IndependentDynamics {
    /// The independent rows of q̈(q, q̇, t; Q) along V (see
    /// [`DynamicsKernel::along`]), minus V on z̈_t. f^i_dyn declines, before
    /// evaluating anything, directions that move q and q̇ in more than n columns.
    fn evaluate_along(
        &self,
        t: f64,
        x: &[&[f64]],
        r: &mut [f64],
        dirs: &[&[f64]],
        c: usize,
        out: &mut [f64],
        ws: &mut Workspace,
    ) -> Result<bool> {
        let Some(max_cols) = self.along_columns() else {
            return Ok(false);
        };
        if !self.inverse && nonzero_columns(&dirs[..2], c) > max_cols {
            return Ok(false);
        }
        let n = self.model.n();
        let ind = &self.independent;
        let (mut kernel, stack) = KernelScratch::new(&self.model, self.kkt.as_ref(), ws.stack());
        let (ddq, extra) = carve(stack, n);
        let (force, force_dirs, columns): (_, &[f64], &[usize]) = if self.inverse {
            (Some(x[3]), dirs[3], &self.all)
        } else {
            (None, &[], &[])
        };
        DynamicsKernel::evaluate(&self.model, x[0], x[1], t, force, ddq, None, &mut kernel)?;
        if !DynamicsKernel::along(
            &self.model,
            (x[0], x[1], t),
            [dirs[0], dirs[1], force_dirs],
            columns,
            Some(ind),
            c,
            out,
            &kernel,
            extra,
            max_cols,
        )? {
            return Ok(false);
        }
        let f = ind.len();
        for (o, v) in out[..f * c].iter_mut().zip(&dirs[2][..f * c]) {
            *o -= v;
        }
        for (k, &i) in ind.iter().enumerate() {
            r[k] = ddq[i] - x[2][k];
        }
        Ok(true)
    }
}
