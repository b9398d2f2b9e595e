//! The `sensors:` and `estimation:` sections of the mbfg scene format.

use super::fields::{name_of, seq, Ctx, Fields, QUOTE};
use super::native::{check_unique, point_ref, q_name, type_of};
use super::yaml::{Node, Value};
use super::{Scene, SensorDef, SensorDefKind};
use crate::error::SceneError;
use crate::expr::excerpt;

const TYPES: &str = "encoder, gyroscope, accelerometer, marker, expression or input";

pub fn read_sensors(ctx: &Ctx, scene: &mut Scene, node: &Node) -> Result<(), SceneError> {
    for (i, item) in seq(ctx, node, "sensors")?.iter().enumerate() {
        let path = format!("sensors[{i}]");
        let mut f = Fields::new(ctx, item, &path)?;
        let (ty, ty_line) = type_of(ctx, &mut f)?;
        let name_node = f.req(ctx, "name")?;
        let name = name_of(ctx, name_node, &f.key("name"))?;
        let mut taken: Vec<&str> = scene.sensors.iter().map(|s| s.name.as_str()).collect();
        // The measurement CSV's first column.
        taken.push("t");
        check_unique(ctx, &taken, &name, name_node.line, &f.key("name"))?;
        let sigma = ctx.positive(f.req(ctx, "sigma")?, &f.key("sigma"), &[])?;
        let rate = match f.get("rate") {
            Some(n) => Some(ctx.positive(n, &f.key("rate"), &[])?),
            None => None,
        };
        let mut resolution = None;
        let body_of = |f: &mut Fields| -> Result<usize, SceneError> {
            let n = f.req(ctx, "body")?;
            let key = f.key("body");
            let text = n.as_text().unwrap_or_default();
            let b = scene
                .bodies
                .iter()
                .position(|b| b.name == text)
                .ok_or_else(|| {
                    ctx.err(
                        n.line,
                        &key,
                        format!(
                            "unknown body '{}'{}",
                            excerpt(&text, QUOTE),
                            super::suggest::hint(
                                &text,
                                "bodies",
                                scene.bodies.iter().map(|b| b.name.as_str())
                            )
                        ),
                    )
                })?;
            let body = &scene.bodies[b];
            if body.points[..2].iter().all(|&p| scene.points[p].fixed) {
                return Err(ctx.err(
                    n.line,
                    &key,
                    format!(
                        "sensor '{name}': body '{}' is fixed; it observes nothing of the motion",
                        body.name
                    ),
                ));
            }
            Ok(b)
        };
        let (kind, allowed): (SensorDefKind, &[&str]) = match ty.as_str() {
            "encoder" => {
                let n = f.req(ctx, "coordinate")?;
                let coordinate = q_name(ctx, scene, n, &f.key("coordinate"))?;
                if let Some(r) = f.get("resolution") {
                    let key = f.key("resolution");
                    let is_angle = scene
                        .coordinate_index(&coordinate)
                        .is_some_and(|c| scene.coordinates[c].kind.is_angle());
                    if !is_angle {
                        return Err(ctx.err(r.line, &key, format!("a resolution is counts per turn; coordinate '{coordinate}' is not an angle")));
                    }
                    let v = ctx.positive(r, &key, &[])?;
                    if v.fract() != 0.0 || v > MAX_RESOLUTION {
                        return Err(ctx.err(
                            r.line,
                            &key,
                            format!("must be a whole number of counts per turn from 1 to {MAX_RESOLUTION:e}, got {v}"),
                        ));
                    }
                    resolution = Some(v as u64);
                }
                (
                    SensorDefKind::Encoder { coordinate },
                    &["type", "name", "sigma", "rate", "coordinate", "resolution"],
                )
            }
            "gyroscope" => (
                SensorDefKind::Gyroscope {
                    body: body_of(&mut f)?,
                },
                &["type", "name", "sigma", "rate", "body"],
            ),
            "accelerometer" => {
                let body = body_of(&mut f)?;
                let n = f.req(ctx, "point")?;
                let point = point_ref(ctx, scene, n, &f.key("point"))?;
                if !scene.bodies[body].points.contains(&point) {
                    return Err(ctx.err(
                        n.line,
                        &f.key("point"),
                        format!(
                            "point '{}' is not on body '{}' (its points: {})",
                            scene.points[point].name,
                            scene.bodies[body].name,
                            scene.bodies[body]
                                .points
                                .iter()
                                .map(|&p| scene.points[p].name.as_str())
                                .collect::<Vec<_>>()
                                .join(", ")
                        ),
                    ));
                }
                (
                    SensorDefKind::Accelerometer { body, point },
                    &["type", "name", "sigma", "rate", "body", "point"],
                )
            }
            "marker" => {
                let n = f.req(ctx, "point")?;
                let point = point_ref(ctx, scene, n, &f.key("point"))?;
                if scene.points[point].fixed {
                    return Err(ctx.err(
                        n.line,
                        &f.key("point"),
                        format!(
                            "sensor '{name}': point '{}' is fixed; it observes nothing of the motion",
                            scene.points[point].name
                        ),
                    ));
                }
                (
                    SensorDefKind::Marker { point },
                    &["type", "name", "sigma", "rate", "point"],
                )
            }
            "expression" => {
                let n = f.req(ctx, "value")?;
                let value = ctx.load_function(n, &f.key("value"), scene)?;
                if !value.is_state_dependent() {
                    return Err(ctx.err(
                        n.line,
                        &f.key("value"),
                        format!(
                            "sensor '{name}': '{}' does not depend on the state; it observes nothing of the motion",
                            excerpt(&value.text, QUOTE)
                        ),
                    ));
                }
                (
                    SensorDefKind::Expression { value },
                    &["type", "name", "sigma", "rate", "value"],
                )
            }
            "input" => {
                let n = f.req(ctx, "coordinate")?;
                let coordinate = q_name(ctx, scene, n, &f.key("coordinate"))?;
                (
                    SensorDefKind::Input { coordinate },
                    &["type", "name", "sigma", "rate", "coordinate"],
                )
            }
            other => {
                return Err(ctx.err(
                    ty_line,
                    &f.key("type"),
                    format!(
                        "unknown sensor type '{}' (expected {TYPES})",
                        excerpt(other, QUOTE)
                    ),
                ))
            }
        };
        f.finish(ctx, allowed)?;
        scene.sensors.push(SensorDef {
            name,
            kind,
            sigma,
            resolution,
            rate,
        });
    }
    Ok(())
}

/// Largest encoder resolution: counts per turn still whole in a double.
const MAX_RESOLUTION: f64 = 9.007_199_254_740_992e15;

/// The names under `estimation: parameters:` as far as they can be read before the
/// rest of the file (the parameters' derivatives are taken as the file is read);
/// [`read_estimation`] checks them.
pub fn identified_names(root: &Node) -> Vec<String> {
    let field = |node: &Node, key: &str| match &node.value {
        Value::Map(pairs) => pairs
            .iter()
            .find(|(k, _)| matches!(&k.value, Value::String(s) if s == key))
            .map(|(_, v)| v.clone()),
        _ => None,
    };
    let Some(list) = field(root, "estimation").and_then(|e| field(&e, "parameters")) else {
        return Vec::new();
    };
    let Value::Seq(items) = &list.value else {
        return Vec::new();
    };
    let mut names: Vec<String> = Vec::new();
    for item in items {
        if let Some(name) = field(item, "name").and_then(|n| n.as_text()) {
            if !names.contains(&name) {
                names.push(name);
            }
        }
    }
    names
}

pub fn read_estimation(ctx: &Ctx, scene: &mut Scene, node: &Node) -> Result<(), SceneError> {
    let mut f = Fields::new(ctx, node, "estimation")?;
    let mut est = super::EstimationDef::default();
    if let Some(n) = f.get("process_sigma") {
        est.process_sigma = Some(ctx.positive(n, &f.key("process_sigma"), &[])?);
    }
    if let Some(n) = f.get("initial_sigma") {
        est.initial_sigma = sigmas(ctx, scene, n, &f.key("initial_sigma"))?;
    }
    if let Some(n) = f.get("initial_velocity_sigma") {
        est.initial_velocity_sigma = sigmas(ctx, scene, n, &f.key("initial_velocity_sigma"))?;
    }
    if let Some(n) = f.get("inputs") {
        for (i, item) in seq(ctx, n, "estimation.inputs")?.iter().enumerate() {
            let mut g = Fields::new(ctx, item, &format!("estimation.inputs[{i}]"))?;
            let c = g.req(ctx, "coordinate")?;
            let name = q_name(ctx, scene, c, &g.key("coordinate"))?;
            if est.inputs.iter().any(|(m, _)| *m == name) {
                return Err(ctx.err(
                    c.line,
                    &g.key("coordinate"),
                    format!("duplicate input on '{name}'"),
                ));
            }
            let sigma = ctx.positive(g.req(ctx, "sigma_rate")?, &g.key("sigma_rate"), &[])?;
            g.finish(ctx, &["coordinate", "sigma_rate"])?;
            est.inputs.push((name, sigma));
        }
    }
    if let Some(n) = f.get("parameters") {
        for (i, item) in seq(ctx, n, "estimation.parameters")?.iter().enumerate() {
            let mut g = Fields::new(ctx, item, &format!("estimation.parameters[{i}]"))?;
            let key = g.key("name");
            let node = g.req(ctx, "name")?;
            let name = node
                .as_text()
                .ok_or_else(|| ctx.err(node.line, &key, "expected a parameter's name"))?;
            if !ctx.params.iter().any(|(p, _)| *p == name) {
                return Err(ctx.err(
                    node.line,
                    &key,
                    format!(
                        "no parameter '{}' in `parameters:`{}",
                        crate::expr::excerpt(&name, 40),
                        super::suggest::did_you_mean(
                            &name,
                            ctx.params.iter().map(|(p, _)| p.as_str())
                        )
                    ),
                ));
            }
            if est.parameters.iter().any(|(p, _)| *p == name) {
                return Err(ctx.err(node.line, &key, format!("'{name}' is identified twice")));
            }
            let sigma = ctx.positive(g.req(ctx, "sigma")?, &g.key("sigma"), &[])?;
            g.finish(ctx, &["name", "sigma"])?;
            est.parameters.push((name, sigma));
        }
    }
    f.finish(
        ctx,
        &[
            "process_sigma",
            "initial_sigma",
            "initial_velocity_sigma",
            "inputs",
            "parameters",
        ],
    )?;
    scene.estimation = est;
    Ok(())
}

/// A mapping coordinate of q → σ (> 0).
fn sigmas(
    ctx: &Ctx,
    scene: &Scene,
    node: &Node,
    key: &str,
) -> Result<Vec<(String, f64)>, SceneError> {
    let Value::Map(pairs) = &node.value else {
        return Err(ctx.err(node.line, key, "expected a mapping coordinate: sigma"));
    };
    let mut out: Vec<(String, f64)> = Vec::new();
    for (k, v) in pairs {
        let name = q_name(ctx, scene, k, key)?;
        let path = format!("{key}.{name}");
        if out.iter().any(|(n, _)| *n == name) {
            return Err(ctx.err(k.line, &path, format!("duplicate name '{name}'")));
        }
        out.push((name, ctx.positive(v, &path, &[])?));
    }
    Ok(out)
}
