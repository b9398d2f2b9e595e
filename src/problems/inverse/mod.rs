//! Inverse dynamics as a factor graph (paper, sections 4.3 and 7.2): given the motion
//! of some coordinates (the actuated ones) at uniformly spaced times, find the motion
//! of all the others and the generalized forces on the actuated ones, solving the
//! whole horizon in batch.
//!
//! Per step the graph holds q, q̇, q̈ and the actuator forces Q; hard factors: the
//! position and velocity constraints, the prescribed values and their velocities and
//! accelerations, Q = 0 where nothing actuates; soft: f^d_idyn and the trapezoidal
//! integrators. The prescribed coordinates' velocities and accelerations at every
//! sample are fourth-order differences of the samples ([`Prescription::derivatives`]):
//! left to the integrators, a derivative of sampled positions carries the trapezoidal
//! rule's alternating (−1)^k mode, which nothing along the chain damps, and Q
//! oscillated with it from one step to the next (1e-5 to 5e-5 of its peak).
//!
//! The solve starts from the classical answer (position, velocity and acceleration
//! problems along the samples, then the augmented system for Q), so a single batch
//! solve converges in a few iterations.
//!
//! Measured samples ([`InverseOptions::sample_sigma`]) are smoothed first
//! ([`smoothing`]): the graph then holds the smoothed values, rates and
//! accelerations in place of the samples and their differences, and the solution's
//! standard deviations follow from the smoothing's covariance through the step's
//! equations ([`sensitivity`]).

pub mod sensitivity;
pub mod smoothing;

pub use smoothing::{ColumnFit, NoiseShape, SampleSigma, Smoothed};

use crate::coordinates::Coordinates;
use crate::error::{Error, Result};
use crate::factors::*;
use crate::graph::{ChainGraph, Layout, Noise, VarKind};
use crate::io::number;
use crate::io::Table;
use crate::kinematics;
use crate::model::Model;
use crate::smoother;
use crate::solver::{Settings, SolveReport, WindowSolver};
use crate::trajectory::Trajectory;
use std::f64::consts::PI;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// The prescribed motion: coordinates (indices in q) and their values at t₀ + k·Δt.
#[derive(Debug, Clone, PartialEq)]
pub struct Prescription {
    pub indices: Vec<usize>,
    pub t0: f64,
    pub dt: f64,
    pub steps: usize,
    /// Row-major steps × indices.len().
    pub values: Vec<f64>,
    /// The samples' own times where they are not t₀ + k·Δt (a logger's jitter); Δt
    /// is then their mean interval, the grid on which the motion is solved. Only
    /// measured samples ([`InverseOptions::sample_sigma`]) may be off the grid: they
    /// are smoothed at their own times, and the smoothed motion read on the grid.
    pub times: Option<Vec<f64>>,
}

/// Fewest samples a prescription needs (the starting derivatives use five).
pub const MIN_SAMPLES: usize = 5;

/// Relative tolerance of an interval taken as the grid's.
const UNIFORM: f64 = 1e-6;

/// The shortest interval between samples, as a fraction of their mean.
const CLOSEST_INTERVAL: f64 = 0.05;

/// Whether times t₀, …, t_{N−1} are the grid t₀ + k·Δt: every interval within 1e-6 of
/// Δt, or every time within the rounding of its printed digits of the grid (times
/// written to fixed decimals, as 300 Hz to 0.1 ms: 0, 0.0033, 0.0067, 0.01; both the
/// time and the grid's ends rounded, so within one unit of the last decimal).
fn on_grid(t: &[f64], dt: f64) -> bool {
    let exact = t
        .windows(2)
        .all(|p| ((p[1] - p[0]) - dt).abs() <= UNIFORM * dt);
    if exact {
        return true;
    }
    let Some(unit) = printed_unit(t) else {
        return false;
    };
    unit <= 0.5 * dt
        && t.iter().enumerate().all(|(k, &tk)| {
            let grid = t[0] + k as f64 * dt;
            (tk - grid).abs() <= unit * (1.0 + 1e-9) + 4.0 * f64::EPSILON * tk.abs().max(grid.abs())
        })
}

/// The unit of the last decimal the times are written to (1e-4 for 0.0033), None
/// where they need more than 12 decimals (not visibly rounded).
fn printed_unit(t: &[f64]) -> Option<f64> {
    let decimals = t
        .iter()
        .map(|v| {
            // The shortest decimal that reads back as v.
            let text = format!("{:e}", v.abs());
            let (mantissa, exponent) = text.split_once('e')?;
            let digits = mantissa.chars().filter(char::is_ascii_digit).count() as i64;
            let exponent: i64 = exponent.parse().ok()?;
            Some((digits - 1 - exponent).max(0))
        })
        .try_fold(0i64, |m, d| d.map(|d| m.max(d)))?;
    (decimals <= 12).then(|| 10f64.powi(-(decimals as i32)))
}

impl Prescription {
    /// The prescribed coordinates' indices from a header `t,<coordinate>,...`, or
    /// why it is not one; checked before a file's rows are read.
    pub fn check_header(model: &Model, columns: &[String], file: &str) -> Result<Vec<usize>> {
        let bad = |m: String| Err(Error::data_in(file, None, m));
        if columns.first().map(String::as_str) != Some("t") {
            return bad("the first column must be `t` (time, in seconds)".into());
        }
        if columns.len() < 2 {
            return bad("no prescribed coordinate: the header is `t` alone".into());
        }
        let mut indices = Vec::new();
        for name in &columns[1..] {
            let Some(i) = model.names.iter().position(|c| c == name) else {
                const SHOWN: usize = 8;
                let mut known = model.names[..model.names.len().min(SHOWN)].join(", ");
                if model.names.len() > SHOWN {
                    known += &format!(", … ({} in all: mbfg check lists them)", model.names.len());
                }
                let name = crate::expr::excerpt(name, 40);
                return bad(format!(
                    "unknown coordinate `{name}`; the scene's coordinates are {known}"
                ));
            };
            if indices.contains(&i) {
                return bad(format!("coordinate `{name}` appears twice"));
            }
            indices.push(i);
        }
        Ok(indices)
    }

    /// Reads a table with header `t,<coordinate>,...`; `file` names it in errors.
    pub fn from_table(model: &Model, table: &Table, file: &str) -> Result<Self> {
        let bad = |m: String| Err(Error::data_in(file, None, m));
        let indices = Self::check_header(model, &table.columns, file)?;
        if table.rows < MIN_SAMPLES {
            return bad(format!(
                "{} samples; at least {MIN_SAMPLES} are needed",
                table.rows
            ));
        }
        let t = table.column("t").expect("checked above");
        let dt = (t[table.rows - 1] - t[0]) / (table.rows - 1) as f64;
        for k in 1..table.rows {
            let step = t[k] - t[k - 1];
            if !(step > 0.0) {
                return bad(format!(
                    "line {}: time {} does not increase (previous {})",
                    k + 2,
                    number(t[k]),
                    number(t[k - 1])
                ));
            }
            // Two samples much closer than the rest: a duplicate, which no smoothing
            // at their own times can tell apart (the prior between them grows as the
            // interval's seventh power).
            if step < CLOSEST_INTERVAL * dt {
                return bad(format!(
                    "line {}: time {} follows the previous sample by only {} s, under {} of \
                     the mean interval {} s: a duplicated sample? remove one",
                    k + 2,
                    number(t[k]),
                    number(step),
                    number(CLOSEST_INTERVAL),
                    number(dt)
                ));
            }
        }
        let times = (!on_grid(&t, dt)).then(|| t.to_vec());
        let p = indices.len();
        let w = table.columns.len();
        let mut values = Vec::with_capacity(table.rows * p);
        for k in 0..table.rows {
            values.extend_from_slice(&table.values[k * w + 1..(k + 1) * w]);
        }
        let at = |k: usize, c: usize, m: String| {
            Err(Error::data_in(
                file,
                Some(k as u64 + 2),
                format!("column `{}`: {m}", table.columns[c + 1]),
            ))
        };
        let limit = crate::limits::MAX_COORDINATE;
        if let Some(i) = values.iter().position(|v| !(v.abs() <= limit)) {
            return at(
                i / p,
                i % p,
                format!(
                    "{} is beyond ±{} (a coordinate of the mechanism, in m or rad)",
                    number(values[i]),
                    number(limit)
                ),
            );
        }
        // An angle that turns more than π between two samples cannot be told from one
        // that turned the other way: an outlier, an angle wrapped to (−π, π], or
        // samples too far apart for the motion. Differentiated, it makes a force
        // orders of magnitude off, and a solve that crawls.
        for (c, &i) in indices.iter().enumerate() {
            if !model.is_angle(i) {
                continue;
            }
            for k in 1..table.rows {
                let jump = values[k * p + c] - values[(k - 1) * p + c];
                if jump.abs() <= PI {
                    continue;
                }
                let turns = (jump / (2.0 * PI)).round();
                let why = if turns != 0.0 && (jump - turns * 2.0 * PI).abs() < 0.5 {
                    format!(
                        "about {}2π: an angle wrapped to (−π, π]; unwrap it (take the 2π out at each jump)",
                        if turns.abs() == 1.0 { String::new() } else { format!("{}·", turns.abs()) }
                    )
                } else {
                    "an outlier, or samples too far apart for the motion: fix the sample, \
                     or sample more often"
                        .to_string()
                };
                return at(
                    k,
                    c,
                    format!(
                        "the angle changes by {} rad from the sample before, more than π in \
                         one time step ({why})",
                        number(jump)
                    ),
                );
            }
        }
        let prescription = Prescription {
            indices,
            t0: t[0],
            dt,
            steps: table.rows,
            values,
            times,
        };
        // The rates and accelerations the samples give must be finite too (a step
        // of 1e-200 s squares to nothing).
        let (rates, accelerations) = prescription.derivatives();
        if let Some(i) = rates
            .iter()
            .zip(&accelerations)
            .position(|(v, a)| !(v.is_finite() && a.is_finite()))
        {
            return at(
                i / p,
                i % p,
                format!(
                    "the samples' rate or acceleration there is not finite (time step {} s)",
                    number(dt)
                ),
            );
        }
        Ok(prescription)
    }

    /// The time of sample k: its own, or the grid's.
    pub fn sample_time(&self, k: usize) -> f64 {
        match &self.times {
            Some(t) => t[k],
            None => self.t0 + k as f64 * self.dt,
        }
    }

    /// Where the samples are off the grid: the first sample (index ≥ 1) whose
    /// interval from the one before is not Δt, and that interval.
    pub fn first_irregular(&self) -> Option<(usize, f64)> {
        let t = self.times.as_ref()?;
        (1..t.len())
            .map(|k| (k, t[k] - t[k - 1]))
            .find(|(_, step)| (step - self.dt).abs() > UNIFORM * self.dt)
            .or(Some((1, t[1] - t[0])))
    }

    /// Whether exact samples can be solved: they must be on the grid (their
    /// derivatives are differences). Else the error names the first sample off it,
    /// in `file`, and the way to smooth them at their own times.
    pub fn check_grid(&self, file: &str) -> Result<()> {
        let Some((k, step)) = self.first_irregular() else {
            return Ok(());
        };
        Err(Error::data_in(
            file,
            Some(k as u64 + 2),
            format!(
                "times are not uniformly spaced (step {} s where the mean step is {} s): exact \
                 samples need a uniform grid; measured ones are smoothed at their own times \
                 with a sample σ (--sample-sigma S or auto; sample_sigma in Python)",
                crate::io::three_digits(step),
                crate::io::three_digits(self.dt)
            ),
        ))
    }

    /// The shortest and longest interval between samples.
    pub fn interval_range(&self) -> (f64, f64) {
        (1..self.steps)
            .map(|k| self.sample_time(k) - self.sample_time(k - 1))
            .fold((f64::INFINITY, 0.0f64), |(a, b), h| (a.min(h), b.max(h)))
    }

    fn value(&self, k: usize, c: usize) -> f64 {
        self.values[k * self.indices.len() + c]
    }

    /// First and second derivatives of every prescribed coordinate at every sample
    /// (row-major steps × indices.len(), like the values), from five samples: centred
    /// fourth-order differences inside, the fourth-order (first derivative) and
    /// third-order (second) off-centre stencils at the two samples at each end. A
    /// smooth function's differences are smooth: their error has no step-to-step mode.
    pub fn derivatives(&self) -> (Vec<f64>, Vec<f64>) {
        let (h, steps, m) = (self.dt, self.steps, self.indices.len());
        // Stencils over five consecutive samples starting at `first`, for the
        // derivative at sample first + at; the last two by mirroring the first two.
        const D1: [[f64; 5]; 3] = [
            [-25.0, 48.0, -36.0, 16.0, -3.0],
            [-3.0, -10.0, 18.0, -6.0, 1.0],
            [1.0, -8.0, 0.0, 8.0, -1.0],
        ];
        const D2: [[f64; 5]; 3] = [
            [35.0, -104.0, 114.0, -56.0, 11.0],
            [11.0, -20.0, 6.0, 4.0, -1.0],
            [-1.0, 16.0, -30.0, 16.0, -1.0],
        ];
        let (mut d1, mut d2) = (vec![0.0; steps * m], vec![0.0; steps * m]);
        for k in 0..steps {
            // (first sample of the stencil, which stencil, mirrored)
            let (first, which, mirrored) = match k {
                0 | 1 => (0, k, false),
                _ if k + 2 >= steps => (steps - 5, steps - 1 - k, true),
                _ => (k - 2, 2, false),
            };
            for c in 0..m {
                let (mut a, mut b) = (0.0, 0.0);
                for j in 0..5 {
                    // Mirrored: the stencil read from the far end, the first
                    // derivative's sign flipped.
                    let sample = if mirrored { first + 4 - j } else { first + j };
                    let v = self.value(sample, c);
                    a += D1[which][j] * v;
                    b += D2[which][j] * v;
                }
                d1[k * m + c] = if mirrored { -a } else { a } / (12.0 * h);
                d2[k * m + c] = b / (12.0 * h * h);
            }
        }
        (d1, d2)
    }
}

/// σ of a weak f_eq between consecutive accelerations in the staged start
/// ([`Start::Staged`]), whose integrators get the prescribed derivatives at the first
/// sample only: it keeps the trapezoidal rule's alternating mode of q̈ from growing
/// there (σ = 1e3 already biased the double pendulum's forces to 1.6e-4 of peak).
const SMOOTHING: f64 = 1e4;

/// How the batch solve is started.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Start {
    /// The classical solution along the samples (position, velocity, acceleration
    /// problems, then the augmented system for Q): the default.
    Kinematic,
    /// The paper's four stages from the scene's initial configuration at every
    /// step: positions (priors, f_pc, f_eq); then velocities, accelerations and the
    /// integrators; then f_vc; then Q and f_idyn (the final solve).
    Staged,
}

/// Options of an inverse-dynamics solve.
#[derive(Debug, Clone, PartialEq)]
pub struct InverseOptions {
    pub start: Start,
    /// DC, or IC with z the prescribed coordinates (they must be the scene's
    /// `independent` set).
    pub coordinates: Coordinates,
    pub noise: InverseNoise,
    /// The solves' settings; the final solve always uses Gauss-Newton's model
    /// (`second_order` off: its reduced Hessian is the exact one there) and
    /// measures steps per variable (`step_per_variable`).
    pub settings: Settings,
    /// None: the samples are exact, their derivatives fourth-order differences.
    /// Some: they are readings with that noise, smoothed first ([`smoothing`]), and
    /// the solution carries standard deviations ([`InverseSolution::sigmas`]).
    pub sample_sigma: Option<SampleSigma>,
}

/// Standard deviations of the soft factors of an inverse solve. The constraint
/// factors, the prescribed motion and the priors are hard (see [`crate::solver`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct InverseNoise {
    /// σ of f^d_idyn (f^i_idyn in independent coordinates).
    pub dynamics: f64,
    /// σ of the integrator of velocities into positions (the staged start's).
    pub integrator_position: f64,
    /// σ of the integrator of accelerations into velocities (the staged start's).
    pub integrator_velocity: f64,
    /// σ of the weak f_eq between consecutive q (IC, and the staged start's first
    /// stage).
    pub equality: f64,
}

impl Default for InverseNoise {
    /// Integrators 100× stiffer than f^d_idyn. In inverse dynamics the unknown
    /// forces make the dynamics factor consistent at every step, so only the
    /// integrators carry information along the horizon; weighted 10× below f_dyn
    /// (the forward defaults) that information sinks under the dynamics' round-off
    /// on the robot, and the banded factorization loses definiteness. f_eq as weak
    /// as in a forward run by default.
    fn default() -> Self {
        InverseNoise {
            dynamics: 1.0,
            integrator_position: 0.01,
            integrator_velocity: 0.01,
            equality: 1e6,
        }
    }
}

impl Default for InverseOptions {
    fn default() -> Self {
        InverseOptions {
            start: Start::Kinematic,
            coordinates: Coordinates::Dependent,
            noise: InverseNoise::default(),
            settings: Settings {
                max_iterations: 50,
                ..Settings::default()
            },
            sample_sigma: None,
        }
    }
}

/// What an inverse solve reports beside the motion and the forces.
#[derive(Debug, Clone, PartialEq)]
pub struct InverseSummary {
    pub steps: usize,
    pub wall_time: Duration,
    pub report: SolveReport,
    /// max |q_c(t_k) − prescribed| over the prescribed coordinates.
    pub worst_tracking: f64,
    pub worst_phi: f64,
    /// What the smoothing of measured samples found, per prescribed coordinate
    /// (None without [`InverseOptions::sample_sigma`]).
    pub smoothing: Option<Vec<ColumnFit>>,
    /// Where the samples were off the grid ([`Prescription::times`]), smoothed at
    /// their own times and read on the grid: their shortest and longest interval.
    pub off_grid: Option<(f64, f64)>,
}

/// Standard deviations of a solution from measured samples, row-major steps × n
/// like the trajectory: of q, q̇, q̈ and the forces (0 where nothing acts).
#[derive(Debug, Clone, PartialEq)]
pub struct Sigmas {
    pub q: Vec<f64>,
    pub dq: Vec<f64>,
    pub ddq: Vec<f64>,
    pub forces: Vec<f64>,
}

/// The motion and the actuator forces (row-major steps × n, zero where nothing acts).
#[derive(Debug, Clone, PartialEq)]
pub struct InverseSolution {
    pub trajectory: Trajectory,
    pub forces: Vec<f64>,
    pub summary: InverseSummary,
    /// With [`InverseOptions::sample_sigma`]: the standard deviations.
    pub sigmas: Option<Sigmas>,
}

/// Solves the inverse-dynamics problem (DC or IC, per `options.coordinates`).
pub fn solve(
    model: Arc<Model>,
    prescription: &Prescription,
    options: &InverseOptions,
) -> Result<InverseSolution> {
    options.settings.validate()?;
    let start = Instant::now();
    check_prescription(&model, prescription)?;
    if options.sample_sigma.is_none() {
        prescription.check_grid("the trajectory")?;
    }
    let n = model.n();
    let (steps, idx) = (prescription.steps, &prescription.indices);
    let names: Vec<&str> = idx.iter().map(|&i| model.names[i].as_str()).collect();
    let smoothed = match &options.sample_sigma {
        None => None,
        Some(sigma) => Some(smoothing::smooth(
            &prescription.values,
            steps,
            prescription.dt,
            prescription.times.as_deref(),
            sigma,
            &names,
        )?),
    };
    // One prescribed coordinate per degree of freedom: each step's motion is known from
    // its samples (or their smoothed values), the hard constraints and the prescribed
    // derivatives, so the graph has no integrators. Kept soft beside them, their
    // truncation error pulled q̈ off the acceleration constraints (2e-6 of the forces'
    // peak on the four-bar, DC).
    let (original, prescription_times) = (prescription, prescription.times.is_some());
    let smoothed_prescription;
    let (prescription, (rates, accelerations)) = match &smoothed {
        None => (prescription, prescription.derivatives()),
        Some(s) => {
            smoothed_prescription = Prescription {
                values: s.values.clone(),
                times: None,
                ..prescription.clone()
            };
            (
                &smoothed_prescription,
                (s.rates.clone(), s.accelerations.clone()),
            )
        }
    };
    let (d1, d2) = (
        rates[..idx.len()].to_vec(),
        accelerations[..idx.len()].to_vec(),
    );
    let derivatives = (rates.as_slice(), accelerations.as_slice());
    let graph = match options.coordinates {
        Coordinates::Dependent => dependent_graph(&model, prescription, derivatives, options)?,
        Coordinates::Independent => independent_graph(&model, prescription, derivatives, options)?,
    };
    let start_blocks = match options.start {
        Start::Kinematic => kinematic_start(&model, prescription, &rates, &accelerations)?,
        Start::Staged => staged_start(&model, prescription, &d1, &d2, options)?,
    };
    let s = graph.layout().size();
    let mut values = Vec::with_capacity(steps * s);
    for k in 0..steps {
        let b = &start_blocks[k * 4 * n..(k + 1) * 4 * n];
        push_start_step(&model, idx, options.coordinates, b, &mut values);
    }
    debug_assert_eq!(values.len(), steps * s);
    // One prescribed coordinate per degree of freedom: the hard equations fix q and
    // q̇ of every step, and the soft factors are linear in what they leave free (q̈,
    // Q), so the reduced exact Hessian is Gauss-Newton's. Its central differences
    // would only add their error, at 6·d gradient passes over the horizon each.
    // A step's q̈ and Q come from one augmented system, so an entry's round-off is
    // that of its vector's largest entry: steps are measured against that.
    let settings = Settings {
        second_order: false,
        step_per_variable: true,
        ..options.settings
    };
    let mut solver = WindowSolver::new(&graph, steps, settings)?;
    solver.optimize_for_batch();
    let report = solver.solve(&graph, &mut values, 0, steps, None)?;
    let solved = Solved {
        graph: &graph,
        values: &values,
        coordinates: options.coordinates,
    };
    let (trajectory, forces, worst_tracking, worst_phi) = solved.read(&model, prescription);
    if !values.iter().all(|v| v.is_finite()) {
        return Err(Error::singular(
            "the inverse solve produced non-finite values",
        ));
    }
    let sigmas = match &smoothed {
        Some(s) => Some(sigmas(&model, idx, &trajectory, &forces, s)?),
        None => None,
    };
    let wall_time = start.elapsed();
    Ok(InverseSolution {
        trajectory,
        forces,
        summary: InverseSummary {
            steps,
            wall_time,
            report,
            worst_tracking,
            worst_phi,
            smoothing: smoothed.map(|s| s.columns),
            off_grid: prescription_times.then(|| original.interval_range()),
        },
        sigmas,
    })
}

/// The standard deviations of the solution from those of the smoothed motion, step
/// by step through [`sensitivity::Sensitivity`].
fn sigmas(
    model: &Arc<Model>,
    idx: &[usize],
    trajectory: &Trajectory,
    forces: &[f64],
    smoothed: &Smoothed,
) -> Result<Sigmas> {
    let (n, p) = (model.n(), idx.len());
    let steps = trajectory.t.len();
    let mut sens = sensitivity::Sensitivity::new(model.clone(), idx.to_vec());
    let mut out = Sigmas {
        q: Vec::with_capacity(steps * n),
        dq: Vec::with_capacity(steps * n),
        ddq: Vec::with_capacity(steps * n),
        forces: Vec::with_capacity(steps * n),
    };
    let mut x = vec![0.0; 3 * n + p];
    for k in 0..steps {
        x[..n].copy_from_slice(&trajectory.q[k * n..(k + 1) * n]);
        x[n..2 * n].copy_from_slice(&trajectory.dq[k * n..(k + 1) * n]);
        x[2 * n..3 * n].copy_from_slice(&trajectory.ddq[k * n..(k + 1) * n]);
        for (c, &i) in idx.iter().enumerate() {
            x[3 * n + c] = forces[k * n + i];
        }
        let j = sens.jacobian(trajectory.t[k], &x)?;
        // Σ_y is block diagonal by coordinate: (z_c, ż_c, z̈_c) at columns c, p + c, 2p + c.
        let variance = |row: usize| -> f64 {
            let mut v = 0.0;
            for c in 0..p {
                let cov = &smoothed.covariances[(k * p + c) * 9..(k * p + c + 1) * 9];
                for a in 0..3 {
                    for b in 0..3 {
                        v += j[(row, a * p + c)] * cov[a * 3 + b] * j[(row, b * p + c)];
                    }
                }
            }
            v.max(0.0).sqrt()
        };
        for i in 0..n {
            out.q.push(variance(i));
        }
        for i in 0..n {
            out.dq.push(variance(n + i));
        }
        for i in 0..n {
            out.ddq.push(variance(2 * n + i));
        }
        let row = out.forces.len();
        out.forces.resize(row + n, 0.0);
        for (c, &i) in idx.iter().enumerate() {
            out.forces[row + i] = variance(3 * n + c);
        }
    }
    Ok(out)
}

/// A prescription fits the mechanism: one prescribed coordinate per degree of freedom
/// (fewer leave a forward problem, more over-prescribe it), and the batch system of
/// its whole horizon fits in memory.
fn check_prescription(model: &Model, prescription: &Prescription) -> Result<()> {
    let n = model.n();
    let steps = prescription.steps;
    let idx = &prescription.indices;
    if idx.len() > model.dof() {
        return Err(Error::InvalidArgument(format!(
            "{}: {} prescribed coordinates over-prescribe a mechanism of {} degree(s) of freedom",
            model.scene.file,
            idx.len(),
            model.dof()
        )));
    }
    if idx.len() < model.dof() {
        let names: Vec<&str> = idx.iter().map(|&i| model.names[i].as_str()).collect();
        return Err(Error::InvalidArgument(format!(
            "{}: inverse dynamics needs one prescribed coordinate per degree of freedom ({}); the trajectory gives {} ({}): a motion that leaves coordinates free is a forward problem for them",
            model.scene.file,
            model.dof(),
            idx.len(),
            names.join(", ")
        )));
    }
    // The batch system of the whole horizon, roughly: each step's variables
    // (q, q̇, q̈, Q and the independent ones) and a banded Hessian three steps wide.
    let per_step = 4.0 * n as f64 + 3.0 * model.independent.len() as f64;
    crate::limits::ensure_fits(
        &format!("an inverse solve of {steps} samples of {n} coordinates"),
        8.0 * steps as f64 * per_step * (3.0 * per_step + 2.0 * model.m() as f64),
    )
}

/// A hard factor holding variable `kind` (of `size` entries) at `indices` to the
/// row-major steps × indices.len() `table` of the prescription's samples.
fn prescribed(
    prescription: &Prescription,
    kind: VarKind,
    size: usize,
    indices: Vec<usize>,
    table: Vec<f64>,
) -> Box<dyn crate::graph::Factor> {
    Box::new(PrescribedMotion::on(
        kind,
        size,
        indices,
        Arc::new(table),
        prescription.t0,
        prescription.dt,
    ))
}

/// The DC graph: per step q, q̇, q̈ and the forces on the prescribed coordinates (the
/// forces that act); the constraints and the prescribed motion with its `derivatives`
/// (rates, accelerations) hard, f^d_idyn soft.
fn dependent_graph(
    model: &Arc<Model>,
    prescription: &Prescription,
    (rates, accelerations): (&[f64], &[f64]),
    options: &InverseOptions,
) -> Result<ChainGraph> {
    let n = model.n();
    let (dt, idx) = (prescription.dt, &prescription.indices);
    let table = Arc::new(prescription.values.clone());
    let layout = Layout::new(&[
        (VarKind::Q, n),
        (VarKind::Dq, n),
        (VarKind::Ddq, n),
        (VarKind::Force, idx.len()),
    ]);
    ChainGraph::builder(layout, dt, prescription.t0)
        .step_constraint(Box::new(PositionConstraints::new(model.clone())))
        .step_constraint(Box::new(VelocityConstraints::new(model.clone())))
        .step_constraint(Box::new(PrescribedMotion::new(
            n,
            idx.clone(),
            table,
            prescription.t0,
            dt,
        )))
        .step_constraint(prescribed(
            prescription,
            VarKind::Dq,
            n,
            idx.clone(),
            rates.to_vec(),
        ))
        .step_constraint(prescribed(
            prescription,
            VarKind::Ddq,
            n,
            idx.clone(),
            accelerations.to_vec(),
        ))
        .step_soft(
            Box::new(Dynamics::inverse_on(model.clone(), idx.clone())),
            Noise::Isotropic(options.noise.dynamics),
        )
        .build()
}

/// The IC graph: per step q, q̇, q̈, the independent z, ż, z̈ (the scene's independent
/// set, in its order, which the prescription must name exactly) and a force on every
/// coordinate, zero where nothing is prescribed; the independent constraints and the
/// prescribed motion with its `derivatives` hard, f^i_idyn and a weak f_eq soft.
fn independent_graph(
    model: &Arc<Model>,
    prescription: &Prescription,
    (rates, accelerations): (&[f64], &[f64]),
    options: &InverseOptions,
) -> Result<ChainGraph> {
    let n = model.n();
    let (dt, steps, idx) = (prescription.dt, prescription.steps, &prescription.indices);
    let nm = options.noise;
    let ind = &model.independent;
    let mut sorted_p = idx.clone();
    sorted_p.sort_unstable();
    let mut sorted_i = ind.clone();
    sorted_i.sort_unstable();
    if sorted_p != sorted_i {
        let theirs = if ind.is_empty() {
            "the scene declares none: add `independent:` or use --coords dc".to_string()
        } else {
            ind.iter()
                .map(|&i| model.names[i].as_str())
                .collect::<Vec<_>>()
                .join(", ")
        };
        return Err(Error::InvalidArgument(format!(
            "{}: inverse dynamics in independent coordinates needs the prescribed coordinates to be the scene's independent ones ({theirs})",
            model.scene.file,
        )));
    }
    let unactuated: Vec<usize> = (0..n).filter(|i| !idx.contains(i)).collect();
    let f = ind.len();
    let col: Vec<usize> = ind
        .iter()
        .map(|i| idx.iter().position(|j| j == i).expect("same set"))
        .collect();
    let ztable: Vec<f64> = (0..steps)
        .flat_map(|k| col.iter().map(move |&c| prescription.value(k, c)))
        .collect();
    let reorder = |d: &[f64]| -> Vec<f64> {
        (0..steps)
            .flat_map(|k| col.iter().map(move |&c| d[k * idx.len() + c]))
            .collect()
    };
    let all: Vec<usize> = (0..f).collect();
    let layout = Layout::new(&[
        (VarKind::Q, n),
        (VarKind::Dq, n),
        (VarKind::Ddq, n),
        (VarKind::Z, f),
        (VarKind::Dz, f),
        (VarKind::Ddz, f),
        (VarKind::Force, n),
    ]);
    ChainGraph::builder(layout, dt, prescription.t0)
        .step_constraint(Box::new(IndependentPosition::new(model.clone())))
        .step_constraint(Box::new(IndependentVelocity::new(model.clone())))
        .step_constraint(Box::new(IndependentAcceleration::new(model.clone())))
        .step_constraint(Box::new(PrescribedMotion::on(
            VarKind::Z,
            f,
            all.clone(),
            Arc::new(ztable),
            prescription.t0,
            dt,
        )))
        .step_constraint(prescribed(
            prescription,
            VarKind::Dz,
            f,
            all.clone(),
            reorder(rates),
        ))
        .step_constraint(prescribed(
            prescription,
            VarKind::Ddz,
            f,
            all.clone(),
            reorder(accelerations),
        ))
        .step_constraint(Box::new(ComponentPrior::new(
            VarKind::Force,
            n,
            unactuated.clone(),
            vec![0.0; unactuated.len()],
        )))
        .step_soft(
            Box::new(IndependentDynamics::inverse(model.clone())),
            Noise::Isotropic(nm.dynamics),
        )
        .step_soft(
            Box::new(Equality::new(VarKind::Q, n)),
            Noise::Isotropic(nm.equality),
        )
        .build()
}

/// Appends one step of the solve's starting values from its start block `b` (q, q̇,
/// q̈, Q of the n coordinates) in the graph's layout: in IC also z, ż, z̈; the forces
/// on the prescribed coordinates only in DC.
fn push_start_step(
    model: &Model,
    idx: &[usize],
    coordinates: Coordinates,
    b: &[f64],
    values: &mut Vec<f64>,
) {
    let n = model.n();
    values.extend_from_slice(&b[..3 * n]);
    if coordinates == Coordinates::Independent {
        for part in 0..3 {
            values.extend(model.independent.iter().map(|&i| b[part * n + i]));
        }
    }
    match coordinates {
        Coordinates::Dependent => values.extend(idx.iter().map(|&i| b[3 * n + i])),
        Coordinates::Independent => values.extend_from_slice(&b[3 * n..]),
    }
}

/// The solved values of an inverse graph, step-major.
struct Solved<'a> {
    graph: &'a ChainGraph,
    values: &'a [f64],
    coordinates: Coordinates,
}

impl Solved<'_> {
    /// The motion, the forces on the n coordinates (row-major steps × n), the worst
    /// tracking error of the prescribed coordinates and the worst |Φ|.
    fn read(&self, model: &Model, prescription: &Prescription) -> (Trajectory, Vec<f64>, f64, f64) {
        let (n, s) = (model.n(), self.graph.layout().size());
        let (steps, idx) = (prescription.steps, &prescription.indices);
        let mut tr = Trajectory {
            names: model.names.clone(),
            t: (0..steps).map(|k| self.graph.run_time(k)).collect(),
            q: Vec::with_capacity(steps * n),
            dq: Vec::with_capacity(steps * n),
            ddq: Vec::with_capacity(steps * n),
        };
        let mut forces = Vec::with_capacity(steps * n);
        let (mut worst_tracking, mut worst_phi) = (0.0f64, 0.0f64);
        let mut phi = vec![0.0; model.m()];
        for k in 0..steps {
            let b = &self.values[k * s..(k + 1) * s];
            tr.q.extend_from_slice(&b[..n]);
            tr.dq.extend_from_slice(&b[n..2 * n]);
            tr.ddq.extend_from_slice(&b[2 * n..3 * n]);
            match self.coordinates {
                Coordinates::Dependent => {
                    let row = forces.len();
                    forces.resize(row + n, 0.0);
                    for (&i, &v) in idx.iter().zip(&b[3 * n..]) {
                        forces[row + i] = v;
                    }
                }
                Coordinates::Independent => forces.extend_from_slice(&b[s - n..]),
            }
            for (c, &i) in idx.iter().enumerate() {
                worst_tracking = worst_tracking.max((b[i] - prescription.value(k, c)).abs());
            }
            model.phi_into(&b[..n], &mut phi);
            worst_phi = phi.iter().fold(worst_phi, |w, v| w.max(v.abs()));
        }
        (tr, forces, worst_tracking, worst_phi)
    }
}

/// The classical answer along the samples: positions by the position problem with the
/// prescribed coordinates fixed (each step from a Taylor step of the previous one when
/// that step is small, so the branch is kept), their velocities and accelerations from
/// `d1`, `d2` ([`Prescription::derivatives`], row-major steps × prescribed), the other
/// coordinates' by the velocity and acceleration problems, and Q by the augmented
/// system.
fn kinematic_start(model: &Model, p: &Prescription, d1: &[f64], d2: &[f64]) -> Result<Vec<f64>> {
    let n = model.n();
    let idx = &p.indices;
    let mut out = vec![0.0; p.steps * 4 * n];
    let mut kin = kinematics::PrescribedKinematics::new(model, idx);
    let mut q = model.initial.q.as_slice().to_vec();
    let mut guess = q.clone();
    let mut force = vec![0.0; idx.len()];
    let m = idx.len();
    for (k, block) in out.chunks_exact_mut(4 * n).enumerate() {
        let t = p.t0 + k as f64 * p.dt;
        let (v, a) = (&d1[k * m..(k + 1) * m], &d2[k * m..(k + 1) * m]);
        for (c, &i) in idx.iter().enumerate() {
            q[i] = p.value(k, c);
            guess[i] = q[i];
        }
        // |Φ| is judged on the scale of the last solution (as `solve_position` would
        // from it), then Newton starts from the Taylor step, unless that step is not
        // small (near a singular configuration the velocities grow without bound).
        let tol = kinematics::position_tolerance_of(&q);
        let size = q.iter().fold(1.0f64, |m, v| m.max(v.abs()));
        if k > 0 && (0..n).all(|i| (guess[i] - q[i]).abs() <= 0.1 * size) {
            q.copy_from_slice(&guess);
        }
        let reach = |e: Error| {
            if k == 0 {
                // Newton starts from the scene's placement: where that is a singular
                // configuration of the prescribed coordinates (a pendulum drawn
                // horizontal, its x prescribed), no step leaves it for either branch.
                return Error::singular(format!(
                    "the prescribed motion's first sample (t = {t}) cannot be reached from \
                     the scene's placement: {e} (beyond the mechanism's reach, or the \
                     placement is a configuration where the prescribed coordinates do not \
                     determine the others: place the mechanism off it, on the branch wanted)"
                ));
            }
            Error::singular(format!(
                "the prescribed motion is out of the mechanism's reach at t = {t} (sample {k}): {e}"
            ))
        };
        kin.position_within(model, &mut q, tol).map_err(reach)?;
        kin.factor(model, &q).map_err(reach)?;
        let (bq, rest) = block.split_at_mut(n);
        let (bdq, rest) = rest.split_at_mut(n);
        let (bddq, bforce) = rest.split_at_mut(n);
        bq.copy_from_slice(&q);
        kin.velocity(v, bdq);
        kin.acceleration(model, &q, bdq, a, bddq);
        kin.forces(model, &q, bdq, bddq, t, &mut force)?;
        for (&i, &f) in idx.iter().zip(&force) {
            bforce[i] = f;
        }
        // The next sample's guess: a second-order Taylor step from this one (Newton
        // then mostly converges in one iteration, from the same branch).
        let h = p.dt;
        for i in 0..n {
            guess[i] = q[i] + h * bdq[i] + 0.5 * h * h * bddq[i];
        }
    }
    Ok(out)
}

/// The paper's stages 1–3 (see [`Start::Staged`]), each a batch solve started from
/// the one before; Q starts at 0. Returns steps × [q, q̇, q̈, Q] like
/// [`kinematic_start`].
fn staged_start(
    model: &Arc<Model>,
    p: &Prescription,
    d1: &[f64],
    d2: &[f64],
    options: &InverseOptions,
) -> Result<Vec<f64>> {
    let n = model.n();
    let (steps, dt, idx) = (p.steps, p.dt, &p.indices);
    let nm = options.noise;
    let table = Arc::new(p.values.clone());
    let prescribed = || -> Box<dyn crate::graph::Factor> {
        Box::new(PrescribedMotion::new(
            n,
            idx.clone(),
            table.clone(),
            p.t0,
            dt,
        ))
    };
    let stage_failed = |stage: usize, report: SolveReport| Error::NotConverged {
        what: format!("the staged start (stage {stage})"),
        report,
    };
    // Stage 1: positions only, the constraints soft (σ = 1e-6) so that
    // Levenberg-Marquardt can damp the long way from the scene's configuration (a
    // hard constraint is solved by an undamped Newton step, which diverges here).
    let g1 = ChainGraph::builder(Layout::new(&[(VarKind::Q, n)]), dt, p.t0)
        .step_soft(
            Box::new(PositionConstraints::new(model.clone())),
            Noise::Isotropic(1e-6),
        )
        .step_constraint(prescribed())
        .step_soft(
            Box::new(Equality::new(VarKind::Q, n)),
            Noise::Isotropic(nm.equality),
        )
        .build()?;
    let mut q: Vec<f64> = (0..steps)
        .flat_map(|_| model.initial.q.iter().copied())
        .collect();
    let r = smoother::batch(&g1, &mut q, steps, options.settings)?;
    if r.termination != crate::solver::Termination::Converged {
        return Err(stage_failed(1, r));
    }
    // Stages 2 and 3: velocities and accelerations, then their constraints.
    let mut x = vec![0.0; steps * 3 * n];
    for k in 0..steps {
        x[k * 3 * n..k * 3 * n + n].copy_from_slice(&q[k * n..(k + 1) * n]);
    }
    for stage in [2, 3] {
        let layout = Layout::new(&[(VarKind::Q, n), (VarKind::Dq, n), (VarKind::Ddq, n)]);
        let mut builder = ChainGraph::builder(layout, dt, p.t0)
            .step_constraint(Box::new(PositionConstraints::new(model.clone())))
            .step_constraint(prescribed())
            .step_soft(
                Box::new(Trapezoidal::new(VarKind::Q, VarKind::Dq, n, dt)),
                Noise::Isotropic(nm.integrator_position),
            )
            .step_soft(
                Box::new(Trapezoidal::new(VarKind::Dq, VarKind::Ddq, n, dt)),
                Noise::Isotropic(nm.integrator_velocity),
            )
            .step_soft(
                Box::new(Equality::new(VarKind::Ddq, n)),
                Noise::Isotropic(SMOOTHING),
            );
        if stage == 3 {
            builder = builder.step_constraint(Box::new(VelocityConstraints::new(model.clone())));
        }
        let g = builder
            .initial_constraint(Box::new(ComponentPrior::new(
                VarKind::Dq,
                n,
                idx.clone(),
                d1.to_vec(),
            )))
            .initial_constraint(Box::new(ComponentPrior::new(
                VarKind::Ddq,
                n,
                idx.clone(),
                d2.to_vec(),
            )))
            .build()?;
        let r = smoother::batch(&g, &mut x, steps, options.settings)?;
        if r.termination != crate::solver::Termination::Converged {
            return Err(stage_failed(stage, r));
        }
    }
    let mut out = Vec::with_capacity(steps * 4 * n);
    for k in 0..steps {
        out.extend_from_slice(&x[k * 3 * n..(k + 1) * 3 * n]);
        out.extend(std::iter::repeat_n(0.0, n));
    }
    Ok(out)
}

/// The exact classical solution for a prescribed motion given with its derivatives:
/// `motion(t)` returns (values, first, second derivatives) of the prescribed
/// coordinates. Used by tests as an independent answer (feature `testing`).
#[cfg(feature = "testing")]
pub fn classical(
    model: &Model,
    indices: &[usize],
    times: &[f64],
    motion: impl Fn(f64) -> (Vec<f64>, Vec<f64>, Vec<f64>),
) -> Result<InverseSolutionClassical> {
    let n = model.n();
    let mut q = model.initial.q.clone();
    let mut out = InverseSolutionClassical {
        q: Vec::new(),
        forces: Vec::new(),
    };
    for &t in times {
        let (x, v, a) = motion(t);
        for (c, &i) in indices.iter().enumerate() {
            q[i] = x[c];
        }
        kinematics::solve_position(model, &mut q, indices)?;
        let dq = kinematics::solve_velocity(model, &q, indices, &v)?;
        let ddq = kinematics::solve_acceleration(model, &q, &dq, indices, &a)?;
        let f = crate::dynamics::actuator_forces(model, &q, &dq, &ddq, t, indices)?;
        out.q.extend_from_slice(q.as_slice());
        out.forces.extend_from_slice(f.as_slice());
        debug_assert_eq!(f.len(), n);
    }
    Ok(out)
}

/// Positions and actuator forces of [`classical`], row-major samples × n.
#[cfg(feature = "testing")]
#[derive(Debug, Clone, PartialEq)]
pub struct InverseSolutionClassical {
    pub q: Vec<f64>,
    pub forces: Vec<f64>,
}
