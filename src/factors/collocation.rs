//! Hermite–Simpson integrator factors: fourth order, on the same variables per step
//! as the trapezoidal rule (positions, velocities, accelerations).
//!
//! Hermite–Simpson collocation (the three-stage Lobatto IIIA method) puts a stage at
//! the middle of each step, where the cubic Hermite interpolants of the step's ends
//! give the state
//!
//! ```text
//! q_m = (q₀ + q₁)/2 + h/8 (q̇₀ − q̇₁)      q̇_m = (q̇₀ + q̇₁)/2 + h/8 (q̈₀ − q̈₁)
//! ```
//!
//! and the step is Simpson's rule on velocities and accelerations:
//!
//! ```text
//! q₁ = q₀ + h/6 (q̇₀ + 4 q̇_m + q̇₁)      q̇₁ = q̇₀ + h/6 (q̈₀ + 4 q̈_m + q̈₁)
//! ```
//!
//! with q̈_m = f(q_m, q̇_m, t + h/2) the dynamics at the stage. The stage's state is
//! eliminated: substituting q̇_m, the position factor is linear in the step's six
//! variables, e = q₁ − q₀ − h/2 (q̇₀ + q̇₁) − h²/12 (q̈₀ − q̈₁); the velocity factor
//! evaluates the dynamics at the stage inside itself. Each stays a factor between two
//! consecutive steps, so windows, the batch and marginalization see the same chain.
//!
//! **Constraints at the stage.** q_m is an interpolant, not a solution of Φ(q) = 0:
//! it is off the manifold by O(h⁴). The dynamics there are the augmented (KKT)
//! system's, which holds Φ_q q̈ = −Φ̇_q q̇ at whatever state it is given; the O(h⁴)
//! offset enters q̈_m smoothly and the step's error stays O(h⁵). The constraints hold
//! exactly at the nodes, where the hard factors are.

use super::{identity, key_accessor};
use crate::dynamics::{DynamicsKernel, KernelScratch, KktStructure};
use crate::error::Result;
use crate::graph::{zeros, Factor, Key, StackReq, VarKind, Workspace, MAX_KEYS};
use crate::model::Model;
use std::sync::Arc;

/// The position and velocity factors of one coordinate set, in that order: q, q̇, q̈
/// for dependent coordinates (`independent` None), or z, ż, z̈ with the velocity rule
/// on the rows of the independent coordinates `independent`.
pub fn factors(model: &Arc<Model>, independent: Option<&[usize]>, dt: f64) -> [Box<dyn Factor>; 2] {
    let (x, dx, ddx, dim) = match independent {
        Some(set) => (VarKind::Z, VarKind::Dz, VarKind::Ddz, set.len()),
        None => (VarKind::Q, VarKind::Dq, VarKind::Ddq, model.n()),
    };
    let velocity = match independent {
        Some(set) => SimpsonVelocity::with_rows(model.clone(), dt, set.to_vec()),
        None => SimpsonVelocity::dependent(model.clone(), dt),
    };
    [
        Box::new(HermitePosition::new(x, dx, ddx, dim, dt)),
        Box::new(velocity),
    ]
}

/// Hermite–Simpson for a position: e = x₁ − x₀ − h/2 (ẋ₀ + ẋ₁) − h²/12 (ẍ₀ − ẍ₁).
pub struct HermitePosition {
    name: String,
    keys: [Key; 6],
    dim: usize,
    dt: f64,
}

impl HermitePosition {
    /// The factor on `x` with rates `dx` and accelerations `ddx` (q, q̇, q̈ or z, ż, z̈).
    pub fn new(x: VarKind, dx: VarKind, ddx: VarKind, dim: usize, dt: f64) -> Self {
        HermitePosition {
            name: format!("f_hs({})", x.symbol()),
            keys: [
                Key::before(x),
                Key::now(x),
                Key::before(dx),
                Key::now(dx),
                Key::before(ddx),
                Key::now(ddx),
            ],
            dim,
            dt,
        }
    }

    /// The coefficients of x₀, x₁, ẋ₀, ẋ₁, ẍ₀, ẍ₁.
    pub fn coefficients(dt: f64) -> [f64; 6] {
        let (h2, h12) = (0.5 * dt, dt * dt / 12.0);
        [-1.0, 1.0, -h2, -h2, -h12, h12]
    }
}

impl Factor for HermitePosition {
    fn name(&self) -> &str {
        &self.name
    }
    key_accessor!();
    fn size(&self, _key: usize) -> usize {
        self.dim
    }
    fn dim(&self) -> usize {
        self.dim
    }
    fn diagonal_jacobian(&self, _key: usize) -> bool {
        true
    }
    fn evaluate(
        &self,
        _t: f64,
        x: &[&[f64]],
        r: &mut [f64],
        jac: Option<&mut [Vec<f64>]>,
        _ws: &mut Workspace,
    ) -> Result<()> {
        let c = Self::coefficients(self.dt);
        for (i, ri) in r.iter_mut().enumerate() {
            *ri = c.iter().zip(x).map(|(c, x)| c * x[i]).sum();
        }
        if let Some(j) = jac {
            for (block, &c) in j.iter_mut().zip(&c) {
                identity(block, self.dim, c);
            }
        }
        Ok(())
    }
}

/// Hermite–Simpson for velocities: e = S (q̇₁ − q̇₀ − h/6 (q̈₀ + 4 q̈_m + q̈₁)), q̈_m the
/// dynamics at the stage state built from q, q̇, q̈ at both ends. In dependent
/// coordinates S = I; in independent ones S selects the independent coordinates (whose
/// q̇, q̈ the hard factors hold equal to ż, z̈).
pub struct SimpsonVelocity {
    model: Arc<Model>,
    name: String,
    keys: Vec<Key>,
    /// The coordinates whose rows the residual has: all n (DC) or the independent ones.
    rows: Vec<usize>,
    dt: f64,
    /// A large mechanism's KKT structure, analysed once.
    kkt: Option<KktStructure>,
}

impl SimpsonVelocity {
    /// Dependent coordinates: keys q₀, q₁, q̇₀, q̇₁, q̈₀, q̈₁.
    pub fn dependent(model: Arc<Model>, dt: f64) -> Self {
        SimpsonVelocity {
            rows: (0..model.n()).collect(),
            kkt: KktStructure::for_model(&model),
            model,
            name: "f_hs(dq)".into(),
            keys: Self::state_keys(),
            dt,
        }
    }

    /// Independent coordinates: the keys of [`SimpsonVelocity::dependent`], the rows
    /// of the scene's independent coordinates.
    pub fn independent(model: Arc<Model>, dt: f64) -> Self {
        let rows = model.independent.clone();
        SimpsonVelocity::with_rows(model, dt, rows)
    }

    /// Independent coordinates: the keys of [`SimpsonVelocity::dependent`], the rows
    /// `rows` (the independent coordinates in use).
    pub fn with_rows(model: Arc<Model>, dt: f64, rows: Vec<usize>) -> Self {
        SimpsonVelocity {
            rows,
            kkt: KktStructure::for_model(&model),
            model,
            name: "f_hs(dz)".into(),
            keys: Self::state_keys(),
            dt,
        }
    }

    fn state_keys() -> Vec<Key> {
        [VarKind::Q, VarKind::Dq, VarKind::Ddq]
            .into_iter()
            .flat_map(|k| [Key::before(k), Key::now(k)])
            .collect()
    }

    /// Scratch beyond the kernel's: q_m, q̇_m, q̈_m and ∂q̈_m/∂q_m, ∂q̈_m/∂q̇_m.
    fn own_scratch(n: usize) -> [usize; 5] {
        [n, n, n, n * n, n * n]
    }
}

impl Factor for SimpsonVelocity {
    fn name(&self) -> &str {
        &self.name
    }
    key_accessor!();
    fn size(&self, _key: usize) -> usize {
        self.model.n()
    }
    fn dim(&self) -> usize {
        self.rows.len()
    }
    fn scratch(&self) -> StackReq {
        let own = Self::own_scratch(self.model.n()).map(StackReq::new::<f64>);
        DynamicsKernel::scratch(&self.model).and(StackReq::all_of(&own))
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
        let h = self.dt;
        let (mut kernel, stack) = KernelScratch::new(&self.model, self.kkt.as_ref(), ws.stack());
        let [qm, vm, am, jq, jv] = Self::own_scratch(n);
        let (qm, stack) = zeros(stack, qm);
        let (vm, stack) = zeros(stack, vm);
        let (am, stack) = zeros(stack, am);
        let (jq, stack) = zeros(stack, jq);
        let (jv, _) = zeros(stack, jv);
        let (qm, vm, am) = (&mut qm[..], &mut vm[..], &mut am[..]);
        let (jq, jv) = (&mut jq[..], &mut jv[..]);
        let (q0, q1, v0, v1, a0, a1) = (x[0], x[1], x[2], x[3], x[4], x[5]);
        for i in 0..n {
            qm[i] = 0.5 * (q0[i] + q1[i]) + 0.125 * h * (v0[i] - v1[i]);
            vm[i] = 0.5 * (v0[i] + v1[i]) + 0.125 * h * (a0[i] - a1[i]);
        }
        let want = jac.is_some();
        DynamicsKernel::evaluate(
            &self.model,
            qm,
            vm,
            t - 0.5 * h,
            None,
            am,
            want.then_some((&mut *jq, &mut *jv)),
            &mut kernel,
        )?;
        let h6 = h / 6.0;
        for (k, &i) in self.rows.iter().enumerate() {
            r[k] = v1[i] - v0[i] - h6 * (a0[i] + 4.0 * am[i] + a1[i]);
        }
        let Some(j) = jac else { return Ok(()) };
        state_jacobians(j, self.rows.iter().copied(), (jq, jv), n, h);
        Ok(())
    }
}

/// The Jacobian blocks of e = q̇₁ − q̇₀ − h/6 (q̈₀ + 4 q̈_m + q̈₁) on the step's q, q̇,
/// q̈ at both ends (`j[0..6]`, rows `rows` of the n coordinates), from G = ∂q̈_m/∂q_m
/// and ∂q̈_m/∂q̇_m (row-major n × n): ∂(4 h/6 q̈_m) through q_m = (q₀+q₁)/2 + h/8 (q̇₀−q̇₁)
/// and q̇_m = (q̇₀+q̇₁)/2 + h/8 (q̈₀−q̈₁), then the ends' own q̇₁ − q̇₀ − h/6 (q̈₀ + q̈₁).
fn state_jacobians(
    j: &mut [Vec<f64>],
    rows: impl Iterator<Item = usize>,
    (jq, jv): (&[f64], &[f64]),
    n: usize,
    h: f64,
) {
    let (c, c2, h6) = (2.0 * h / 3.0, h * h / 12.0, h / 6.0);
    for (k, i) in rows.enumerate() {
        for col in 0..n {
            let (gq, gv) = (jq[i * n + col], jv[i * n + col]);
            let at = k * n + col;
            j[0][at] = -0.5 * c * gq;
            j[1][at] = -0.5 * c * gq;
            j[2][at] = -c2 * gq - 0.5 * c * gv;
            j[3][at] = c2 * gq - 0.5 * c * gv;
            j[4][at] = -c2 * gv;
            j[5][at] = c2 * gv;
        }
        let at = k * n + i;
        j[2][at] -= 1.0;
        j[3][at] += 1.0;
        j[4][at] -= h6;
        j[5][at] -= h6;
    }
}

/// Hermite–Simpson for velocities with the stage's dynamics those of an estimate's
/// dynamics factor `stage` (f^d_dyn, f^d_idyn or f^d_par: e = q̈(q, q̇, t; w) − q̈_t with
/// keys q, q̇, q̈ of the step and then its other variables w, such as the identified
/// parameters or the unknown inputs): e = q̇₁ − q̇₀ − h/6 (q̈₀ + 4 q̈_m + q̈₁) with
/// q̈_m = q̈(q_m, q̇_m, t − h/2; w_m), w_m = (w₀ + w₁)/2, the variables at the middle of
/// a step on which they are linear (an input's random walk) or constant (a parameter).
/// Its keys are [`SimpsonVelocity`]'s, then w₀ and w₁ of each of `stage`'s other keys.
pub struct SimpsonVelocityThrough {
    stage: Box<dyn Factor>,
    name: String,
    keys: Vec<Key>,
    n: usize,
    dt: f64,
}

impl SimpsonVelocityThrough {
    /// The factor at step `dt` whose stage is evaluated by `stage` (keys q, q̇, q̈ of
    /// the step first, n rows).
    pub fn new(stage: Box<dyn Factor>, dt: f64) -> Self {
        let n = stage.dim();
        let own = [VarKind::Q, VarKind::Dq, VarKind::Ddq].map(Key::now);
        assert!(
            stage.keys()[..3] == own,
            "a stage's dynamics factor reads q, q̇, q̈ of its step first"
        );
        let mut keys = SimpsonVelocity::state_keys();
        for key in &stage.keys()[3..] {
            keys.extend([Key::before(key.kind), Key::now(key.kind)]);
        }
        SimpsonVelocityThrough {
            name: format!("f_hs(dq; {})", stage.name()),
            stage,
            keys,
            n,
            dt,
        }
    }

    /// How many of the stage's keys follow q, q̇, q̈.
    fn others(&self) -> usize {
        self.stage.keys().len() - 3
    }
}

impl Factor for SimpsonVelocityThrough {
    fn name(&self) -> &str {
        &self.name
    }
    key_accessor!();
    fn size(&self, key: usize) -> usize {
        match key {
            0..=5 => self.n,
            k => self.stage.size(3 + (k - 6) / 2),
        }
    }
    fn dim(&self) -> usize {
        self.n
    }
    fn scratch(&self) -> StackReq {
        self.stage.scratch()
    }
    fn evaluate(
        &self,
        t: f64,
        x: &[&[f64]],
        r: &mut [f64],
        jac: Option<&mut [Vec<f64>]>,
        ws: &mut Workspace,
    ) -> Result<()> {
        let (n, h) = (self.n, self.dt);
        let (q0, q1, v0, v1, a0, a1) = (x[0], x[1], x[2], x[3], x[4], x[5]);
        let others = self.others();
        let want = jac.is_some();
        STAGE.with_borrow_mut(|b| -> Result<()> {
            // q_m, q̇_m, and q̈_t = 0 (the stage factor's residual is then q̈_m itself),
            // then each other variable's average over the step.
            let widths = (3..3 + others).map(|k| self.stage.size(k));
            b.inputs.clear();
            b.inputs.resize(3 * n + widths.clone().sum::<usize>(), 0.0);
            let (state, averages) = b.inputs.split_at_mut(3 * n);
            for i in 0..n {
                state[i] = 0.5 * (q0[i] + q1[i]) + 0.125 * h * (v0[i] - v1[i]);
                state[n + i] = 0.5 * (v0[i] + v1[i]) + 0.125 * h * (a0[i] - a1[i]);
            }
            let mut inputs: [&[f64]; MAX_KEYS] = [&[]; MAX_KEYS];
            let (qm, rest) = state.split_at(n);
            let (vm, zero) = rest.split_at(n);
            inputs[..3].copy_from_slice(&[qm, vm, zero]);
            let mut rest = &mut *averages;
            for (k, width) in widths.enumerate() {
                let (w, tail) = std::mem::take(&mut rest).split_at_mut(width);
                let (w0, w1) = (x[6 + 2 * k], x[7 + 2 * k]);
                for ((o, a), b) in w.iter_mut().zip(w0).zip(w1) {
                    *o = 0.5 * (a + b);
                }
                inputs[3 + k] = w;
                rest = tail;
            }
            b.am.clear();
            b.am.resize(n, 0.0);
            b.jac.resize_with(self.stage.keys().len(), Vec::new);
            for (k, block) in b.jac.iter_mut().enumerate() {
                block.clear();
                block.resize(n * self.stage.size(k), 0.0);
            }
            let stage_jac = want.then_some(&mut b.jac[..]);
            self.stage
                .evaluate(t - 0.5 * h, &inputs[..3 + others], &mut b.am, stage_jac, ws)
        })?;
        STAGE.with_borrow(|b| {
            let am = &b.am;
            let h6 = h / 6.0;
            for i in 0..n {
                r[i] = v1[i] - v0[i] - h6 * (a0[i] + 4.0 * am[i] + a1[i]);
            }
            let Some(j) = jac else { return };
            // As SimpsonVelocity's, with G = ∂q̈_m/∂(q_m, q̇_m) from the stage factor;
            // each other variable enters q̈_m through its average, half from each end.
            let g = &b.jac;
            state_jacobians(j, 0..n, (&g[0], &g[1]), n, h);
            let c = 2.0 * h / 3.0;
            for k in 0..others {
                for end in 0..2 {
                    for (o, d) in j[6 + 2 * k + end].iter_mut().zip(&g[3 + k]) {
                        *o = -0.5 * c * d;
                    }
                }
            }
        });
        Ok(())
    }
}

/// The buffers of a [`SimpsonVelocityThrough`] evaluation, kept on each thread so that
/// the solver's iterations allocate nothing: the stage factor's inputs (q_m, q̇_m,
/// zeros for q̈_t, the averaged other variables), its residual q̈_m and its Jacobian.
#[derive(Default)]
struct StageBuffers {
    inputs: Vec<f64>,
    am: Vec<f64>,
    jac: Vec<Vec<f64>>,
}

thread_local! {
    static STAGE: std::cell::RefCell<StageBuffers> = std::cell::RefCell::new(StageBuffers::default());
}
