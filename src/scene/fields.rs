//! Typed access to located YAML nodes, shared by both file formats: every failure is a
//! [`SceneError`] naming the file, the line and the key path.

use super::derivatives::{Derivatives, GradientError};
use super::yaml::{Node, Value};
use super::{LoadFunction, Scene};
use crate::error::SceneError;
use crate::expr::{abbreviated, excerpt, Expr, ExprError};

/// Whether a document is an MBSE mechanism file (it has `planar_bodies`).
pub fn is_mbse(root: &Node) -> bool {
    match &root.value {
        Value::Map(pairs) => pairs
            .iter()
            .any(|(k, _)| matches!(&k.value, Value::String(s) if s == "planar_bodies")),
        _ => false,
    }
}

/// What every reader carries: the file name and the parameters defined so far.
pub struct Ctx<'a> {
    pub file: &'a str,
    pub params: Vec<(String, f64)>,
    /// Values that replace the file's own for parameters of these names (a study's
    /// sweep), checked to name parameters the file has.
    pub overrides: &'a [(String, f64)],
    /// The parameters an estimate identifies (`estimation: parameters:`) and the
    /// derivatives of every number read with respect to them ([`Derivatives`]).
    pub derivatives: Derivatives,
}

impl<'a> Ctx<'a> {
    pub fn with_overrides(file: &'a str, overrides: &'a [(String, f64)]) -> Self {
        Ctx {
            file,
            params: Vec::new(),
            overrides,
            derivatives: Derivatives::default(),
        }
    }

    /// An error at `line`; key and message are cut so that the whole one-line
    /// message stays within [`MAX_MESSAGE`] characters (unless the file name alone
    /// is that long): messages quote the file, whose values may be huge.
    pub fn err(&self, line: u64, key: &str, message: impl Into<String>) -> SceneError {
        let key = excerpt(key, MAX_KEY);
        let used = self.file.chars().count() + key.chars().count() + 30;
        let room = MAX_MESSAGE.saturating_sub(used).max(60);
        SceneError {
            file: self.file.to_string(),
            line: (line > 0).then_some(line),
            key,
            message: excerpt(&message.into(), room),
        }
    }

    fn lookup<'b>(&'b self, extra: &'b [(&'b str, f64)]) -> impl Fn(&str) -> Option<f64> + 'b {
        move |name: &str| {
            extra
                .iter()
                .rev()
                .find(|(n, _)| *n == name)
                .map(|(_, v)| *v)
                .or_else(|| {
                    self.params
                        .iter()
                        .rev()
                        .find(|(n, _)| n == name)
                        .map(|(_, v)| *v)
                })
        }
    }

    /// A number: a YAML number or an expression over the parameters and `extra`.
    /// Its derivative with respect to the identified parameters, where it has one,
    /// waits under `key` for the reader that uses it ([`Derivatives::take`]).
    pub fn num(&self, node: &Node, key: &str, extra: &[(&str, f64)]) -> Result<f64, SceneError> {
        let (value, gradient) = self.num_with_gradient(node, key, extra)?;
        if let Some(g) = gradient {
            self.derivatives.record(key, node.line, g);
        }
        Ok(value)
    }

    /// A number and its gradient with respect to the identified parameters (`None`:
    /// it does not depend on them).
    fn num_with_gradient(
        &self,
        node: &Node,
        key: &str,
        extra: &[(&str, f64)],
    ) -> Result<(f64, Option<Vec<f64>>), SceneError> {
        match &node.value {
            Value::Number(v) if v.is_finite() => Ok((*v, None)),
            Value::Number(_) => Err(self.err(node.line, key, "must be a finite number")),
            Value::String(text) => {
                let expr = Expr::parse(text).map_err(|e| self.expr_err(node, key, text, e))?;
                let lookup = self.lookup(extra);
                let value = expr
                    .eval(&lookup)
                    .map_err(|e| self.expr_err(node, key, text, e))?;
                let gradient = self.gradient(&expr, extra, &lookup).map_err(|e| match e {
                    GradientError::Expr(e) => self.expr_err(node, key, text, e),
                    GradientError::Nonlinear(a, b) => self.err(
                        node.line,
                        key,
                        format!(
                            "'{}' is not linear in the identified parameters ('{a}' and \
                                 '{b}' multiply or a power holds them): an estimate identifies \
                                 parameters that enter the model linearly",
                            excerpt(text, QUOTE)
                        ),
                    ),
                })?;
                Ok((value, gradient))
            }
            _ => Err(self.err(
                node.line,
                key,
                format!("expected a number or an expression, found {}", node.kind()),
            )),
        }
    }

    /// The gradient of a name: a parameter's, or one `extra` name's that the reader
    /// set ([`Derivatives::set_extra`]); `None` where it is zero.
    fn name_gradient(&self, name: &str, extra: &[(&str, f64)]) -> Option<Vec<f64>> {
        if extra.iter().any(|(n, _)| *n == name) {
            return self.derivatives.extra(name);
        }
        let i = self.params.iter().rposition(|(n, _)| n == name)?;
        self.derivatives.params.get(i).cloned().flatten()
    }

    /// ∂expr/∂p by the chain rule over the names it uses, each derivative symbolic;
    /// refused where a second derivative among those names does not vanish (the model
    /// would not be linear in the parameters there).
    fn gradient(
        &self,
        expr: &Expr,
        extra: &[(&str, f64)],
        lookup: &dyn Fn(&str) -> Option<f64>,
    ) -> Result<Option<Vec<f64>>, GradientError> {
        if self.derivatives.unknown.is_empty() {
            return Ok(None);
        }
        let names: Vec<(String, Vec<f64>)> = expr
            .names()
            .into_iter()
            .filter_map(|n| self.name_gradient(&n, extra).map(|g| (n, g)))
            .collect();
        if names.is_empty() {
            return Ok(None);
        }
        let mut out = vec![0.0; self.derivatives.unknown.len()];
        for (name, g) in &names {
            let d = expr.derivative(name).map_err(GradientError::Expr)?;
            let dv = d.eval(lookup).map_err(GradientError::Expr)?;
            for (o, gj) in out.iter_mut().zip(g) {
                *o += dv * gj;
            }
            for (other, _) in &names {
                let dd = d
                    .derivative(other)
                    .and_then(|e| e.eval(lookup))
                    .map_err(GradientError::Expr)?;
                if dd != 0.0 {
                    return Err(GradientError::Nonlinear(name.clone(), other.clone()));
                }
            }
        }
        Ok(Some(out))
    }

    /// A number that must be > 0.
    pub fn positive(
        &self,
        node: &Node,
        key: &str,
        extra: &[(&str, f64)],
    ) -> Result<f64, SceneError> {
        self.bounded(node, key, extra, |v| v > 0.0, "must be positive")
    }

    /// A number that must be ≥ 0.
    pub fn non_negative(&self, node: &Node, key: &str) -> Result<f64, SceneError> {
        self.non_negative_with(node, key, &[])
    }

    /// [`Self::non_negative`] with `extra` names (`auto`) in its expression.
    pub fn non_negative_with(
        &self,
        node: &Node,
        key: &str,
        extra: &[(&str, f64)],
    ) -> Result<f64, SceneError> {
        self.bounded(node, key, extra, |v| v >= 0.0, "must not be negative")
    }

    /// A number that `holds`, or the error `what` with the value.
    fn bounded(
        &self,
        node: &Node,
        key: &str,
        extra: &[(&str, f64)],
        holds: impl Fn(f64) -> bool,
        what: &str,
    ) -> Result<f64, SceneError> {
        let v = self.num(node, key, extra)?;
        if holds(v) {
            Ok(v)
        } else {
            Err(self.err(node.line, key, format!("{what}, got {v}")))
        }
    }

    /// An effect's or a sensor's value: a number or an expression in the time `t`, the
    /// parameters (bound now) and the state quantities of `scene`
    /// ([`Scene::state_quantity`]). The parameters an estimate identifies stay names of
    /// the expression, so that it sees their estimate.
    pub fn load_function(
        &self,
        node: &Node,
        key: &str,
        scene: &Scene,
    ) -> Result<LoadFunction, SceneError> {
        let text = node.as_text().ok_or_else(|| {
            self.err(
                node.line,
                key,
                format!(
                    "expected a number or an expression in t and the state, found {}",
                    node.kind()
                ),
            )
        })?;
        let expr = Expr::parse(&text).map_err(|e| self.expr_err(node, key, &text, e))?;
        let lookup = self.lookup(&[]);
        for name in expr.names() {
            let quantity = scene.state_quantity(&name);
            if let Some((accessor, arg)) = name.strip_suffix(')').and_then(|n| n.split_once('(')) {
                if quantity.is_none() {
                    let (what, known): (_, Vec<&str>) = match accessor {
                        "rate" => (
                            "relative coordinate",
                            scene.coordinates.iter().map(|c| c.name.as_str()).collect(),
                        ),
                        "angle" | "omega" => (
                            "body",
                            scene.bodies.iter().map(|b| b.name.as_str()).collect(),
                        ),
                        _ => (
                            "point",
                            scene.points.iter().map(|p| p.name.as_str()).collect(),
                        ),
                    };
                    let known = if known.is_empty() {
                        "the scene has none".to_string()
                    } else {
                        abbreviated(&known)
                    };
                    return Err(self.err(
                        node.line,
                        key,
                        format!(
                            "'{}' in '{}': no {what} named '{}' ({known})",
                            excerpt(&name, QUOTE),
                            excerpt(&text, QUOTE),
                            excerpt(arg, QUOTE)
                        ),
                    ));
                }
            } else if quantity.is_some() && lookup(&name).is_some() {
                return Err(self.err(
                    node.line,
                    key,
                    format!(
                        "'{name}' in '{}' is both a parameter and a coordinate: rename one",
                        excerpt(&text, QUOTE)
                    ),
                ));
            }
        }
        let unknown = &self.derivatives.unknown;
        let mut parameters = Vec::new();
        for name in expr.names() {
            if self.name_gradient(&name, &[]).is_none() {
                continue;
            }
            let why = if unknown.contains(&name) {
                let value = lookup(&name).unwrap_or(f64::NAN);
                parameters.push((name, value));
                continue;
            } else {
                "a parameter computed from an identified one: write the identified \
                 parameter itself in the value"
            };
            let what = if unknown.contains(&name) {
                "a parameter the estimate identifies"
            } else {
                "which depends on a parameter the estimate identifies"
            };
            return Err(self.err(
                node.line,
                key,
                format!("'{}' uses '{name}', {what}: {why}", excerpt(&text, QUOTE)),
            ));
        }
        let keep = |n: &str| {
            n == "t" || scene.state_quantity(n).is_some() || parameters.iter().any(|(p, _)| p == n)
        };
        let bound = expr
            .bind(&keep, &lookup)
            .map_err(|e| self.expr_err(node, key, &text, e))?;
        let mut value = LoadFunction::new(bound, text);
        value.parameters = parameters;
        // Catch a function of time that is not finite at the start of the motion (one
        // of the state is checked at the initial state, by the model).
        if !value.is_state_dependent() {
            value
                .expr()
                .eval(&|n| value.fixed(n, 0.0))
                .map_err(|e| self.expr_err(node, key, &value.text, e))?;
        }
        Ok(value)
    }

    fn expr_err(&self, node: &Node, key: &str, text: &str, e: ExprError) -> SceneError {
        let what = match e {
            ExprError::Syntax { .. } => "malformed expression",
            ExprError::Undefined(_) => "undefined name in expression",
            ExprError::NotFinite => "expression is not finite",
            ExprError::TooLarge(_) => "expression refused",
        };
        // YAML's {…} ends the value at a comma: `{value: 20*min(1, t)}` arrives as
        // `20*min(1`.
        let opened = text.matches('(').count() > text.matches(')').count();
        let hint = match &e {
            ExprError::Syntax { .. } if opened => {
                "; in {…} a comma ends the value: quote an expression that has one (value: \"20*min(1, t)\")".to_string()
            }
            ExprError::Undefined(name) if name.contains('(') => {
                "; state quantities such as rate(theta) or x(P) may appear only in the value of a torque or a force".to_string()
            }
            ExprError::Undefined(name) => super::suggest::did_you_mean(
                name,
                self.params.iter().map(|(n, _)| n.as_str()),
            ),
            _ => String::new(),
        };
        let text = excerpt(text, QUOTE);
        self.err(node.line, key, format!("{what} '{text}': {e}{hint}"))
    }

    /// The `parameters` section: name → number or expression over earlier parameters.
    pub fn read_parameters(&mut self, node: &Node) -> Result<(), SceneError> {
        let Value::Map(pairs) = &node.value else {
            return Err(self.err(node.line, "parameters", "expected a mapping name: value"));
        };
        for (k, v) in pairs {
            let name = name_of(self, k, "parameters")?;
            let key = format!("parameters.{name}");
            if self.params.iter().any(|(n, _)| *n == name) {
                return Err(self.err(k.line, &key, format!("duplicate parameter '{name}'")));
            }
            let unknown = self.derivatives.unknown.iter().position(|n| *n == name);
            let (value, gradient) = match self.overrides.iter().find(|(n, _)| *n == name) {
                Some((_, v)) => (*v, None),
                None => self.num_with_gradient(v, &key, &[])?,
            };
            // An identified parameter is a variable of its own; its file value is the
            // prior's mean.
            let gradient = match unknown {
                Some(j) => {
                    let mut e = vec![0.0; self.derivatives.unknown.len()];
                    e[j] = 1.0;
                    Some(e)
                }
                None => gradient,
            };
            self.derivatives.params.push(gradient);
            self.params.push((name, value));
        }
        Ok(())
    }

    /// Refuses overrides of parameters the file does not have, naming those it has.
    pub fn check_overrides(&self, line: u64) -> Result<(), SceneError> {
        for (name, value) in self.overrides {
            if !value.is_finite() {
                return Err(self.err(
                    line,
                    "parameters",
                    format!("override of '{}' is not finite", excerpt(name, QUOTE)),
                ));
            }
            if !self.params.iter().any(|(n, _)| n == name) {
                let known: Vec<&str> = self
                    .params
                    .iter()
                    .take(12)
                    .map(|(n, _)| n.as_str())
                    .collect();
                let known = if known.is_empty() {
                    "none".to_string()
                } else {
                    known.join(", ")
                };
                return Err(self.err(
                    line,
                    "parameters",
                    format!(
                        "no parameter '{}' to override{} (the file's parameters: {known})",
                        excerpt(name, QUOTE),
                        super::suggest::did_you_mean(
                            name,
                            self.params.iter().map(|(n, _)| n.as_str())
                        )
                    ),
                ));
            }
        }
        Ok(())
    }
}

/// Longest message an error may have, file, line and key included, in characters.
pub const MAX_MESSAGE: usize = 300;
/// Longest key path quoted in a message.
const MAX_KEY: usize = 80;
/// Longest piece of the file (an expression, a name) quoted in a message.
pub const QUOTE: usize = 60;

/// A valid name: letters, digits, `_`, `-`, starting with a letter or `_`.
pub fn name_of(ctx: &Ctx, node: &Node, key: &str) -> Result<String, SceneError> {
    let Value::String(s) = &node.value else {
        return Err(ctx.err(
            node.line,
            key,
            format!("expected a name, found {}", node.kind()),
        ));
    };
    let ok = s
        .chars()
        .next()
        .is_some_and(|c| c.is_alphabetic() || c == '_')
        && s.chars()
            .all(|c| c.is_alphanumeric() || c == '_' || c == '-');
    if ok {
        Ok(s.clone())
    } else {
        Err(ctx.err(
            node.line,
            key,
            format!(
                "'{}' is not a valid name (letters, digits, '_' and '-', starting with a letter)",
                excerpt(s, QUOTE)
            ),
        ))
    }
}

pub fn seq<'n>(ctx: &Ctx, node: &'n Node, key: &str) -> Result<&'n [Node], SceneError> {
    match &node.value {
        Value::Seq(items) => Ok(items),
        _ => Err(ctx.err(
            node.line,
            key,
            format!("expected a list, found {}", node.kind()),
        )),
    }
}

pub fn boolean(ctx: &Ctx, node: &Node, key: &str) -> Result<bool, SceneError> {
    match node.value {
        Value::Bool(b) => Ok(b),
        _ => Err(ctx.err(
            node.line,
            key,
            format!("expected true or false, found {}", node.kind()),
        )),
    }
}

/// A pair of numbers `[a, b]`.
pub fn pair(
    ctx: &Ctx,
    node: &Node,
    key: &str,
    extra: &[(&str, f64)],
) -> Result<[f64; 2], SceneError> {
    let items = seq(ctx, node, key)?;
    if items.len() != 2 {
        return Err(ctx.err(
            node.line,
            key,
            format!("expected two numbers [x, y], found {}", items.len()),
        ));
    }
    Ok([
        ctx.num(&items[0], &format!("{key}[0]"), extra)?,
        ctx.num(&items[1], &format!("{key}[1]"), extra)?,
    ])
}

/// The keys of one mapping, read one by one; keys never asked for are reported.
pub struct Fields<'n> {
    pub line: u64,
    pub path: String,
    pairs: &'n [(Node, Node)],
    used: Vec<bool>,
}

impl<'n> Fields<'n> {
    pub fn new(ctx: &Ctx, node: &'n Node, path: &str) -> Result<Fields<'n>, SceneError> {
        let Value::Map(pairs) = &node.value else {
            return Err(ctx.err(
                node.line,
                path,
                format!("expected a mapping, found {}", node.kind()),
            ));
        };
        for (k, _) in pairs {
            if !matches!(k.value, Value::String(_)) {
                return Err(ctx.err(
                    k.line,
                    path,
                    format!("keys must be names, found {}", k.kind()),
                ));
            }
        }
        Ok(Fields {
            line: node.line,
            path: path.to_string(),
            pairs,
            used: vec![false; pairs.len()],
        })
    }

    /// The path of a key of this mapping, for messages.
    pub fn key(&self, key: &str) -> String {
        if self.path.is_empty() {
            key.to_string()
        } else {
            format!("{}.{key}", self.path)
        }
    }

    pub fn get(&mut self, key: &str) -> Option<&'n Node> {
        for (i, (k, v)) in self.pairs.iter().enumerate() {
            if matches!(&k.value, Value::String(s) if s == key) {
                self.used[i] = true;
                return Some(v);
            }
        }
        None
    }

    pub fn has(&self, key: &str) -> bool {
        self.pairs
            .iter()
            .any(|(k, _)| matches!(&k.value, Value::String(s) if s == key))
    }

    pub fn req(&mut self, ctx: &Ctx, key: &str) -> Result<&'n Node, SceneError> {
        let line = self.line;
        let path = self.key(key);
        self.get(key)
            .ok_or_else(|| ctx.err(line, &path, "missing required key"))
    }

    /// Fails on the first key that was never read, naming it and the allowed keys.
    pub fn finish(self, ctx: &Ctx, allowed: &[&str]) -> Result<(), SceneError> {
        for (i, (k, _)) in self.pairs.iter().enumerate() {
            if !self.used[i] {
                let name = k.as_text().unwrap_or_default();
                let path = self.key(&name);
                return Err(ctx.err(
                    k.line,
                    &path,
                    format!(
                        "unknown key '{}' (expected one of: {})",
                        excerpt(&name, QUOTE),
                        allowed.join(", ")
                    ),
                ));
            }
        }
        Ok(())
    }
}
