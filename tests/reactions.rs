//! Joint forces against an independent computation: the Newton–Euler equations of
//! every body (force and moment about its centre of mass, from the trajectory's
//! accelerations) and the balance of every free point, solved for the pin forces
//! (and the sliders' normal forces) by least squares, without multipliers.

use mbfg::forward::{simulate, Coordinates, ForwardOptions};
use mbfg::model::{mass, PointSlot};
use mbfg::reactions::joint_forces;
use mbfg::scene::{ConstraintKind, Effect, RelativeKind};
use mbfg::smoother::Mode;
use mbfg::{Model, Scene};
use nalgebra::{DMatrix, DVector};
use std::sync::Arc;

fn model(name: &str) -> Arc<Model> {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("scenes")
        .join(name);
    Arc::new(Model::new(&Scene::load(path).unwrap()).unwrap())
}

fn cross(a: [f64; 2], b: [f64; 2]) -> f64 {
    a[0] * b[1] - a[1] * b[0]
}

/// The pin forces on each body at each of its points from Newton–Euler alone.
fn newton_euler(model: &Model, q: &[f64], dq: &[f64], ddq: &[f64], t: f64) -> Vec<Vec<[f64; 2]>> {
    let scene = &model.scene;
    // Torques on absolute angle coordinates (motors, rotational springs) act on the
    // body the angle is measured along.
    let qf = model
        .generalized_forces(
            &DVector::from_column_slice(q),
            &DVector::from_column_slice(dq),
            t,
        )
        .unwrap();
    let torque_on = |b: usize| -> f64 {
        scene
            .coordinates
            .iter()
            .filter_map(|c| match c.kind {
                RelativeKind::AbsoluteAngle { from, to }
                    if scene.bodies[b].points.contains(&from)
                        && scene.bodies[b].points.contains(&to) =>
                {
                    model.index_of(&c.name).map(|i| qf[i])
                }
                _ => None,
            })
            .sum()
    };
    let g = scene
        .effects
        .iter()
        .find_map(|e| match e {
            Effect::Gravity { vector } => Some(*vector),
            _ => None,
        })
        .unwrap_or([0.0; 2]);
    // Unknowns: (body, point) pin forces, then one normal force per fixed slider.
    let pairs: Vec<(usize, usize)> = scene
        .bodies
        .iter()
        .enumerate()
        .flat_map(|(b, body)| body.points.iter().map(move |&p| (b, p)))
        .collect();
    let sliders: Vec<(usize, [f64; 2])> = scene
        .constraints
        .iter()
        .filter_map(|c| match c.kind {
            ConstraintKind::FixedSlider { point, line } => {
                let (a, b) = (&scene.points[line[0]], &scene.points[line[1]]);
                let d = [b.x - a.x, b.y - a.y];
                let l = d[0].hypot(d[1]);
                Some((point, [-d[1] / l, d[0] / l]))
            }
            _ => None,
        })
        .collect();
    let unknowns = 2 * pairs.len() + sliders.len();
    let mut rows: Vec<(Vec<f64>, f64)> = Vec::new();
    let r = |p: usize| model.point_position(q, p);
    let a = |p: usize| model.point_velocity(ddq, p);
    for (b, body) in scene.bodies.iter().enumerate() {
        let (p1, p2) = (body.points[0], body.points[1]);
        let rg = mass::body_cog_position(body, r(p1), r(p2));
        let ag = mass::body_cog_position(body, a(p1), a(p2));
        let d = [r(p2)[0] - r(p1)[0], r(p2)[1] - r(p1)[1]];
        let da = [a(p2)[0] - a(p1)[0], a(p2)[1] - a(p1)[1]];
        let alpha = cross(d, da) / (d[0] * d[0] + d[1] * d[1]);
        let off = [rg[0] - r(p1)[0], rg[1] - r(p1)[1]];
        let i_g = body.i0 - body.mass * (off[0] * off[0] + off[1] * off[1]);
        for axis in 0..2 {
            let mut row = vec![0.0; unknowns];
            for (u, &(bb, _)) in pairs.iter().enumerate() {
                if bb == b {
                    row[2 * u + axis] = 1.0;
                }
            }
            rows.push((row, body.mass * (ag[axis] - g[axis])));
        }
        let mut row = vec![0.0; unknowns];
        for (u, &(bb, p)) in pairs.iter().enumerate() {
            if bb == b {
                let arm = [r(p)[0] - rg[0], r(p)[1] - rg[1]];
                row[2 * u] = -arm[1];
                row[2 * u + 1] = arm[0];
            }
        }
        rows.push((row, i_g * alpha - torque_on(b)));
    }
    // A free point: its mass times its acceleration is gravity, the forces applied
    // there, its slider's normal force, and the reactions of the bodies' pin forces.
    let applied = |p: usize| -> [f64; 2] {
        let mut total = [0.0; 2];
        for (force, effect) in model.forces.iter().zip(&scene.effects) {
            if let (Effect::Force { point, .. }, PointSlot::Free(i)) = (effect, model.points[p]) {
                if *point == p {
                    let mut out = vec![0.0; model.n()];
                    force.add_to(model, q, dq, t, &mut out).unwrap();
                    total[0] += out[i];
                    total[1] += out[i + 1];
                }
            }
        }
        total
    };
    for (p, point) in scene.points.iter().enumerate() {
        if point.fixed {
            continue;
        }
        let f = applied(p);
        for axis in 0..2 {
            let mut row = vec![0.0; unknowns];
            for (u, &(_, pp)) in pairs.iter().enumerate() {
                if pp == p {
                    row[2 * u + axis] = -1.0;
                }
            }
            for (s, &(sp, n)) in sliders.iter().enumerate() {
                if sp == p {
                    row[2 * pairs.len() + s] = n[axis];
                }
            }
            rows.push((row, point.mass * (a(p)[axis] - g[axis]) - f[axis]));
        }
    }
    let m = DMatrix::from_fn(rows.len(), unknowns, |i, j| rows[i].0[j]);
    let rhs = DVector::from_iterator(rows.len(), rows.iter().map(|r| r.1));
    let x = m.svd(true, true).solve(&rhs, 1e-12).unwrap();
    let mut out: Vec<Vec<[f64; 2]>> = scene
        .bodies
        .iter()
        .map(|b| vec![[0.0; 2]; b.points.len()])
        .collect();
    for (u, &(b, p)) in pairs.iter().enumerate() {
        let slot = scene.bodies[b]
            .points
            .iter()
            .position(|&bp| bp == p)
            .unwrap();
        out[b][slot] = [x[2 * u], x[2 * u + 1]];
    }
    out
}

fn agree(name: &str, coords: Coordinates) {
    let model = model(name);
    let opts = ForwardOptions::new(coords, 1e-3, 2.0, Mode::FixedLag(1));
    let (tr, _) = simulate(model.clone(), &opts, &mut |_, _| {}).unwrap();
    let n = model.n();
    let mut worst = 0.0f64;
    let mut scale = 0.0f64;
    for k in (0..tr.len()).step_by(50) {
        let (q, dq, ddq) = (tr.q_at(k), tr.dq_at(k), &tr.ddq[k * n..(k + 1) * n]);
        let ours = joint_forces(&model, q, dq, ddq, tr.t[k], None).unwrap();
        let theirs = newton_euler(&model, q, dq, ddq, tr.t[k]);
        for (fb, gb) in ours.iter().zip(&theirs) {
            for (f, g) in fb.iter().zip(gb) {
                worst = worst.max((f[0] - g[0]).abs().max((f[1] - g[1]).abs()));
                scale = scale.max(g[0].abs().max(g[1].abs()));
            }
        }
    }
    eprintln!("{name}: worst difference {worst:.3e} N of {scale:.3e} N");
    assert!(scale > 1.0, "{name}: forces of {scale} N");
    assert!(
        worst <= 1e-6 * scale,
        "{name}: differ by {worst:e} N of {scale:e} N"
    );
}

#[test]
fn fourbar_joint_forces_agree_with_newton_euler() {
    agree("fourbar.yaml", Coordinates::Dependent);
}

#[test]
fn slider_crank_joint_forces_agree_with_newton_euler() {
    agree("slider-crank.yaml", Coordinates::Dependent);
    agree("slider-crank.yaml", Coordinates::Independent);
}

/// A motor's torque acts on the crank through its angle coordinate: the pin forces
/// are those of the crank driven by that torque.
#[test]
fn a_motor_driven_crank_rocker_agrees_with_newton_euler() {
    agree("driven/dc-motor-crank-rocker.yaml", Coordinates::Dependent);
    agree(
        "driven/dc-motor-crank-rocker.yaml",
        Coordinates::Independent,
    );
}

/// Loads that depend on the state (a PD controller on the crank, drag at the coupler
/// point, a gas force on the piston): the pin forces balance them too.
#[test]
fn state_dependent_loads_agree_with_newton_euler() {
    agree(
        "driven/controlled-crank-rocker.yaml",
        Coordinates::Dependent,
    );
    agree(
        "driven/compressor-slider-crank.yaml",
        Coordinates::Independent,
    );
}
