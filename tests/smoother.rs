//! The fixed-lag smoother marginalizes for real: on a linear-Gaussian chain its newest
//! estimate equals the batch solution of the graph up to that step, for every window.

use mbfg::error::Result;
use mbfg::factors::{Prior, Trapezoidal};
use mbfg::graph::{ChainGraph, Factor, Key, Layout, Noise, VarKind, Workspace};
use mbfg::smoother::{self, FixedLag, Hooks, Next};
use mbfg::solver::{Method, Settings, SolveReport, Termination};

/// e = A x_t + B x_{t−1} − y(t): a linear factor coupling two steps, with a
/// time-varying target so that every step carries different information.
struct Linear {
    keys: [Key; 2],
    a: [[f64; 2]; 2],
    b: [[f64; 2]; 2],
}

impl Factor for Linear {
    fn name(&self) -> &str {
        "linear"
    }
    fn keys(&self) -> &[Key] {
        &self.keys
    }
    fn size(&self, _key: usize) -> usize {
        2
    }
    fn dim(&self) -> usize {
        2
    }
    fn evaluate(
        &self,
        t: f64,
        x: &[&[f64]],
        r: &mut [f64],
        jac: Option<&mut [Vec<f64>]>,
        _ws: &mut Workspace,
    ) -> Result<()> {
        let y = [(3.0 * t).sin(), (2.0 * t).cos() + t];
        for i in 0..2 {
            r[i] = self.a[i][0] * x[0][0]
                + self.a[i][1] * x[0][1]
                + self.b[i][0] * x[1][0]
                + self.b[i][1] * x[1][1]
                - y[i];
        }
        if let Some(j) = jac {
            for i in 0..2 {
                for k in 0..2 {
                    j[0][i * 2 + k] = self.a[i][k];
                    j[1][i * 2 + k] = self.b[i][k];
                }
            }
        }
        Ok(())
    }
}

/// A unary linear factor on the velocity: e = C v_t − w(t).
struct Observe {
    keys: [Key; 1],
}

impl Factor for Observe {
    fn name(&self) -> &str {
        "observe"
    }
    fn keys(&self) -> &[Key] {
        &self.keys
    }
    fn size(&self, _key: usize) -> usize {
        2
    }
    fn dim(&self) -> usize {
        1
    }
    fn evaluate(
        &self,
        t: f64,
        x: &[&[f64]],
        r: &mut [f64],
        jac: Option<&mut [Vec<f64>]>,
        _ws: &mut Workspace,
    ) -> Result<()> {
        r[0] = x[0][0] - 2.0 * x[0][1] - (5.0 * t).sin();
        if let Some(j) = jac {
            j[0].copy_from_slice(&[1.0, -2.0]);
        }
        Ok(())
    }
}

fn chain() -> ChainGraph {
    let layout = Layout::new(&[(VarKind::Q, 2), (VarKind::Dq, 2)]);
    ChainGraph::builder(layout, 0.1, 0.0)
        .step_soft(
            Box::new(Trapezoidal::new(VarKind::Q, VarKind::Dq, 2, 0.1)),
            Noise::Isotropic(0.05),
        )
        .step_soft(
            Box::new(Linear {
                keys: [Key::now(VarKind::Q), Key::before(VarKind::Dq)],
                a: [[1.0, 0.5], [-0.3, 2.0]],
                b: [[0.2, -1.0], [0.7, 0.1]],
            }),
            Noise::Diagonal(vec![0.3, 0.7]),
        )
        .step_soft(
            Box::new(Observe {
                keys: [Key::now(VarKind::Dq)],
            }),
            Noise::Isotropic(0.2),
        )
        .initial_soft(
            Box::new(Prior::new(VarKind::Q, vec![1.0, -0.5])),
            Noise::Isotropic(0.1),
        )
        .initial_soft(
            Box::new(Prior::new(VarKind::Dq, vec![0.0, 0.3])),
            Noise::Diagonal(vec![0.5, 0.25]),
        )
        .build()
        .unwrap()
}

fn settings() -> Settings {
    Settings {
        method: Method::GaussNewton,
        ..Settings::default()
    }
}

/// The hooks of these runs: each step's guess is the step before, each newest
/// estimate is kept, and the steps handed out final are collected.
#[derive(Default)]
struct Recorder {
    s: usize,
    newest: Vec<Vec<f64>>,
    finals: Vec<(usize, Vec<f64>)>,
    all_converged: bool,
}

impl Recorder {
    fn new(s: usize) -> Self {
        Recorder {
            s,
            all_converged: true,
            ..Recorder::default()
        }
    }
}

impl Hooks for Recorder {
    fn predict(&mut self, v: &mut [f64], k: usize) {
        let s = self.s;
        let (prev, next) = v.split_at_mut(k * s);
        next[..s].copy_from_slice(&prev[(k - 1) * s..]);
    }

    fn on_step(&mut self, k: usize, _: usize, report: &SolveReport, v: &[f64]) -> Next {
        self.all_converged &= report.termination == Termination::Converged;
        self.newest.push(v[k * self.s..(k + 1) * self.s].to_vec());
        Next::Continue
    }

    fn on_final(&mut self, j: usize, block: &[f64]) -> Result<()> {
        self.finals.push((j, block.to_vec()));
        Ok(())
    }
}

fn horizon(steps: usize, window: usize, capacity: Option<usize>) -> FixedLag {
    FixedLag {
        steps,
        window,
        settings: settings(),
        capacity,
    }
}

#[test]
fn newest_smoother_estimate_equals_the_batch_solution() {
    let graph = chain();
    let s = graph.layout().size();
    let steps = 25;
    for window in [1, 2, 3, 5, 10, 30] {
        let mut values = vec![0.0; steps * s];
        let mut hooks = Recorder::new(s);
        smoother::fixed_lag(
            &graph,
            &mut values,
            &horizon(steps, window, None),
            &mut hooks,
        )
        .unwrap();
        assert!(hooks.all_converged, "window {window}");
        let newest = hooks.newest;
        for k in 0..steps {
            let mut batch = vec![0.0; (k + 1) * s];
            let report = smoother::batch(&graph, &mut batch, k + 1, settings()).unwrap();
            assert_eq!(report.termination, Termination::Converged);
            let expect = &batch[k * s..];
            for i in 0..s {
                let err = (newest[k][i] - expect[i]).abs();
                assert!(
                    err <= 1e-10 * expect[i].abs().max(1.0),
                    "window {window}, step {k}, unknown {i}: smoother {} vs batch {} (error {err:.2e})",
                    newest[k][i],
                    expect[i]
                );
            }
        }
    }
}

#[test]
fn smoother_with_whole_horizon_window_reproduces_the_batch_everywhere() {
    let graph = chain();
    let s = graph.layout().size();
    let steps = 12;
    let mut values = vec![0.0; steps * s];
    let mut hooks = Recorder::new(s);
    smoother::fixed_lag(
        &graph,
        &mut values,
        &horizon(steps, steps, None),
        &mut hooks,
    )
    .unwrap();
    let mut batch = vec![0.0; steps * s];
    smoother::batch(&graph, &mut batch, steps, settings()).unwrap();
    for (a, b) in values.iter().zip(&batch) {
        assert!((a - b).abs() < 1e-10 * b.abs().max(1.0));
    }
}

#[test]
fn a_streaming_run_in_a_small_buffer_equals_the_run_in_place_to_the_bit() {
    // A buffer of 7 steps over 60: the window moves to the buffer's start every few
    // steps, and each step leaves through `on_final` with the bits it has in place.
    let graph = chain();
    let s = graph.layout().size();
    let steps = 60;
    for window in [1, 3] {
        let mut in_place = vec![0.0; steps * s];
        let mut first = Recorder::new(s);
        smoother::fixed_lag(
            &graph,
            &mut in_place,
            &horizon(steps, window, None),
            &mut first,
        )
        .unwrap();
        let newest_in_place = first.newest;
        let capacity = window + 4;
        let mut buffer = vec![0.0; capacity * s];
        let mut streamed = Recorder::new(s);
        let end = smoother::fixed_lag(
            &graph,
            &mut buffer,
            &horizon(steps, window, Some(capacity)),
            &mut streamed,
        )
        .unwrap();
        let (base, handed) = (end.base, end.handed);
        let (newest, mut finals) = (streamed.newest, streamed.finals);
        assert!(base > 0, "window {window}: the buffer was never compacted");
        assert_eq!(
            newest, newest_in_place,
            "window {window}: the newest estimates"
        );
        // Handed out in order, then the rest from the buffer.
        let handed_steps: Vec<usize> = finals.iter().map(|(j, _)| *j).collect();
        assert_eq!(handed_steps, (0..handed).collect::<Vec<_>>());
        for j in handed..steps {
            finals.push((j, buffer[(j - base) * s..(j - base + 1) * s].to_vec()));
        }
        for (j, block) in &finals {
            let expect = &in_place[j * s..(j + 1) * s];
            assert!(
                block
                    .iter()
                    .zip(expect)
                    .all(|(a, b)| a.to_bits() == b.to_bits()),
                "window {window}, step {j}: {block:?} vs {expect:?}"
            );
        }
    }
}
