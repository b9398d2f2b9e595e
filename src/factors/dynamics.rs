//! The dynamics factor of dependent coordinates, f^d_dyn, and its inverse-dynamics
//! form f^d_idyn with the actuator forces a variable ([`Dynamics`]), on the
//! [`DynamicsKernel`].

use super::shared::{identity, key_accessor, nonzero_columns};
use crate::dynamics::{DynamicsKernel, KernelScratch, KktStructure};
use crate::error::Result;
use crate::graph::{zeros, AlongDirections, Factor, Key, StackReq, VarKind, Workspace};
use crate::model::Model;
use std::sync::Arc;

/// Coordinates from which f^d_dyn linearizes along the window's directions
/// ([`Dynamics::along`]) rather than forming ∂q̈/∂q and ∂q̈/∂q̇: a solve per
/// direction the hard equations leave free instead of one per coordinate.
pub const ALONG_FROM: usize = 20;

/// f^d_dyn: e = q̈(q, q̇, t) − q̈_t; with [`Dynamics::inverse`], f^d_idyn:
/// e = q̈(q, q̇, t; Q_scene + Q) − q̈_t with the actuator forces Q a variable (fourth
/// key), ∂e/∂Q the first n rows of the augmented system's inverse applied to [I; 0].
pub struct Dynamics {
    model: Arc<Model>,
    keys: Vec<Key>,
    /// Inverse dynamics: the coordinates the forces Q act on (see [`Actuated`]).
    actuated: Option<Actuated>,
    /// A large mechanism's KKT structure, analysed once.
    kkt: Option<KktStructure>,
}

/// The coordinates an inverse-dynamics factor's forces act on: all of them (Q has n
/// entries), or the listed ones (Q has one entry per listed coordinate, in that
/// order), which spares a pair of triangular solves per other column of ∂e/∂Q and
/// the solver the unknowns that would only be held at 0.
#[derive(Debug, Clone)]
struct Actuated {
    all: bool,
    indices: Vec<usize>,
}

impl Actuated {
    fn all(n: usize) -> Self {
        Actuated {
            all: true,
            indices: (0..n).collect(),
        }
    }

    fn only(n: usize, indices: Vec<usize>) -> Self {
        assert!(
            indices.iter().all(|&i| i < n),
            "an actuated coordinate past q"
        );
        let mut sorted = indices.clone();
        sorted.sort_unstable();
        sorted.dedup();
        assert_eq!(sorted.len(), indices.len(), "an actuated coordinate twice");
        Actuated {
            all: indices.iter().copied().eq(0..n),
            indices,
        }
    }

    /// The generalized forces on all n coordinates: Q itself, or Q spread into `own`.
    fn forces<'a>(&self, q: &'a [f64], own: &'a mut [f64]) -> &'a [f64] {
        if self.all {
            return q;
        }
        own.fill(0.0);
        for (&i, &v) in self.indices.iter().zip(q) {
            own[i] = v;
        }
        own
    }
}

impl Dynamics {
    pub fn new(model: Arc<Model>) -> Self {
        Dynamics {
            kkt: KktStructure::for_model(&model),
            model,
            keys: vec![
                Key::now(VarKind::Q),
                Key::now(VarKind::Dq),
                Key::now(VarKind::Ddq),
            ],
            actuated: None,
        }
    }

    /// f^d_idyn, with forces on every coordinate.
    pub fn inverse(model: Arc<Model>) -> Self {
        let n = model.n();
        let mut f = Dynamics::new(model);
        f.keys.push(Key::now(VarKind::Force));
        f.actuated = Some(Actuated::all(n));
        f
    }

    /// f^d_idyn with forces on the coordinates `actuated` only: its Q variable has
    /// one entry per actuated coordinate, in that order.
    pub fn inverse_on(model: Arc<Model>, actuated: Vec<usize>) -> Self {
        let n = model.n();
        let mut f = Dynamics::inverse(model);
        f.actuated = Some(Actuated::only(n, actuated));
        f
    }
}

impl Factor for Dynamics {
    fn name(&self) -> &str {
        if self.actuated.is_some() {
            "f^d_idyn"
        } else {
            "f^d_dyn"
        }
    }
    key_accessor!();
    fn size(&self, key: usize) -> usize {
        match (&self.actuated, key) {
            (Some(a), 3) => a.indices.len(),
            _ => self.model.n(),
        }
    }
    fn dim(&self) -> usize {
        self.model.n()
    }
    /// The kernel's, the forces on all n coordinates, and (f^d_idyn)
    /// [`DynamicsKernel::along`]'s.
    fn scratch(&self) -> StackReq {
        let n = self.model.n();
        let kernel = DynamicsKernel::scratch(&self.model).and(StackReq::new::<f64>(n));
        match self.along_columns() {
            Some(max_cols) => kernel.and(DynamicsKernel::along_scratch(&self.model, max_cols)),
            None => kernel,
        }
    }
    fn diagonal_jacobian(&self, key: usize) -> bool {
        key == 2
    }
    /// f^d_idyn, and f^d_dyn of [`ALONG_FROM`] coordinates on.
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
        let (mut kernel, stack) = KernelScratch::new(&self.model, self.kkt.as_ref(), ws.stack());
        let (own, _) = zeros(stack, n);
        let force = self.actuated.as_ref().map(|a| a.forces(x[3], own));
        match jac {
            Some(j) => {
                let (jq, rest) = j.split_at_mut(1);
                let (jv, rest) = rest.split_at_mut(1);
                let (ja, jf) = rest.split_at_mut(1);
                DynamicsKernel::evaluate(
                    &self.model,
                    x[0],
                    x[1],
                    t,
                    force,
                    r,
                    Some((&mut jq[0], &mut jv[0])),
                    &mut kernel,
                )?;
                identity(&mut ja[0], n, -1.0);
                if let Some(a) = &self.actuated {
                    DynamicsKernel::force_jacobian(
                        &self.model,
                        &a.indices,
                        &mut jf[0],
                        &mut kernel,
                    )?;
                }
            }
            None => {
                DynamicsKernel::evaluate(&self.model, x[0], x[1], t, force, r, None, &mut kernel)?
            }
        }
        for i in 0..n {
            r[i] -= x[2][i];
        }
        Ok(())
    }
}

impl Dynamics {
    /// The most directions it linearizes along (see [`Dynamics::along`]): f^d_idyn's
    /// Jacobians take a solve per coordinate and force, f^d_dyn's one per coordinate
    /// twice; more directions than n make f^d_dyn's Jacobians the cheaper.
    fn along_columns(&self) -> Option<usize> {
        let n = self.model.n();
        match &self.actuated {
            Some(a) => Some(2 * n + a.indices.len()),
            None => (n >= ALONG_FROM).then_some(n),
        }
    }
}

impl AlongDirections for Dynamics {
    /// e = q̈(q, q̇, t; Q) − q̈_t along V: K⁻¹ applied to the Jacobians' right-hand
    /// sides times V (see [`DynamicsKernel::along`]), minus V on q̈_t. f^d_dyn
    /// declines, before evaluating anything, directions that move q and q̇ in more
    /// than n columns.
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
        if self.actuated.is_none() && nonzero_columns(&dirs[..2], c) > max_cols {
            return Ok(false);
        }
        let n = self.model.n();
        let (mut kernel, stack) = KernelScratch::new(&self.model, self.kkt.as_ref(), ws.stack());
        let (own, extra) = zeros(stack, n);
        let (force, force_dirs, columns): (_, &[f64], &[usize]) = match &self.actuated {
            Some(a) => (Some(a.forces(x[3], own)), dirs[3], &a.indices),
            None => (None, &[], &[]),
        };
        DynamicsKernel::evaluate(&self.model, x[0], x[1], t, force, r, None, &mut kernel)?;
        if !DynamicsKernel::along(
            &self.model,
            (x[0], x[1], t),
            [dirs[0], dirs[1], force_dirs],
            columns,
            None,
            c,
            out,
            &kernel,
            extra,
            max_cols,
        )? {
            return Ok(false);
        }
        for (o, v) in out[..n * c].iter_mut().zip(&dirs[2][..n * c]) {
            *o -= v;
        }
        for i in 0..n {
            r[i] -= x[2][i];
        }
        Ok(true)
    }
}
