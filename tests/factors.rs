//! Every factor's closed-form Jacobian blocks against central finite differences of
//! its own residual, evaluated through the `Factor` trait exactly as the solver does;
//! the dynamics factors against the classical solutions at consistent states; the
//! exact Jacobians of the dynamics kernel off the constraint manifold; and evaluation
//! leaving nothing behind in its workspace.

use mbfg::dynamics;
use mbfg::factors::{
    ComponentPrior, Dynamics, DynamicsKernel, Equality, Euler, Form, HermitePosition,
    IndependentAcceleration, IndependentDynamics, IndependentPosition, IndependentVelocity,
    Integrator, KernelScratch, ParametricDynamics, PositionConstraints, PrescribedMotion, Prior,
    Projected, Reading, SimpsonVelocity, SimpsonVelocityThrough, Trapezoidal, VelocityConstraints,
};
use mbfg::graph::{Factor, Key, StackReq, VarKind, Workspace};
use mbfg::kinematics;
use mbfg::{Model, Scene};
use nalgebra::DVector;
use std::collections::BTreeMap;
mod common;
use common::{scene_path, Rng};
use std::sync::Arc;

/// The scenes whose factors are checked: dependent coordinates only (fourbar), an
/// angle coordinate (fourbar-theta), a redundant constraint and 2 dof
/// (pick-and-place), velocity-dependent forces (spring-damper), a mobile slider and a
/// torque (slotted-lever), a fixed slider (slider-crank).
const SCENES: &[&str] = &[
    "fourbar.yaml",
    "fourbar-theta.yaml",
    "pick-and-place.yaml",
    "spring-damper.yaml",
    "slotted-lever.yaml",
    "slider-crank.yaml",
];

/// Time at which factors are evaluated (forces may depend on it).
const T: f64 = 0.3;
/// Relative finite-difference step, scaled by max(1, |x|).
const FD_STEP: f64 = 1e-6;
/// Largest accepted |closed form − finite differences| / max(1, |block|max).
const FD_TOLERANCE: f64 = 1e-6;
/// Random points per scene and factor.
const TRIALS: usize = 5;

fn load(name: &str) -> Arc<Model> {
    let scene = Scene::load(scene_path(name)).unwrap_or_else(|e| panic!("{name}: {e}"));
    Arc::new(Model::new(&scene).unwrap_or_else(|e| panic!("{name}: {e}")))
}

// ---------------------------------------------------------------------------------
// Points at which factors are evaluated.
// ---------------------------------------------------------------------------------

/// Size of a variable of `kind` for `model`.
fn size(model: &Model, kind: VarKind) -> usize {
    match kind {
        VarKind::Q | VarKind::Dq | VarKind::Ddq | VarKind::Force => model.n(),
        VarKind::Z | VarKind::Dz | VarKind::Ddz => model.independent.len(),
        VarKind::Param => model.parameters.as_ref().map_or(0, |p| p.len()),
    }
}

/// A configuration near the initial one, randomly perturbed: not on the constraint
/// manifold (the derivative identities hold anywhere).
fn random_configuration(model: &Model, rng: &mut Rng, scale: f64) -> Vec<f64> {
    model
        .initial
        .q
        .iter()
        .map(|v| v + scale * rng.uniform())
        .collect()
}

/// Values of every variable kind at one time step.
struct Step {
    q: Vec<f64>,
    dq: Vec<f64>,
    ddq: Vec<f64>,
    z: Vec<f64>,
    dz: Vec<f64>,
    ddz: Vec<f64>,
    force: Vec<f64>,
    /// The identified parameters: their file values, perturbed by up to 30 %.
    param: Vec<f64>,
}

impl Step {
    /// q near the initial configuration, everything else random of order 1.
    fn random(model: &Model, rng: &mut Rng) -> Step {
        let (n, f) = (model.n(), model.independent.len());
        Step {
            q: random_configuration(model, rng, 0.2),
            dq: rng.values(n, 1.0),
            ddq: rng.values(n, 1.0),
            z: rng.values(f, 1.0),
            dz: rng.values(f, 1.0),
            ddz: rng.values(f, 1.0),
            force: rng.values(n, 1.0),
            param: model.parameters.as_ref().map_or(Vec::new(), |p| {
                p.values
                    .iter()
                    .map(|v| v * (1.0 + 0.3 * rng.uniform()))
                    .collect()
            }),
        }
    }

    fn get(&self, kind: VarKind) -> &[f64] {
        match kind {
            VarKind::Q => &self.q,
            VarKind::Dq => &self.dq,
            VarKind::Ddq => &self.ddq,
            VarKind::Z => &self.z,
            VarKind::Dz => &self.dz,
            VarKind::Ddz => &self.ddz,
            VarKind::Force => &self.force,
            VarKind::Param => &self.param,
        }
    }
}

/// The inputs of `factor`, one vector per key, from the values of its step (`now`)
/// and of the step before.
fn inputs(factor: &dyn Factor, now: &Step, before: &Step) -> Vec<Vec<f64>> {
    factor
        .keys()
        .iter()
        .map(|k| match k.lag {
            0 => now.get(k.kind).to_vec(),
            1 => before.get(k.kind).to_vec(),
            lag => panic!("{}: key with lag {lag}", factor.name()),
        })
        .collect()
}

fn key_label(key: &Key) -> String {
    match key.lag {
        0 => format!("{}_t", key.kind.symbol()),
        lag => format!("{}_(t-{lag})", key.kind.symbol()),
    }
}

// ---------------------------------------------------------------------------------
// Evaluation and the finite-difference check.
// ---------------------------------------------------------------------------------

/// Residual and (optionally) Jacobian blocks of one evaluation. The outputs are
/// filled with NaN beforehand, so an entry the factor fails to write shows.
struct Evaluation {
    r: Vec<f64>,
    jac: Option<Vec<Vec<f64>>>,
}

fn evaluate(
    factor: &dyn Factor,
    t: f64,
    xs: &[Vec<f64>],
    with_jacobians: bool,
    ws: &mut Workspace,
) -> Evaluation {
    let dim = factor.dim();
    let slices: Vec<&[f64]> = xs.iter().map(Vec::as_slice).collect();
    let mut r = vec![f64::NAN; dim];
    let mut jac: Option<Vec<Vec<f64>>> =
        with_jacobians.then(|| xs.iter().map(|x| vec![f64::NAN; dim * x.len()]).collect());
    factor
        .evaluate(t, &slices, &mut r, jac.as_deref_mut(), ws)
        .unwrap_or_else(|e| panic!("{}: evaluation failed: {e}", factor.name()));
    Evaluation { r, jac }
}

fn workspace_for(factor: &dyn Factor) -> Workspace {
    Workspace::new(factor.scratch())
}

fn same_bits(a: &[f64], b: &[f64]) -> bool {
    a.len() == b.len() && a.iter().zip(b).all(|(x, y)| x.to_bits() == y.to_bits())
}

/// Checks every Jacobian block of `factor` at the inputs `xs` against central finite
/// differences of its residual, and that the residual does not depend on whether
/// Jacobians are requested. Returns the largest relative error over the blocks.
fn check_factor(name: &str, factor: &dyn Factor, xs: &[Vec<f64>], t: f64) -> f64 {
    check_factor_with(FD_STEP, name, factor, xs, t)
}

/// [`check_factor`] with relative finite-difference step `step`.
fn check_factor_with(step: f64, name: &str, factor: &dyn Factor, xs: &[Vec<f64>], t: f64) -> f64 {
    let dim = factor.dim();
    assert_eq!(
        factor.keys().len(),
        xs.len(),
        "{name}: one input per key expected"
    );
    for (k, x) in xs.iter().enumerate() {
        assert_eq!(
            factor.size(k),
            x.len(),
            "{name}: declared size of key {k} differs from its input"
        );
    }
    let mut ws = workspace_for(factor);
    let full = evaluate(factor, t, xs, true, &mut ws);
    let jac = full.jac.expect("jacobians requested");
    assert!(
        full.r.iter().all(|v| v.is_finite()),
        "{name}: residual not finite (or not written): {:?}",
        full.r
    );
    for (k, block) in jac.iter().enumerate() {
        // A block declared diagonal (the solver reads only its diagonal) must be.
        if factor.diagonal_jacobian(k) {
            let n = xs[k].len();
            assert_eq!(n, dim, "{name}: a diagonal ∂r/∂x{k} must be square");
            let off = (0..dim * n).find(|&i| i / n != i % n && block[i] != 0.0);
            assert!(
                off.is_none(),
                "{name}: ∂r/∂{} declared diagonal has entry {:?} off it",
                key_label(&factor.keys()[k]),
                off.map(|i| (i / n, i % n))
            );
        }
        if let Some(i) = block.iter().position(|v| !v.is_finite()) {
            let n = xs[k].len();
            panic!(
                "{name}: ∂r/∂{} entry ({}, {}) not finite or never written",
                key_label(&factor.keys()[k]),
                i / n,
                i % n
            );
        }
    }
    let plain = evaluate(factor, t, xs, false, &mut ws);
    assert!(
        same_bits(&plain.r, &full.r),
        "{name}: residual without Jacobians {:?} differs from residual with them {:?}",
        plain.r,
        full.r
    );

    let mut worst = 0.0f64;
    for (k, x) in xs.iter().enumerate() {
        let cols = x.len();
        let block = &jac[k];
        let scale = block.iter().fold(1.0f64, |m, v| m.max(v.abs()));
        let mut fd = vec![0.0; dim * cols];
        for j in 0..cols {
            let h = step * x[j].abs().max(1.0);
            let (mut up, mut dn) = (xs.to_vec(), xs.to_vec());
            up[k][j] = x[j] + h;
            dn[k][j] = x[j] - h;
            let step = up[k][j] - dn[k][j];
            let ru = evaluate(factor, t, &up, false, &mut ws).r;
            let rd = evaluate(factor, t, &dn, false, &mut ws).r;
            for i in 0..dim {
                fd[i * cols + j] = (ru[i] - rd[i]) / step;
            }
        }
        let (mut err, mut at) = (0.0f64, 0);
        for (e, (a, b)) in block.iter().zip(&fd).enumerate() {
            let d = (a - b).abs();
            if d > err || d.is_nan() {
                err = d;
                at = e;
            }
        }
        // Central differences cannot resolve below the residual's round-off over 2h:
        // ε·max|r|/h (with a factor for the round-off of the evaluation itself, which
        // goes through a factorization).
        let h_min = step * x.iter().fold(1.0f64, |m, v| m.min(v.abs().max(1.0)));
        let r_max = full.r.iter().fold(1.0f64, |m, v| m.max(v.abs()));
        let floor = 1e2 * f64::EPSILON * r_max / h_min / scale;
        let rel = err / scale;
        assert!(
            rel <= FD_TOLERANCE + floor,
            "{name}: ∂r/∂{} entry ({}, {}): closed form {:e} vs finite differences {:e} \
             (relative error {rel:.3e}, block scale {scale:.3e})",
            key_label(&factor.keys()[k]),
            at / cols,
            at % cols,
            block[at],
            fd[at]
        );
        worst = worst.max(rel);
    }
    worst
}

/// Largest relative error seen per factor, printed at the end of a test
/// (`cargo test --release --test factors -- --nocapture`).
#[derive(Default)]
struct Errors(BTreeMap<String, f64>);

impl Errors {
    fn record(&mut self, label: &str, err: f64) {
        let e = self.0.entry(label.to_string()).or_insert(0.0);
        *e = e.max(err);
    }

    fn print(&self, title: &str) {
        println!("{title}: largest relative error closed form vs finite differences");
        for (label, err) in &self.0 {
            println!("  {label:<28} {err:.2e}");
        }
    }
}

// ---------------------------------------------------------------------------------
// The factors of a model.
// ---------------------------------------------------------------------------------

/// The generic factors (prior, equality, Euler, trapezoidal with two Δt) on every
/// variable kind of `model`, with labels.
fn generic_factors(model: &Model, rng: &mut Rng) -> Vec<(String, Box<dyn Factor>)> {
    let mut kinds = vec![VarKind::Q, VarKind::Dq, VarKind::Ddq, VarKind::Force];
    let mut rates = vec![(VarKind::Q, VarKind::Dq), (VarKind::Dq, VarKind::Ddq)];
    if !model.independent.is_empty() {
        kinds.extend([VarKind::Z, VarKind::Dz, VarKind::Ddz]);
        rates.extend([(VarKind::Z, VarKind::Dz), (VarKind::Dz, VarKind::Ddz)]);
    }
    let mut out: Vec<(String, Box<dyn Factor>)> = Vec::new();
    for &kind in &kinds {
        let d = size(model, kind);
        let prior = Prior::new(kind, rng.values(d, 1.0));
        out.push((prior.name().to_string(), Box::new(prior)));
        let eq = Equality::new(kind, d);
        out.push((eq.name().to_string(), Box::new(eq)));
    }
    for &(x, dx) in &rates {
        let d = size(model, x);
        for dt in [1e-3, 0.05] {
            let ei = Euler::new(x, dx, d, dt);
            out.push((format!("{} dt={dt}", ei.name()), Box::new(ei)));
            let ti = Trapezoidal::new(x, dx, d, dt);
            out.push((format!("{} dt={dt}", ti.name()), Box::new(ti)));
        }
    }
    out
}

/// The model factors in dependent coordinates.
fn dependent_factors(model: &Arc<Model>) -> Vec<Box<dyn Factor>> {
    vec![
        Box::new(PositionConstraints::new(model.clone())),
        Box::new(VelocityConstraints::new(model.clone())),
        Box::new(Dynamics::new(model.clone())),
    ]
}

/// The kinematic factors in independent coordinates (none without them).
fn independent_kinematic_factors(model: &Arc<Model>) -> Vec<Box<dyn Factor>> {
    if model.independent.is_empty() {
        return Vec::new();
    }
    vec![
        Box::new(IndependentPosition::new(model.clone())),
        Box::new(IndependentVelocity::new(model.clone())),
        Box::new(IndependentAcceleration::new(model.clone())),
    ]
}

/// Every factor of `model`, with labels.
fn all_factors(model: &Arc<Model>, rng: &mut Rng) -> Vec<(String, Box<dyn Factor>)> {
    let mut out = generic_factors(model, rng);
    let mut own = dependent_factors(model);
    own.extend(independent_kinematic_factors(model));
    if !model.independent.is_empty() {
        own.push(Box::new(IndependentDynamics::new(model.clone())));
    }
    out.extend(own.into_iter().map(|f| (f.name().to_string(), f)));
    out
}

/// Runs `check_factor` on `factors` at TRIALS random points of every scene.
fn check_family(
    title: &str,
    seed: u64,
    factors: impl Fn(&Arc<Model>, &mut Rng) -> Vec<(String, Box<dyn Factor>)>,
) -> Errors {
    check_family_with(FD_STEP, title, seed, factors)
}

/// [`check_family`] with relative finite-difference step `step`.
fn check_family_with(
    step: f64,
    title: &str,
    seed: u64,
    factors: impl Fn(&Arc<Model>, &mut Rng) -> Vec<(String, Box<dyn Factor>)>,
) -> Errors {
    let mut rng = Rng(seed);
    let mut errors = Errors::default();
    let mut checked = 0;
    for name in SCENES {
        let model = load(name);
        let list = factors(&model, &mut rng);
        for _ in 0..TRIALS {
            let now = Step::random(&model, &mut rng);
            let before = Step::random(&model, &mut rng);
            for (label, factor) in &list {
                let xs = inputs(factor.as_ref(), &now, &before);
                let err =
                    check_factor_with(step, &format!("{name}: {label}"), factor.as_ref(), &xs, T);
                errors.record(label, err);
                checked += 1;
            }
        }
    }
    assert!(checked > 0, "{title}: nothing checked");
    errors.print(title);
    errors
}

fn labelled(factors: Vec<Box<dyn Factor>>) -> Vec<(String, Box<dyn Factor>)> {
    factors
        .into_iter()
        .map(|f| (f.name().to_string(), f))
        .collect()
}

// ---------------------------------------------------------------------------------
// Jacobians against finite differences, one test per factor family.
// ---------------------------------------------------------------------------------

#[test]
fn generic_factors_match_finite_differences() {
    let errors = check_family("generic factors", 1, |m, rng| generic_factors(m, rng));
    // Prior, equality, Euler and trapezoidal on q, q̇ (and z, ż where present).
    for label in [
        "f_prior(q)",
        "f_eq(dq)",
        "f_ei(q) dt=0.001",
        "f_ti(dq) dt=0.05",
        "f_ti(z) dt=0.001",
        "f_ei(dz) dt=0.05",
    ] {
        assert!(errors.0.contains_key(label), "{label} not checked");
    }
}

#[test]
fn tangent_integrators_match_finite_differences() {
    // P(q_t) e for q and q̇, trapezoidal and Euler, at coarse and fine steps; the
    // scenes include a redundant constraint (pick-and-place: the SVD path).
    let errors = check_family("tangent integrators", 7, |m, _| {
        let mut list: Vec<(String, Box<dyn Factor>)> = Vec::new();
        for (integrator, dt) in [(Integrator::Trapezoidal, 0.05), (Integrator::Euler, 0.001)] {
            for f in integrator.factors(m, Form::Tangent, dt) {
                list.push((format!("{} dt={dt}", f.name()), f));
            }
        }
        list
    });
    assert!(
        errors.0.contains_key("P f_ti(dq) dt=0.05"),
        "P f_ti(dq) not checked"
    );
}

#[test]
fn hermite_simpson_factors_match_finite_differences() {
    // The fourth-order integrators: the linear position rule on q and z, the velocity
    // rule with the dynamics at the step's middle (DC rows, IC rows), and both
    // projected on the tangent space; at a coarse and a fine step. The differences
    // step 1e-5: the projected residual P e is small beside e (at these off-manifold
    // states most of e lies across the manifold), and the round-off of e, ε‖e‖, not
    // the checker's floor ε‖Pe‖, limits small steps (1e-7 to 1e-6 scatter to 6e-6 on
    // pick-and-place; 3e-6 and 1e-5 agree to 1e-6).
    let errors = check_family_with(1e-5, "Hermite–Simpson", 11, |m, _| {
        let mut list: Vec<(String, Box<dyn Factor>)> = Vec::new();
        for dt in [0.05, 0.001] {
            let n = m.n();
            let hq = || HermitePosition::new(VarKind::Q, VarKind::Dq, VarKind::Ddq, n, dt);
            let hv = || SimpsonVelocity::dependent(m.clone(), dt);
            list.push((format!("f_hs(q) dt={dt}"), Box::new(hq())));
            list.push((format!("f_hs(dq) dt={dt}"), Box::new(hv())));
            list.push((
                format!("P f_hs(q) dt={dt}"),
                Box::new(Projected::new(m.clone(), Box::new(hq()))),
            ));
            list.push((
                format!("P f_hs(dq) dt={dt}"),
                Box::new(Projected::new(m.clone(), Box::new(hv()))),
            ));
            if !m.independent.is_empty() {
                let f = m.independent.len();
                list.push((
                    format!("f_hs(z) dt={dt}"),
                    Box::new(HermitePosition::new(
                        VarKind::Z,
                        VarKind::Dz,
                        VarKind::Ddz,
                        f,
                        dt,
                    )),
                ));
                list.push((
                    format!("f_hs(dz) dt={dt}"),
                    Box::new(SimpsonVelocity::independent(m.clone(), dt)),
                ));
            }
        }
        list
    });
    for label in [
        "f_hs(dq) dt=0.05",
        "P f_hs(dq) dt=0.001",
        "f_hs(dz) dt=0.05",
        "f_hs(z) dt=0.001",
    ] {
        assert!(errors.0.contains_key(label), "{label} not checked");
    }
}

#[test]
fn constraint_factors_match_finite_differences() {
    check_family("f^d_pc, f^d_vc", 2, |m, _| {
        let mut list = labelled(dependent_factors(m));
        list.retain(|(l, _)| l != "f^d_dyn");
        list
    });
}

#[test]
fn dynamics_factor_matches_finite_differences() {
    check_family("f^d_dyn", 3, |m, _| {
        labelled(vec![Box::new(Dynamics::new(m.clone()))])
    });
}

/// Scenes that identify masses (of bodies and of a point), an inertia, gravity
/// (bilinear with the masses), a spring's and a rotational spring's stiffness and
/// damping, some with unknown inputs.
const IDENTIFYING: [&str; 4] = [
    "fourbar-masses.yaml",
    "spring-damper.yaml",
    "point-mass.yaml",
    "loads.yaml",
];

/// The model of an identification scene of tests/data, and the coordinates its unknown
/// inputs act on.
fn identifying(name: &str) -> (Arc<Model>, Vec<usize>) {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data/identification")
        .join(name);
    let scene = Scene::load(&path).unwrap_or_else(|e| panic!("{name}: {e}"));
    let model = Arc::new(Model::new(&scene).unwrap_or_else(|e| panic!("{name}: {e}")));
    let actuated = model.estimation.inputs.iter().map(|&(c, _)| c).collect();
    (model, actuated)
}

#[test]
fn parametric_dynamics_matches_finite_differences() {
    // f^d_par on scenes that identify masses (of bodies and of a point), an inertia,
    // gravity (bilinear with the masses), a spring's and a rotational spring's
    // stiffness and damping, parameters inside torques' and forces' expressions
    // (nonlinearly too), with and without unknown inputs: ∂/∂q, ∂/∂q̇, ∂/∂q̈, ∂/∂p
    // and ∂/∂u.
    let mut rng = Rng(11);
    let mut checked = 0;
    for name in IDENTIFYING {
        let (model, actuated) = identifying(name);
        for with_inputs in [false, true] {
            let on = if with_inputs {
                actuated.clone()
            } else {
                Vec::new()
            };
            if with_inputs && on.is_empty() {
                continue;
            }
            let factor = ParametricDynamics::new(model.clone(), on).expect("parameters");
            for _ in 0..TRIALS {
                let now = Step::random(&model, &mut rng);
                let before = Step::random(&model, &mut rng);
                let mut xs = inputs(&factor, &now, &before);
                if with_inputs {
                    // The Force key holds one entry per input coordinate.
                    xs[4].truncate(actuated.len());
                }
                let err = check_factor_with(FD_STEP, &format!("{name}: f^d_par"), &factor, &xs, T);
                assert!(err < FD_TOLERANCE, "{name}: f^d_par off by {err:e}");
                checked += 1;
            }
        }
    }
    assert_eq!(checked, 5 * TRIALS);
}

#[test]
fn hermite_simpson_through_the_estimates_dynamics_matches_finite_differences() {
    // An estimate's Hermite–Simpson velocity factor, its stage the dynamics factor of
    // the estimate (f^d_par with identified parameters, with and without unknown
    // inputs, at both ends of the step), bare and projected, at a coarse and a fine
    // step: ∂/∂q, ∂/∂q̇, ∂/∂q̈ at both ends and ∂/∂p, ∂/∂u at both.
    let mut rng = Rng(12);
    let mut checked = 0;
    for name in IDENTIFYING {
        let (model, actuated) = identifying(name);
        for with_inputs in [false, true] {
            if with_inputs && actuated.is_empty() {
                continue;
            }
            let on = if with_inputs {
                actuated.clone()
            } else {
                Vec::new()
            };
            for dt in [0.05, 0.001] {
                let stage = || {
                    Box::new(
                        ParametricDynamics::new(model.clone(), on.clone()).expect("parameters"),
                    ) as Box<dyn Factor>
                };
                let bare = SimpsonVelocityThrough::new(stage(), dt);
                let projected = Projected::new(
                    model.clone(),
                    Box::new(SimpsonVelocityThrough::new(stage(), dt)),
                );
                for factor in [&bare as &dyn Factor, &projected] {
                    let label = format!("{name}: {} dt={dt}", factor.name());
                    for _ in 0..TRIALS {
                        let now = Step::random(&model, &mut rng);
                        let before = Step::random(&model, &mut rng);
                        let mut xs = inputs(factor, &now, &before);
                        for (x, k) in xs.iter_mut().zip(factor.keys()) {
                            if k.kind == VarKind::Force {
                                // One entry per input coordinate.
                                x.truncate(actuated.len());
                            }
                        }
                        let err = check_factor_with(FD_STEP, &label, factor, &xs, T);
                        assert!(err < 1e-5, "{label} off by {err:e}");
                        checked += 1;
                    }
                }
            }
        }
    }
    assert_eq!(checked, 5 * 2 * 2 * TRIALS);
}

#[test]
fn hermite_simpson_through_the_plain_dynamics_is_the_simulators_factor() {
    // With f^d_dyn as its stage, the estimate's factor is the simulator's
    // Hermite–Simpson velocity factor: the same residual and Jacobians.
    let mut rng = Rng(13);
    for name in SCENES {
        let model = load(name);
        let dt = 0.02;
        let through = SimpsonVelocityThrough::new(Box::new(Dynamics::new(model.clone())), dt);
        let plain = SimpsonVelocity::dependent(model.clone(), dt);
        assert_eq!(through.keys(), plain.keys(), "{name}");
        let mut ws = Workspace::new(through.scratch().or(plain.scratch()));
        for _ in 0..TRIALS {
            let now = Step::random(&model, &mut rng);
            let before = Step::random(&model, &mut rng);
            let xs = inputs(&plain, &now, &before);
            let a = evaluate(&through, T, &xs, true, &mut ws);
            let b = evaluate(&plain, T, &xs, true, &mut ws);
            let close = |x: &[f64], y: &[f64]| {
                x.iter()
                    .zip(y)
                    .all(|(u, v)| (u - v).abs() <= 1e-9 * (1.0 + v.abs()))
            };
            assert!(close(&a.r, &b.r), "{name}: residuals {:?} {:?}", a.r, b.r);
            for (ja, jb) in a.jac.unwrap().iter().zip(b.jac.as_ref().unwrap()) {
                assert!(close(ja, jb), "{name}: Jacobians differ");
            }
        }
    }
}

#[test]
fn inverse_dynamics_factors_match_finite_differences() {
    // f^d_idyn on every scene (∂/∂Q included), and the component and prescribed priors.
    let errors = check_family("f^d_idyn, priors on components", 6, |m, rng| {
        let n = m.n();
        let idx: Vec<usize> = (0..n).step_by(2).collect();
        let steps = 3;
        let table: Vec<f64> = rng.values(steps * idx.len(), 1.0);
        let mut list: Vec<(String, Box<dyn Factor>)> =
            vec![("f^d_idyn".into(), Box::new(Dynamics::inverse(m.clone())))];
        if !m.independent.is_empty() {
            list.push((
                "f^i_idyn".into(),
                Box::new(IndependentDynamics::inverse(m.clone())),
            ));
        }
        list.push((
            "f_prior(Q[…])".into(),
            Box::new(ComponentPrior::new(
                VarKind::Force,
                n,
                idx.clone(),
                vec![0.0; idx.len()],
            )),
        ));
        list.push((
            "f_prior(q prescribed)".into(),
            Box::new(PrescribedMotion::new(
                n,
                idx,
                std::sync::Arc::new(table),
                0.0,
                1.0,
            )),
        ));
        list
    });
    assert_eq!(errors.0.len(), 4);
}

#[test]
fn inverse_dynamics_with_zero_force_is_forward_dynamics() {
    let mut rng = Rng(77);
    for name in SCENES {
        let model = load(name);
        let step = Step::random(&model, &mut rng);
        let forward = Dynamics::new(model.clone());
        let inverse = Dynamics::inverse(model.clone());
        let zero = vec![0.0; model.n()];
        let mut ws = workspace_for(&forward);
        let (mut a, mut b) = (vec![0.0; model.n()], vec![0.0; model.n()]);
        forward
            .evaluate(0.3, &[&step.q, &step.dq, &step.ddq], &mut a, None, &mut ws)
            .unwrap();
        inverse
            .evaluate(
                0.3,
                &[&step.q, &step.dq, &step.ddq, &zero],
                &mut b,
                None,
                &mut ws,
            )
            .unwrap();
        assert!(
            max_abs_diff(&a, &b) <= 1e-12 * (1.0 + max_abs(&a)),
            "{name}"
        );
    }
}

#[test]
fn inverse_dynamics_on_some_coordinates_is_the_full_factor_with_the_other_forces_zero() {
    // f^d_idyn with Q on every other coordinate (Q then has one entry per actuated
    // coordinate): the full factor with the other forces 0, its ∂e/∂Q the full one's
    // columns on the actuated coordinates.
    let mut rng = Rng(91);
    for name in SCENES {
        let model = load(name);
        let n = model.n();
        let step = Step::random(&model, &mut rng);
        let on: Vec<usize> = (0..n).rev().step_by(2).collect();
        let p = on.len();
        let acting: Vec<f64> = on.iter().map(|&i| step.force[i]).collect();
        let mut spread = vec![0.0; n];
        for &i in &on {
            spread[i] = step.force[i];
        }
        let full = Dynamics::inverse(model.clone());
        let some = Dynamics::inverse_on(model.clone(), on.clone());
        let mut ws = workspace_for(&some);
        let run = |f: &Dynamics, force: &[f64], ws: &mut Workspace| {
            let mut r = vec![0.0; n];
            let mut jac = vec![vec![0.0; n * n]; 3];
            jac.push(vec![0.0; n * force.len()]);
            f.evaluate(
                0.3,
                &[&step.q, &step.dq, &step.ddq, force],
                &mut r,
                Some(&mut jac),
                ws,
            )
            .unwrap();
            (r, jac)
        };
        let (r_full, j_full) = run(&full, &spread, &mut ws);
        let (r_some, j_some) = run(&some, &acting, &mut ws);
        assert!(same_bits(&r_full, &r_some), "{name}: residual");
        for k in 0..3 {
            assert!(same_bits(&j_full[k], &j_some[k]), "{name}: Jacobian {k}");
        }
        for i in 0..n {
            for (c, &j) in on.iter().enumerate() {
                assert_eq!(
                    j_some[3][i * p + c],
                    j_full[3][i * n + j],
                    "{name}: ∂e/∂Q[{i}][{j}]"
                );
            }
        }
    }
}

#[test]
fn inverse_dynamics_along_directions_is_the_jacobian_times_them() {
    // f^d_idyn on some coordinates and f^i_idyn.
    let mut rng = Rng(17);
    for name in SCENES {
        let model = load(name);
        let n = model.n();
        let on: Vec<usize> = (0..n).step_by(2).collect();
        let mut factors: Vec<Box<dyn Factor>> =
            vec![Box::new(Dynamics::inverse_on(model.clone(), on.clone()))];
        if !model.independent.is_empty() {
            factors.push(Box::new(IndependentDynamics::inverse(model.clone())));
        }
        for factor in &factors {
            check_along(factor.as_ref(), &model, name, &mut rng);
        }
    }
    // f^d_dyn of a small mechanism forms its Jacobians.
    let model = load("fourbar.yaml");
    let forward = Dynamics::new(model.clone());
    assert!(model.n() < mbfg::factors::ALONG_FROM);
    assert!(forward.along().is_none());
}

#[test]
fn forward_dynamics_of_a_large_mechanism_along_directions_is_the_jacobian_times_them() {
    let mut rng = Rng(23);
    for name in ["scale/n-fourbar-10.yaml", "scale/n-pendulum-8.yaml"] {
        let model = load(name);
        assert!(model.n() >= mbfg::factors::ALONG_FROM, "{name}");
        assert!(!model.independent.is_empty(), "{name}");
        check_along(&Dynamics::new(model.clone()), &model, name, &mut rng);
        check_along(
            &IndependentDynamics::new(model.clone()),
            &model,
            name,
            &mut rng,
        );
    }
    // f^i_dyn of a small mechanism forms its Jacobians.
    let model = load("fourbar-theta.yaml");
    assert!(IndependentDynamics::new(model).along().is_none());
}

/// Near a singular configuration the dynamics regularize K, and their Jacobians
/// carry the regularization's derivative, which directions leave out: f_dyn and
/// f^i_dyn decline there (their Jacobians are formed instead). Without this the 40
/// four-bar loops' DC batch at 10 ms no longer converged with the paper's
/// integrators.
#[test]
fn dynamics_decline_directions_where_they_regularize() {
    let model = load("scale/n-fourbar-10.yaml");
    let theta: f64 = 1e-3;
    let mut q = model.initial.q.as_slice().to_vec();
    for i in 0..=10 {
        for (axis, value) in [("x", i as f64 + theta.cos()), ("y", theta.sin())] {
            let k = model
                .index_of(&format!("B{i}.{axis}"))
                .expect("a coordinate");
            q[k] = value;
        }
    }
    q[model.index_of("theta").expect("the crank angle")] = theta;
    let (_, w, _) = DynamicsKernel::regularization_at(&model, &q);
    assert!(w > 0.0, "not regularized at θ = {theta}");
    let mut rng = Rng(5);
    let dq = rng.values(model.n(), 1.0);
    let factors: [Box<dyn Factor>; 2] = [
        Box::new(Dynamics::new(model.clone())),
        Box::new(IndependentDynamics::new(model.clone())),
    ];
    for factor in &factors {
        let along = factor.along().expect("linearizes along directions");
        let xs = [q.clone(), dq.clone(), vec![0.0; factor.size(2)]];
        let c = 3;
        let dirs: Vec<Vec<f64>> = xs.iter().map(|x| rng.values(x.len() * c, 1.0)).collect();
        let slices: Vec<&[f64]> = xs.iter().map(Vec::as_slice).collect();
        let dir_slices: Vec<&[f64]> = dirs.iter().map(Vec::as_slice).collect();
        let mut ws = workspace_for(factor.as_ref());
        let (mut r, mut out) = (vec![0.0; factor.dim()], vec![0.0; factor.dim() * c]);
        let done = along
            .evaluate_along(T, &slices, &mut r, &dir_slices, c, &mut out, &mut ws)
            .unwrap();
        assert!(
            !done,
            "{} linearized along directions where it regularizes",
            factor.name()
        );
    }
}

/// evaluate_along against J·V from the (finite-difference checked) Jacobians; V has
/// zero rows and columns like a null-space basis restricted to a factor's keys; too
/// many nonzero columns are declined.
fn check_along(factor: &dyn Factor, model: &Model, name: &str, rng: &mut Rng) {
    let n = model.n();
    assert!(factor.along().is_some());
    let step = Step::random(model, rng);
    let mut xs = inputs(factor, &step, &step);
    if let Some(f) = xs.get_mut(3) {
        f.truncate(factor.size(3));
    }
    let dim = factor.dim();
    let c = 7;
    let dirs: Vec<Vec<f64>> = xs
        .iter()
        .map(|x| {
            (0..x.len() * c)
                .map(|i| {
                    let (row, col) = (i / c, i % c);
                    if col == 3 || (row + col) % 3 == 0 {
                        0.0
                    } else {
                        rng.values(1, 1.0)[0]
                    }
                })
                .collect()
        })
        .collect();
    let slices: Vec<&[f64]> = xs.iter().map(Vec::as_slice).collect();
    let mut ws = workspace_for(factor);
    let mut r = vec![0.0; dim];
    let mut jac: Vec<Vec<f64>> = xs.iter().map(|x| vec![0.0; dim * x.len()]).collect();
    factor
        .evaluate(T, &slices, &mut r, Some(&mut jac), &mut ws)
        .unwrap();
    let mut expect = vec![0.0; dim * c];
    for (a, x) in xs.iter().enumerate() {
        let d = x.len();
        for i in 0..dim {
            for j in 0..c {
                expect[i * c + j] += (0..d)
                    .map(|k| jac[a][i * d + k] * dirs[a][k * c + j])
                    .sum::<f64>();
            }
        }
    }
    let dir_slices: Vec<&[f64]> = dirs.iter().map(Vec::as_slice).collect();
    let (mut r2, mut out) = (vec![f64::NAN; dim], vec![f64::NAN; dim * c]);
    let along = factor.along().expect("linearizes along directions");
    let done = along
        .evaluate_along(T, &slices, &mut r2, &dir_slices, c, &mut out, &mut ws)
        .unwrap();
    assert!(done, "{name}: {}", factor.name());
    assert!(same_bits(&r, &r2), "{name}: {} residual", factor.name());
    let scale = expect.iter().fold(1.0f64, |m, v| m.max(v.abs()));
    assert!(
        max_abs_diff(&out, &expect) <= 1e-10 * scale,
        "{name}: {} J·V off by {:.2e}",
        factor.name(),
        max_abs_diff(&out, &expect)
    );
    for (i, v) in out.iter().enumerate() {
        if i % c == 3 {
            assert_eq!(*v, 0.0, "{name}: a zero direction gives 0");
        }
    }
    // More nonzero directions than the Jacobians have columns: declined.
    let wide = 3 * n + 2;
    let dense: Vec<Vec<f64>> = xs.iter().map(|x| rng.values(x.len() * wide, 1.0)).collect();
    let dense_slices: Vec<&[f64]> = dense.iter().map(Vec::as_slice).collect();
    let mut out = vec![0.0; dim * wide];
    assert!(!along
        .evaluate_along(T, &slices, &mut r2, &dense_slices, wide, &mut out, &mut ws)
        .unwrap());
}

#[test]
fn independent_kinematic_factors_match_finite_differences() {
    let errors = check_family("f^i_pc, f^i_vc, f^i_ac", 4, |m, _| {
        labelled(independent_kinematic_factors(m))
    });
    assert_eq!(errors.0.len(), 3);
}

#[test]
fn independent_dynamics_factor_matches_finite_differences() {
    let errors = check_family("f^i_dyn", 5, |m, _| {
        if m.independent.is_empty() {
            return Vec::new();
        }
        labelled(vec![Box::new(IndependentDynamics::new(m.clone()))])
    });
    assert_eq!(errors.0.len(), 1);
}

// ---------------------------------------------------------------------------------
// The dynamics kernel and the constraint Hessians, directly.
// ---------------------------------------------------------------------------------

/// Central-difference Jacobian (row-major rows × x.len()) of a vector function.
fn fd_jacobian(x: &[f64], f: &dyn Fn(&[f64]) -> Vec<f64>) -> Vec<f64> {
    fd_jacobian_with(FD_STEP, x, f)
}

/// [`fd_jacobian`] with a given relative step.
fn fd_jacobian_with(step: f64, x: &[f64], f: &dyn Fn(&[f64]) -> Vec<f64>) -> Vec<f64> {
    let rows = f(x).len();
    let cols = x.len();
    let mut out = vec![0.0; rows * cols];
    for j in 0..cols {
        let h = step * x[j].abs().max(1.0);
        let (mut up, mut dn) = (x.to_vec(), x.to_vec());
        up[j] += h;
        dn[j] -= h;
        let step = up[j] - dn[j];
        let (fu, fd) = (f(&up), f(&dn));
        for i in 0..rows {
            out[i * cols + j] = (fu[i] - fd[i]) / step;
        }
    }
    out
}

/// max |a − b| / max(1, |a|max), asserted ≤ FD_TOLERANCE.
fn assert_close(a: &[f64], b: &[f64], cols: usize, what: &str) -> f64 {
    assert_eq!(a.len(), b.len(), "{what}: sizes");
    let scale = a.iter().fold(1.0f64, |m, v| m.max(v.abs()));
    let (mut err, mut at) = (0.0f64, 0);
    for (e, (x, y)) in a.iter().zip(b).enumerate() {
        let d = (x - y).abs();
        if d > err || d.is_nan() {
            err = d;
            at = e;
        }
    }
    let rel = err / scale;
    assert!(
        rel <= FD_TOLERANCE,
        "{what}: entry ({}, {}): closed form {:e} vs finite differences {:e} \
         (relative error {rel:.3e}, scale {scale:.3e})",
        at / cols,
        at % cols,
        a[at],
        b[at]
    );
    rel
}

/// q̈ and, when asked for, (∂q̈/∂q, ∂q̈/∂q̇).
type KernelOutput = (Vec<f64>, Option<(Vec<f64>, Vec<f64>)>);

/// q̈ of the dynamics kernel and, with `jacobians`, ∂q̈/∂q and ∂q̈/∂q̇.
fn kernel(
    model: &Model,
    q: &[f64],
    dq: &[f64],
    force: Option<&[f64]>,
    jacobians: bool,
) -> KernelOutput {
    kernel_with(model, None, (q, dq), force, jacobians)
}

/// [`kernel`] with K factored sparse (`sparse`) or dense.
fn kernel_with(
    model: &Model,
    sparse: Option<&dynamics::KktStructure>,
    (q, dq): (&[f64], &[f64]),
    force: Option<&[f64]>,
    jacobians: bool,
) -> KernelOutput {
    let n = model.n();
    let mut ws = Workspace::new(DynamicsKernel::scratch(model));
    let (mut scratch, _) = KernelScratch::new(model, sparse, ws.stack());
    let mut ddq = vec![f64::NAN; n];
    let mut jq = vec![f64::NAN; n * n];
    let mut jv = vec![f64::NAN; n * n];
    DynamicsKernel::evaluate(
        model,
        q,
        dq,
        T,
        force,
        &mut ddq,
        jacobians.then_some((&mut jq[..], &mut jv[..])),
        &mut scratch,
    )
    .unwrap_or_else(|e| panic!("dynamics kernel: {e}"));
    (ddq, jacobians.then_some((jq, jv)))
}

/// A large mechanism's KKT system factored sparse gives the dense LU's q̈ and
/// Jacobians, with the scene's forces and with given ones, off the constraint
/// manifold (the 100 four-bar loops, 405 unknowns; the 64-link pendulum, 320).
#[test]
fn a_sparse_kkt_system_gives_the_dense_results() {
    let mut rng = Rng(41);
    for name in ["scale/n-fourbar-100.yaml", "scale/n-pendulum-64.yaml"] {
        let model = load(name);
        let n = model.n();
        let structure = dynamics::KktStructure::for_model(&model)
            .unwrap_or_else(|| panic!("{name}: large enough to be factored sparse"));
        let q = random_configuration(&model, &mut rng, 0.05);
        let dq = rng.values(n, 1.0);
        let given = rng.values(n, 2.0);
        for force in [None, Some(given.as_slice())] {
            let (a, ja) = kernel_with(&model, Some(&structure), (&q, &dq), force, true);
            let (b, jb) = kernel_with(&model, None, (&q, &dq), force, true);
            let close = |x: &[f64], y: &[f64], what: &str| {
                let scale = y.iter().fold(1.0f64, |m, v| m.max(v.abs()));
                let worst = x
                    .iter()
                    .zip(y)
                    .fold(0.0f64, |m, (u, v)| m.max((u - v).abs()));
                assert!(
                    worst <= 1e-9 * scale,
                    "{name}: {what} differs by {worst:.1e} (of {scale:.1e})"
                );
            };
            close(&a, &b, "q̈");
            let ((jqa, jva), (jqb, jvb)) = (ja.unwrap(), jb.unwrap());
            close(&jqa, &jqb, "∂q̈/∂q");
            close(&jva, &jvb, "∂q̈/∂q̇");
        }
    }
}

/// The kernel's ∂q̈/∂q and ∂q̈/∂q̇ hold anywhere, not only on the constraint manifold:
/// checked at states far from it (|Φ(q)| and |Φ_q q̇| of order 1), with the scene's
/// forces and with a given force vector (inverse dynamics), and q̈ itself against the
/// KKT solution of `dynamics::lagrange` at the same inconsistent state (where Φ_q
/// is not near rank loss, so the kernel is the KKT system).
#[test]
fn dynamics_kernel_jacobians_hold_off_the_constraint_manifold() {
    let mut rng = Rng(6);
    let mut errors = Errors::default();
    let mut regularized = 0;
    for name in SCENES {
        let model = load(name);
        let n = model.n();
        for _ in 0..TRIALS {
            let q = random_configuration(&model, &mut rng, 0.3);
            let dq = rng.values(n, 1.0);
            let qv = DVector::from_column_slice(&q);
            let dqv = DVector::from_column_slice(&dq);
            let phi = model.phi(&qv).amax();
            let vel = (model.jacobian(&qv) * &dqv).amax();
            assert!(
                phi > 1e-3 && vel > 1e-3,
                "{name}: state should be inconsistent (|Φ| = {phi:.1e}, |Φ_q q̇| = {vel:.1e})"
            );
            let given = rng.values(n, 2.0);
            for force in [None, Some(given.as_slice())] {
                let what = match force {
                    None => format!("{name}: kernel, scene forces"),
                    Some(_) => format!("{name}: kernel, given force"),
                };
                let (ddq, jac) = kernel(&model, &q, &dq, force, true);
                let (jq, jv) = jac.unwrap();
                let (plain, _) = kernel(&model, &q, &dq, force, false);
                assert!(
                    same_bits(&plain, &ddq),
                    "{what}: q̈ depends on whether Jacobians are requested"
                );
                let fd_q = fd_jacobian(&q, &|x| kernel(&model, x, &dq, force, false).0);
                let fd_v = fd_jacobian(&dq, &|v| kernel(&model, &q, v, force, false).0);
                let eq = assert_close(&jq, &fd_q, n, &format!("{what}: ∂q̈/∂q"));
                let ev = assert_close(&jv, &fd_v, n, &format!("{what}: ∂q̈/∂q̇"));
                let label = if force.is_none() {
                    "kernel (scene forces)"
                } else {
                    "kernel (given force)"
                };
                errors.record(label, eq.max(ev));
                // Where Φ_q is far from losing a rank the kernel is the KKT system
                // (near rank loss it is regularized: tested below).
                let (_, weight, _) = DynamicsKernel::regularization_at(&model, &q);
                if weight > 0.0 {
                    regularized += 1;
                }
                if force.is_none() && weight == 0.0 {
                    let kkt = dynamics::lagrange(&model, &qv, &dqv, T)
                        .unwrap_or_else(|e| panic!("{name}: lagrange: {e}"));
                    let scale = kkt.ddq.amax().max(1.0);
                    let err = ddq
                        .iter()
                        .zip(kkt.ddq.iter())
                        .fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
                    assert!(
                        err <= 1e-9 * scale,
                        "{name}: kernel q̈ vs lagrange q̈ off the manifold: {err:.3e}"
                    );
                }
            }
        }
    }
    // A random state off the manifold lands near rank loss now and then (one of
    // pick-and-place's); most must be compared with the KKT solution.
    assert!(
        regularized <= 2 * SCENES.len(),
        "{regularized} of {} states regularized",
        2 * TRIALS * SCENES.len()
    );
    errors.print("dynamics kernel off the manifold");
}

/// `add_weighted_hessians` adds ∂(Φ_qᵀλ)/∂q over the active constraints, with λ
/// indexed like `model.active` (pick-and-place has a redundant constraint to skip).
#[test]
fn weighted_hessians_match_finite_differences_of_phi_q_transpose_lambda() {
    let mut rng = Rng(7);
    let mut errors = Errors::default();
    for name in SCENES {
        let model = load(name);
        let n = model.n();
        if *name == "pick-and-place.yaml" {
            assert_eq!(model.redundant.len(), 1, "{name}: one redundant constraint");
        }
        for _ in 0..TRIALS {
            let q = random_configuration(&model, &mut rng, 0.2);
            let lambda = rng.values(model.active.len(), 3.0);
            let base = rng.values(n * n, 1.0);
            let mut out = base.clone();
            model.add_weighted_hessians(&q, &lambda, &mut out);
            let added: Vec<f64> = out.iter().zip(&base).map(|(a, b)| a - b).collect();
            let phi_q_t_lambda = |x: &[f64]| -> Vec<f64> {
                let jac = model.jacobian(&DVector::from_column_slice(x));
                (0..n)
                    .map(|i| {
                        model
                            .active
                            .iter()
                            .zip(&lambda)
                            .map(|(&k, l)| jac[(k, i)] * l)
                            .sum()
                    })
                    .collect()
            };
            let fd = fd_jacobian(&q, &phi_q_t_lambda);
            let err = assert_close(&added, &fd, n, &format!("{name}: ∂(Φ_qᵀλ)/∂q"));
            errors.record("add_weighted_hessians", err);
        }
    }
    errors.print("Model::add_weighted_hessians");
}

// ---------------------------------------------------------------------------------
// The dynamics factors against the classical solutions.
// ---------------------------------------------------------------------------------

/// A consistent state away from the initial one: perturb the independent
/// coordinates, close the position problem, give random independent velocities.
fn consistent_state(model: &Model, independent: &[usize], rng: &mut Rng) -> (Vec<f64>, Vec<f64>) {
    let mut q = model.initial.q.clone();
    for &i in independent {
        q[i] += 0.2 * rng.uniform();
    }
    kinematics::solve_position(model, &mut q, independent).expect("position problem");
    let dz: Vec<f64> = independent.iter().map(|_| rng.uniform()).collect();
    let dq = kinematics::solve_velocity(model, &q, independent, &dz).expect("velocity problem");
    (q.as_slice().to_vec(), dq.as_slice().to_vec())
}

fn max_abs_diff(a: &[f64], b: &[f64]) -> f64 {
    a.iter()
        .zip(b)
        .fold(0.0f64, |m, (x, y)| m.max((x - y).abs()))
}

fn max_abs(a: &[f64]) -> f64 {
    a.iter().fold(0.0f64, |m, x| m.max(x.abs()))
}

/// At a consistent state, f^d_dyn at q̈_t = 0 is the KKT acceleration of
/// `dynamics::lagrange`, f^i_dyn at z̈_t = 0 the R-matrix z̈, and the kinematic
/// factors vanish at the matching values.
#[test]
fn dynamics_factors_give_the_classical_accelerations_at_consistent_states() {
    let mut rng = Rng(8);
    for name in SCENES {
        let model = load(name);
        let (n, f) = (model.n(), model.independent.len());
        let independent = if model.independent.is_empty() {
            kinematics::choose_independent(&model, &model.initial.q)
        } else {
            model.independent.clone()
        };
        assert_eq!(independent.len(), model.dof(), "{name}");
        let dynamics_factor = Dynamics::new(model.clone());
        let independent_dynamics = IndependentDynamics::new(model.clone());
        for _ in 0..TRIALS {
            let (q, dq) = consistent_state(&model, &independent, &mut rng);
            let (qv, dqv) = (
                DVector::from_column_slice(&q),
                DVector::from_column_slice(&dq),
            );
            let kkt = dynamics::lagrange(&model, &qv, &dqv, T)
                .unwrap_or_else(|e| panic!("{name}: lagrange: {e}"));
            let scale = kkt.ddq.amax().max(1.0);

            let zero = vec![0.0; n];
            let xs = vec![q.clone(), dq.clone(), zero];
            let mut ws = workspace_for(&dynamics_factor);
            let r = evaluate(&dynamics_factor, T, &xs, false, &mut ws).r;
            let err = max_abs_diff(&r, kkt.ddq.as_slice());
            assert!(
                err <= 1e-10 * scale,
                "{name}: f^d_dyn(q̈_t = 0) − q̈_lagrange = {err:.3e} (scale {scale:.3e})"
            );

            // f^d_dyn vanishes at the KKT acceleration; so do the constraint factors.
            let xs = vec![q.clone(), dq.clone(), kkt.ddq.as_slice().to_vec()];
            let r = evaluate(&dynamics_factor, T, &xs, false, &mut ws).r;
            assert!(
                max_abs(&r) <= 1e-10 * scale,
                "{name}: f^d_dyn at q̈_lagrange"
            );
            for factor in [
                &PositionConstraints::new(model.clone()) as &dyn Factor,
                &VelocityConstraints::new(model.clone()),
            ] {
                let xs = inputs_from(factor, &q, &dq, kkt.ddq.as_slice(), &independent);
                let mut ws = workspace_for(factor);
                let r = evaluate(factor, T, &xs, false, &mut ws).r;
                let tol = 1e-10 * (1.0 + max_abs(&q).powi(2)) * (1.0 + max_abs(&dq));
                assert!(
                    max_abs(&r) <= tol,
                    "{name}: {} = {:.3e} at a consistent state",
                    factor.name(),
                    max_abs(&r)
                );
            }

            if f == 0 {
                continue;
            }
            let rm = dynamics::r_matrix(&model, &qv, &dqv, T, &model.independent)
                .unwrap_or_else(|e| panic!("{name}: r_matrix: {e}"));
            let xs = vec![q.clone(), dq.clone(), vec![0.0; f]];
            let mut ws = workspace_for(&independent_dynamics);
            let r = evaluate(&independent_dynamics, T, &xs, false, &mut ws).r;
            let err = max_abs_diff(&r, rm.ddz.as_slice());
            assert!(
                err <= 1e-10 * scale,
                "{name}: f^i_dyn(z̈_t = 0) − z̈_R = {err:.3e} (scale {scale:.3e})"
            );
            for factor in independent_kinematic_factors(&model) {
                let xs = inputs_from(factor.as_ref(), &q, &dq, kkt.ddq.as_slice(), &independent);
                let mut ws = workspace_for(factor.as_ref());
                let r = evaluate(factor.as_ref(), T, &xs, false, &mut ws).r;
                let tol = 1e-9 * scale.max(max_abs(&q).powi(2));
                assert!(
                    max_abs(&r) <= tol,
                    "{name}: {} = {:.3e} at a consistent state",
                    factor.name(),
                    max_abs(&r)
                );
            }
        }
    }
}

/// Inputs of a model factor at a consistent state: z, ż, z̈ taken from q, q̇, q̈.
fn inputs_from(
    factor: &dyn Factor,
    q: &[f64],
    dq: &[f64],
    ddq: &[f64],
    independent: &[usize],
) -> Vec<Vec<f64>> {
    let pick = |v: &[f64]| independent.iter().map(|&i| v[i]).collect::<Vec<_>>();
    factor
        .keys()
        .iter()
        .map(|k| match k.kind {
            VarKind::Q => q.to_vec(),
            VarKind::Dq => dq.to_vec(),
            VarKind::Ddq => ddq.to_vec(),
            VarKind::Z => pick(q),
            VarKind::Dz => pick(dq),
            VarKind::Ddz => pick(ddq),
            VarKind::Force => panic!("{}: no force at a state", factor.name()),
            VarKind::Param => panic!("{}: no parameters at a state", factor.name()),
        })
        .collect()
}

// ---------------------------------------------------------------------------------
// Workspace hygiene.
// ---------------------------------------------------------------------------------

/// Evaluating a factor twice with the same workspace, after another evaluation at a
/// different point or with the workspace filled with garbage, gives bit-identical
/// outputs: nothing is carried over between evaluations.
#[test]
fn evaluation_leaves_no_state_in_the_workspace() {
    let mut rng = Rng(9);
    let mut count = 0;
    for name in SCENES {
        let model = load(name);
        let a_now = Step::random(&model, &mut rng);
        let a_before = Step::random(&model, &mut rng);
        let b_now = Step::random(&model, &mut rng);
        let b_before = Step::random(&model, &mut rng);
        for (label, factor) in all_factors(&model, &mut rng) {
            let factor = factor.as_ref();
            let what = format!("{name}: {label}");
            let xa = inputs(factor, &a_now, &a_before);
            let xb = inputs(factor, &b_now, &b_before);
            let mut ws = workspace_for(factor);
            let first = evaluate(factor, T, &xa, true, &mut ws);
            let same = |e: &Evaluation, when: &str| {
                assert!(same_bits(&e.r, &first.r), "{what}: residual differs {when}");
                let (j1, j2) = (e.jac.as_ref().unwrap(), first.jac.as_ref().unwrap());
                for (k, (a, b)) in j1.iter().zip(j2).enumerate() {
                    assert!(
                        same_bits(a, b),
                        "{what}: ∂r/∂{} differs {when}",
                        key_label(&factor.keys()[k])
                    );
                }
            };
            let again = evaluate(factor, T, &xa, true, &mut ws);
            same(&again, "on a second evaluation with the same workspace");
            evaluate(factor, T, &xb, true, &mut ws);
            evaluate(factor, T + 0.1, &xb, false, &mut ws);
            let after = evaluate(factor, T, &xa, true, &mut ws);
            same(&after, "after evaluations at another point");
            {
                let stack = ws.stack();
                let len = stack.len_bytes() / std::mem::size_of::<f64>();
                if len > 0 {
                    let _garbage = stack.make_with(len, |_| f64::NAN);
                }
            }
            let dirty = evaluate(factor, T, &xa, true, &mut ws);
            same(&dirty, "with a workspace full of garbage");
            let plain = evaluate(factor, T, &xa, false, &mut ws);
            assert!(
                same_bits(&plain.r, &first.r),
                "{what}: residual-only evaluation differs"
            );
            count += 1;
        }
    }
    assert!(count > 0);
}

// ---------------------------------------------------------------------------------
// The checker itself.
// ---------------------------------------------------------------------------------

/// A deliberate defect injected into a correct factor.
#[derive(Clone, Copy, Debug)]
enum Defect {
    /// One entry of block `key` off by 1e-5 of the block's scale.
    WrongEntry { key: usize },
    /// One entry of block `key` left unwritten.
    Unwritten { key: usize },
    /// The residual-only evaluation off in its last digit.
    ResidualOnly,
}

struct Defective {
    inner: Box<dyn Factor>,
    defect: Defect,
}

impl Factor for Defective {
    fn name(&self) -> &str {
        self.inner.name()
    }
    fn keys(&self) -> &[Key] {
        self.inner.keys()
    }
    fn dim(&self) -> usize {
        self.inner.dim()
    }
    fn size(&self, key: usize) -> usize {
        self.inner.size(key)
    }
    fn scratch(&self) -> StackReq {
        self.inner.scratch()
    }
    fn evaluate(
        &self,
        t: f64,
        x: &[&[f64]],
        r: &mut [f64],
        jacobians: Option<&mut [Vec<f64>]>,
        ws: &mut Workspace,
    ) -> mbfg::Result<()> {
        match jacobians {
            Some(jac) => {
                self.inner.evaluate(t, x, r, Some(&mut *jac), ws)?;
                match self.defect {
                    Defect::WrongEntry { key } => {
                        let block = &mut jac[key];
                        let scale = block.iter().fold(1.0f64, |m, v| m.max(v.abs()));
                        let mid = block.len() / 2;
                        block[mid] += 1e-5 * scale;
                    }
                    Defect::Unwritten { key } => {
                        let mid = jac[key].len() / 2;
                        jac[key][mid] = f64::NAN;
                    }
                    Defect::ResidualOnly => {}
                }
            }
            None => {
                self.inner.evaluate(t, x, r, None, ws)?;
                if let Defect::ResidualOnly = self.defect {
                    r[0] = r[0] * (1.0 + f64::EPSILON) + f64::MIN_POSITIVE;
                }
            }
        }
        Ok(())
    }
}

/// `check_factor` rejects a Jacobian entry off by 1e-5 relative, an unwritten entry,
/// and a residual that changes when Jacobians are not requested.
#[test]
fn checker_detects_defective_factors() {
    let mut rng = Rng(10);
    let model = load("pick-and-place.yaml");
    let now = Step::random(&model, &mut rng);
    let before = Step::random(&model, &mut rng);
    type Build = fn(&Arc<Model>) -> Box<dyn Factor>;
    let make: [(&str, Build); 3] = [
        ("f^d_dyn", |m| Box::new(Dynamics::new(m.clone()))),
        ("f^d_vc", |m| Box::new(VelocityConstraints::new(m.clone()))),
        ("f^i_dyn", |m| Box::new(IndependentDynamics::new(m.clone()))),
    ];
    for (label, build) in make {
        let keys = build(&model).keys().len();
        let mut defects = vec![Defect::ResidualOnly];
        for key in 0..keys {
            defects.push(Defect::WrongEntry { key });
            defects.push(Defect::Unwritten { key });
        }
        // The intact factor passes.
        let intact = build(&model);
        let xs = inputs(intact.as_ref(), &now, &before);
        check_factor(label, intact.as_ref(), &xs, T);
        for defect in defects {
            let factor = Defective {
                inner: build(&model),
                defect,
            };
            let caught = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
                check_factor(label, &factor, &xs, T)
            }))
            .is_err();
            assert!(caught, "{label}: {defect:?} not detected");
        }
    }
}

// ---------------------------------------------------------------------------------
// The regularized augmented system near singular configurations.
// ---------------------------------------------------------------------------------

/// `hessian_rows_into` applies each constraint's Hessian to its own vector: row k is
/// the gradient of aₖ(q)·vₖ.
#[test]
fn hessian_rows_match_finite_differences() {
    let mut rng = Rng(9);
    let mut errors = Errors::default();
    for name in SCENES.iter().copied().chain(["hard/parallelogram.yaml"]) {
        let model = load(name);
        let (n, m) = (model.n(), model.m());
        for _ in 0..TRIALS {
            let q = random_configuration(&model, &mut rng, 0.2);
            let v = rng.values(m * n, 1.0);
            let mut out = vec![f64::NAN; m * n];
            model.hessian_rows_into(&q, &v, &mut out);
            let rows_dot = |x: &[f64]| -> Vec<f64> {
                let jac = model.jacobian(&DVector::from_column_slice(x));
                (0..m)
                    .map(|k| (0..n).map(|j| jac[(k, j)] * v[k * n + j]).sum())
                    .collect()
            };
            let fd = fd_jacobian(&q, &rows_dot);
            let err = assert_close(&out, &fd, n, &format!("{name}: Φᵏ_qq vₖ"));
            errors.record("hessian_rows_into", err);
        }
    }
    errors.print("Model::hessian_rows_into");
}

/// The parallelogram on its branch at θ = π + d (coupler horizontal), turning at ω,
/// moved off the constraint manifold by `off` in a random direction.
fn parallelogram_state(d: f64, off: f64, rng: &mut Rng) -> (Vec<f64>, Vec<f64>) {
    let (th, w) = (std::f64::consts::PI + d, 3.0);
    let (c, s) = (th.cos(), th.sin());
    let mut q = vec![c, s, c + 2.0, s, th];
    let mut dq = vec![-w * s, w * c, -w * s, w * c, w];
    for (x, e) in q.iter_mut().zip(rng.values(5, off)) {
        *x += e;
    }
    for (x, e) in dq.iter_mut().zip(rng.values(5, off)) {
        *x += e;
    }
    (q, dq)
}

/// Near the parallelogram's flat configuration the kernel switches from the KKT
/// system (s ≥ 1e-2) through the ramp to the fully regularized one (s ≤ 1e-3, down
/// to the singular configuration itself, where the KKT system has no solution): its
/// ∂q̈/∂q and ∂q̈/∂q̇ match central differences in every regime, on the constraint
/// manifold and off it, and q̈ stays close to the exact motion's (−ω²(cos θ, sin θ)
/// for both points, θ̈ = 0).
#[test]
fn regularized_kernel_jacobians_match_finite_differences_near_a_flat_configuration() {
    let model = load("hard/parallelogram.yaml");
    let n = model.n();
    let mut rng = Rng(10);
    let mut errors = Errors::default();
    let mut regimes = [0usize; 3];
    for &d in &[3e-2, 1e-2, 4e-3, 2e-3, 1e-3, 3e-4, 1e-5, 0.0, -5e-4, -6e-3] {
        for &off in &[0.0, 1e-4] {
            let (q, dq) = parallelogram_state(d, off, &mut rng);
            let (s, w, ds) = DynamicsKernel::regularization_at(&model, &q);
            if let Some(ds) = ds {
                // The distance to rank loss itself: ∂s/∂q against central differences.
                let fd = fd_jacobian_with(1e-6, &q, &|x| {
                    vec![DynamicsKernel::regularization_at(&model, x).0]
                });
                let err = assert_close(&ds, &fd, n, &format!("d = {d:e}: ∂s/∂q"));
                errors.record("distance to rank loss s", err);
            }
            let regime = if w == 0.0 {
                0
            } else if w < 1.0 {
                1
            } else {
                2
            };
            regimes[regime] += 1;
            let what =
                format!("parallelogram, d = {d:e}, off by {off:e} (s = {s:.2e}, w = {w:.3})");
            let (ddq, jac) = kernel(&model, &q, &dq, None, true);
            let (jq, jv) = jac.unwrap();
            // The regularized q̈ varies on the scale √ε ≈ 1e-3 of s: a step of 1e-7
            // keeps the central differences' truncation error near 1e-8.
            let fd_q = fd_jacobian_with(1e-7, &q, &|x| kernel(&model, x, &dq, None, false).0);
            let fd_v = fd_jacobian_with(1e-7, &dq, &|v| kernel(&model, &q, v, None, false).0);
            let eq = assert_close(&jq, &fd_q, n, &format!("{what}: ∂q̈/∂q"));
            let ev = assert_close(&jv, &fd_v, n, &format!("{what}: ∂q̈/∂q̇"));
            errors.record(["KKT", "ramp", "regularized"][regime], eq.max(ev));
            if off == 0.0 {
                let th = std::f64::consts::PI + d;
                let exact = [
                    -9.0 * th.cos(),
                    -9.0 * th.sin(),
                    -9.0 * th.cos(),
                    -9.0 * th.sin(),
                    0.0,
                ];
                let err = max_abs_diff(&ddq, &exact);
                let bound = if w == 0.0 { 1e-9 } else { 1e-3 };
                assert!(
                    err <= bound,
                    "{what}: q̈ off the exact motion's by {err:.3e}"
                );
            }
        }
    }
    assert!(
        regimes.iter().all(|&c| c > 0),
        "every regime visited: {regimes:?}"
    );
    errors.print("regularized dynamics kernel near a flat configuration");
}

/// f_sensor of expression sensors whose readings use identified parameters (an
/// offset, a scale): ∂/∂q, ∂/∂q̇, ∂/∂q̈ and ∂/∂p, at the step and between steps; the
/// value that of the sensor at the parameters' estimate.
#[test]
fn sensor_readings_with_identified_parameters_match_finite_differences() {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("scenes/identification/sensor-calibration-bad.yaml");
    let model = Arc::new(Model::new(&Scene::load(&path).unwrap()).unwrap());
    let mut rng = Rng(13);
    let mut checked = 0;
    for before in [0.0, 2.1e-3] {
        for _ in 0..TRIALS {
            let now = Step::random(&model, &mut rng);
            for (k, sensor) in model.sensors.iter().enumerate() {
                assert!(sensor.uses_parameters(), "{}", sensor.name);
                let datum = rng.values(sensor.dim(), 1.0);
                let factor = Reading::new(model.clone(), k, datum.clone()).taken_before(before);
                assert_eq!(factor.keys().len(), 4, "the parameters are a key");
                let xs = inputs(&factor, &now, &now);
                let err = check_factor_with(FD_STEP, factor.name(), &factor, &xs, T);
                assert!(err < FD_TOLERANCE, "{}: off by {err:e}", factor.name());
                if before == 0.0 {
                    let mut h = vec![0.0; sensor.dim()];
                    let state = [&now.q[..], &now.dq[..], &now.ddq[..]];
                    sensor
                        .value_at(&model, T, state, Some(&xs[3]), &mut h)
                        .unwrap();
                    let r = evaluate(&factor, T, &xs, false, &mut workspace_for(&factor)).r;
                    assert_eq!(r[0], h[0] - datum[0]);
                }
                checked += 1;
            }
        }
    }
    assert_eq!(checked, 2 * 2 * TRIALS);
}

/// f_sensor of every sensor of a four-bar with one of each kind, at generic states
/// (off the constraints, random rates and accelerations), through the `Factor` trait.
#[test]
fn sensor_readings_match_finite_differences() {
    let scene =
        Scene::from_str(common::SENSOR_SCENE, std::path::Path::new("sensors.yaml")).unwrap();
    let model = Arc::new(Model::new(&scene).unwrap());
    let mut rng = Rng(3);
    let mut errors = Errors::default();
    for _ in 0..TRIALS {
        let now = Step::random(&model, &mut rng);
        for (k, sensor) in model.sensors.iter().enumerate() {
            let datum = rng.values(sensor.dim(), 1.0);
            let factor = Reading::new(model.clone(), k, datum.clone());
            assert_eq!(factor.name(), format!("f_sensor({})", sensor.name));
            let xs = inputs(&factor, &now, &now);
            errors.record(factor.name(), check_factor(factor.name(), &factor, &xs, T));
            // r = h − datum.
            let mut h = vec![0.0; sensor.dim()];
            sensor
                .value(&model, T, &now.q, &now.dq, &now.ddq, &mut h)
                .unwrap();
            let r = evaluate(&factor, T, &xs, false, &mut workspace_for(&factor)).r;
            for i in 0..h.len() {
                assert_eq!(r[i], h[i] - datum[i]);
            }
        }
    }
    // Taken between steps (δ before the step, or after it): Jacobians through the
    // expansion, and the value that of the sensor at the expanded state and t − δ.
    for before in [2.1e-3, -1.3e-3] {
        for _ in 0..TRIALS {
            let now = Step::random(&model, &mut rng);
            for (k, sensor) in model.sensors.iter().enumerate() {
                let datum = rng.values(sensor.dim(), 1.0);
                let factor = Reading::new(model.clone(), k, datum.clone()).taken_before(before);
                let xs = inputs(&factor, &now, &now);
                errors.record(
                    "f_sensor taken between steps",
                    check_factor(factor.name(), &factor, &xs, T),
                );
                let b = before;
                let q: Vec<f64> = (0..now.q.len())
                    .map(|i| now.q[i] - b * now.dq[i] + 0.5 * b * b * now.ddq[i])
                    .collect();
                let dq: Vec<f64> = (0..now.q.len())
                    .map(|i| now.dq[i] - b * now.ddq[i])
                    .collect();
                let mut h = vec![0.0; sensor.dim()];
                sensor
                    .value(&model, T - b, &q, &dq, &now.ddq, &mut h)
                    .unwrap();
                let r = evaluate(&factor, T, &xs, false, &mut workspace_for(&factor)).r;
                for i in 0..h.len() {
                    assert!((r[i] - (h[i] - datum[i])).abs() <= 1e-12 * (1.0 + h[i].abs()));
                }
            }
        }
    }
    // A datum of the wrong size or a sensor the model lacks: an error, not a panic.
    let mut ws = Workspace::new(StackReq::EMPTY);
    let now = Step::random(&model, &mut rng);
    for factor in [
        Reading::new(model.clone(), 0, vec![1.0, 2.0]),
        Reading::new(model.clone(), 99, vec![1.0]),
    ] {
        let xs = inputs(&factor, &now, &now);
        let slices: Vec<&[f64]> = xs.iter().map(Vec::as_slice).collect();
        let mut r = vec![0.0; factor.dim()];
        assert!(factor.evaluate(T, &slices, &mut r, None, &mut ws).is_err());
    }
    errors.print("sensors");
}

/// A step's projected integrators share the projector made at its positions; a
/// model of other constraints at the same positions makes its own, and so does a
/// clone of a model (which may be changed after it is made).
#[test]
fn a_projector_is_shared_only_within_a_model_at_the_same_positions() {
    let (a, b) = (load("fourbar-theta.yaml"), load("estimation/fourbar.yaml"));
    assert_eq!(a.n(), b.n());
    assert_ne!(a.identity, (*a).clone().identity);
    let q = a.initial.q.as_slice().to_vec();
    let dq: Vec<f64> = (0..a.n()).map(|i| 0.1 * (i as f64 + 1.0)).collect();
    let residual = |m: &Arc<Model>| {
        let f = Projected::new(
            m.clone(),
            Box::new(Trapezoidal::new(VarKind::Q, VarKind::Dq, m.n(), 0.01)),
        );
        let mut ws = workspace_for(&f);
        // Keys: q_t, q_(t−1), q̇_t, q̇_(t−1) (the inner factor's), q_t again
        // where the inner factor does not list it.
        let xs: Vec<Vec<f64>> = f
            .keys()
            .iter()
            .map(|k| match (k.kind, k.lag) {
                (VarKind::Q, 0) => q.clone(),
                (VarKind::Q, _) => q.iter().map(|v| v - 1e-3).collect(),
                _ => dq.clone(),
            })
            .collect();
        evaluate(&f, 0.0, &xs, false, &mut ws).r
    };
    let b_alone = residual(&b);
    let a_first = residual(&a);
    let b_after_a = residual(&b);
    assert!(
        same_bits(&b_alone, &b_after_a),
        "{b_alone:?} vs {b_after_a:?}"
    );
    assert!(
        !same_bits(&a_first, &b_after_a),
        "two mechanisms, one projector"
    );
    assert!(same_bits(&residual(&a), &a_first));
}
