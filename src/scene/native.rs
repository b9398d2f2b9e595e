//! The mbfg scene format (see `docs/scene-format.md`).

use super::bodies::{body_spec, BodyStyle};
use super::build;
use super::fields::{boolean, name_of, pair, seq, Ctx, Fields, QUOTE};
use super::yaml::{Node, Value};
use super::{
    ConstraintDef, ConstraintKind, Effect, Point, RelativeCoordinate, RelativeKind, Scene,
};
use crate::error::{Error, SceneError};
use crate::expr::excerpt;
use std::path::Path;

const TOP_KEYS: &[&str] = &[
    "name",
    "description",
    "parameters",
    "mechanism",
    "points",
    "bodies",
    "coordinates",
    "constraints",
    "effects",
    "independent",
    "initial",
    "sensors",
    "estimation",
];

pub fn read(
    root: &Node,
    file: &str,
    dir: &Path,
    overrides: &[(String, f64)],
) -> crate::Result<Scene> {
    let mut ctx = Ctx::with_overrides(file, overrides);
    ctx.derivatives.unknown = super::sensors::identified_names(root);
    let mut top = Fields::new(&ctx, root, "")?;
    for k in ["name", "description"] {
        if let Some(n) = top.get(k) {
            if !matches!(n.value, Value::String(_)) {
                return Err(ctx.err(n.line, k, "expected text").into());
            }
        }
    }
    let mut scene = if let Some(mech) = top.get("mechanism") {
        for k in ["points", "bodies"] {
            if top.has(k) {
                return Err(ctx
                    .err(
                        top.line,
                        k,
                        "a scene naming a mechanism file takes its points and bodies from it",
                    )
                    .into());
            }
        }
        let Value::String(rel) = &mech.value else {
            return Err(ctx
                .err(mech.line, "mechanism", "expected a file name")
                .into());
        };
        let path = dir.join(rel);
        // Only a regular file: a device or a pipe could be read forever.
        let regular = std::fs::metadata(&path).map(|m| m.is_file());
        if let Ok(false) = regular {
            return Err(ctx
                .err(
                    mech.line,
                    "mechanism",
                    format!("'{}' is not a regular file", excerpt(rel, QUOTE)),
                )
                .into());
        }
        let text = super::read_text(&path).map_err(|source| {
            Error::Scene(ctx.err(
                mech.line,
                "mechanism",
                format!(
                    "cannot read '{}': {source}",
                    excerpt(&path.display().to_string(), 120)
                ),
            ))
        })?;
        // Only an MBSE file: a scene as its own mechanism would be read forever.
        let mech_file = path.display().to_string();
        let mech_root = super::parse_root(&text, &mech_file)?;
        if !super::fields::is_mbse(&mech_root) {
            return Err(ctx
                .err(
                    mech.line,
                    "mechanism",
                    format!(
                        "'{mech_file}' is not an MBSE mechanism file (it has no planar_bodies)"
                    ),
                )
                .into());
        }
        let mut base = super::mbse::read(&mech_root, &mech_file, &[])?;
        base.file = file.to_string();
        base.mechanism = Some(mech_file.clone());
        if let Some(p) = top.get("parameters") {
            ctx.read_parameters(p)?;
        }
        ctx.check_overrides(top.get("parameters").map_or(0, |p| p.line))?;
        base
    } else {
        if let Some(p) = top.get("parameters") {
            ctx.read_parameters(p)?;
        }
        ctx.check_overrides(top.get("parameters").map_or(0, |p| p.line))?;
        let mut scene = build::empty(file);
        read_points(&ctx, &mut scene, top.req(&ctx, "points")?)?;
        if let Some(b) = top.get("bodies") {
            read_bodies(&ctx, &mut scene, b)?;
        }
        scene
    };
    if let Some(n) = top.get("constraints") {
        read_constraints(&ctx, &mut scene, n)?;
    }
    if let Some(n) = top.get("coordinates") {
        read_coordinates(&ctx, &mut scene, n)?;
    }
    if let Some(n) = top.get("effects") {
        read_effects(&ctx, &mut scene, n)?;
    }
    if let Some(n) = top.get("independent") {
        read_independent(&ctx, &mut scene, n)?;
    }
    if let Some(n) = top.get("initial") {
        read_initial(&ctx, &mut scene, n)?;
    }
    if let Some(n) = top.get("sensors") {
        super::sensors::read_sensors(&ctx, &mut scene, n)?;
    }
    if let Some(n) = top.get("estimation") {
        super::sensors::read_estimation(&ctx, &mut scene, n)?;
    }
    top.finish(&ctx, TOP_KEYS)?;
    if let Some((key, line)) = ctx.derivatives.unclaimed() {
        // A motor's no-load speed enters its torque as 1/ω₀: a torque written as an
        // expression carries it any way, and its value is differentiated symbolically.
        let message = if key.ends_with(".no_load_speed") {
            "uses an identified parameter, which a no-load speed cannot be; write the motor \
             as a torque, `value: \"ts*(1 - rate(theta)/w0)\"`, whose parameters can"
        } else {
            "depends on a parameter the estimate identifies (`estimation: parameters:`): an \
             estimate varies masses, inertias, gravity, spring and damper constants, motors' \
             stall torques and the values of torques, forces and sensors only, not geometry \
             or starts; give this key a value of its own"
        };
        return Err(ctx.err(line, &key, message).into());
    }
    scene.identified = ctx.derivatives.identified(&ctx.params);
    if scene.bodies.is_empty() && scene.points.iter().all(|p| p.mass == 0.0) {
        return Err(ctx
            .err(
                root.line,
                "bodies",
                "the scene has no bodies and no point masses",
            )
            .into());
    }
    Ok(scene)
}

/// Resolves a point named in the scene.
pub fn point_ref(ctx: &Ctx, scene: &Scene, node: &Node, key: &str) -> Result<usize, SceneError> {
    let name = node.as_text().ok_or_else(|| {
        ctx.err(
            node.line,
            key,
            format!("expected a point name, found {}", node.kind()),
        )
    })?;
    scene.point_index(&name).ok_or_else(|| {
        ctx.err(
            node.line,
            key,
            format!(
                "unknown point '{}'{}",
                excerpt(&name, QUOTE),
                super::suggest::hint(
                    &name,
                    "points",
                    scene.points.iter().map(|p| p.name.as_str())
                )
            ),
        )
    })
}

fn point_pair(ctx: &Ctx, scene: &Scene, node: &Node, key: &str) -> Result<[usize; 2], SceneError> {
    let items = seq(ctx, node, key)?;
    if items.len() != 2 {
        return Err(ctx.err(
            node.line,
            key,
            format!("expected two points, found {}", items.len()),
        ));
    }
    Ok([
        point_ref(ctx, scene, &items[0], key)?,
        point_ref(ctx, scene, &items[1], key)?,
    ])
}

pub(super) fn check_unique(
    ctx: &Ctx,
    taken: &[&str],
    name: &str,
    line: u64,
    key: &str,
) -> Result<(), SceneError> {
    if taken.contains(&name) {
        return Err(ctx.err(line, key, format!("duplicate name '{name}'")));
    }
    Ok(())
}

fn read_points(ctx: &Ctx, scene: &mut Scene, node: &Node) -> Result<(), SceneError> {
    let items = seq(ctx, node, "points")?;
    if items.is_empty() {
        return Err(ctx.err(node.line, "points", "no points defined"));
    }
    for (i, item) in items.iter().enumerate() {
        let path = format!("points[{i}]");
        let mut f = Fields::new(ctx, item, &path)?;
        let name_node = f.req(ctx, "name")?;
        let name = name_of(ctx, name_node, &f.key("name"))?;
        let taken: Vec<&str> = scene.points.iter().map(|p| p.name.as_str()).collect();
        check_unique(ctx, &taken, &name, name_node.line, &f.key("name"))?;
        let x = ctx.num(f.req(ctx, "x")?, &f.key("x"), &[])?;
        let y = ctx.num(f.req(ctx, "y")?, &f.key("y"), &[])?;
        let fixed = match f.get("fixed") {
            Some(n) => boolean(ctx, n, &f.key("fixed"))?,
            None => false,
        };
        let mass = match f.get("mass") {
            Some(n) => ctx.positive(n, &f.key("mass"), &[])?,
            None => 0.0,
        };
        if let Some(dm) = ctx.derivatives.take(&f.key("mass")) {
            ctx.derivatives.point(scene.points.len(), dm);
        }
        f.finish(ctx, &["name", "x", "y", "fixed", "mass"])?;
        scene.points.push(Point {
            name,
            x,
            y,
            fixed,
            mass,
        });
    }
    if scene.points.iter().all(|p| p.fixed) {
        return Err(ctx.err(
            node.line,
            "points",
            "every point is fixed: nothing can move",
        ));
    }
    Ok(())
}

fn read_bodies(ctx: &Ctx, scene: &mut Scene, node: &Node) -> Result<(), SceneError> {
    for (i, item) in seq(ctx, node, "bodies")?.iter().enumerate() {
        let path = format!("bodies[{i}]");
        let mut f = Fields::new(ctx, item, &path)?;
        let (name, name_line) = match f.get("name") {
            Some(n) => (name_of(ctx, n, &f.key("name"))?, n.line),
            None => (format!("body{i}"), item.line),
        };
        let taken: Vec<&str> = scene.bodies.iter().map(|b| b.name.as_str()).collect();
        check_unique(ctx, &taken, &name, name_line, &f.key("name"))?;
        let pts_node = f.req(ctx, "points")?;
        let points = seq(ctx, pts_node, &f.key("points"))?
            .iter()
            .map(|p| point_ref(ctx, scene, p, &f.key("points")))
            .collect::<Result<Vec<_>, _>>()?;
        if points.len() < 2 {
            return Err(ctx.err(
                pts_node.line,
                &f.key("points"),
                format!("body '{name}' needs 2 or more points, has {}", points.len()),
            ));
        }
        let spec = body_spec(ctx, scene, &mut f, name, points, BodyStyle::Scene)?;
        f.finish(
            ctx,
            &["name", "points", "mass", "length", "cog", "inertia", "I0"],
        )?;
        build::add_body(ctx, scene, item.line, &path, spec)?;
    }
    Ok(())
}

fn read_constraints(ctx: &Ctx, scene: &mut Scene, node: &Node) -> Result<(), SceneError> {
    for (i, item) in seq(ctx, node, "constraints")?.iter().enumerate() {
        let path = format!("constraints[{i}]");
        let mut f = Fields::new(ctx, item, &path)?;
        let (ty, ty_line) = type_of(ctx, &mut f)?;
        let (name, name_line) = match f.get("name") {
            Some(n) => (name_of(ctx, n, &f.key("name"))?, n.line),
            None => (format!("{ty}{i}"), item.line),
        };
        let taken: Vec<&str> = scene.constraints.iter().map(|c| c.name.as_str()).collect();
        check_unique(ctx, &taken, &name, name_line, &f.key("name"))?;
        let kind = match ty.as_str() {
            "distance" => {
                let points = point_pair(ctx, scene, f.req(ctx, "points")?, &f.key("points"))?;
                let auto = build::distance(&scene.points, points[0], points[1]);
                let length = match f.get("length") {
                    None => auto,
                    Some(n) if matches!(&n.value, Value::String(s) if s.trim() == "auto") => auto,
                    Some(n) => ctx.positive(n, &f.key("length"), &[("auto", auto)])?,
                };
                if points[0] == points[1] || build::coincide(&scene.points, points[0], points[1]) {
                    return Err(ctx.err(item.line, &f.key("points"), "the two points coincide"));
                }
                f.finish(ctx, &["type", "name", "points", "length"])?;
                ConstraintKind::Distance { points, length }
            }
            "fixed_slider" | "mobile_slider" => {
                let point = point_ref(ctx, scene, f.req(ctx, "point")?, &f.key("point"))?;
                let line = point_pair(ctx, scene, f.req(ctx, "line")?, &f.key("line"))?;
                let (point_key, line_key) = (f.key("point"), f.key("line"));
                f.finish(ctx, &["type", "name", "point", "line"])?;
                if scene.points[point].fixed {
                    return Err(ctx.err(item.line, &point_key, format!("point '{}' is fixed: it cannot slide", scene.points[point].name)));
                }
                if line.contains(&point) || line[0] == line[1] || build::coincide(&scene.points, line[0], line[1]) {
                    return Err(ctx.err(item.line, &line_key, "the line needs two distinct points other than the sliding one"));
                }
                let fixed_line = line.iter().all(|&p| scene.points[p].fixed);
                if ty == "fixed_slider" {
                    if !fixed_line {
                        return Err(ctx.err(item.line, &line_key, "a fixed slider's line points must be fixed (use mobile_slider for a moving line)"));
                    }
                    ConstraintKind::FixedSlider { point, line }
                } else {
                    ConstraintKind::MobileSlider { point, line }
                }
            }
            other => {
                return Err(ctx.err(ty_line, &f.key("type"), format!("unknown constraint type '{}' (expected distance, fixed_slider or mobile_slider)", excerpt(other, QUOTE))))
            }
        };
        scene.constraints.push(ConstraintDef { name, kind });
    }
    Ok(())
}

/// The `type` of an entry and the line it is on.
pub(super) fn type_of(ctx: &Ctx, f: &mut Fields) -> Result<(String, u64), SceneError> {
    let n = f.req(ctx, "type")?;
    let ty = n.as_text().ok_or_else(|| {
        ctx.err(
            n.line,
            &f.key("type"),
            format!("expected a type name, found {}", n.kind()),
        )
    })?;
    Ok((ty, n.line))
}

fn read_coordinates(ctx: &Ctx, scene: &mut Scene, node: &Node) -> Result<(), SceneError> {
    for (i, item) in seq(ctx, node, "coordinates")?.iter().enumerate() {
        let path = format!("coordinates[{i}]");
        let mut f = Fields::new(ctx, item, &path)?;
        let (ty, ty_line) = type_of(ctx, &mut f)?;
        let name_node = f.req(ctx, "name")?;
        let name = name_of(ctx, name_node, &f.key("name"))?;
        let mut taken: Vec<&str> = scene.coordinates.iter().map(|c| c.name.as_str()).collect();
        taken.extend(scene.points.iter().map(|p| p.name.as_str()));
        check_unique(ctx, &taken, &name, name_node.line, &f.key("name"))?;
        let (kind, allowed): (RelativeKind, &[&str]) = match ty.as_str() {
            "angle" => {
                let [from, to] = point_pair(ctx, scene, f.req(ctx, "points")?, &f.key("points"))?;
                (
                    RelativeKind::AbsoluteAngle { from, to },
                    &["type", "name", "points", "initial"],
                )
            }
            "relative_angle" => {
                let segs_node = f.req(ctx, "segments")?;
                let segs = seq(ctx, segs_node, &f.key("segments"))?;
                if segs.len() != 2 {
                    return Err(ctx.err(
                        segs_node.line,
                        &f.key("segments"),
                        "expected two segments [[A, B], [C, D]]",
                    ));
                }
                let a = point_pair(ctx, scene, &segs[0], &f.key("segments"))?;
                let b = point_pair(ctx, scene, &segs[1], &f.key("segments"))?;
                (
                    RelativeKind::RelativeAngle { a, b },
                    &["type", "name", "segments", "initial"],
                )
            }
            "distance" => {
                let point = point_ref(ctx, scene, f.req(ctx, "point")?, &f.key("point"))?;
                let along = point_pair(ctx, scene, f.req(ctx, "along")?, &f.key("along"))?;
                (
                    RelativeKind::Distance { point, along },
                    &["type", "name", "point", "along", "initial"],
                )
            }
            other => {
                return Err(ctx.err(
                    ty_line,
                    &f.key("type"),
                    format!(
                        "unknown coordinate type '{}' (expected angle, relative_angle or distance)",
                        excerpt(other, QUOTE)
                    ),
                ))
            }
        };
        build::check_relative(ctx, scene, item.line, &path, &kind)?;
        let initial = match f.get("initial") {
            Some(n) => Some(ctx.num(n, &f.key("initial"), &[])?),
            None => None,
        };
        f.finish(ctx, allowed)?;
        scene.coordinates.push(RelativeCoordinate {
            name,
            kind,
            initial,
        });
    }
    Ok(())
}

fn angle_coordinate(ctx: &Ctx, scene: &Scene, f: &mut Fields) -> Result<usize, SceneError> {
    let n = f.req(ctx, "coordinate")?;
    let key = f.key("coordinate");
    let name = n.as_text().unwrap_or_default();
    let idx = scene.coordinate_index(&name).ok_or_else(|| {
        ctx.err(
            n.line,
            &key,
            format!(
                "unknown coordinate '{}' (effects act on relative coordinates){}",
                excerpt(&name, QUOTE),
                super::suggest::hint(
                    &name,
                    "relative coordinates",
                    scene.coordinates.iter().map(|c| c.name.as_str())
                )
            ),
        )
    })?;
    if !scene.coordinates[idx].kind.is_angle() {
        return Err(ctx.err(n.line, &key, format!("coordinate '{name}' is not an angle")));
    }
    Ok(idx)
}

fn read_effects(ctx: &Ctx, scene: &mut Scene, node: &Node) -> Result<(), SceneError> {
    let mut names: Vec<String> = Vec::new();
    for (i, item) in seq(ctx, node, "effects")?.iter().enumerate() {
        let path = format!("effects[{i}]");
        let mut f = Fields::new(ctx, item, &path)?;
        let (ty, ty_line) = type_of(ctx, &mut f)?;
        let (name, name_line) = match f.get("name") {
            Some(n) => (name_of(ctx, n, &f.key("name"))?, n.line),
            None => (format!("{ty}{i}"), item.line),
        };
        let taken: Vec<&str> = names.iter().map(String::as_str).collect();
        check_unique(ctx, &taken, &name, name_line, &f.key("name"))?;
        let effect = match ty.as_str() {
            "gravity" => {
                if scene.effects.iter().any(|e| matches!(e, Effect::Gravity { .. })) {
                    return Err(ctx.err(item.line, &path, "gravity is given twice"));
                }
                let vector = pair(ctx, f.req(ctx, "vector")?, &f.key("vector"), &[])?;
                let v = f.key("vector");
                ctx.derivatives.effect(scene.effects.len(), [&format!("{v}[0]"), &format!("{v}[1]")]);
                f.finish(ctx, &["type", "name", "vector"])?;
                Effect::Gravity { vector }
            }
            "spring_damper" => {
                let points = point_pair(ctx, scene, f.req(ctx, "points")?, &f.key("points"))?;
                if points[0] == points[1] {
                    return Err(ctx.err(item.line, &f.key("points"), "a spring needs two different points"));
                }
                let stiffness = opt_non_negative(ctx, &mut f, "stiffness")?;
                let damping = opt_non_negative(ctx, &mut f, "damping")?;
                let auto = build::distance(&scene.points, points[0], points[1]);
                let rest_length = match f.get("rest_length") {
                    None => auto,
                    Some(n) if matches!(&n.value, Value::String(s) if s.trim() == "auto") => auto,
                    Some(n) => ctx.non_negative_with(n, &f.key("rest_length"), &[("auto", auto)])?,
                };
                ctx.derivatives.effect(scene.effects.len(), [&f.key("stiffness"), &f.key("damping")]);
                f.finish(ctx, &["type", "name", "points", "stiffness", "rest_length", "damping"])?;
                if stiffness == 0.0 && damping == 0.0 {
                    return Err(ctx.err(item.line, &path, "a spring_damper needs a positive stiffness or damping"));
                }
                Effect::SpringDamper { name: name.clone(), points, stiffness, rest_length, damping }
            }
            "rotational_spring_damper" => {
                let coordinate = angle_coordinate(ctx, scene, &mut f)?;
                let stiffness = opt_non_negative(ctx, &mut f, "stiffness")?;
                let damping = opt_non_negative(ctx, &mut f, "damping")?;
                let rest_angle = match f.get("rest_angle") {
                    Some(n) => ctx.num(n, &f.key("rest_angle"), &[])?,
                    None if stiffness > 0.0 => {
                        return Err(ctx.err(item.line, &f.key("rest_angle"), "missing required key (with a stiffness)"))
                    }
                    None => 0.0,
                };
                ctx.derivatives.effect(scene.effects.len(), [&f.key("stiffness"), &f.key("damping")]);
                f.finish(ctx, &["type", "name", "coordinate", "stiffness", "rest_angle", "damping"])?;
                if stiffness == 0.0 && damping == 0.0 {
                    return Err(ctx.err(item.line, &path, "a rotational_spring_damper needs a positive stiffness or damping"));
                }
                Effect::RotationalSpringDamper { name: name.clone(), coordinate, stiffness, rest_angle, damping }
            }
            "dc_motor" => {
                let coordinate = angle_coordinate(ctx, scene, &mut f)?;
                let stall_torque = ctx.num(f.req(ctx, "stall_torque")?, &f.key("stall_torque"), &[])?;
                let no_load_speed = ctx.num(f.req(ctx, "no_load_speed")?, &f.key("no_load_speed"), &[])?;
                if !(no_load_speed != 0.0) {
                    return Err(ctx.err(item.line, &f.key("no_load_speed"), "must not be 0 (the speed at which the motor's torque falls to 0, rad/s; negative turns it the other way)"));
                }
                // The torque is linear in its stall torque only (no_load_speed divides).
                ctx.derivatives.effect(scene.effects.len(), [&f.key("stall_torque"), ""]);
                f.finish(ctx, &["type", "name", "coordinate", "stall_torque", "no_load_speed"])?;
                Effect::Motor { name: name.clone(), coordinate, stall_torque, no_load_speed }
            }
            "torque" => {
                let coordinate = angle_coordinate(ctx, scene, &mut f)?;
                let value = ctx.load_function(f.req(ctx, "value")?, &f.key("value"), scene)?;
                f.finish(ctx, &["type", "name", "coordinate", "value"])?;
                Effect::Torque { name: name.clone(), coordinate, value }
            }
            "force" => {
                let point = point_ref(ctx, scene, f.req(ctx, "point")?, &f.key("point"))?;
                if scene.points[point].fixed {
                    return Err(ctx.err(item.line, &f.key("point"), format!("point '{}' is fixed: a force there does no work", scene.points[point].name)));
                }
                let v = f.req(ctx, "value")?;
                let items = seq(ctx, v, &f.key("value"))?;
                if items.len() != 2 {
                    return Err(ctx.err(v.line, &f.key("value"), "expected [fx, fy]"));
                }
                let value = [
                    ctx.load_function(&items[0], &f.key("value[0]"), scene)?,
                    ctx.load_function(&items[1], &f.key("value[1]"), scene)?,
                ];
                f.finish(ctx, &["type", "name", "point", "value"])?;
                Effect::Force { name: name.clone(), point, value }
            }
            other => {
                return Err(ctx.err(ty_line, &f.key("type"), format!("unknown effect type '{}' (expected gravity, spring_damper, rotational_spring_damper, dc_motor, torque or force)", excerpt(other, QUOTE))))
            }
        };
        names.push(name);
        scene.effects.push(effect);
    }
    Ok(())
}

fn opt_non_negative(ctx: &Ctx, f: &mut Fields, key: &str) -> Result<f64, SceneError> {
    match f.get(key) {
        Some(n) => ctx.non_negative(n, &f.key(key)),
        None => Ok(0.0),
    }
}

/// Checks that `name` is a coordinate of q.
pub(super) fn q_name(
    ctx: &Ctx,
    scene: &Scene,
    node: &Node,
    key: &str,
) -> Result<String, SceneError> {
    let name = node.as_text().ok_or_else(|| {
        ctx.err(
            node.line,
            key,
            format!("expected a coordinate name, found {}", node.kind()),
        )
    })?;
    if build::is_coordinate_name(scene, &name) {
        return Ok(name);
    }
    let hint = match name.split_once('.') {
        Some((p, _)) if scene.point_index(p).is_some_and(|i| scene.points[i].fixed) => {
            format!(" (point '{p}' is fixed)")
        }
        _ => String::new(),
    };
    let names = build::coordinate_names(scene);
    let near = super::suggest::did_you_mean(&name, names.iter().map(String::as_str));
    Err(ctx.err(node.line, key, format!("unknown coordinate '{}'{hint} (coordinates are <point>.x, <point>.y of free points and relative coordinates){near}", excerpt(&name, QUOTE))))
}

fn read_independent(ctx: &Ctx, scene: &mut Scene, node: &Node) -> Result<(), SceneError> {
    scene.independent_line = (node.line > 0).then_some(node.line);
    for item in seq(ctx, node, "independent")? {
        let name = q_name(ctx, scene, item, "independent")?;
        if scene.independent.contains(&name) {
            return Err(ctx.err(item.line, "independent", format!("duplicate name '{name}'")));
        }
        scene.independent.push(name);
    }
    Ok(())
}

fn read_initial(ctx: &Ctx, scene: &mut Scene, node: &Node) -> Result<(), SceneError> {
    let mut f = Fields::new(ctx, node, "initial")?;
    if let Some(n) = f.get("positions") {
        for (name, value) in named_values(ctx, scene, n, "initial.positions")? {
            scene.initial_positions.push((name, value));
        }
    }
    if let Some(n) = f.get("velocities") {
        let Value::Map(pairs) = &n.value else {
            return Err(ctx.err(
                n.line,
                "initial.velocities",
                "expected a mapping coordinate: value",
            ));
        };
        let values = named_values(ctx, scene, n, "initial.velocities")?;
        for ((name, value), (k, _)) in values.into_iter().zip(pairs) {
            if !scene.independent.contains(&name) {
                return Err(ctx.err(k.line, &format!("initial.velocities.{name}"), "initial velocities are given for independent coordinates only; declare it in `independent`"));
            }
            scene.initial_velocities.push((name, value));
        }
    }
    f.finish(ctx, &["positions", "velocities"])?;
    Ok(())
}

fn named_values(
    ctx: &Ctx,
    scene: &Scene,
    node: &Node,
    key: &str,
) -> Result<Vec<(String, f64)>, SceneError> {
    let Value::Map(pairs) = &node.value else {
        return Err(ctx.err(node.line, key, "expected a mapping coordinate: value"));
    };
    let mut out: Vec<(String, f64)> = Vec::new();
    for (k, v) in pairs {
        let name = q_name(ctx, scene, k, key)?;
        let path = format!("{key}.{name}");
        if out.iter().any(|(n, _)| *n == name) {
            return Err(ctx.err(k.line, &path, format!("duplicate name '{name}'")));
        }
        out.push((name, ctx.num(v, &path, &[])?));
    }
    Ok(out)
}
