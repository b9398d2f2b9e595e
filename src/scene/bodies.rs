//! A body's inertial data as both formats read it ([`body_spec`]): mass, length,
//! centre of mass and inertia, with the scene format's defaults or MBSE's required
//! keys ([`BodyStyle`]).

use super::build::{self, BodySpec};
use super::fields::{pair, Ctx, Fields};
use super::yaml::Value;
use super::Scene;
use crate::error::SceneError;

/// Which inertia keys a body uses: the scene format's `inertia` (about the centre of
/// mass, with slender-rod defaults) or MBSE's mandatory `I0` (about the first point).
#[derive(PartialEq)]
pub enum BodyStyle {
    Scene,
    Mbse,
}

/// Reads mass, length, centre of mass and inertia of a body whose points are known.
/// Expressions see `length` (and `L`), `auto` (in `length`), `lengthIJ` (1-based
/// pairs), `index` and, once read, `mass` and `I0`.
pub fn body_spec(
    ctx: &Ctx,
    scene: &Scene,
    f: &mut Fields,
    name: String,
    points: Vec<usize>,
    style: BodyStyle,
) -> Result<BodySpec, SceneError> {
    let index = scene.bodies.len() as f64;
    let auto = build::distance(&scene.points, points[0], points[1]);
    let mut pair_names: Vec<(String, f64)> = Vec::new();
    for a in 0..points.len() {
        for b in 0..points.len() {
            if a != b {
                let d = build::distance(&scene.points, points[a], points[b]);
                pair_names.push((format!("length{}{}", a + 1, b + 1), d));
            }
        }
    }
    let mut vars: Vec<(&str, f64)> = pair_names.iter().map(|(n, v)| (n.as_str(), *v)).collect();
    vars.push(("index", index));
    let length = match f.get("length") {
        // Bodies on 3 or more points are rigid as placed: MBSE ignores their length.
        Some(_) if points.len() > 2 => auto,
        Some(n) if matches!(&n.value, Value::String(s) if s.trim() == "auto") => auto,
        Some(n) => {
            let mut v = vars.clone();
            v.push(("auto", auto));
            ctx.positive(n, &f.key("length"), &v)?
        }
        None if style == BodyStyle::Mbse && points.len() == 2 => {
            return Err(ctx.err(
                f.line,
                &f.key("length"),
                "missing required key (a number, an expression or auto)",
            ))
        }
        None => auto,
    };
    vars.push(("length", length));
    vars.push(("L", length));
    let mass = ctx.positive(f.req(ctx, "mass")?, &f.key("mass"), &vars)?;
    let d = &ctx.derivatives;
    let dmass = d.take(&f.key("mass"));
    d.set_extra("mass", dmass.clone());
    vars.push(("mass", mass));
    let two_point = points.len() == 2;
    let i0_node = f.get("I0");
    let inertia_node = if style == BodyStyle::Scene {
        f.get("inertia")
    } else {
        None
    };
    let cog = match f.get("cog") {
        Some(n) => pair(ctx, n, &f.key("cog"), &vars)?,
        None if two_point && style == BodyStyle::Scene => [0.5 * length, 0.0],
        None => {
            return Err(ctx.err(
                f.line,
                &f.key("cog"),
                format!(
                    "missing required key: body '{name}' on {} points needs its centre of mass",
                    points.len()
                ),
            ))
        }
    };
    let cog2 = cog[0] * cog[0] + cog[1] * cog[1];
    // ∂I₀/∂p of I₀ = I_G + m |cog|² (the centre fixed: geometry is not identified).
    let scaled = |g: &Option<Vec<f64>>, k: f64| {
        g.as_ref()
            .map(|g| g.iter().map(|v| v * k).collect::<Vec<f64>>())
    };
    let sum = |a: Option<Vec<f64>>, b: Option<Vec<f64>>| match (a, b) {
        (Some(a), Some(b)) => Some(a.iter().zip(&b).map(|(x, y)| x + y).collect()),
        (a, b) => a.or(b),
    };
    let (i0, di0) = match (i0_node, inertia_node) {
        (Some(_), Some(_)) => {
            return Err(ctx.err(f.line, &f.key("inertia"), "give either inertia (about the centre of mass) or I0 (about the first point), not both"))
        }
        (Some(n), None) => {
            let v = ctx.positive(n, &f.key("I0"), &vars)?;
            (v, d.take(&f.key("I0")))
        }
        (None, Some(n)) => {
            let v = ctx.positive(n, &f.key("inertia"), &vars)?;
            (v + mass * cog2, sum(d.take(&f.key("inertia")), scaled(&dmass, cog2)))
        }
        (None, None) if two_point && style == BodyStyle::Scene => {
            let k = length * length / 12.0 + cog2;
            (mass * k, scaled(&dmass, k))
        }
        (None, None) => {
            let k = if style == BodyStyle::Mbse { "I0" } else { "inertia" };
            return Err(ctx.err(f.line, &f.key(k), format!("missing required key: body '{name}' needs its moment of inertia")));
        }
    };
    d.set_extra("mass", None);
    if dmass.is_some() || di0.is_some() {
        let p = d.unknown.len();
        let index = scene.bodies.len();
        d.body(
            index,
            dmass.unwrap_or(vec![0.0; p]),
            di0.unwrap_or(vec![0.0; p]),
        );
    }
    Ok(BodySpec {
        name,
        points,
        mass,
        cog,
        i0,
        i0_line: i0_node.map_or(f.line, |n| n.line),
        length,
    })
}
