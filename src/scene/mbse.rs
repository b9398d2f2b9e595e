//! MBSE mechanism files, the YAML of the paper's C++ library: `points` (unnamed,
//! `{x, y, fixed}`; expressions may use earlier points' `x<i>`, `y<i>`),
//! `planar_bodies` (`points` by index, `length` (`auto` allowed), `mass`, `I0` about
//! the first point, `cog` in the body frame), `relative_coordinates` of type
//! `RelativeAngleAbsoluteDOF`, and `parameters`. Points are named `p<index>`,
//! relative coordinates `r<index>`, bodies `body<index>`.

use super::bodies::{body_spec, BodyStyle};
use super::build;
use super::fields::{boolean, seq, Ctx, Fields, QUOTE};
use super::yaml::Node;
use super::{Point, RelativeCoordinate, RelativeKind, Scene};
use crate::error::SceneError;
use crate::expr::excerpt;

pub fn read(root: &Node, file: &str, overrides: &[(String, f64)]) -> Result<Scene, SceneError> {
    let mut ctx = Ctx::with_overrides(file, overrides);
    let mut top = Fields::new(&ctx, root, "")?;
    if let Some(p) = top.get("parameters") {
        ctx.read_parameters(p)?;
    }
    ctx.check_overrides(top.get("parameters").map_or(0, |p| p.line))?;
    let mut scene = build::empty(file);
    let points = top.req(&ctx, "points")?;
    read_points(&mut ctx, &mut scene, points)?;
    read_bodies(&ctx, &mut scene, top.req(&ctx, "planar_bodies")?)?;
    if let Some(n) = top.get("relative_coordinates") {
        read_relative(&ctx, &mut scene, n)?;
    }
    top.finish(
        &ctx,
        &[
            "parameters",
            "points",
            "planar_bodies",
            "relative_coordinates",
        ],
    )?;
    Ok(scene)
}

fn read_points(ctx: &mut Ctx, scene: &mut Scene, node: &Node) -> Result<(), SceneError> {
    let items = seq(ctx, node, "points")?;
    if items.is_empty() {
        return Err(ctx.err(node.line, "points", "no points defined"));
    }
    let base = ctx.params.len();
    for (i, item) in items.iter().enumerate() {
        let path = format!("points[{i}]");
        let mut f = Fields::new(ctx, item, &path)?;
        let x = ctx.num(f.req(ctx, "x")?, &f.key("x"), &[])?;
        let y = ctx.num(f.req(ctx, "y")?, &f.key("y"), &[])?;
        let fixed = match f.get("fixed") {
            Some(n) => boolean(ctx, n, &f.key("fixed"))?,
            None => false,
        };
        f.finish(ctx, &["x", "y", "fixed"])?;
        // Later points may refer to this one's coordinates.
        ctx.params.push((format!("x{i}"), x));
        ctx.params.push((format!("y{i}"), y));
        scene.points.push(Point {
            name: format!("p{i}"),
            x,
            y,
            fixed,
            mass: 0.0,
        });
    }
    ctx.params.truncate(base);
    if scene.points.iter().all(|p| p.fixed) {
        return Err(ctx.err(
            node.line,
            "points",
            "every point is fixed: nothing can move",
        ));
    }
    Ok(())
}

/// A point given by index (a number or an expression that rounds to one).
fn point_index(ctx: &Ctx, scene: &Scene, node: &Node, key: &str) -> Result<usize, SceneError> {
    let v = ctx.num(node, key, &[])?;
    let i = v.round();
    if (v - i).abs() > 1e-9 || i < 0.0 || i as usize >= scene.points.len() {
        return Err(ctx.err(
            node.line,
            key,
            format!(
                "unknown point {v}: points are numbered 0 to {}",
                scene.points.len() - 1
            ),
        ));
    }
    Ok(i as usize)
}

fn read_bodies(ctx: &Ctx, scene: &mut Scene, node: &Node) -> Result<(), SceneError> {
    let items = seq(ctx, node, "planar_bodies")?;
    if items.is_empty() {
        return Err(ctx.err(node.line, "planar_bodies", "no bodies defined"));
    }
    for (i, item) in items.iter().enumerate() {
        let path = format!("planar_bodies[{i}]");
        let mut f = Fields::new(ctx, item, &path)?;
        let pts_node = f.req(ctx, "points")?;
        let points = seq(ctx, pts_node, &f.key("points"))?
            .iter()
            .map(|p| point_index(ctx, scene, p, &f.key("points")))
            .collect::<Result<Vec<_>, _>>()?;
        if points.len() < 2 {
            return Err(ctx.err(
                pts_node.line,
                &f.key("points"),
                format!("body {i} needs 2 or more points, has {}", points.len()),
            ));
        }
        let spec = body_spec(
            ctx,
            scene,
            &mut f,
            format!("body{i}"),
            points,
            BodyStyle::Mbse,
        )?;
        // Drawing hints of the paper's library: no part of the dynamics.
        if f.get("visual").is_some() {
            scene.notes.push(format!(
                "{}: {path}.visual is a drawing hint: ignored",
                ctx.file
            ));
        }
        f.finish(ctx, &["points", "length", "mass", "I0", "cog", "visual"])?;
        build::add_body(ctx, scene, item.line, &path, spec)?;
    }
    Ok(())
}

fn read_relative(ctx: &Ctx, scene: &mut Scene, node: &Node) -> Result<(), SceneError> {
    for (i, item) in seq(ctx, node, "relative_coordinates")?.iter().enumerate() {
        let path = format!("relative_coordinates[{i}]");
        let mut f = Fields::new(ctx, item, &path)?;
        let ty_node = f.req(ctx, "type")?;
        let ty = ty_node.as_text().unwrap_or_default();
        if ty != "RelativeAngleAbsoluteDOF" {
            return Err(ctx.err(
                ty_node.line,
                &f.key("type"),
                format!(
                    "unknown relative coordinate type '{}' (expected RelativeAngleAbsoluteDOF)",
                    excerpt(&ty, QUOTE)
                ),
            ));
        }
        let pts_node = f.req(ctx, "points")?;
        let pts = seq(ctx, pts_node, &f.key("points"))?;
        if pts.len() != 2 {
            return Err(ctx.err(pts_node.line, &f.key("points"), "expected two points"));
        }
        let from = point_index(ctx, scene, &pts[0], &f.key("points"))?;
        let to = point_index(ctx, scene, &pts[1], &f.key("points"))?;
        f.finish(ctx, &["type", "points"])?;
        let kind = RelativeKind::AbsoluteAngle { from, to };
        build::check_relative(ctx, scene, item.line, &path, &kind)?;
        scene.coordinates.push(RelativeCoordinate {
            name: format!("r{i}"),
            kind,
            initial: None,
        });
    }
    Ok(())
}
