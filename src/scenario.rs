//! Small valid scenes made from arbitrary bytes, run through what the command line
//! runs (assembly and the check's figures, forward runs in DC and IC with each
//! integrator, an inverse solve) under a budget, and the oracle that judges them: no
//! non-finite output, one-line errors, a converged run's |Φ| and energy balance
//! plausible or warned of, and every load's derivatives equal to finite differences.
//! The structured fuzz target (`fuzz/fuzz_targets/runs.rs`) and `tests/scenario.rs`
//! call it; [`judge_with`] takes the derivatives to check from its caller, so that a
//! test can show the oracle catching a wrong one.

use crate::forward::{self, Coordinates, ForwardOptions, Trajectory};
use crate::inverse::{self, InverseOptions, Prescription};
use crate::model::forces::Force;
use crate::smoother::Mode;
use crate::{Model, Scene};
use std::sync::Arc;

/// The choices a scene is made of, read from bytes (zeros once they run out).
pub struct Choices<'a> {
    bytes: &'a [u8],
    at: usize,
}

impl<'a> Choices<'a> {
    pub fn new(bytes: &'a [u8]) -> Self {
        Choices { bytes, at: 0 }
    }

    fn byte(&mut self) -> u8 {
        let b = self.bytes.get(self.at).copied().unwrap_or(0);
        self.at += 1;
        b
    }

    /// One of `n` choices.
    fn pick(&mut self, n: usize) -> usize {
        self.byte() as usize % n
    }

    /// A value in [lo, hi], in 256 levels.
    fn within(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * f64::from(self.byte()) / 255.0
    }
}

/// Torques on the crank angle `theta`: smooth in t, θ and θ̇ (their derivatives are
/// compared with finite differences), of every kind the expression loads take.
/// `K` stands for the scale chosen.
const TORQUES: [&str; 6] = [
    "K*sin(3*t)",
    "-K*theta",
    "-K*rate(theta)",
    "K*cos(theta)",
    "K*exp(-t)*sin(theta)",
    "-K*rate(theta)^3/(1 + rate(theta)^2)",
];

/// A chain of one to three links hanging from a fixed point (the first link's angle
/// `theta` declared independent), or a four-bar, with gravity and, as chosen, a
/// spring-damper from the ground to the last point, a rotational spring-damper and a
/// torque on `theta`, and a force on the last point.
pub fn scene_text(c: &mut Choices) -> String {
    let mut points = vec!["  - {name: A, x: 0, y: 0, fixed: true}".to_string()];
    let mut bodies = Vec::new();
    // Every link's angle, the crank's `theta` first: as many independent coordinates
    // as degrees of freedom.
    let mut angles = vec!["  - {name: theta, type: angle, points: [A, P1]}".to_string()];
    let mut independent = vec!["theta".to_string()];
    let four_bar = c.pick(4) == 0;
    let last;
    if four_bar {
        // The paper's four-bar, scaled, its rocker drawn to its length.
        let s = c.within(0.2, 3.0);
        points.push(format!("  - {{name: P1, x: {s}, y: 0}}"));
        points.push(format!("  - {{name: P2, x: {s}, y: {}}}", 2.0 * s));
        points.push(format!(
            "  - {{name: B, x: {}, y: 0, fixed: true}}",
            4.0 * s
        ));
        for (name, ends) in [
            ("crank", "[A, P1]"),
            ("coupler", "[P1, P2]"),
            ("rocker", "[P2, B]"),
        ] {
            let mass = c.within(0.1, 5.0);
            bodies.push(format!(
                "  - {{name: {name}, points: {ends}, mass: {mass}}}"
            ));
        }
        last = "P2".to_string();
    } else {
        let links = 1 + c.pick(3);
        let (mut x, mut y) = (0.0f64, 0.0f64);
        let mut previous = "A".to_string();
        for k in 1..=links {
            let length = c.within(0.1, 2.0);
            let angle = c.within(-3.1, 3.1);
            x += length * angle.cos();
            y += length * angle.sin();
            let name = format!("P{k}");
            points.push(format!("  - {{name: {name}, x: {x}, y: {y}}}"));
            let mass = c.within(0.05, 5.0);
            bodies.push(format!(
                "  - {{name: link{k}, points: [{previous}, {name}], mass: {mass}}}"
            ));
            if k > 1 {
                angles.push(format!(
                    "  - {{name: phi{k}, type: angle, points: [{previous}, {name}]}}"
                ));
                independent.push(format!("phi{k}"));
            }
            previous = name;
        }
        last = previous;
    }
    let mut effects = vec!["  - {type: gravity, vector: [0, -9.81]}".to_string()];
    if c.pick(2) == 1 {
        // A spring-damper needs a stiffness or a damping: the stiffness is never 0.
        let (k, d) = (c.within(0.5, 50.0), c.within(0.0, 2.0));
        effects.push(format!(
            "  - {{name: spring, type: spring_damper, points: [A, {last}], stiffness: {k}, damping: {d}}}"
        ));
    }
    if c.pick(2) == 1 {
        let (k, d) = (c.within(0.5, 20.0), c.within(0.0, 1.0));
        effects.push(format!(
            "  - {{name: hinge, type: rotational_spring_damper, coordinate: theta, stiffness: {k}, rest_angle: 0, damping: {d}}}"
        ));
    }
    if c.pick(2) == 1 {
        let torque =
            TORQUES[c.pick(TORQUES.len())].replace('K', &format!("{}", c.within(0.0, 5.0)));
        effects.push(format!(
            "  - {{name: drive, type: torque, coordinate: theta, value: \"{torque}\"}}"
        ));
    }
    if c.pick(2) == 1 {
        let f = c.within(-5.0, 5.0);
        effects.push(format!(
            "  - {{name: push, type: force, point: {last}, value: [\"{f}*cos(2*t)\", 0]}}"
        ));
    }
    let omega0 = c.within(-2.0, 2.0);
    format!(
        "name: generated\npoints:\n{}\nbodies:\n{}\ncoordinates:\n{}\nindependent: [{}]\ninitial:\n  velocities: {{theta: {omega0}}}\neffects:\n{}\n",
        points.join("\n"),
        bodies.join("\n"),
        angles.join("\n"),
        independent.join(", "),
        effects.join("\n")
    )
}

/// A load's derivatives ∂Q/∂q and ∂Q/∂q̇ (row-major n × n) added at (q, q̇, t), as
/// the solver takes them: [`closed_form`], or a test's own.
pub type Derivatives<'a> =
    &'a dyn Fn(&Force, &Model, (&[f64], &[f64], f64), &mut [f64], &mut [f64]) -> crate::Result<()>;

/// The model's own closed-form derivatives.
pub fn closed_form(
    force: &Force,
    model: &Model,
    state: (&[f64], &[f64], f64),
    kq: &mut [f64],
    kv: &mut [f64],
) -> crate::Result<()> {
    force.add_jacobians(model, state, kq, kv)
}

/// What a run of a generated scene must never show, or None.
pub fn judge(bytes: &[u8]) -> Option<String> {
    judge_with(bytes, &closed_form)
}

/// [`judge`] with the load derivatives `derivatives` checked against finite differences.
pub fn judge_with(bytes: &[u8], derivatives: Derivatives) -> Option<String> {
    let mut c = Choices::new(bytes);
    let text = scene_text(&mut c);
    let scene = match Scene::from_str(&text, std::path::Path::new("generated.yaml")) {
        Ok(s) => s,
        Err(e) => return Some(format!("a generated scene is refused: {e}\n{text}")),
    };
    let model = match Model::new(&scene) {
        Ok(m) => m,
        Err(e) => return Some(format!("a generated scene does not assemble: {e}\n{text}")),
    };
    let init = &model.initial;
    if let Some(bad) = derivative_mismatch(
        &model,
        derivatives,
        init.q.as_slice(),
        init.dq.as_slice(),
        0.1,
    ) {
        return Some(format!("{bad}\n{text}"));
    }
    let dt = [1e-3, 4e-3, 1e-2][c.pick(3)];
    let steps = 5 + c.pick(20);
    let coordinates = [Coordinates::Dependent, Coordinates::Independent][c.pick(2)];
    let mut first = None;
    for integrator in [
        forward::Integrator::Trapezoidal,
        forward::Integrator::Euler,
        forward::Integrator::HermiteSimpson,
    ] {
        let mut options =
            ForwardOptions::new(coordinates, dt, dt * steps as f64, Mode::FixedLag(1));
        options.integrator = integrator;
        options.settings.max_iterations = 50;
        // Every step kept, so that the energy columns are those the CLI writes.
        let mut steps = crate::derived::Steps::new(&model, true);
        let run = forward::simulate_streaming(
            Arc::new(model.clone()),
            &options,
            &mut |_, _| std::ops::ControlFlow::Continue(()),
            &mut steps,
        );
        match run.map(|summary| (steps, summary)) {
            Err(e) => {
                if let Err(m) = one_line(&e.to_string()) {
                    return Some(format!("{m}\n{text}"));
                }
            }
            Ok((steps, summary)) => {
                let rule = crate::derived::WorkRule::of(summary.plan.integrator);
                let energy = steps.columns(&model, &[crate::derived::Group::Energy], rule);
                let tr = steps.into_rows();
                if let Some(bad) = judge_run(&model, &tr, &summary, energy.ok(), derivatives) {
                    return Some(format!(
                        "{integrator:?}, {coordinates:?}, dt {dt}: {bad}\n{text}"
                    ));
                }
                if first.is_none()
                    && summary.failures.is_empty()
                    && tr.len() >= inverse::MIN_SAMPLES
                {
                    first = Some(tr);
                }
            }
        }
    }
    // The inverse of the first converged run, theta prescribed.
    let tr = first?;
    let theta = model.index_of("theta")?;
    let prescription = Prescription {
        indices: vec![theta],
        t0: 0.0,
        dt,
        steps: tr.len(),
        values: (0..tr.len()).map(|k| tr.q_at(k)[theta]).collect(),
        times: None,
    };
    let mut options = InverseOptions {
        coordinates,
        ..InverseOptions::default()
    };
    options.settings.max_iterations = 50;
    match inverse::solve(Arc::new(model.clone()), &prescription, &options) {
        Err(e) => one_line(&e.to_string())
            .err()
            .map(|m| format!("inverse: {m}\n{text}")),
        Ok(sol) => (!finite(&sol.trajectory) || !sol.forces.iter().all(|v| v.is_finite()))
            .then(|| format!("inverse: a non-finite value in the solution\n{text}")),
    }
}

/// A run's output finite, and a converged run's |Φ| and energy balance plausible
/// unless the run warns of them.
fn judge_run(
    model: &Model,
    tr: &Trajectory,
    summary: &forward::RunSummary,
    energy: Option<crate::derived::Columns>,
    derivatives: Derivatives,
) -> Option<String> {
    if !finite(tr) {
        return Some("a non-finite value in the trajectory".into());
    }
    for f in &summary.failures {
        if let Err(m) = one_line(&f.message()) {
            return Some(m);
        }
    }
    if !summary.failures.is_empty() {
        return None;
    }
    let scale = tr.q.iter().fold(1.0f64, |m, v| m.max(v.abs()));
    if !(summary.worst_phi <= 1e-8 * scale * scale) {
        return Some(format!(
            "converged with worst |Φ| = {:e}",
            summary.worst_phi
        ));
    }
    let warned = forward::energy_checks::energy_warning(summary).is_some()
        || forward::energy_checks::balance_warning(summary).is_some()
        || summary.load_jump.is_some()
        || crate::model::plausibility::step_warning(model, tr.t[1] - tr.t[0]).is_some();
    // The product checks the energy of every run: a conservative scene's drift, the
    // balance against the work of the others (every integrator, DC and IC).
    if !warned {
        let energy = energy?;
        let balance = energy.column("energy_balance")?;
        let kinetic = energy.column("kinetic")?;
        let potential = energy.column("potential")?;
        let span = |v: &[f64]| {
            let (lo, hi) = v
                .iter()
                .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), x| {
                    (a.min(*x), b.max(*x))
                });
            hi - lo
        };
        let scale = kinetic.iter().fold(0.0f64, |m, v| m.max(v.abs())) + span(&potential) + 1e-6;
        let worst = balance.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        if worst > 0.05 * scale {
            return Some(format!(
                "converged without a warning, its energy balance off by {worst:.3e} J against an energy scale of {scale:.3e} J"
            ));
        }
    }
    // The derivatives along the run, as at its start.
    let k = tr.len() - 1;
    derivative_mismatch(model, derivatives, tr.q_at(k), tr.dq_at(k), tr.t[k])
}

/// The first load whose derivatives at (q, q̇, t) differ from central differences of
/// its value, named with the entry; None if all agree.
pub fn derivative_mismatch(
    model: &Model,
    derivatives: Derivatives,
    q: &[f64],
    dq: &[f64],
    t: f64,
) -> Option<String> {
    let n = model.n();
    let value = |f: &Force, q: &[f64], dq: &[f64]| -> Option<Vec<f64>> {
        let mut out = vec![0.0; n];
        f.add_to(model, q, dq, t, &mut out).ok()?;
        Some(out)
    };
    for (force, effect) in model.forces.iter().zip(&model.scene.effects) {
        let (mut kq, mut kv) = (vec![0.0; n * n], vec![0.0; n * n]);
        if derivatives(force, model, (q, dq, t), &mut kq, &mut kv).is_err() {
            continue;
        }
        for (which, analytic) in [("q", &kq), ("q̇", &kv)] {
            for j in 0..n {
                let (mut qp, mut qm, mut vp, mut vm) =
                    (q.to_vec(), q.to_vec(), dq.to_vec(), dq.to_vec());
                let x = if which == "q" { q[j] } else { dq[j] };
                let h = 1e-6 * (1.0 + x.abs());
                if which == "q" {
                    qp[j] += h;
                    qm[j] -= h;
                } else {
                    vp[j] += h;
                    vm[j] -= h;
                }
                let (Some(plus), Some(minus)) = (value(force, &qp, &vp), value(force, &qm, &vm))
                else {
                    continue;
                };
                for i in 0..n {
                    let fd = (plus[i] - minus[i]) / (2.0 * h);
                    let a = analytic[i * n + j];
                    if (a - fd).abs() > 1e-5 * (1.0 + fd.abs()) {
                        return Some(format!(
                            "effect {:?}: ∂Q[{}]/∂{which}[{}] = {a:e}, finite differences {fd:e}",
                            crate::derived::effect_name(effect),
                            model.names[i],
                            model.names[j]
                        ));
                    }
                }
            }
        }
    }
    None
}

fn finite(tr: &Trajectory) -> bool {
    tr.t.iter()
        .chain(&tr.q)
        .chain(&tr.dq)
        .chain(&tr.ddq)
        .all(|v| v.is_finite())
}

/// An error message as the contract has it: one line of at most 300 characters.
fn one_line(message: &str) -> Result<(), String> {
    if message.contains('\n') || message.chars().count() > 300 || message.is_empty() {
        return Err(format!(
            "an error message not one line of at most 300 characters: {message:?}"
        ));
    }
    Ok(())
}
