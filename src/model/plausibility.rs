//! Checks on a model before it runs, each reported with its numbers: a time step too
//! coarse for the scene's stiffest spring or damper (`mbfg simulate --strict` refuses
//! the run), points that assembly moved from where the scene placed them, motions
//! without inertia, and a mechanism nothing sets moving (`mbfg check` prints these
//! three). The checks on a run's result are in [`crate::forward::energy_checks`].

use crate::model::Model;
use nalgebra::{DMatrix, DVector};

/// The largest ω·Δt (ω the fastest natural frequency one effect gives the mechanism,
/// in rad/s; or its damping rate c/m, in 1/s) at which the trapezoidal rule still
/// follows the motion: at ω·Δt = 1 a step is a sixth of the period, and the period
/// comes out about 8 % long; beyond it the motion is not resolved.
pub const MAX_OMEGA_DT: f64 = 1.0;

/// The fastest time scale of one effect at the initial state.
#[derive(Debug, Clone, PartialEq)]
pub struct TimeScale {
    /// The effect, as `mbfg check` describes it.
    pub effect: String,
    /// Its name in the scene (`'tie'`), or its kind where it has none.
    pub name: String,
    /// Fastest natural frequency from its stiffness, rad/s (0 when it has none).
    pub omega: f64,
    /// Fastest decay rate from its damping, 1/s (0 when it has none).
    pub rate: f64,
}

impl TimeScale {
    /// The larger of ω and the damping rate, in 1/s.
    pub fn speed(&self) -> f64 {
        self.omega.max(self.rate)
    }
}

/// The spring and damper effects' time scales at the model's initial state, on the
/// motions the constraints allow: ω² and the rates are the largest generalized
/// eigenvalues of the effect's stiffness −∂Q/∂q and damping −∂Q/∂q̇ against M, both
/// projected on the null space of Φ_q. Empty when the mass matrix does not cover the
/// free motion (massless coordinates): then nothing can be said this way.
pub fn time_scales(model: &Model) -> Vec<TimeScale> {
    let n = model.n();
    let (q, dq) = (&model.initial.q, &model.initial.dq);
    // Only springs, dampers and state-dependent loads have a time scale: without one
    // the basis (an eigendecomposition of n × n) is not formed.
    if !model.forces.iter().any(|f| {
        f.jacobian_pattern(model)
            .is_none_or(|(rows, cols)| !rows.is_empty() && !cols.is_empty())
    }) {
        return Vec::new();
    }
    let Some(basis) = free_motions(model, q) else {
        return Vec::new();
    };
    if basis.ncols() == 0 {
        return Vec::new();
    }
    let mr = basis.transpose() * &model.mass * &basis;
    let Some(chol) = mr.clone().cholesky() else {
        return Vec::new();
    };
    let l_inv = match chol.l().try_inverse() {
        Some(l) => l,
        None => return Vec::new(),
    };
    let largest = |k: &DMatrix<f64>| -> f64 {
        let kr = basis.transpose() * k * &basis;
        let a = &l_inv * kr * l_inv.transpose();
        let sym = (&a + a.transpose()) * 0.5;
        if !sym.iter().all(|v| v.is_finite()) {
            return 0.0;
        }
        sym.symmetric_eigenvalues().max().max(0.0)
    };
    let mut out = Vec::new();
    for (i, force) in model.forces.iter().enumerate() {
        let (mut kq, mut kv) = (vec![0.0; n * n], vec![0.0; n * n]);
        if force
            .add_jacobians(model, (q.as_slice(), dq.as_slice(), 0.0), &mut kq, &mut kv)
            .is_err()
        {
            continue;
        }
        if kq.iter().chain(&kv).all(|v| *v == 0.0) {
            continue;
        }
        let stiffness = -DMatrix::from_row_slice(n, n, &kq);
        let damping = -DMatrix::from_row_slice(n, n, &kv);
        let effect = &model.scene.effects[i];
        let scale = TimeScale {
            effect: effect.describe(&model.scene),
            name: effect
                .name()
                .map_or_else(|| "gravity".into(), |n| format!("'{n}'")),
            omega: largest(&stiffness).sqrt(),
            rate: largest(&damping),
        };
        if scale.speed() > 0.0 {
            out.push(scale);
        }
    }
    out
}

/// An orthonormal basis of the motions Φ_q allows at q (n × dof), or None when Φ_q
/// is not finite there.
fn free_motions(model: &Model, q: &DVector<f64>) -> Option<DMatrix<f64>> {
    let n = model.n();
    let jac = model.jacobian(q);
    let rows = &model.active;
    if rows.is_empty() {
        return Some(DMatrix::identity(n, n));
    }
    let a = DMatrix::from_fn(rows.len(), n, |r, c| jac[(rows[r], c)]);
    if !a.iter().all(|v| v.is_finite()) {
        return None;
    }
    // The eigenvectors of AᵀA with eigenvalue ~0 span its null space.
    let ata = a.transpose() * &a;
    if !ata.iter().all(|v| v.is_finite()) {
        return None;
    }
    let eig = ata.symmetric_eigen();
    let top = eig.eigenvalues.amax();
    let keep: Vec<usize> = (0..n)
        .filter(|&i| eig.eigenvalues[i] <= 1e-10 * top)
        .collect();
    Some(DMatrix::from_fn(n, keep.len(), |r, c| {
        eig.eigenvectors[(r, keep[c])]
    }))
}

/// The fastest effect's time scale where `dt` is too coarse for it (ω·dt above
/// [`MAX_OMEGA_DT`] at the initial state).
pub fn too_fast(model: &Model, dt: f64) -> Option<TimeScale> {
    time_scales(model)
        .into_iter()
        .max_by(|a, b| a.speed().total_cmp(&b.speed()))
        .filter(|fastest| fastest.speed() * dt > MAX_OMEGA_DT)
}

/// A warning when `dt` is too coarse for the fastest effect, with its numbers.
pub fn step_warning(model: &Model, dt: f64) -> Option<String> {
    let fastest = too_fast(model, dt)?;
    let speed = fastest.speed();
    let what = if fastest.omega >= fastest.rate {
        format!(
            "its period is {:.3e} s (ω = {:.3e} rad/s)",
            2.0 * std::f64::consts::PI / fastest.omega,
            fastest.omega
        )
    } else {
        format!("its damping rate is {:.3e} 1/s", fastest.rate)
    };
    Some(format!(
        "dt = {} s is too coarse for {}: {what}, and ω·dt = {} > {MAX_OMEGA_DT}; \
         dt ≤ {:.2e} s resolves it",
        crate::io::number(dt),
        fastest.effect,
        short(speed * dt),
        MAX_OMEGA_DT / speed
    ))
}

/// Three decimals, or scientific notation for numbers far from 1.
fn short(v: f64) -> String {
    if (1e-3..1e4).contains(&v.abs()) {
        format!("{v:.3}")
    } else {
        format!("{v:.3e}")
    }
}

/// The largest move, as a fraction of the scene's extent, from a placed point to where
/// the position problem assembled it that is taken as rounding in the placement.
pub const PLACEMENT_TOLERANCE: f64 = 1e-3;

/// A warning when assembly moved points from where the scene placed them by more
/// than [`PLACEMENT_TOLERANCE`] of the scene's extent (a length that contradicts the
/// drawing assembles the mechanism elsewhere), naming the points and distances.
pub fn placement_warning(model: &Model) -> Option<String> {
    let scene = &model.scene;
    let q = model.initial.q.as_slice();
    let extent = scene
        .points
        .iter()
        .flat_map(|a| {
            scene
                .points
                .iter()
                .map(move |b| (a.x - b.x).hypot(a.y - b.y))
        })
        .fold(0.0f64, f64::max);
    let tolerance = PLACEMENT_TOLERANCE * extent.max(f64::MIN_POSITIVE);
    let mut moved: Vec<(&str, f64)> = scene
        .points
        .iter()
        .enumerate()
        .map(|(i, p)| {
            let [x, y] = model.point_position(q, i);
            (p.name.as_str(), (x - p.x).hypot(y - p.y))
        })
        .filter(|(_, d)| *d > tolerance)
        .collect();
    if moved.is_empty() {
        return None;
    }
    moved.sort_by(|a, b| b.1.total_cmp(&a.1));
    let shown: Vec<String> = moved
        .iter()
        .take(4)
        .map(|(n, d)| format!("{n} by {d:.3e} m"))
        .collect();
    let more = if moved.len() > 4 {
        format!(" and {} more", moved.len() - 4)
    } else {
        String::new()
    };
    Some(format!(
        "assembling the constraints moved {}{more} from where the scene places them \
         (tolerance {tolerance:.1e} m): a length or an initial value contradicts the drawing",
        shown.join(", ")
    ))
}

/// Coordinates from which [`inertia_warning`] first tries the sparse certificate
/// [`mass_covers_free_motions`]: below, the eigendecomposition costs less.
const SPARSE_INERTIA_FROM: usize = 48;

/// Whether the mass matrix certainly covers every motion the constraints allow at
/// q, with its smallest eigenvalue there well above [`MASSLESS_MOTION`] of the
/// largest, shown without the n × n eigendecomposition. On a motion v the
/// constraints allow (Av = 0, |v| = 1), vᵀMv = vᵀ(M + ρAᵀA)v, so the smallest such
/// value is at least the smallest eigenvalue of M + ρAᵀA, itself at least
/// 1 / tr (M + ρAᵀA)⁻¹ (a sparse Cholesky factor and its selected inversion); the
/// largest is at most M's largest row sum. ρ scales AᵀA to M. `false` leaves the
/// question to the eigendecomposition.
fn mass_covers_free_motions(model: &Model, q: &DVector<f64>) -> bool {
    let n = model.n();
    let mass = &model.mass;
    let largest = (0..n)
        .map(|i| mass.row(i).iter().map(|v| v.abs()).sum::<f64>())
        .fold(0.0, f64::max);
    let jac = model.jacobian(q);
    let rows: Vec<Vec<(usize, f64)>> = model
        .active
        .iter()
        .map(|&k| {
            (0..n)
                .filter(|&j| jac[(k, j)] != 0.0)
                .map(|j| (j, jac[(k, j)]))
                .collect()
        })
        .collect();
    let mut gram_diagonal = vec![0.0; n];
    for row in &rows {
        for &(j, v) in row {
            gram_diagonal[j] += v * v;
        }
    }
    let top_gram = gram_diagonal.iter().fold(0.0, |m: f64, v| m.max(*v));
    let top_mass = (0..n).map(|i| mass[(i, i)]).fold(0.0, f64::max);
    if !(largest.is_finite() && top_mass > 0.0 && top_gram.is_finite()) {
        return false;
    }
    let rho = if top_gram > 0.0 {
        top_mass / top_gram
    } else {
        0.0
    };
    let mut lower = Vec::new();
    for c in 0..n {
        for r in c..n {
            if mass[(r, c)] != 0.0 {
                lower.push((r, c, mass[(r, c)]));
            }
        }
    }
    for row in &rows {
        for &(i, vi) in row {
            for &(j, vj) in row {
                if j <= i {
                    lower.push((i, j, rho * vi * vj));
                }
            }
        }
    }
    let Some(trace) = crate::linalg::sparse::spd_inverse_trace(n, &lower) else {
        return false;
    };
    trace > 0.0 && 1.0 / trace > 10.0 * MASSLESS_MOTION * largest
}

/// Eigenvalues of the mass matrix on the free motions below this fraction of the
/// largest count as no inertia at all (a point without mass): far below any mixture
/// of scales a mechanism has (a 2 mm crank's 1e-9 kg·m² beside a 10 g slider).
pub const MASSLESS_MOTION: f64 = 1e-14;

/// A warning when the masses and inertias do not cover every motion the constraints
/// allow at the initial state: along a motion without inertia (a point with no mass
/// on no body) the dynamics does not determine the acceleration, and a run stops
/// where that motion matters (a knee between two massless rods, when the chain
/// straightens). Names the moving points that carry no mass.
pub fn inertia_warning(model: &Model) -> Option<String> {
    if model.n() >= SPARSE_INERTIA_FROM && mass_covers_free_motions(model, &model.initial.q) {
        return None;
    }
    let basis = free_motions(model, &model.initial.q)?;
    if basis.ncols() == 0 {
        return None;
    }
    let reduced = basis.transpose() * &model.mass * &basis;
    let eigen = reduced.symmetric_eigenvalues();
    let top = eigen.max();
    let low = eigen
        .iter()
        .filter(|&&v| v <= MASSLESS_MOTION * top)
        .count();
    if low == 0 {
        return None;
    }
    let massless = massless_points(model);
    let which = if massless.is_empty() {
        String::new()
    } else {
        format!(" (moving without mass: {})", massless.join(", "))
    };
    Some(format!(
        "{low} of the {} motions the constraints allow carry no inertia{which}: the \
         dynamics does not determine their accelerations, and a run may stop where they \
         matter; give those points a mass or put them on a body",
        basis.ncols()
    ))
}

/// The free points that carry no mass: on no body, without a point mass.
pub fn massless_points(model: &Model) -> Vec<&str> {
    model
        .points
        .iter()
        .zip(&model.scene.points)
        .filter_map(|(slot, p)| match slot {
            crate::model::PointSlot::Free(i) => (model.mass[(*i, *i)] == 0.0
                && model.mass[(i + 1, i + 1)] == 0.0)
                .then_some(p.name.as_str()),
            crate::model::PointSlot::Fixed(_) => None,
        })
        .collect()
}

/// A warning when the constraints leave the mechanism no degree of freedom, naming
/// the constraint that takes the last one.
pub fn locked_warning(model: &Model) -> Option<String> {
    if model.dof() > 0 || model.n() == 0 {
        return None;
    }
    let culprit = crate::kinematics::locking_constraint(model, &model.initial.q)
        .map(|c| {
            format!(
                "; constraint '{}' takes its last degree of freedom",
                model.constraints[c].name
            )
        })
        .unwrap_or_default();
    Some(format!(
        "the mechanism cannot move: its constraints leave none of its {} coordinate(s) \
         free (0 degrees of freedom){culprit}",
        model.n()
    ))
}

/// Angles above this (rad) where the scene expects an angle suggest degrees.
const MAX_PLAUSIBLE_ANGLE: f64 = std::f64::consts::TAU;

/// A body longer than this (m) that weighs less than [`MIN_LINEAR_DENSITY`] per metre,
/// or any scene whose median body is longer than [`MM_MEDIAN_LENGTH`], suggests
/// lengths in millimetres.
const MM_BODY_LENGTH: f64 = 5.0;
/// kg/m: a steel wire of 3 mm weighs 0.055 kg/m.
const MIN_LINEAR_DENSITY: f64 = 0.05;
const MM_MEDIAN_LENGTH: f64 = 50.0;
/// kg/m³: a body whose mass exceeds this times the cube of its length is denser than
/// any metal (osmium, 22 590 kg/m³) even as a solid cube: masses in grams.
const MAX_CUBE_DENSITY: f64 = 25_000.0;
/// kg: below it a small dense body (a 5 mm crank on a flywheel) is plausible.
const MIN_GRAMS_MASS: f64 = 10.0;

/// Warnings for values whose size suggests other units than the SI ones mbfg reads:
/// angle constants beyond 2π (degrees for radians), lengths in millimetres, masses
/// in grams.
pub fn units_warnings(model: &Model) -> Vec<String> {
    let scene = &model.scene;
    let mut out = Vec::new();
    let degrees = |v: f64| {
        format!(
            "angles are in radians ({v} degrees would be {:.4} rad)",
            v.to_radians()
        )
    };
    for effect in &scene.effects {
        if let crate::scene::Effect::RotationalSpringDamper {
            name, rest_angle, ..
        } = effect
        {
            if rest_angle.abs() > MAX_PLAUSIBLE_ANGLE {
                out.push(format!(
                    "effect '{name}': rest_angle {rest_angle} is beyond 2π: {}",
                    degrees(*rest_angle)
                ));
            }
        }
    }
    for c in scene.coordinates.iter().filter(|c| c.kind.is_angle()) {
        let given = c.initial.into_iter().chain(
            scene
                .initial_positions
                .iter()
                .filter(|(n, _)| *n == c.name)
                .map(|(_, v)| *v),
        );
        for v in given.filter(|v| v.abs() > MAX_PLAUSIBLE_ANGLE) {
            out.push(format!(
                "coordinate '{}': initial angle {v} is beyond 2π: {}",
                c.name,
                degrees(v)
            ));
        }
    }
    let mut lengths: Vec<f64> = scene.bodies.iter().map(|b| b.length).collect();
    lengths.sort_by(f64::total_cmp);
    let median = lengths.get(lengths.len() / 2).copied().unwrap_or(0.0);
    let light_and_long = scene.bodies.iter().find(|b| {
        b.length > MM_BODY_LENGTH && b.mass > 0.0 && b.mass / b.length < MIN_LINEAR_DENSITY
    });
    if median > MM_MEDIAN_LENGTH || light_and_long.is_some() {
        let why = match light_and_long {
            Some(b) => format!(
                "body '{}' is {} m long and weighs {} kg",
                b.name,
                short(b.length),
                short(b.mass)
            ),
            None => format!("the bodies are {} m long (median)", short(median)),
        };
        out.push(format!(
            "{why}: lengths are in metres; a scene in millimetres must be converted \
             (divide lengths by 1000)"
        ));
    }
    if let Some(b) = scene
        .bodies
        .iter()
        .find(|b| b.mass > MIN_GRAMS_MASS && b.mass > MAX_CUBE_DENSITY * b.length.powi(3))
    {
        out.push(format!(
            "body '{}' weighs {} kg on {} m, denser than any metal even as a solid cube: \
             masses are in kg; a scene in grams must be converted (divide masses by 1000)",
            b.name,
            short(b.mass),
            short(b.length)
        ));
    }
    out
}

/// A warning when nothing can set the mechanism moving: no effect, no unknown input
/// an estimate would find (`estimation: inputs:`), and at rest.
pub fn idle_warning(model: &Model) -> Option<String> {
    let at_rest = model.initial.dq.iter().all(|v| *v == 0.0);
    let driven = !model.estimation.inputs.is_empty();
    (model.scene.effects.is_empty() && at_rest && !driven).then(|| {
        format!(
            "{}: no effects (no gravity either) and at rest: nothing moves the mechanism \
             (an MBSE mechanism file declares none; name it with `mechanism:` in a scene \
             that adds `effects:`)",
            model.scene.file
        )
    })
}
