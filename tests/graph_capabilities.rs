//! Factors of chosen steps (readings that exist at some steps) and parameters
//! constant over the horizon ([`VarKind::Param`] held by its link): a window holds a
//! reading only when it holds the reading's step, and the fixed-lag smoother keeps
//! the parameters' information as it marginalizes steps.

use std::sync::{Arc, Mutex};

use mbfg::error::{Error, Result};
use mbfg::factors::{Equality, Prior, Trapezoidal};
use mbfg::graph::{ChainGraph, Factor, Key, Layout, Noise, VarKind, Workspace};
use mbfg::smoother::{self, Finished, FixedLag, Hooks, Next};
use mbfg::solver::{Method, Settings, SolveReport, Termination, WindowSolver};

const G: f64 = 9.81;

fn gauss_newton() -> Settings {
    Settings {
        method: Method::GaussNewton,
        ..Settings::default()
    }
}

/// The smoother's hooks from closures: each step's prediction, and what each window
/// solve's newest step does; the steps a streamed buffer hands out are kept.
struct Closures<P, S> {
    predict: P,
    step: S,
    finals: Vec<(usize, Vec<f64>)>,
}

impl<P, S> Hooks for Closures<P, S>
where
    P: FnMut(&mut [f64], usize),
    S: FnMut(usize, &SolveReport, &[f64]) -> Next,
{
    fn predict(&mut self, values: &mut [f64], k: usize) {
        (self.predict)(values, k);
    }

    fn on_step(&mut self, k: usize, _: usize, report: &SolveReport, values: &[f64]) -> Next {
        (self.step)(k, report, values)
    }

    fn on_final(&mut self, j: usize, block: &[f64]) -> Result<()> {
        self.finals.push((j, block.to_vec()));
        Ok(())
    }
}

/// The fixed-lag smoother (Gauss–Newton) over `steps` steps, in place or in a
/// buffer of `capacity` steps: where it ended, and the steps handed out.
fn fixed_lag(
    graph: &ChainGraph,
    values: &mut [f64],
    steps: usize,
    window: usize,
    capacity: Option<usize>,
    predict: impl FnMut(&mut [f64], usize),
    step: impl FnMut(usize, &SolveReport, &[f64]) -> Next,
) -> (Finished, Vec<(usize, Vec<f64>)>) {
    let mut hooks = Closures {
        predict,
        step,
        finals: Vec::new(),
    };
    let horizon = FixedLag {
        steps,
        window,
        settings: gauss_newton(),
        capacity,
    };
    let end = smoother::fixed_lag(graph, values, &horizon, &mut hooks).unwrap();
    (end, hooks.finals)
}

/// Checks every Jacobian block of `factor` at `xs` (time `t`) against central
/// differences: |closed form − difference| ≤ 1e-7 · max(1, |entry|).
fn check_jacobians(factor: &dyn Factor, t: f64, xs: &[Vec<f64>]) {
    let dim = factor.dim();
    let mut ws = Workspace::new(factor.scratch());
    let eval = |xs: &[Vec<f64>], ws: &mut Workspace, jac: Option<&mut [Vec<f64>]>| {
        let refs: Vec<&[f64]> = xs.iter().map(|x| x.as_slice()).collect();
        let mut r = vec![0.0; dim];
        factor.evaluate(t, &refs, &mut r, jac, ws).unwrap();
        r
    };
    let mut jac: Vec<Vec<f64>> = (0..xs.len())
        .map(|a| vec![f64::NAN; dim * factor.size(a)])
        .collect();
    eval(xs, &mut ws, Some(&mut jac));
    for (a, x) in xs.iter().enumerate() {
        let d = factor.size(a);
        for j in 0..d {
            let h = 1e-6 * x[j].abs().max(1.0);
            let mut plus = xs.to_vec();
            plus[a][j] += h;
            let mut minus = xs.to_vec();
            minus[a][j] -= h;
            let (rp, rm) = (eval(&plus, &mut ws, None), eval(&minus, &mut ws, None));
            for i in 0..dim {
                let fd = (rp[i] - rm[i]) / (2.0 * h);
                let cf = jac[a][i * d + j];
                assert!(
                    (cf - fd).abs() <= 1e-7 * cf.abs().max(1.0),
                    "{}: ∂r{i}/∂x{a}[{j}] closed form {cf} vs differences {fd}",
                    factor.name()
                );
            }
        }
    }
}

// ---------------------------------------------------------------------------------
// Test factors.

/// The pendulum's equation of motion with its length a parameter:
/// e = θ̈ + (g/L) sin θ, on (θ, θ̈, L) at one step.
struct Pendulum {
    keys: [Key; 3],
}

impl Pendulum {
    fn new() -> Self {
        Pendulum {
            keys: [
                Key::now(VarKind::Q),
                Key::now(VarKind::Ddq),
                Key::now(VarKind::Param),
            ],
        }
    }
}

impl Factor for Pendulum {
    fn name(&self) -> &str {
        "pendulum"
    }
    fn keys(&self) -> &[Key] {
        &self.keys
    }
    fn size(&self, _key: usize) -> usize {
        1
    }
    fn dim(&self) -> usize {
        1
    }
    fn evaluate(
        &self,
        _t: f64,
        x: &[&[f64]],
        r: &mut [f64],
        jac: Option<&mut [Vec<f64>]>,
        _ws: &mut Workspace,
    ) -> Result<()> {
        let (theta, acc, length) = (x[0][0], x[1][0], x[2][0]);
        if length <= 0.0 {
            return Err(Error::singular(format!("pendulum length {length} ≤ 0")));
        }
        r[0] = acc + G / length * theta.sin();
        if let Some(j) = jac {
            j[0][0] = G / length * theta.cos();
            j[1][0] = 1.0;
            j[2][0] = -G / (length * length) * theta.sin();
        }
        Ok(())
    }
}

/// A reading of a position offset by a constant bias: e = q + b − y, on (q, b).
struct BiasedReading {
    keys: [Key; 2],
    y: f64,
}

impl BiasedReading {
    fn new(y: f64) -> Self {
        BiasedReading {
            keys: [Key::now(VarKind::Q), Key::now(VarKind::Param)],
            y,
        }
    }
}

impl Factor for BiasedReading {
    fn name(&self) -> &str {
        "biased reading"
    }
    fn keys(&self) -> &[Key] {
        &self.keys
    }
    fn size(&self, _key: usize) -> usize {
        1
    }
    fn dim(&self) -> usize {
        1
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
        r[0] = x[0][0] + x[1][0] - self.y;
        if let Some(j) = jac {
            j[0][0] = 1.0;
            j[1][0] = 1.0;
        }
        Ok(())
    }
}

/// A reading of the displacement since the step before: e = q_k − q_{k−1} − d.
struct Displacement {
    keys: [Key; 2],
    d: f64,
}

impl Factor for Displacement {
    fn name(&self) -> &str {
        "displacement"
    }
    fn keys(&self) -> &[Key] {
        &self.keys
    }
    fn size(&self, _key: usize) -> usize {
        1
    }
    fn dim(&self) -> usize {
        1
    }
    fn evaluate(
        &self,
        _t: f64,
        x: &[&[f64]],
        r: &mut [f64],
        jac: Option<&mut [Vec<f64>]>,
        _ws: &mut Workspace,
    ) -> Result<()> {
        r[0] = x[1][0] - x[0][0] - self.d;
        if let Some(j) = jac {
            j[0][0] = -1.0;
            j[1][0] = 1.0;
        }
        Ok(())
    }
}

impl Displacement {
    fn new(d: f64) -> Self {
        Displacement {
            keys: [Key::before(VarKind::Q), Key::now(VarKind::Q)],
            d,
        }
    }
}

/// A prior on q that logs the times it is evaluated at.
struct Logged {
    prior: Prior,
    log: Arc<Mutex<Vec<f64>>>,
}

impl Factor for Logged {
    fn name(&self) -> &str {
        "logged"
    }
    fn keys(&self) -> &[Key] {
        self.prior.keys()
    }
    fn size(&self, key: usize) -> usize {
        self.prior.size(key)
    }
    fn dim(&self) -> usize {
        self.prior.dim()
    }
    fn evaluate(
        &self,
        t: f64,
        x: &[&[f64]],
        r: &mut [f64],
        jac: Option<&mut [Vec<f64>]>,
        ws: &mut Workspace,
    ) -> Result<()> {
        self.log.lock().unwrap().push(t);
        self.prior.evaluate(t, x, r, jac, ws)
    }
}

#[test]
fn test_factors_jacobians_match_finite_differences() {
    for (theta, acc, length) in [(0.3, -1.0, 0.9), (-1.2, 4.0, 2.5), (2.9, 0.1, 0.4)] {
        check_jacobians(
            &Pendulum::new(),
            0.0,
            &[vec![theta], vec![acc], vec![length]],
        );
    }
    check_jacobians(&BiasedReading::new(0.7), 0.0, &[vec![0.2], vec![-0.1]]);
    check_jacobians(&Displacement::new(0.3), 0.0, &[vec![0.2], vec![1.1]]);
    // The parameters' link is f_eq on p.
    check_jacobians(
        &Equality::new(VarKind::Param, 2),
        0.0,
        &[vec![0.2, 3.0], vec![1.1, -0.5]],
    );
}

// ---------------------------------------------------------------------------------
// Factors of chosen steps.

/// q, q̇ per step, the trapezoid between steps and a random walk on q̇.
fn walk(dt: f64) -> mbfg::graph::ChainGraphBuilder {
    let layout = Layout::new(&[(VarKind::Q, 1), (VarKind::Dq, 1)]);
    ChainGraph::builder(layout, dt, 0.0)
        .step_soft(
            Box::new(Trapezoidal::new(VarKind::Q, VarKind::Dq, 1, dt)),
            Noise::Isotropic(0.05),
        )
        .step_soft(
            Box::new(Equality::new(VarKind::Dq, 1)),
            Noise::Isotropic(0.3),
        )
        // Every window is well posed on its own.
        .step_soft(
            Box::new(Prior::new(VarKind::Q, vec![0.0])),
            Noise::Isotropic(10.0),
        )
}

#[test]
fn a_reading_enters_a_window_only_when_the_window_holds_its_step() {
    let log = Arc::new(Mutex::new(Vec::new()));
    let dt = 0.1;
    let graph = walk(dt)
        .soft_at(
            20,
            Box::new(Logged {
                prior: Prior::new(VarKind::Q, vec![5.0]),
                log: log.clone(),
            }),
            Noise::Isotropic(0.01),
        )
        .build()
        .unwrap();
    let plain = walk(dt).build().unwrap();
    let s = 2;
    let steps = 30;
    let mut solver = WindowSolver::new(&graph, steps, gauss_newton()).unwrap();
    let mut without = WindowSolver::new(&plain, steps, gauss_newton()).unwrap();
    // Windows that end before step 20 or start after it: as if there were no reading.
    for (k0, k1) in [(0, 20), (5, 15), (21, 30)] {
        let mut a = vec![0.1; steps * s];
        let mut b = a.clone();
        let ra = solver.solve(&graph, &mut a, k0, k1, None).unwrap();
        let rb = without.solve(&plain, &mut b, k0, k1, None).unwrap();
        assert_eq!(ra.termination, Termination::Converged);
        assert_eq!(ra.cost.to_bits(), rb.cost.to_bits(), "window {k0}..{k1}");
        assert!(a.iter().zip(&b).all(|(x, y)| x.to_bits() == y.to_bits()));
        assert!(log.lock().unwrap().is_empty(), "window {k0}..{k1}");
    }
    // Windows that hold it: evaluated at step 20's time, and it pulls q_20 to 5.
    for (k0, k1) in [(0, 30), (20, 21), (15, 25)] {
        let mut a = vec![0.1; steps * s];
        solver.solve(&graph, &mut a, k0, k1, None).unwrap();
        let times = std::mem::take(&mut *log.lock().unwrap());
        assert!(!times.is_empty(), "window {k0}..{k1}");
        assert!(times.iter().all(|&t| t == graph.run_time(20)), "{times:?}");
        assert!(
            (a[20 * s] - 5.0).abs() < 1e-2,
            "window {k0}..{k1}: q_20 = {}",
            a[20 * s]
        );
    }
}

#[test]
fn build_refuses_a_reading_on_a_variable_the_layout_lacks() {
    let graph = walk(0.1)
        .soft_at(
            3,
            Box::new(Prior::new(VarKind::Ddq, vec![0.0])),
            Noise::Isotropic(1.0),
        )
        .build();
    match graph {
        Err(Error::InvalidArgument(m)) => {
            assert!(
                m.contains("f_prior(ddq) at step 3 touches ddq(lag 0)"),
                "{m}"
            )
        }
        Err(e) => panic!("another error: {e}"),
        Ok(_) => panic!("built"),
    }
}

/// The linear chain `walk` with a constant bias b on its position readings (every
/// third step), displacement readings at a few steps, and a prior on b.
fn biased_chain(link_sigma: f64) -> ChainGraph {
    let dt = 0.1;
    let layout = Layout::new(&[(VarKind::Q, 1), (VarKind::Dq, 1), (VarKind::Param, 1)]);
    let mut b = ChainGraph::builder(layout, dt, 0.0)
        .step_soft(
            Box::new(Trapezoidal::new(VarKind::Q, VarKind::Dq, 1, dt)),
            Noise::Isotropic(0.05),
        )
        .step_soft(
            Box::new(Equality::new(VarKind::Dq, 1)),
            Noise::Isotropic(0.3),
        )
        .constant_link(link_sigma)
        // q₀ known well (the readings' sine starts at 0): the readings' offset is b's.
        .initial_soft(
            Box::new(Prior::new(VarKind::Q, vec![0.0])),
            Noise::Isotropic(0.01),
        )
        .initial_soft(
            Box::new(Prior::new(VarKind::Dq, vec![0.0])),
            Noise::Isotropic(1.0),
        )
        .initial_soft(
            Box::new(Prior::new(VarKind::Param, vec![0.0])),
            Noise::Isotropic(2.0),
        );
    for k in (0..40).step_by(3) {
        let t = k as f64 * dt;
        let y = (1.3 * t).sin() + 0.4;
        b = b.soft_at(k, Box::new(BiasedReading::new(y)), Noise::Isotropic(0.1));
    }
    for k in [4, 5, 11, 17, 30] {
        let t = k as f64 * dt;
        let d = (1.3 * t).sin() - (1.3 * (t - dt)).sin();
        b = b.soft_at(k, Box::new(Displacement::new(d)), Noise::Isotropic(0.02));
    }
    b.build().unwrap()
}

/// The linear chain's link: the smoother's agreement with the batch is limited by
/// the round-off of subtracting terms of size 1/σ² in marginalization (ε/σ² against
/// the bias's information, ~1e3), the copies' agreement by σ itself.
const LINEAR_LINK: f64 = 1e-5;

fn copy_previous(s: usize) -> impl FnMut(&mut [f64], usize) {
    move |v: &mut [f64], k: usize| {
        let (prev, next) = v.split_at_mut(k * s);
        next[..s].copy_from_slice(&prev[(k - 1) * s..]);
    }
}

#[test]
fn linear_chain_with_readings_and_a_bias_smoother_newest_equals_the_batch() {
    // Linear and Gaussian: the fixed-lag smoother's newest estimate is the batch
    // solution of the graph up to that step, bias included, for every window (to
    // the link's round-off, see LINEAR_LINK).
    let graph = biased_chain(LINEAR_LINK);
    let s = graph.layout().size();
    let steps = 36;
    let mut batches = Vec::new();
    for k in 0..steps {
        let mut batch = vec![0.0; (k + 1) * s];
        let report = smoother::batch(&graph, &mut batch, k + 1, gauss_newton()).unwrap();
        assert_eq!(report.termination, Termination::Converged);
        batches.push(batch);
    }
    let mut worst: f64 = 0.0;
    for window in [1, 2, 4, 10] {
        let mut values = vec![0.0; steps * s];
        let mut newest: Vec<Vec<f64>> = Vec::new();
        fixed_lag(
            &graph,
            &mut values,
            steps,
            window,
            None,
            copy_previous(s),
            |k, report, v| {
                assert_eq!(report.termination, Termination::Converged);
                newest.push(v[k * s..(k + 1) * s].to_vec());
                Next::Continue
            },
        );
        for (k, batch) in batches.iter().enumerate() {
            let expect = &batch[k * s..];
            for i in 0..s {
                let err = (newest[k][i] - expect[i]).abs();
                worst = worst.max(err / expect[i].abs().max(1.0));
                assert!(
                    err <= 1e-7 * expect[i].abs().max(1.0),
                    "window {window}, step {k}, unknown {i}: smoother {} vs batch {} ({err:.1e})",
                    newest[k][i],
                    expect[i]
                );
            }
        }
    }
    // The bias is found (the readings' offset, 0.4) and every step's copy agrees.
    let last = &batches[steps - 1];
    let bias = last[2];
    assert!((bias - 0.4).abs() < 0.05, "bias {bias}");
    let spread = (0..steps)
        .map(|k| (last[k * s + 2] - bias).abs())
        .fold(0.0, f64::max);
    eprintln!("smoother vs batch {worst:.1e}, copies of b within {spread:.1e}");
    // Far below the bias's own σ (~0.03).
    assert!(spread <= 1e-8, "copies of the bias differ by {spread:.1e}");
}

#[test]
fn a_streaming_run_with_readings_equals_the_run_in_place_to_the_bit() {
    // The buffer moves the values; the readings stay at their run steps.
    let graph = biased_chain(1e-6);
    let s = graph.layout().size();
    let steps = 36;
    let window = 3;
    let mut in_place = vec![0.0; steps * s];
    fixed_lag(
        &graph,
        &mut in_place,
        steps,
        window,
        None,
        copy_previous(s),
        |_, _, _| Next::Continue,
    );
    let capacity = window + 4;
    let mut buffer = vec![0.0; capacity * s];
    let (end, finals) = fixed_lag(
        &graph,
        &mut buffer,
        steps,
        window,
        Some(capacity),
        copy_previous(s),
        |_, _, _| Next::Continue,
    );
    let (base, handed) = (end.base, end.handed);
    assert!(base > 0, "the buffer never moved");
    for (j, block) in &finals {
        let expect = &in_place[j * s..(j + 1) * s];
        assert!(
            block
                .iter()
                .zip(expect)
                .all(|(a, b)| a.to_bits() == b.to_bits()),
            "step {j}: {block:?} vs {expect:?}"
        );
    }
    for j in handed..steps {
        let got = &buffer[(j - base) * s..(j - base + 1) * s];
        let expect = &in_place[j * s..(j + 1) * s];
        assert!(got
            .iter()
            .zip(expect)
            .all(|(a, b)| a.to_bits() == b.to_bits()));
    }
}

// ---------------------------------------------------------------------------------
// A pendulum whose length is a constant to estimate.

const DT: f64 = 0.01;
const STEPS: usize = 201;
const EVERY: usize = 5;
const TRUE_LENGTH: f64 = 1.0;

/// The pendulum's discrete motion under the trapezoid, the graph's own model:
/// (θ, θ̇, θ̈) at every step from θ₀, θ̇₀ with length `length`.
fn simulate(theta0: f64, rate0: f64, length: f64) -> Vec<[f64; 3]> {
    let acc = |th: f64| -G / length * th.sin();
    let mut out = vec![[theta0, rate0, acc(theta0)]];
    for _ in 1..STEPS {
        let [th, w, a] = *out.last().unwrap();
        // θ' = θ + h/2 (ω + ω'), ω' = ω + h/2 (a + a(θ')): Newton on θ'.
        let mut next = th + DT * w;
        for _ in 0..50 {
            let w1 = w + 0.5 * DT * (a + acc(next));
            let f = next - th - 0.5 * DT * (w + w1);
            let df = 1.0 - 0.25 * DT * DT * (-G / length * next.cos());
            let step = f / df;
            next -= step;
            if step.abs() < 1e-15 {
                break;
            }
        }
        let a1 = acc(next);
        out.push([next, w + 0.5 * DT * (a + a1), a1]);
    }
    out
}

/// A fixed-seed normal generator (xorshift64* and Box-Muller).
struct Normal(u64);

impl Normal {
    fn uniform(&mut self) -> f64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        let bits = self.0.wrapping_mul(0x2545_F491_4F6C_DD1D) >> 11;
        (bits as f64 + 0.5) / (1u64 << 53) as f64
    }
    fn sample(&mut self) -> f64 {
        let (u, v) = (self.uniform(), self.uniform());
        (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
    }
}

/// The priors: where they are centred and their σ (θ₀, θ̇₀, L).
const PRIOR: [f64; 3] = [0.4, 0.0, 1.2];
const PRIOR_SIGMA: [f64; 3] = [0.5, 1.0, 0.5];
const LINK_SIGMA: f64 = 1e-7;
const INTEGRATOR_SIGMA: f64 = 1e-5;

/// Layout (θ, θ̇, θ̈, L); the trapezoid on θ and θ̇ (soft), the equation of motion
/// (hard), L held constant by its link, priors on θ₀, θ̇₀, L, and a reading of θ
/// every fifth step.
fn pendulum_graph(readings: &[(usize, f64)], sigma: f64) -> ChainGraph {
    let layout = Layout::new(&[
        (VarKind::Q, 1),
        (VarKind::Dq, 1),
        (VarKind::Ddq, 1),
        (VarKind::Param, 1),
    ]);
    let mut b = ChainGraph::builder(layout, DT, 0.0)
        .step_soft(
            Box::new(Trapezoidal::new(VarKind::Q, VarKind::Dq, 1, DT)),
            Noise::Isotropic(INTEGRATOR_SIGMA),
        )
        .step_soft(
            Box::new(Trapezoidal::new(VarKind::Dq, VarKind::Ddq, 1, DT)),
            Noise::Isotropic(INTEGRATOR_SIGMA),
        )
        .step_constraint(Box::new(Pendulum::new()))
        .constant_link(LINK_SIGMA);
    for (kind, (mean, sigma)) in [VarKind::Q, VarKind::Dq, VarKind::Param]
        .into_iter()
        .zip(PRIOR.into_iter().zip(PRIOR_SIGMA))
    {
        b = b.initial_soft(
            Box::new(Prior::new(kind, vec![mean])),
            Noise::Isotropic(sigma),
        );
    }
    for &(k, y) in readings {
        b = b.soft_at(
            k,
            Box::new(Prior::new(VarKind::Q, vec![y])),
            Noise::Isotropic(sigma),
        );
    }
    b.build().unwrap()
}

/// Readings of θ every fifth step of the true motion, with noise of σ `sigma`.
fn readings(truth: &[[f64; 3]], sigma: f64, seed: u64) -> Vec<(usize, f64)> {
    let mut noise = Normal(seed);
    (0..STEPS)
        .step_by(EVERY)
        .map(|k| (k, truth[k][0] + sigma * noise.sample()))
        .collect()
}

/// The batch solution, started from the motion the priors' means give.
fn pendulum_batch(graph: &ChainGraph) -> Vec<f64> {
    let guess = simulate(PRIOR[0], PRIOR[1], PRIOR[2]);
    let mut values: Vec<f64> = guess
        .iter()
        .flat_map(|&[th, w, a]| [th, w, a, PRIOR[2]])
        .collect();
    let report = smoother::batch(graph, &mut values, STEPS, gauss_newton()).unwrap();
    assert_eq!(report.termination, Termination::Converged, "{report:?}");
    values
}

/// The fixed-lag smoother's estimates, each step's as it leaves the window (the
/// last `window` steps' at the end of the run); each step predicted from the one
/// before by a Taylor step at its estimated length.
fn pendulum_fixed_lag(graph: &ChainGraph, window: usize) -> Vec<f64> {
    let s = 4;
    let mut values = vec![0.0; STEPS * s];
    values[..s].copy_from_slice(&[PRIOR[0], PRIOR[1], 0.0, PRIOR[2]]);
    values[2] = -G / PRIOR[2] * PRIOR[0].sin();
    fixed_lag(
        graph,
        &mut values,
        STEPS,
        window,
        None,
        |v, k| {
            let [th, w, a, l] = [
                v[(k - 1) * s],
                v[(k - 1) * s + 1],
                v[(k - 1) * s + 2],
                v[(k - 1) * s + 3],
            ];
            let th1 = th + DT * w + 0.5 * DT * DT * a;
            v[k * s..(k + 1) * s].copy_from_slice(&[th1, w + DT * a, -G / l * th1.sin(), l]);
        },
        |k, report, _| {
            assert_eq!(
                report.termination,
                Termination::Converged,
                "step {k}: {report:?}"
            );
            Next::Continue
        },
    );
    values
}

/// σ of the estimate of L from readings of σ `sigma`: (F⁻¹)_LL of the Fisher
/// information of (θ₀, θ̇₀, L), F = SᵀS/σ² + the priors', S the readings'
/// sensitivities by central differences of the simulation.
fn length_sigma(truth0: [f64; 2], sigma: f64) -> f64 {
    let at = |p: [f64; 3]| simulate(p[0], p[1], p[2]);
    let base = [truth0[0], truth0[1], TRUE_LENGTH];
    let mut sens = vec![[0.0; 3]; STEPS];
    for j in 0..3 {
        let h = 1e-6;
        let (mut plus, mut minus) = (base, base);
        plus[j] += h;
        minus[j] -= h;
        let (a, b) = (at(plus), at(minus));
        for k in 0..STEPS {
            sens[k][j] = (a[k][0] - b[k][0]) / (2.0 * h);
        }
    }
    let mut f = [[0.0; 3]; 3];
    for k in (0..STEPS).step_by(EVERY) {
        for i in 0..3 {
            for j in 0..3 {
                f[i][j] += sens[k][i] * sens[k][j] / (sigma * sigma);
            }
        }
    }
    for i in 0..3 {
        f[i][i] += 1.0 / (PRIOR_SIGMA[i] * PRIOR_SIGMA[i]);
    }
    // (F⁻¹)_22 = cofactor / determinant.
    let det = f[0][0] * (f[1][1] * f[2][2] - f[1][2] * f[2][1])
        - f[0][1] * (f[1][0] * f[2][2] - f[1][2] * f[2][0])
        + f[0][2] * (f[1][0] * f[2][1] - f[1][1] * f[2][0]);
    ((f[0][0] * f[1][1] - f[0][1] * f[1][0]) / det).sqrt()
}

/// Largest |L_k − L_0| / L_0 over the steps of `values`.
fn spread(values: &[f64]) -> f64 {
    let l0 = values[3];
    values
        .chunks_exact(4)
        .map(|b| (b[3] - l0).abs() / l0)
        .fold(0.0, f64::max)
}

#[test]
fn pendulum_length_from_noise_free_readings() {
    let truth = simulate(0.5, 0.0, TRUE_LENGTH);
    let sigma = 1e-3;
    let graph = pendulum_graph(&readings(&truth, 0.0, 1), sigma);
    let batch = pendulum_batch(&graph);
    let length = batch[3];
    // The weak priors (centred off the truth) bias it by ~ their share of the
    // information, far below 1e-6.
    assert!(
        (length - TRUE_LENGTH).abs() <= 1e-6 * TRUE_LENGTH,
        "batch length {length}"
    );
    let drift = spread(&batch);
    eprintln!("L: batch {length:.9}, copies within {drift:.1e}");
    assert!(
        drift <= 1e-9,
        "batch copies of L differ by {drift:.1e} relative"
    );
    for (k, state) in truth.iter().enumerate() {
        assert!((batch[4 * k] - state[0]).abs() <= 1e-6, "θ at step {k}");
    }
    let lag = pendulum_fixed_lag(&graph, 10);
    let last = lag[4 * (STEPS - 1) + 3];
    eprintln!("L: batch {length:.9} fixed-lag {last:.9}");
    assert!(
        (last - length).abs() <= 1e-6 * length,
        "fixed-lag length {last} vs batch {length}"
    );
    let drift = spread(&lag[4 * (STEPS - 10)..]);
    assert!(
        drift <= 1e-9,
        "window copies of L differ by {drift:.1e} relative"
    );
}

#[test]
fn pendulum_length_from_noisy_readings() {
    let truth = simulate(0.5, 0.0, TRUE_LENGTH);
    let sigma = 0.02;
    let graph = pendulum_graph(&readings(&truth, sigma, 0x5eed_1234), sigma);
    let batch = pendulum_batch(&graph);
    let length = batch[3];
    let sd = length_sigma([0.5, 0.0], sigma);
    assert!(
        (length - TRUE_LENGTH).abs() <= 3.0 * sd,
        "batch length {length}, σ {sd:.2e}"
    );
    let drift = spread(&batch);
    assert!(
        drift <= 1e-9,
        "batch copies of L differ by {drift:.1e} relative"
    );
    let lag = pendulum_fixed_lag(&graph, 10);
    let last = lag[4 * (STEPS - 1) + 3];
    // The marginal priors were linearized where each step left the window, early
    // ones about lengths far from the last (the prior's 1.2): the smoother's
    // estimate agrees with the batch's to a fraction of σ, not to round-off.
    assert!(
        (last - length).abs() <= 0.25 * sd,
        "fixed-lag length {last} vs batch {length} (σ {sd:.2e})"
    );
    eprintln!(
        "L: batch {length:.6} fixed-lag {last:.6} σ {sd:.2e}, |Δ|/σ = {:.2e}",
        (last - length).abs() / sd
    );
}
