//! Quantities derived from a trajectory, for the optional CSV columns of
//! `mbfg simulate --columns` and `mbfg inverse --columns`:
//! - `bodies`: for every body its angle (of the axis from its first to its second
//!   point, unwrapped over time), the position and the velocity of its centre of mass;
//! - `energy`: kinetic and potential energy, the work done since t = 0 by every
//!   effect that has no potential (dampers, torques, forces), and the energy balance
//!   that these should close;
//! - `joints`: the force the rest of the mechanism exerts on every body at each of its
//!   points ([`crate::reactions`]).

use crate::error::{Error, Result};
use crate::model::forces::Force;
use crate::model::{mass, Model};
use crate::scene::Effect;
use crate::trajectory::Trajectory;
use std::f64::consts::PI;

/// How the `energy` group integrates each effect's power between two samples.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum WorkRule {
    /// The trapezoidal rule on the power at the samples: second order, as the
    /// trapezoidal and Euler integrators.
    #[default]
    Trapezoidal,
    /// Simpson's rule, the power in the middle taken on the cubic Hermite interpolant
    /// of the two samples' q, q̇, q̈: fourth order, as Hermite–Simpson. The trapezoidal
    /// rule would read its own error as the fourth-order run's.
    HermiteSimpson,
}

impl WorkRule {
    /// The rule of the integrator's order.
    pub fn of(integrator: crate::forward::Integrator) -> WorkRule {
        match integrator {
            crate::forward::Integrator::HermiteSimpson => WorkRule::HermiteSimpson,
            _ => WorkRule::Trapezoidal,
        }
    }

    /// The work over a step of length h from the power at its ends, and in its
    /// middle for Simpson's rule (`None`: the trapezoidal rule).
    pub(crate) fn over_step(h: f64, before: f64, middle: Option<f64>, after: f64) -> f64 {
        match middle {
            Some(m) => h / 6.0 * (before + 4.0 * m + after),
            None => 0.5 * h * (before + after),
        }
    }
}

/// The middle of a step of length h between two samples `a` and `b` (each q, q̇, q̈
/// of n coordinates in a row) on the cubic Hermite interpolants: of q from q, q̇, of q̇
/// from q̇, q̈.
pub(crate) fn hermite_middle(a: &[f64], b: &[f64], h: f64, q_mid: &mut [f64], dq_mid: &mut [f64]) {
    let n = q_mid.len();
    for i in 0..n {
        q_mid[i] = 0.5 * (a[i] + b[i]) + 0.125 * h * (a[n + i] - b[n + i]);
        dq_mid[i] = 0.5 * (a[n + i] + b[n + i]) + 0.125 * h * (a[2 * n + i] - b[2 * n + i]);
    }
}

/// A group of optional columns.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum Group {
    Bodies,
    Energy,
    Joints,
    Constraints,
}

impl Group {
    /// Every group, in the order their columns are written.
    pub const ALL: [Group; 4] = [
        Group::Bodies,
        Group::Energy,
        Group::Joints,
        Group::Constraints,
    ];

    pub fn name(self) -> &'static str {
        match self {
            Group::Bodies => "bodies",
            Group::Energy => "energy",
            Group::Joints => "joints",
            Group::Constraints => "constraints",
        }
    }

    /// Parses a comma-separated list such as `bodies,energy`; the result is in the
    /// order of [`Group::ALL`] without repeats, so the columns do not depend on how
    /// the list was spelled. The error names the valid groups.
    pub fn parse_list(list: &str) -> std::result::Result<Vec<Group>, String> {
        let valid = || {
            Group::ALL
                .iter()
                .map(|g| g.name())
                .collect::<Vec<_>>()
                .join(", ")
        };
        let mut groups = Vec::new();
        for word in list.split(',').map(str::trim).filter(|w| !w.is_empty()) {
            let Some(g) = Group::ALL.iter().find(|g| g.name() == word) else {
                return Err(format!(
                    "--columns: unknown column group `{}`; the valid ones are {}",
                    crate::expr::excerpt(word, 40),
                    valid()
                ));
            };
            groups.push(*g);
        }
        if groups.is_empty() {
            return Err(format!(
                "--columns needs at least one of {} (comma-separated)",
                valid()
            ));
        }
        groups.sort();
        groups.dedup();
        Ok(groups)
    }
}

/// Columns computed for every sample of a trajectory.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Columns {
    pub names: Vec<String>,
    /// Row-major samples × names.
    pub values: Vec<f64>,
}

impl Columns {
    /// The values of column `name`, one per sample.
    pub fn column(&self, name: &str) -> Option<Vec<f64>> {
        let j = self.names.iter().position(|c| c == name)?;
        let w = self.names.len();
        Some(self.values.iter().skip(j).step_by(w).copied().collect())
    }

    /// Side by side: `self`'s columns, then `other`'s (same samples).
    fn beside(self, other: Columns, samples: usize) -> Columns {
        let (a, b) = (self.names.len(), other.names.len());
        let mut values = Vec::with_capacity(samples * (a + b));
        for k in 0..samples {
            values.extend_from_slice(&self.values[k * a..(k + 1) * a]);
            values.extend_from_slice(&other.values[k * b..(k + 1) * b]);
        }
        let mut names = self.names;
        names.extend(other.names);
        Columns { names, values }
    }
}

/// The columns of `groups` (in their order) for every sample of `trajectory`.
/// `actuators` are the generalized forces an inverse solve found (row-major samples
/// × n): their work is counted in the energy balance as `work:Q`. `rule` integrates
/// the work columns.
pub fn columns(
    model: &Model,
    trajectory: &Trajectory,
    groups: &[Group],
    actuators: Option<&[f64]>,
    rule: WorkRule,
) -> Result<Columns> {
    let mut out = Columns::default();
    for g in groups {
        let next = match g {
            Group::Bodies => bodies(model, trajectory),
            Group::Energy => energy(model, trajectory, actuators, rule)?,
            Group::Joints => joints(model, trajectory, actuators)?,
            Group::Constraints => constraints(model, trajectory, actuators)?,
        };
        out = out.beside(next, trajectory.len());
    }
    Ok(out)
}

/// A run's rows and, for a refined run, the steps taken between them
/// ([`StepSink::between`](crate::forward::StepSink::between)): the columns integrate
/// the work, and unwrap the angles, over every step taken, then keep the rows.
pub struct Steps {
    /// Every step handed on, rows and (where kept) those between.
    taken: Trajectory,
    /// The index in `taken` of each row.
    rows: Vec<usize>,
    /// Whether the steps between rows are kept (only the columns need them).
    between: bool,
}

impl Steps {
    /// Holds the rows, and the steps between them where `between`.
    pub fn new(model: &Model, between: bool) -> Steps {
        Steps {
            between,
            taken: Trajectory {
                names: model.names.clone(),
                t: Vec::new(),
                q: Vec::new(),
                dq: Vec::new(),
                ddq: Vec::new(),
            },
            rows: Vec::new(),
        }
    }

    /// The rows handed on, as a trajectory.
    pub fn into_rows(self) -> Trajectory {
        match self.rows.len() == self.taken.len() {
            true => self.taken,
            false => self.taken.pick(&self.rows),
        }
    }

    /// The number of rows handed on.
    pub fn len(&self) -> usize {
        self.rows.len()
    }

    pub fn is_empty(&self) -> bool {
        self.rows.is_empty()
    }

    /// The columns of `groups` at the rows, computed over every step taken.
    pub fn columns(&self, model: &Model, groups: &[Group], rule: WorkRule) -> Result<Columns> {
        // (Steps after the last row, of an interrupted run, change none before it.)
        let all = columns(model, &self.taken, groups, None, rule)?;
        let width = all.names.len();
        let mut values = Vec::with_capacity(self.rows.len() * width);
        for &k in &self.rows {
            values.extend_from_slice(&all.values[k * width..(k + 1) * width]);
        }
        Ok(Columns {
            names: all.names,
            values,
        })
    }
}

impl crate::forward::StepSink for Steps {
    fn step(&mut self, t: f64, q: &[f64], dq: &[f64], ddq: &[f64]) -> Result<()> {
        self.rows.push(self.taken.len());
        self.taken.step(t, q, dq, ddq)
    }

    fn between(&mut self, t: f64, q: &[f64], dq: &[f64], ddq: &[f64]) -> Result<()> {
        match self.between {
            true => self.taken.step(t, q, dq, ddq),
            false => Ok(()),
        }
    }

    fn restart(&mut self) -> Result<()> {
        self.rows.clear();
        self.taken.restart()
    }
}

/// `F:<body>@<point>.x`, `.y` for every body and each of its points: the force on
/// the body there, N. `actuators` (an inverse solve's) are among the loads.
pub fn joints(
    model: &Model,
    trajectory: &Trajectory,
    actuators: Option<&[f64]>,
) -> Result<Columns> {
    let scene = &model.scene;
    let mut names = Vec::new();
    for b in &scene.bodies {
        for &p in &b.points {
            for axis in ["x", "y"] {
                names.push(format!("F:{}@{}.{axis}", b.name, scene.points[p].name));
            }
        }
    }
    let n = model.n();
    let mut values = Vec::with_capacity(trajectory.len() * names.len());
    for k in 0..trajectory.len() {
        let forces = crate::reactions::joint_forces(
            model,
            trajectory.q_at(k),
            trajectory.dq_at(k),
            &trajectory.ddq[k * n..(k + 1) * n],
            trajectory.t[k],
            actuators.map(|a| &a[k * n..(k + 1) * n]),
        )?;
        values.extend(forces.iter().flatten().flatten());
    }
    Ok(Columns { names, values })
}

/// `R:<constraint>` for every constraint of the scene's `constraints`: a distance's
/// tension, a slider's normal force on its point, N (`reactions::constraint_forces`).
pub fn constraints(
    model: &Model,
    trajectory: &Trajectory,
    actuators: Option<&[f64]>,
) -> Result<Columns> {
    let names: Vec<String> = model
        .scene
        .constraints
        .iter()
        .map(|c| format!("R:{}", c.name))
        .collect();
    let n = model.n();
    let mut values = Vec::with_capacity(trajectory.len() * names.len());
    for k in 0..trajectory.len() {
        values.extend(crate::reactions::constraint_forces(
            model,
            trajectory.q_at(k),
            trajectory.dq_at(k),
            &trajectory.ddq[k * n..(k + 1) * n],
            trajectory.t[k],
            actuators.map(|a| &a[k * n..(k + 1) * n]),
        )?);
    }
    Ok(Columns { names, values })
}

/// `angle:<body>`, `x:<body>`, `y:<body>`, `vx:<body>`, `vy:<body>` for every body.
pub fn bodies(model: &Model, trajectory: &Trajectory) -> Columns {
    let bodies = &model.scene.bodies;
    let mut names = Vec::with_capacity(5 * bodies.len());
    for b in bodies {
        for p in ["angle", "x", "y", "vx", "vy"] {
            names.push(format!("{p}:{}", b.name));
        }
    }
    let mut values = Vec::with_capacity(trajectory.len() * names.len());
    let mut previous: Vec<f64> = Vec::new();
    for k in 0..trajectory.len() {
        let (q, dq) = (trajectory.q_at(k), trajectory.dq_at(k));
        for (i, b) in bodies.iter().enumerate() {
            let (r1, r2) = (
                model.point_position(q, b.points[0]),
                model.point_position(q, b.points[1]),
            );
            let raw = (r2[1] - r1[1]).atan2(r2[0] - r1[0]);
            let angle = match previous.get(i) {
                Some(&before) => before + wrap(raw - before),
                None => raw,
            };
            if k == 0 {
                previous.push(angle);
            } else {
                previous[i] = angle;
            }
            let cog = mass::body_cog_position(b, r1, r2);
            // The centre is linear in the two points' positions (no constant term),
            // so the same map takes their velocities to its velocity.
            let v = mass::body_cog_position(
                b,
                model.point_velocity(dq, b.points[0]),
                model.point_velocity(dq, b.points[1]),
            );
            values.extend_from_slice(&[angle, cog[0], cog[1], v[0], v[1]]);
        }
    }
    Columns { names, values }
}

/// An angle difference brought into [−π, π): the step between two samples, so that
/// the body angle is continuous where atan2 jumps by 2π.
fn wrap(d: f64) -> f64 {
    d - 2.0 * PI * ((d + PI) / (2.0 * PI)).floor()
}

/// The part of an effect that has no potential, or None when it has all of it
/// (gravity, an undamped spring): a damper without its spring, a torque, a force.
pub(crate) fn non_conservative(force: &Force) -> Option<Force> {
    match force {
        Force::Gravity { .. } => None,
        Force::SpringDamper { damping, .. } | Force::RotationalSpringDamper { damping, .. }
            if *damping == 0.0 =>
        {
            None
        }
        // The damper alone (a spring's rest length kept for its direction check).
        Force::SpringDamper { damping, .. } | Force::RotationalSpringDamper { damping, .. } => {
            force.with_constants(0.0, *damping)
        }
        Force::Torque { .. }
        | Force::PointForce { .. }
        | Force::Motor { .. }
        | Force::External { .. } => Some(force.clone()),
    }
}

pub fn effect_name(effect: &Effect) -> &str {
    effect.name().unwrap_or("gravity")
}

/// `kinetic`, `potential`, `work:<effect>` for every effect with a non-conservative
/// part (and `work:Q` for `actuators`), and `energy_balance` = kinetic + potential −
/// their values at the first sample − Σ work. The work is the integral of the power
/// Q_effect(q, q̇, t)·q̇ by `rule` over every sample given, so decimate after this;
/// that of `actuators`, known at the samples only, by the trapezoidal rule.
pub fn energy(
    model: &Model,
    trajectory: &Trajectory,
    actuators: Option<&[f64]>,
    rule: WorkRule,
) -> Result<Columns> {
    let n = model.n();
    let mut effects: Vec<(String, Force)> = Vec::new();
    for (force, effect) in model.forces.iter().zip(&model.scene.effects) {
        if let Some(f) = non_conservative(force) {
            effects.push((effect_name(effect).to_string(), f));
        }
    }
    if actuators.is_some() && effects.iter().any(|(name, _)| name == "Q") {
        return Err(Error::InvalidArgument(
            "an effect named `Q` would share its work column with the inverse forces `work:Q`"
                .into(),
        ));
    }
    let mut names = vec!["kinetic".to_string(), "potential".to_string()];
    names.extend(effects.iter().map(|(name, _)| format!("work:{name}")));
    if actuators.is_some() {
        names.push("work:Q".into());
    }
    names.push("energy_balance".into());
    let works = names.len() - 3;

    let mut values = Vec::with_capacity(trajectory.len() * names.len());
    let mut work = vec![0.0; works];
    let mut power_before = vec![0.0; works];
    let mut power = vec![0.0; works];
    let mut initial = 0.0;
    let mut generalized = vec![0.0; n];
    let power_of = |f: &Force, name: &str, q: &[f64], dq: &[f64], t: f64, g: &mut [f64]| {
        g.fill(0.0);
        f.add_to(model, q, dq, t, g).map_err(|e| {
            Error::InvalidArgument(format!("the work of effect {name} at t = {t} s: {e}"))
        })?;
        Ok::<f64, Error>(g.iter().zip(dq).map(|(a, b)| a * b).sum())
    };
    let (mut before, mut now) = (vec![0.0; 3 * n], vec![0.0; 3 * n]);
    let (mut q_mid, mut dq_mid) = (vec![0.0; n], vec![0.0; n]);
    for k in 0..trajectory.len() {
        let (q, dq, t) = (trajectory.q_at(k), trajectory.dq_at(k), trajectory.t[k]);
        for (j, (name, f)) in effects.iter().enumerate() {
            power[j] = power_of(f, name, q, dq, t, &mut generalized)?;
        }
        if let Some(a) = actuators {
            power[works - 1] = a[k * n..(k + 1) * n]
                .iter()
                .zip(dq)
                .map(|(f, v)| f * v)
                .sum();
        }
        now[..n].copy_from_slice(q);
        now[n..2 * n].copy_from_slice(dq);
        now[2 * n..].copy_from_slice(trajectory.ddq_at(k));
        if k > 0 {
            let h = t - trajectory.t[k - 1];
            let simpson = rule == WorkRule::HermiteSimpson;
            if simpson {
                hermite_middle(&before, &now, h, &mut q_mid, &mut dq_mid);
            }
            for j in 0..works {
                // (The actuators' forces are known at the samples only.)
                let middle = match effects.get(j) {
                    Some((name, f)) if simpson => {
                        let t_mid = t - 0.5 * h;
                        Some(power_of(f, name, &q_mid, &dq_mid, t_mid, &mut generalized)?)
                    }
                    _ => None,
                };
                work[j] += WorkRule::over_step(h, power_before[j], middle, power[j]);
            }
        }
        std::mem::swap(&mut before, &mut now);
        power_before.copy_from_slice(&power);
        let kinetic = model.kinetic_energy(&nalgebra::DVector::from_column_slice(dq));
        let potential = model.potential_energy(&nalgebra::DVector::from_column_slice(q));
        if k == 0 {
            initial = kinetic + potential;
        }
        let balance = kinetic + potential - initial - work.iter().sum::<f64>();
        values.push(kinetic);
        values.push(potential);
        values.extend_from_slice(&work);
        values.push(balance);
    }
    Ok(Columns { names, values })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::forward::{simulate, Coordinates, ForwardOptions};
    use crate::smoother::Mode;
    use crate::Scene;
    use std::sync::Arc;

    fn run(scene: &str, t_end: f64) -> (Model, Trajectory) {
        let path = format!("{}/scenes/{scene}", env!("CARGO_MANIFEST_DIR"));
        let model = Model::new(&Scene::load(path).unwrap()).unwrap();
        let options = ForwardOptions::new(Coordinates::Dependent, 1e-3, t_end, Mode::FixedLag(1));
        let (tr, summary) = simulate(Arc::new(model.clone()), &options, &mut |_, _| {}).unwrap();
        assert!(summary.failures.is_empty());
        (model, tr)
    }

    fn max_abs(v: &[f64]) -> f64 {
        v.iter().fold(0.0, |a, b| a.max(b.abs()))
    }

    #[test]
    fn group_lists_parse_in_canonical_order() {
        assert_eq!(
            Group::parse_list("energy, bodies,energy").unwrap(),
            [Group::Bodies, Group::Energy]
        );
        let e = Group::parse_list("bodies,speed").unwrap_err();
        assert!(e.contains("`speed`") && e.contains("bodies, energy"), "{e}");
        assert!(Group::parse_list(" , ").is_err());
    }

    #[test]
    fn angles_unwrap_across_the_branch_cut() {
        assert!((wrap(2.0 * PI - 0.1) + 0.1).abs() < 1e-12);
        assert!((wrap(-2.0 * PI + 0.1) - 0.1).abs() < 1e-12);
        assert_eq!(wrap(0.25), 0.25);
    }

    #[test]
    fn pendulum_energy_balances_and_body_angle_is_theta() {
        let (model, tr) = run("pendulum.yaml", 2.0);
        let c = columns(
            &model,
            &tr,
            &[Group::Bodies, Group::Energy],
            None,
            WorkRule::Trapezoidal,
        )
        .unwrap();
        // Gravity only: no work column.
        assert!(
            !c.names.iter().any(|n| n.starts_with("work:")),
            "{:?}",
            c.names
        );
        let kinetic = c.column("kinetic").unwrap();
        let peak = max_abs(&kinetic);
        let balance = max_abs(&c.column("energy_balance").unwrap());
        assert!(peak > 1.0 && balance <= 1e-3 * peak, "{balance} vs {peak}");

        // Released from horizontal, the rod swings through −π (where atan2 jumps).
        let theta = model.index_of("theta").unwrap();
        let angle = c.column("angle:rod").unwrap();
        let q: Vec<f64> = (0..tr.len()).map(|k| tr.q_at(k)[theta]).collect();
        assert!(q.iter().any(|&v| v < -3.0), "does not reach the branch cut");
        for (a, b) in angle.iter().zip(&q) {
            assert!((a - b).abs() < 1e-9, "{a} vs {b}");
        }

        // The uniform rod's centre is at its middle; its speed is half the tip's.
        let (x, vy) = (c.column("x:rod").unwrap(), c.column("vy:rod").unwrap());
        let p = model.scene.point_index("P").unwrap();
        let k = tr.len() / 3;
        let tip = model.point_position(tr.q_at(k), p);
        let tip_v = model.point_velocity(tr.dq_at(k), p);
        assert!((x[k] - 0.5 * tip[0]).abs() < 1e-12);
        assert!((vy[k] - 0.5 * tip_v[1]).abs() < 1e-12);
    }

    #[test]
    fn damper_work_closes_the_balance() {
        let (model, tr) = run("spring-damper.yaml", 3.0);
        let c = energy(&model, &tr, None, WorkRule::Trapezoidal).unwrap();
        assert_eq!(
            c.names,
            ["kinetic", "potential", "work:spring", "energy_balance"]
        );
        let kinetic = c.column("kinetic").unwrap();
        let potential = c.column("potential").unwrap();
        let peak = max_abs(&kinetic);
        let drift = kinetic
            .iter()
            .zip(&potential)
            .map(|(k, v)| k + v - kinetic[0] - potential[0]);
        let drift = drift.fold(0.0f64, |a, b| a.max(b.abs()));
        let balance = max_abs(&c.column("energy_balance").unwrap());
        let work = c.column("work:spring").unwrap();
        // A damper only takes energy out.
        assert!(work.windows(2).all(|w| w[1] <= w[0] + 1e-15));
        assert!(balance <= 1e-3 * peak, "{balance} vs {peak}");
        assert!(drift > 50.0 * balance && drift > 1e-2 * peak, "{drift}");
    }

    #[test]
    fn hermite_simpson_work_falls_at_fourth_order() {
        // A Hermite–Simpson run's balance, its work by Simpson's rule on the Hermite
        // middle, falls 16× a halving of dt; by the trapezoidal rule it is that rule's
        // error, larger and second order.
        let path = format!("{}/scenes/spring-damper.yaml", env!("CARGO_MANIFEST_DIR"));
        let model = Model::new(&Scene::load(path).unwrap()).unwrap();
        let balance = |dt: f64, rule: WorkRule| {
            let mut options =
                ForwardOptions::new(Coordinates::Dependent, dt, 2.0, Mode::FixedLag(1));
            options.integrator = crate::forward::Integrator::HermiteSimpson;
            let (tr, summary) =
                simulate(Arc::new(model.clone()), &options, &mut |_, _| {}).unwrap();
            assert!(summary.failures.is_empty());
            let c = energy(&model, &tr, None, rule).unwrap();
            max_abs(&c.column("energy_balance").unwrap())
        };
        let (coarse, fine) = (
            balance(0.02, WorkRule::HermiteSimpson),
            balance(0.01, WorkRule::HermiteSimpson),
        );
        assert!(coarse / fine > 12.0, "{coarse} / {fine}");
        let trapezoidal = balance(0.01, WorkRule::Trapezoidal);
        assert!(trapezoidal > 100.0 * fine, "{trapezoidal} vs {fine}");
    }

    #[test]
    fn actuator_work_is_its_own_column() {
        let (model, tr) = run("pendulum.yaml", 0.1);
        let n = model.n();
        // A made-up constant force on every coordinate: its work is Σ f·Δq.
        let forces = vec![1.0; tr.len() * n];
        let c = energy(&model, &tr, Some(&forces), WorkRule::Trapezoidal).unwrap();
        let work = c.column("work:Q").unwrap();
        let last = tr.len() - 1;
        let expected: f64 = (0..n).map(|i| tr.q_at(last)[i] - tr.q_at(0)[i]).sum();
        assert!(
            (work[last] - expected).abs() < 1e-4,
            "{} vs {expected}",
            work[last]
        );
    }
}
