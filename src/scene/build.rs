//! Semantic checks shared by both formats: bodies, relative coordinates and names;
//! and the empty scene both readers start from.

use super::fields::Ctx;
use super::{Body, Point, RelativeKind, Scene};
use crate::error::SceneError;

/// Points closer than this (relative to the mechanism's size) coincide.
const COINCIDENT: f64 = 1e-9;

pub fn scale(points: &[Point]) -> f64 {
    points
        .iter()
        .map(|p| p.x.abs().max(p.y.abs()))
        .fold(1.0, f64::max)
}

pub fn distance(points: &[Point], a: usize, b: usize) -> f64 {
    (points[a].x - points[b].x).hypot(points[a].y - points[b].y)
}

pub fn coincide(points: &[Point], a: usize, b: usize) -> bool {
    distance(points, a, b) <= COINCIDENT * scale(points)
}

/// The scene both formats start from and fill.
pub fn empty(file: &str) -> Scene {
    Scene {
        file: file.to_string(),
        points: Vec::new(),
        bodies: Vec::new(),
        coordinates: Vec::new(),
        constraints: Vec::new(),
        effects: Vec::new(),
        independent: Vec::new(),
        independent_line: None,
        initial_positions: Vec::new(),
        initial_velocities: Vec::new(),
        notes: Vec::new(),
        sensors: Vec::new(),
        estimation: Default::default(),
        mechanism: None,
        identified: Default::default(),
    }
}

/// Inertial data of a body, before validation.
pub struct BodySpec {
    pub name: String,
    pub points: Vec<usize>,
    pub mass: f64,
    pub cog: [f64; 2],
    pub i0: f64,
    /// The line of `I0` when the file gives it (else the body's).
    pub i0_line: u64,
    pub length: f64,
}

/// Checks a body's points and inertia and appends it.
pub fn add_body(
    ctx: &Ctx,
    scene: &mut Scene,
    line: u64,
    key: &str,
    spec: BodySpec,
) -> Result<(), SceneError> {
    let pts = &spec.points;
    if pts.len() < 2 {
        return Err(ctx.err(
            line,
            key,
            format!(
                "body '{}' needs 2 or more points, has {}",
                spec.name,
                pts.len()
            ),
        ));
    }
    for (k, &a) in pts.iter().enumerate() {
        for &b in &pts[k + 1..] {
            let (na, nb) = (&scene.points[a].name, &scene.points[b].name);
            if a == b {
                return Err(ctx.err(
                    line,
                    key,
                    format!("body '{}' names point '{na}' twice", spec.name),
                ));
            }
            if coincide(&scene.points, a, b) {
                return Err(ctx.err(
                    line,
                    key,
                    format!("body '{}': points '{na}' and '{nb}' coincide", spec.name),
                ));
            }
        }
    }
    if pts.iter().all(|&p| scene.points[p].fixed) {
        return Err(ctx.err(
            line,
            key,
            format!(
                "body '{}' has only fixed points; leave it out (it cannot move)",
                spec.name
            ),
        ));
    }
    if !(spec.mass > 0.0) {
        return Err(ctx.err(
            line,
            &format!("{key}.mass"),
            format!("must be positive, got {}", spec.mass),
        ));
    }
    if !(spec.i0 > 0.0) {
        return Err(ctx.err(
            line,
            &format!("{key}.inertia"),
            format!("must be positive, got {}", spec.i0),
        ));
    }
    if !(spec.length > 0.0) {
        return Err(ctx.err(
            line,
            &format!("{key}.length"),
            format!("must be positive, got {}", spec.length),
        ));
    }
    let body = Body {
        name: spec.name,
        points: spec.points,
        mass: spec.mass,
        cog: spec.cog,
        i0: spec.i0,
        length: spec.length,
    };
    let ig = body.inertia_at_cog();
    if ig < -1e-12 * body.i0.abs() {
        return Err(ctx.err(
            if spec.i0_line > 0 { spec.i0_line } else { line },
            &format!("{key}.I0"),
            format!(
                "inertia about the first point ({}) is less than mass·|cog|² ({}): the inertia about the centre of mass would be negative",
                body.i0,
                body.mass * (body.cog[0].powi(2) + body.cog[1].powi(2))
            ),
        ));
    }
    scene.bodies.push(body);
    Ok(())
}

/// Whether the distance between two points is kept constant (both fixed, on one body,
/// or tied by an explicit distance constraint).
pub fn rigid_pair(scene: &Scene, a: usize, b: usize) -> bool {
    (scene.points[a].fixed && scene.points[b].fixed)
        || scene
            .bodies
            .iter()
            .any(|body| body.points.contains(&a) && body.points.contains(&b))
        || scene.constraints.iter().any(|c| {
            matches!(c.kind, super::ConstraintKind::Distance { points, .. }
                if points == [a, b] || points == [b, a])
        })
}

/// Checks that the segments of a relative coordinate are rigid and non-degenerate.
pub fn check_relative(
    ctx: &Ctx,
    scene: &Scene,
    line: u64,
    key: &str,
    kind: &RelativeKind,
) -> Result<(), SceneError> {
    let segments: Vec<[usize; 2]> = match *kind {
        RelativeKind::AbsoluteAngle { from, to } => vec![[from, to]],
        RelativeKind::RelativeAngle { a, b } => vec![a, b],
        RelativeKind::Distance { along, .. } => vec![along],
    };
    for [a, b] in segments {
        let (na, nb) = (&scene.points[a].name, &scene.points[b].name);
        if a == b || coincide(&scene.points, a, b) {
            return Err(ctx.err(line, key, format!("segment '{na}'–'{nb}' has no length")));
        }
        if !rigid_pair(scene, a, b) {
            return Err(ctx.err(
                line,
                key,
                format!("segment '{na}'–'{nb}' is not rigid: its points are not on one body"),
            ));
        }
    }
    if let RelativeKind::Distance { point, along } = *kind {
        if along.contains(&point) {
            return Err(ctx.err(
                line,
                key,
                format!(
                    "point '{}' is one end of its own segment",
                    scene.points[point].name
                ),
            ));
        }
    }
    Ok(())
}

/// The value a relative coordinate takes at the scene's initial point positions.
pub fn relative_value(points: &[Point], kind: &RelativeKind) -> f64 {
    let d = |a: usize, b: usize| [points[b].x - points[a].x, points[b].y - points[a].y];
    match *kind {
        RelativeKind::AbsoluteAngle { from, to } => {
            let u = d(from, to);
            u[1].atan2(u[0])
        }
        RelativeKind::RelativeAngle { a, b } => {
            let (u, v) = (d(a[0], a[1]), d(b[0], b[1]));
            (u[0] * v[1] - u[1] * v[0]).atan2(u[0] * v[0] + u[1] * v[1])
        }
        RelativeKind::Distance { point, along } => {
            let (u, w) = (d(along[0], along[1]), d(along[0], point));
            (u[0] * w[0] + u[1] * w[1]) / u[0].hypot(u[1])
        }
    }
}

/// Names of q in model order: free points' `<name>.x`, `<name>.y`, then relative
/// coordinates.
/// Whether `name` is one of [`coordinate_names`], without listing them (a scene
/// names its coordinates one by one: listing them each time costs n² strings).
pub fn is_coordinate_name(scene: &Scene, name: &str) -> bool {
    let free_point_axis = name.rsplit_once('.').is_some_and(|(point, axis)| {
        (axis == "x" || axis == "y")
            && scene
                .point_index(point)
                .is_some_and(|i| !scene.points[i].fixed)
    });
    free_point_axis || scene.coordinate_index(name).is_some()
}

pub fn coordinate_names(scene: &Scene) -> Vec<String> {
    let mut names = Vec::new();
    for p in scene.points.iter().filter(|p| !p.fixed) {
        names.push(format!("{}.x", p.name));
        names.push(format!("{}.y", p.name));
    }
    names.extend(scene.coordinates.iter().map(|c| c.name.clone()));
    names
}
