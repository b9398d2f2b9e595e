//! Sparse nonlinear least squares over a window of time steps of a [`ChainGraph`]:
//! Gauss-Newton or Levenberg-Marquardt on the block-tridiagonal normal equations, and
//! the marginalization that turns the oldest step of a window into a Gaussian prior on
//! the next one (the Schur complement of the linearized system).

use crate::error::{Error, Result};
use crate::graph::{ChainGraph, Factor, Workspace};
use crate::linalg::banded::{BandedCholesky, BlockTridiagonal};

/// The nonlinear least-squares method.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Method {
    GaussNewton,
    LevenbergMarquardt,
}

/// Stopping rules. A solve stops when an undamped step satisfies
/// |δᵢ| ≤ `step_tolerance`·(1 + |xᵢ|) for every component, or is predicted to lower
/// the cost by less than 1e-6 of itself plus 1e-20 (converged), after `max_iterations` linear
/// solves (iteration limit), or when the cost is not finite or LM's damping exceeds
/// 1e16 without progress (diverged).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Settings {
    pub method: Method,
    pub max_iterations: usize,
    pub step_tolerance: f64,
    /// LM's damping when a step first fails, relative to the diagonal of the normal
    /// equations (solves start undamped).
    pub initial_damping: f64,
}

impl Default for Settings {
    fn default() -> Self {
        Settings {
            method: Method::LevenbergMarquardt,
            max_iterations: 50,
            step_tolerance: 1e-10,
            initial_damping: 1e-4,
        }
    }
}

impl Settings {
    /// Refuses settings that make no sense.
    pub fn validate(&self) -> Result<()> {
        if self.max_iterations == 0 {
            return Err(Error::InvalidArgument(
                "max_iterations must be at least 1".into(),
            ));
        }
        if !(self.step_tolerance > 0.0 && self.step_tolerance < 1.0) {
            return Err(Error::InvalidArgument(format!(
                "step_tolerance must be in (0, 1), got {}",
                self.step_tolerance
            )));
        }
        if !(self.initial_damping >= 0.0 && self.initial_damping.is_finite()) {
            return Err(Error::InvalidArgument(format!(
                "initial_damping must be ≥ 0, got {}",
                self.initial_damping
            )));
        }
        Ok(())
    }
}

/// Why a solve stopped.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Termination {
    Converged,
    IterationLimit,
    Diverged,
}

impl std::fmt::Display for Termination {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Termination::Converged => "converged",
            Termination::IterationLimit => "iteration limit",
            Termination::Diverged => "diverged",
        })
    }
}

/// The outcome of one solve.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SolveReport {
    /// Linear solves performed.
    pub iterations: usize,
    pub termination: Termination,
    /// ½ Σ‖whitened residual‖² at the returned estimate (prior included).
    pub cost: f64,
}

/// A Gaussian prior on one step's block left by marginalization, in square-root form:
/// ½‖R δ + e‖² with δ = x − x̄ (so Λ = RᵀR and b = Rᵀe). The cost of a prior with
/// large information is a sum of squares, not a difference of large terms, so it
/// stays accurate to round-off near the optimum.
#[derive(Debug, Clone, PartialEq)]
pub struct LinearPrior {
    /// Row-major rows × s.
    pub r: Vec<f64>,
    pub rows: usize,
    pub e: Vec<f64>,
    pub xbar: Vec<f64>,
}

/// Buffers of one factor: residual and Jacobian blocks.
struct FactorBuffers {
    r: Vec<f64>,
    jac: Vec<Vec<f64>>,
}

impl FactorBuffers {
    fn new(graph: &ChainGraph, f: &dyn Factor) -> Self {
        FactorBuffers {
            r: vec![0.0; f.dim()],
            jac: f
                .keys()
                .iter()
                .map(|k| {
                    let (_, d) = graph.layout.slot(k.kind).unwrap_or((0, 0));
                    vec![0.0; f.dim() * d]
                })
                .collect(),
        }
    }
}

/// Which factors a linearization takes.
#[derive(Clone, Copy)]
enum Scope {
    /// Every factor inside the window [k0, k1).
    Window,
    /// Only the factors touching step k0 (for its marginalization; k1 = k0 + 2).
    Oldest,
}

/// A reusable solver for windows of up to `capacity` steps; it allocates once.
pub struct WindowSolver {
    settings: Settings,
    s: usize,
    h: BlockTridiagonal,
    chol: BandedCholesky,
    g: Vec<f64>,
    delta: Vec<f64>,
    damping: Vec<f64>,
    saved: Vec<f64>,
    hd: Vec<f64>,
    step_buffers: Vec<FactorBuffers>,
    initial_buffers: Vec<FactorBuffers>,
    ws: Workspace,
    scratch: Vec<f64>,
    /// Whitened rows [J over blocks k0, k0+1 | r] collected for marginalization.
    rows: Vec<f64>,
}

impl WindowSolver {
    pub fn new(graph: &ChainGraph, capacity: usize, settings: Settings) -> Result<Self> {
        settings.validate()?;
        for f in graph.step_factors.iter().chain(&graph.initial_factors) {
            f.noise()
                .validate(f.dim())
                .map_err(|e| Error::InvalidArgument(format!("noise of {}: {e}", f.name())))?;
            for k in f.keys() {
                if graph.layout.slot(k.kind).is_none() || k.lag > 1 {
                    return Err(Error::InvalidArgument(format!(
                        "factor {} touches {}(lag {}), which the graph does not hold",
                        f.name(),
                        k.kind.symbol(),
                        k.lag
                    )));
                }
            }
        }
        let s = graph.layout.size();
        let capacity = capacity.max(2);
        let n = capacity * s;
        Ok(WindowSolver {
            settings,
            s,
            h: BlockTridiagonal::new(capacity, s),
            chol: BandedCholesky::new(capacity, s),
            g: vec![0.0; n],
            delta: vec![0.0; n],
            damping: vec![0.0; n],
            saved: vec![0.0; n],
            hd: vec![0.0; n],
            step_buffers: graph
                .step_factors
                .iter()
                .map(|f| FactorBuffers::new(graph, f.as_ref()))
                .collect(),
            initial_buffers: graph
                .initial_factors
                .iter()
                .map(|f| FactorBuffers::new(graph, f.as_ref()))
                .collect(),
            ws: graph.workspace(),
            scratch: vec![0.0; 4 * s * s + 2 * s],
            rows: Vec::new(),
        })
    }

    pub fn settings(&self) -> &Settings {
        &self.settings
    }

    /// Evaluates the factors of a scope at `values` (the whole trajectory, step-major)
    /// and returns the cost; with `linearize`, also fills H and g for the blocks
    /// k0..k1.
    #[allow(clippy::too_many_arguments)]
    fn evaluate(
        &mut self,
        graph: &ChainGraph,
        values: &[f64],
        k0: usize,
        k1: usize,
        prior: Option<&LinearPrior>,
        scope: Scope,
        linearize: bool,
    ) -> Result<f64> {
        let s = self.s;
        let blocks = k1 - k0;
        if linearize {
            self.h.reset(blocks);
            self.g[..blocks * s].fill(0.0);
        }
        let mut cost = 0.0;
        let initial = k0 == 0;
        for (list, is_initial) in [(&graph.step_factors, false), (&graph.initial_factors, true)] {
            if is_initial && !initial {
                continue;
            }
            for (fi, factor) in list.iter().enumerate() {
                let steps: &[usize] = if is_initial { &[0] } else { &[] };
                let range = if is_initial { 0..0 } else { k0..k1 };
                for step in steps.iter().copied().chain(range) {
                    let keys = factor.keys();
                    let max_lag = keys.iter().map(|k| k.lag).max().unwrap_or(0);
                    if step < k0 + max_lag {
                        continue; // touches a step outside the window
                    }
                    if let Scope::Oldest = scope {
                        let touches_oldest = keys.iter().any(|k| step - k.lag == k0);
                        if !touches_oldest {
                            continue;
                        }
                    }
                    let buf = if is_initial {
                        &mut self.initial_buffers[fi]
                    } else {
                        &mut self.step_buffers[fi]
                    };
                    let mut xs: [&[f64]; 8] = [&[]; 8];
                    for (slot, k) in xs.iter_mut().zip(keys) {
                        let (off, d) = graph.layout.slot(k.kind).unwrap_or((0, 0));
                        let base = (step - k.lag) * s + off;
                        *slot = &values[base..base + d];
                    }
                    let t = graph.time(step);
                    factor
                        .evaluate(
                            t,
                            &xs[..keys.len()],
                            &mut buf.r,
                            linearize.then_some(buf.jac.as_mut_slice()),
                            &mut self.ws,
                        )
                        .map_err(|e| match e {
                            Error::Singular(m) => Error::Singular(format!(
                                "{} at step {step} (t = {t}): {m}",
                                factor.name()
                            )),
                            other => other,
                        })?;
                    let noise = factor.noise();
                    let dim = factor.dim();
                    for i in 0..dim {
                        let w = noise.weight(i);
                        buf.r[i] *= w;
                        cost += 0.5 * buf.r[i] * buf.r[i];
                        if linearize {
                            for (ki, k) in keys.iter().enumerate() {
                                let (_, d) = graph.layout.slot(k.kind).unwrap_or((0, 0));
                                for v in &mut buf.jac[ki][i * d..(i + 1) * d] {
                                    *v *= w;
                                }
                            }
                        }
                    }
                    if linearize {
                        accumulate(&mut self.h, &mut self.g, graph, keys, step - k0, buf, s);
                        if let Scope::Oldest = scope {
                            collect_rows(&mut self.rows, graph, keys, step - k0, buf, s);
                        }
                    }
                }
            }
        }
        if let Some(p) = prior {
            let x = &values[k0 * s..(k0 + 1) * s];
            let (d, res) = self.scratch.split_at_mut(s);
            for i in 0..s {
                d[i] = x[i] - p.xbar[i];
            }
            let res = &mut res[..p.rows];
            for (i, ri) in res.iter_mut().enumerate() {
                let row = &p.r[i * s..(i + 1) * s];
                *ri = p.e[i] + row.iter().zip(d.iter()).map(|(a, b)| a * b).sum::<f64>();
                cost += 0.5 * *ri * *ri;
            }
            if linearize && matches!(scope, Scope::Oldest) {
                for (i, &ri) in res.iter().enumerate() {
                    self.rows.extend_from_slice(&p.r[i * s..(i + 1) * s]);
                    self.rows.extend(std::iter::repeat_n(0.0, s));
                    self.rows.push(ri);
                }
            }
            if linearize {
                let h0 = self.h.diag_mut(0);
                for (i, &ri) in res.iter().enumerate() {
                    let row = &p.r[i * s..(i + 1) * s];
                    for a in 0..s {
                        self.g[a] += row[a] * ri;
                        for b in 0..s {
                            h0[a * s + b] += row[a] * row[b];
                        }
                    }
                }
            }
        }
        if !cost.is_finite() {
            return Err(Error::Singular("the cost is not finite".into()));
        }
        Ok(cost)
    }

    /// Optimizes steps k0..k1 of `values` (step-major, the whole trajectory) with an
    /// optional prior on step k0; the rest of `values` is read, not changed.
    pub fn solve(
        &mut self,
        graph: &ChainGraph,
        values: &mut [f64],
        k0: usize,
        k1: usize,
        prior: Option<&LinearPrior>,
    ) -> Result<SolveReport> {
        if k1 <= k0 || k1 - k0 > self.h.capacity() {
            return Err(Error::InvalidArgument(format!(
                "window {k0}..{k1} is empty or larger than the solver's capacity {}",
                self.h.capacity()
            )));
        }
        let s = self.s;
        let n = (k1 - k0) * s;
        let lm = self.settings.method == Method::LevenbergMarquardt;
        // Start undamped: with a good guess the Gauss-Newton step is accepted; damping
        // (relative to diag H) is switched on only when a step fails to lower the cost.
        let mut mu: f64 = 0.0;
        let mut nu = 2.0;
        let diverged = |cost: f64, iterations| SolveReport {
            iterations,
            termination: Termination::Diverged,
            cost,
        };
        let mut cost = match self.evaluate(graph, values, k0, k1, prior, Scope::Window, true) {
            Ok(c) => c,
            Err(_) => return Ok(diverged(f64::INFINITY, 0)),
        };
        let mut iterations = 0;
        while iterations < self.settings.max_iterations {
            iterations += 1;
            for i in 0..n {
                let (b, r) = (i / s, i % s);
                let d = self.h.diag(b)[r * s + r];
                self.damping[i] = mu * d.max(1e-12);
            }
            if self
                .chol
                .factor(&self.h, if lm { &self.damping[..n] } else { &[] })
                .is_err()
            {
                if !lm || mu > 1e16 {
                    return Ok(diverged(cost, iterations));
                }
                mu = (mu * 10.0).max(self.settings.initial_damping);
                continue;
            }
            for i in 0..n {
                self.delta[i] = -self.g[i];
            }
            self.chol.solve(&mut self.delta[..n]);
            let window = &mut values[k0 * s..k1 * s];
            self.saved[..n].copy_from_slice(window);
            let mut small = true;
            for i in 0..n {
                let x = window[i];
                small &= self.delta[i].abs() <= self.settings.step_tolerance * (1.0 + x.abs());
                window[i] = x + self.delta[i];
            }
            let trial = self.evaluate(graph, values, k0, k1, prior, Scope::Window, false);
            // Converged when an undamped step is small, or when the decrease the linear
            // model predicts (−gᵀδ − ½δᵀHδ) is negligible against the cost. A small
            // damped step proves nothing: damping alone can make it small.
            self.h.multiply(&self.delta[..n], &mut self.hd[..n]);
            let predicted: f64 = (0..n)
                .map(|i| -self.g[i] * self.delta[i] - 0.5 * self.delta[i] * self.hd[i])
                .sum();
            let flat = predicted <= 1e-6 * cost.abs() + 1e-20;
            let converged = (small || flat) && mu == 0.0;

            match trial {
                Ok(c) if converged || c <= cost || !lm => {
                    if converged {
                        return Ok(SolveReport {
                            iterations,
                            termination: Termination::Converged,
                            cost: c,
                        });
                    }
                    // Relinearize at the accepted point.
                    cost = match self.evaluate(graph, values, k0, k1, prior, Scope::Window, true) {
                        Ok(c) => c,
                        Err(_) => return Ok(diverged(f64::INFINITY, iterations)),
                    };
                    mu = if mu < 1e-12 { 0.0 } else { mu / 3.0 };
                    nu = 2.0;
                }
                _ => {
                    values[k0 * s..k1 * s].copy_from_slice(&self.saved[..n]);
                    if !lm {
                        return Ok(diverged(cost, iterations));
                    }
                    if small {
                        // The damped step vanished without lowering the cost: try the
                        // undamped one again.
                        mu = 0.0;
                        continue;
                    }
                    mu = (mu * nu).max(self.settings.initial_damping);
                    nu *= 2.0;
                    if mu > 1e16 {
                        return Ok(diverged(cost, iterations));
                    }
                    // H and g still hold the linearization at the restored point.
                }
            }
        }
        Ok(SolveReport {
            iterations,
            termination: Termination::IterationLimit,
            cost,
        })
    }

    /// Marginalizes step k0 (with `prior` on it, if any) into a prior on step k0+1:
    /// the factors touching k0 are linearized at `values` and their whitened rows
    /// [J₀ J₁ | r] reduced by a QR factorization; the rows left without k0 form the
    /// square-root prior ½‖R₁₁ δ₁ + e₁‖². This is the Schur complement
    /// Λ = H₁₁ − H₁₀H₀₀⁻¹H₀₁ of the normal equations, computed without squaring
    /// their condition number (hard constraints make it large).
    pub fn marginalize(
        &mut self,
        graph: &ChainGraph,
        values: &[f64],
        k0: usize,
        prior: Option<&LinearPrior>,
    ) -> Result<LinearPrior> {
        let s = self.s;
        self.rows.clear();
        self.evaluate(graph, values, k0, k0 + 2, prior, Scope::Oldest, true)?;
        let width = 2 * s + 1;
        let nrows = self.rows.len() / width;
        let mut a = nalgebra::DMatrix::from_row_slice(nrows, width, &self.rows);
        // Householder QR of [J₀ J₁ | r], column by column; the augmented column
        // carries Qᵀr along.
        let cols = (2 * s).min(nrows);
        for k in 0..cols {
            let norm = a.view((k, k), (nrows - k, 1)).norm();
            if norm == 0.0 {
                continue;
            }
            let alpha = if a[(k, k)] > 0.0 { -norm } else { norm };
            let mut v = a.view((k, k), (nrows - k, 1)).into_owned();
            v[0] -= alpha;
            let vnorm2 = v.norm_squared();
            if vnorm2 == 0.0 {
                continue;
            }
            for j in k..width {
                let dot: f64 = (0..nrows - k).map(|i| v[i] * a[(k + i, j)]).sum();
                let f = 2.0 * dot / vnorm2;
                for i in 0..nrows - k {
                    a[(k + i, j)] -= f * v[i];
                }
            }
        }
        // Rows s..2s of the triangle involve only block k0+1.
        let rows = cols.saturating_sub(s);
        let mut r = Vec::with_capacity(rows * s);
        let mut e = Vec::with_capacity(rows);
        for i in s..s + rows {
            for j in 0..s {
                r.push(a[(i, s + j)]);
            }
            e.push(a[(i, 2 * s)]);
        }
        if !r.iter().chain(&e).all(|v| v.is_finite()) {
            return Err(Error::Singular(format!(
                "marginalizing step {k0}: non-finite values"
            )));
        }
        Ok(LinearPrior {
            r,
            rows,
            e,
            xbar: values[(k0 + 1) * s..(k0 + 2) * s].to_vec(),
        })
    }
}

/// Appends a whitened factor's rows [J over blocks 0, 1 of the pair | r].
fn collect_rows(
    rows: &mut Vec<f64>,
    graph: &ChainGraph,
    keys: &[crate::graph::Key],
    step: usize,
    buf: &FactorBuffers,
    s: usize,
) {
    let width = 2 * s + 1;
    for r in 0..buf.r.len() {
        let start = rows.len();
        rows.extend(std::iter::repeat_n(0.0, width));
        let row = &mut rows[start..];
        for (a, k) in keys.iter().enumerate() {
            let (off, d) = graph.layout.slot(k.kind).unwrap_or((0, 0));
            let block = step - k.lag;
            for i in 0..d {
                row[block * s + off + i] += buf.jac[a][r * d + i];
            }
        }
        row[2 * s] = buf.r[r];
    }
}

/// Adds a whitened factor's JᵀJ and Jᵀr into the block-tridiagonal system; `step` is
/// the factor's step relative to the window start.
fn accumulate(
    h: &mut BlockTridiagonal,
    g: &mut [f64],
    graph: &ChainGraph,
    keys: &[crate::graph::Key],
    step: usize,
    buf: &FactorBuffers,
    s: usize,
) {
    let dim = buf.r.len();
    for (a, ka) in keys.iter().enumerate() {
        let (oa, da) = graph.layout.slot(ka.kind).unwrap_or((0, 0));
        let ba = step - ka.lag;
        let ja = &buf.jac[a];
        for i in 0..da {
            let mut acc = 0.0;
            for r in 0..dim {
                acc += ja[r * da + i] * buf.r[r];
            }
            g[ba * s + oa + i] += acc;
        }
        for (b, kb) in keys.iter().enumerate() {
            let bb = step - kb.lag;
            if ba < bb {
                continue; // the upper block is the transpose of a lower one
            }
            let (ob, db) = graph.layout.slot(kb.kind).unwrap_or((0, 0));
            let jb = &buf.jac[b];
            let block = if ba == bb {
                h.diag_mut(ba)
            } else {
                h.lower_mut(ba)
            };
            for i in 0..da {
                for j in 0..db {
                    let mut acc = 0.0;
                    for r in 0..dim {
                        acc += ja[r * da + i] * jb[r * db + j];
                    }
                    block[(oa + i) * s + ob + j] += acc;
                }
            }
        }
    }
}
