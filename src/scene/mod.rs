//! Scene files: the mechanism, its initial state and every effect that acts on it.
//!
//! Two formats are read. The mbfg scene format (named points, `bodies`, `coordinates`,
//! `constraints`, `effects`, `independent`, `initial`; documented in
//! `docs/scene-format.md`) and the MBSE mechanism format of the paper's C++ library
//! (`points`, `planar_bodies`, `relative_coordinates`), which a scene may name with
//! `mechanism: file.yaml`. Both end in the same validated [`Scene`], with every
//! expression evaluated.

mod bodies;
mod build;
mod derivatives;
mod fields;
mod mbse;
mod native;
mod sensors;
mod suggest;
pub mod yaml;

use crate::error::{Error, SceneError};
use crate::expr::Expr;
use std::path::Path;

pub use build::{coordinate_names, relative_value};
pub use derivatives::Identified;
pub use suggest::did_you_mean;

/// A named point of the mechanism, fixed or free.
#[derive(Debug, Clone, PartialEq)]
pub struct Point {
    pub name: String,
    /// Initial (approximate, for free points) coordinates.
    pub x: f64,
    pub y: f64,
    pub fixed: bool,
    /// A point mass carried by the point, 0 when none.
    pub mass: f64,
}

/// A rigid body on two or more points. Its frame has its origin at the first point
/// and its x axis towards the second.
#[derive(Debug, Clone, PartialEq)]
pub struct Body {
    pub name: String,
    /// Indices into [`Scene::points`].
    pub points: Vec<usize>,
    pub mass: f64,
    /// Centre of mass in the body frame.
    pub cog: [f64; 2],
    /// Polar moment of inertia about the first point.
    pub i0: f64,
    /// Distance between the first two points, the frame's length scale. For a
    /// two-point body this is the length its distance constraint keeps.
    pub length: f64,
}

impl Body {
    /// Moment of inertia about the centre of mass.
    pub fn inertia_at_cog(&self) -> f64 {
        self.i0 - self.mass * (self.cog[0].powi(2) + self.cog[1].powi(2))
    }
}

/// A relative coordinate, added to q beside the point coordinates.
#[derive(Debug, Clone, PartialEq)]
pub struct RelativeCoordinate {
    pub name: String,
    pub kind: RelativeKind,
    /// Initial value, when the scene gives one; otherwise computed from the points.
    pub initial: Option<f64>,
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub enum RelativeKind {
    /// Angle of the segment `from → to` against the global x axis (paper, Appendix III).
    AbsoluteAngle { from: usize, to: usize },
    /// Angle from segment `a` to segment `b`, counter-clockwise.
    RelativeAngle { a: [usize; 2], b: [usize; 2] },
    /// Distance of `point` from `along[0]`, measured along the segment `along`.
    Distance { point: usize, along: [usize; 2] },
}

impl RelativeKind {
    pub fn is_angle(&self) -> bool {
        !matches!(self, RelativeKind::Distance { .. })
    }
}

/// A constraint the scene declares explicitly (rigid-body distances are generated).
#[derive(Debug, Clone, PartialEq)]
pub struct ConstraintDef {
    pub name: String,
    pub kind: ConstraintKind,
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ConstraintKind {
    Distance {
        points: [usize; 2],
        length: f64,
    },
    /// The point slides on the line through two fixed points.
    FixedSlider {
        point: usize,
        line: [usize; 2],
    },
    /// The point slides on the line through two points that move.
    MobileSlider {
        point: usize,
        line: [usize; 2],
    },
}

/// An effect's value from the scene: a constant, an expression in the time `t`, or an
/// expression in `t` and the mechanism's state (`rate(theta)`, `x(P)`, …), with the
/// parameters already substituted, but for those an estimate identifies.
#[derive(Debug, Clone, PartialEq)]
pub struct LoadFunction {
    expr: Expr,
    pub text: String,
    /// The identified parameters the expression keeps as names, with their values in
    /// the file (`estimation: parameters:`).
    pub parameters: Vec<(String, f64)>,
}

impl LoadFunction {
    pub fn constant(value: f64) -> Self {
        LoadFunction {
            expr: Expr::constant(value),
            text: format!("{value}"),
            parameters: Vec::new(),
        }
    }

    pub(crate) fn new(expr: Expr, text: String) -> Self {
        LoadFunction {
            expr,
            text,
            parameters: Vec::new(),
        }
    }

    /// The expression, its names `t`, the state quantities of
    /// [`Scene::is_state_name`] and the identified [`LoadFunction::parameters`].
    pub fn expr(&self) -> &Expr {
        &self.expr
    }

    /// The state quantities the value depends on, in order of appearance.
    pub fn state_names(&self) -> Vec<String> {
        let mut names = self.expr.names();
        names.retain(|n| n != "t" && !self.parameters.iter().any(|(p, _)| p == n));
        names
    }

    /// The value of name `n` other than a state quantity: `t`, or an identified
    /// parameter at its file value.
    fn fixed(&self, n: &str, t: f64) -> Option<f64> {
        if n == "t" {
            return Some(t);
        }
        self.parameters
            .iter()
            .find(|(p, _)| p == n)
            .map(|&(_, v)| v)
    }

    /// Whether the value depends on the state, not on time alone.
    pub fn is_state_dependent(&self) -> bool {
        !self.state_names().is_empty()
    }

    /// Value at time `t` of a value that depends on time alone; a non-finite value
    /// (say `1/t` at 0) is reported as an error, and so is a state-dependent value.
    pub fn at(&self, t: f64) -> crate::Result<f64> {
        if let Some(c) = self.expr.as_constant() {
            return Ok(c);
        }
        let text = crate::expr::excerpt(&self.text, fields::QUOTE);
        if self.is_state_dependent() {
            return Err(Error::InvalidArgument(format!(
                "'{text}' depends on the state ({}), not on time alone",
                self.state_names().join(", ")
            )));
        }
        self.expr
            .eval(&|n| self.fixed(n, t))
            .map_err(|e| Error::InvalidArgument(format!("'{text}' at t = {t}: {e}")))
    }
}

/// Something that acts on the mechanism. Nothing acts unless the scene names it.
#[derive(Debug, Clone, PartialEq)]
pub enum Effect {
    /// Uniform gravity acting on every mass.
    Gravity { vector: [f64; 2] },
    /// A linear spring and/or damper between two points.
    SpringDamper {
        name: String,
        points: [usize; 2],
        stiffness: f64,
        rest_length: f64,
        damping: f64,
    },
    /// A rotational spring and/or damper on an angle coordinate.
    RotationalSpringDamper {
        name: String,
        coordinate: usize,
        stiffness: f64,
        rest_angle: f64,
        damping: f64,
    },
    /// A DC motor on an angle coordinate: its torque falls linearly with its speed,
    /// T = T_s (1 − ω/ω₀), from the stall torque T_s at rest to 0 at the no-load
    /// speed ω₀ (and brakes beyond it).
    Motor {
        name: String,
        coordinate: usize,
        stall_torque: f64,
        no_load_speed: f64,
    },
    /// A torque on an angle coordinate.
    Torque {
        name: String,
        coordinate: usize,
        value: LoadFunction,
    },
    /// A force at a point, in global axes.
    Force {
        name: String,
        point: usize,
        value: [LoadFunction; 2],
    },
    /// Generalized forces computed outside the scene (a Python callable), added with
    /// [`crate::Model::add_external_load`].
    External { name: String },
}

/// A quantity of the mechanism's state that an effect's value may use: by its bare
/// name a relative coordinate, `rate(c)` its rate, `x(P)`, `y(P)`, `vx(P)`, `vy(P)` a
/// point's position and velocity, `angle(B)`, `omega(B)` the angle of a body's first
/// two points against the x axis, in (−π, π], and its rate.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum StateQuantity {
    Coordinate(usize),
    Rate(usize),
    X(usize),
    Y(usize),
    Vx(usize),
    Vy(usize),
    Angle(usize),
    Omega(usize),
}

/// A validated scene.
#[derive(Debug, Clone, PartialEq)]
pub struct Scene {
    /// The file it was read from, as named by the user.
    pub file: String,
    pub points: Vec<Point>,
    pub bodies: Vec<Body>,
    /// Indices into `coordinates` order are the relative coordinates' order in q.
    pub coordinates: Vec<RelativeCoordinate>,
    pub constraints: Vec<ConstraintDef>,
    pub effects: Vec<Effect>,
    /// Names of the coordinates declared independent (a subset of q's names).
    pub independent: Vec<String>,
    /// The line of `independent:` in the file, for messages about it.
    pub independent_line: Option<u64>,
    /// Initial values given for coordinates of q, by name (kept by the position problem
    /// when the coordinate is independent).
    pub initial_positions: Vec<(String, f64)>,
    /// Initial velocities of independent coordinates, by name.
    pub initial_velocities: Vec<(String, f64)>,
    /// What the reader accepted but does not use (an MBSE body's `visual` drawing
    /// hints), for `mbfg check` to mention.
    pub notes: Vec<String>,
    /// The sensors the scene declares (`sensors:`), in file order.
    pub sensors: Vec<SensorDef>,
    /// What an estimator assumes beyond the sensors (`estimation:`); empty when not
    /// given.
    pub estimation: EstimationDef,
    /// The MBSE mechanism file a scene names (`mechanism:`), as read.
    pub mechanism: Option<String>,
    /// The parameters an estimate identifies and the derivatives of the quantities
    /// that depend on them; empty when `estimation: parameters:` is not given.
    pub identified: Identified,
}

/// A sensor as the scene declares it: what it reads, its noise, its quantization
/// and its rate. Names of q are resolved by the model.
#[derive(Debug, Clone, PartialEq)]
pub struct SensorDef {
    pub name: String,
    pub kind: SensorDefKind,
    /// Standard deviation of the reading's noise, in the reading's unit.
    pub sigma: f64,
    /// Counts per turn of an encoder.
    pub resolution: Option<u64>,
    /// Readings per second; None: the rate of the run or of the trajectory.
    pub rate: Option<f64>,
}

#[derive(Debug, Clone, PartialEq)]
pub enum SensorDefKind {
    /// A coordinate of q, by name.
    Encoder { coordinate: String },
    /// A body's angular velocity (index into [`Scene::bodies`]).
    Gyroscope { body: usize },
    /// A point's specific force in the body's frame.
    Accelerometer { body: usize, point: usize },
    /// A point's position.
    Marker { point: usize },
    /// An expression of the state, as an effect's value.
    Expression { value: LoadFunction },
    /// The generalized force the actuators put on a coordinate of q, by name: the
    /// scene's torques on it where readings are made, the unknown input on it in an
    /// estimate.
    Input { coordinate: String },
}

impl SensorDefKind {
    /// The `type` of the scene file.
    pub fn type_name(&self) -> &'static str {
        match self {
            SensorDefKind::Encoder { .. } => "encoder",
            SensorDefKind::Gyroscope { .. } => "gyroscope",
            SensorDefKind::Accelerometer { .. } => "accelerometer",
            SensorDefKind::Marker { .. } => "marker",
            SensorDefKind::Expression { .. } => "expression",
            SensorDefKind::Input { .. } => "input",
        }
    }
}

/// The `estimation:` section: noise of the dynamics, priors on the initial state and
/// unknown inputs, with coordinates of q by name. Default: nothing given.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct EstimationDef {
    /// σ of the dynamics factor.
    pub process_sigma: Option<f64>,
    /// σ of the prior on the initial positions of named coordinates.
    pub initial_sigma: Vec<(String, f64)>,
    /// σ of the prior on the initial velocities of named coordinates.
    pub initial_velocity_sigma: Vec<(String, f64)>,
    /// Unknown generalized forces on named coordinates, random walks of σ per √s.
    pub inputs: Vec<(String, f64)>,
    /// Scene parameters identified by an estimate: (name, σ of the prior about the
    /// file's value).
    pub parameters: Vec<(String, f64)>,
}

impl Scene {
    /// Reads and validates a scene or MBSE mechanism file.
    pub fn load(path: impl AsRef<Path>) -> crate::Result<Scene> {
        let path = path.as_ref();
        let text = read_text(path).map_err(|source| Error::Io {
            path: path.display().to_string(),
            source,
        })?;
        Scene::from_str(&text, path)
    }

    /// Parses scene text; `path` names the file in messages and resolves `mechanism:`.
    pub fn from_str(text: &str, path: &Path) -> crate::Result<Scene> {
        Scene::from_str_with(text, path, &[])
    }

    /// [`Scene::load`] with some of the file's `parameters` given other values (a
    /// parameter study): expressions that use them, later parameters included, see the
    /// new values. Naming a parameter the file does not have is an error.
    pub fn load_with(path: impl AsRef<Path>, overrides: &[(String, f64)]) -> crate::Result<Scene> {
        let path = path.as_ref();
        let text = read_text(path).map_err(|source| Error::Io {
            path: path.display().to_string(),
            source,
        })?;
        Scene::from_str_with(&text, path, overrides)
    }

    /// [`Scene::from_str`] with parameter overrides ([`Scene::load_with`]).
    pub fn from_str_with(
        text: &str,
        path: &Path,
        overrides: &[(String, f64)],
    ) -> crate::Result<Scene> {
        let file = path.display().to_string();
        if text.len() > MAX_SCENE_BYTES {
            return Err(SceneError {
                file,
                line: None,
                key: String::new(),
                message: format!(
                    "file too large: {} bytes, the limit is {MAX_SCENE_BYTES}",
                    text.len()
                ),
            }
            .into());
        }
        let root = parse_root(text, &file)?;
        if fields::is_mbse(&root) {
            Ok(mbse::read(&root, &file, overrides)?)
        } else {
            native::read(
                &root,
                &file,
                path.parent().unwrap_or(Path::new(".")),
                overrides,
            )
        }
    }

    pub fn point_index(&self, name: &str) -> Option<usize> {
        self.points.iter().position(|p| p.name == name)
    }

    pub fn coordinate_index(&self, name: &str) -> Option<usize> {
        self.coordinates.iter().position(|c| c.name == name)
    }

    /// The state quantity `name` stands for in an effect's value (`theta`,
    /// `rate(theta)`, `x(P)`, `omega(crank)`, …), if any.
    pub fn state_quantity(&self, name: &str) -> Option<StateQuantity> {
        let Some((accessor, arg)) = name.strip_suffix(')').and_then(|n| n.split_once('(')) else {
            return self.coordinate_index(name).map(StateQuantity::Coordinate);
        };
        let point = || self.point_index(arg);
        let body = || self.bodies.iter().position(|b| b.name == arg);
        match accessor {
            "rate" => self.coordinate_index(arg).map(StateQuantity::Rate),
            "x" => point().map(StateQuantity::X),
            "y" => point().map(StateQuantity::Y),
            "vx" => point().map(StateQuantity::Vx),
            "vy" => point().map(StateQuantity::Vy),
            "angle" => body().map(StateQuantity::Angle),
            "omega" => body().map(StateQuantity::Omega),
            _ => None,
        }
    }

    /// Whether any effect is present that makes the scene non-conservative
    /// (dampers, or forces and torques that vary in time).
    pub fn is_conservative(&self) -> bool {
        self.effects.iter().all(|e| match e {
            Effect::Gravity { .. } => true,
            Effect::SpringDamper { damping, .. }
            | Effect::RotationalSpringDamper { damping, .. } => *damping == 0.0,
            Effect::Torque { .. }
            | Effect::Force { .. }
            | Effect::Motor { .. }
            | Effect::External { .. } => false,
        })
    }
}

/// Largest scene or mechanism file read, in bytes. Real scenes are a few kB; the
/// bound keeps a file such as /dev/zero from being read forever.
pub const MAX_SCENE_BYTES: usize = 4 << 20;

/// Reads a text file of at most [`MAX_SCENE_BYTES`], stopping there.
fn read_text(path: &Path) -> std::io::Result<String> {
    use std::io::Read;
    let mut text = String::new();
    std::fs::File::open(path)?
        .take(MAX_SCENE_BYTES as u64 + 1)
        .read_to_string(&mut text)?;
    if text.len() > MAX_SCENE_BYTES {
        return Err(std::io::Error::other(format!(
            "file larger than {MAX_SCENE_BYTES} bytes"
        )));
    }
    Ok(text)
}

/// Parses YAML text into a located tree; a syntax error names `file` and its line.
fn parse_root(text: &str, file: &str) -> Result<yaml::Node, SceneError> {
    yaml::parse(text).map_err(|e| SceneError {
        file: file.to_string(),
        line: e.line,
        // An empty file and a value such as `.nan` are not errors of syntax.
        message: match e.line.is_some() && !e.message.contains("not a finite number") {
            true => format!("YAML syntax error: {}", e.message),
            false => e.message,
        },
        key: e.key,
    })
}

impl Effect {
    /// A one-line description for `mbfg check`.
    pub fn describe(&self, scene: &Scene) -> String {
        let p = |i: usize| scene.points[i].name.as_str();
        let c = |i: usize| scene.coordinates[i].name.as_str();
        // Shortest round-trip form, scientific where plain would run to dozens of digits.
        let v = crate::io::number;
        match self {
            Effect::Gravity { vector } => {
                format!("gravity ({}, {}) m/s²", v(vector[0]), v(vector[1]))
            }
            Effect::SpringDamper {
                name,
                points,
                stiffness,
                rest_length,
                damping,
            } => format!(
                "{name}: spring-damper {}–{}: k = {} N/m, rest length {} m, c = {} N·s/m",
                p(points[0]),
                p(points[1]),
                v(*stiffness),
                v(*rest_length),
                v(*damping)
            ),
            Effect::RotationalSpringDamper {
                name,
                coordinate,
                stiffness,
                rest_angle,
                damping,
            } => format!(
                "{name}: rotational spring-damper on {}: k = {} N·m/rad, rest angle {} rad, c = {} N·m·s/rad",
                c(*coordinate),
                v(*stiffness),
                v(*rest_angle),
                v(*damping)
            ),
            Effect::Motor {
                name,
                coordinate,
                stall_torque,
                no_load_speed,
            } => format!(
                "{name}: DC motor on {}: stall torque {} N·m, no-load speed {} rad/s",
                c(*coordinate),
                v(*stall_torque),
                v(*no_load_speed)
            ),
            Effect::Torque {
                name,
                coordinate,
                value,
            } => format!("{name}: torque on {} = {} N·m", c(*coordinate), value.text),
            Effect::Force { name, point, value } => format!(
                "{name}: force at {} = ({}, {}) N",
                p(*point),
                value[0].text,
                value[1].text
            ),
            Effect::External { name } => {
                format!("{name}: generalized forces from a callable (outside the scene)")
            }
        }
    }

    /// Whether the effect's value jumps somewhere (a torque or force expression that
    /// calls `sign`): an implicit step across the jump may have no solution.
    pub fn jumps(&self) -> bool {
        match self {
            Effect::Torque { value, .. } => value.expr.jumps(),
            Effect::Force { value, .. } => value.iter().any(|v| v.expr.jumps()),
            _ => false,
        }
    }

    /// The effect's name (gravity has none).
    pub fn name(&self) -> Option<&str> {
        match self {
            Effect::Gravity { .. } => None,
            Effect::SpringDamper { name, .. }
            | Effect::RotationalSpringDamper { name, .. }
            | Effect::Motor { name, .. }
            | Effect::Torque { name, .. }
            | Effect::Force { name, .. }
            | Effect::External { name } => Some(name),
        }
    }
}
