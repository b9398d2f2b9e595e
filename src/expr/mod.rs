//! Arithmetic expressions in scene files: `2*L`, `sqrt(13)`, `(1/3)*mass*length^2`,
//! `pi`, functions of time such as `5*sin(2*t)`, and of the mechanism's state such as
//! `20 - 0.8*rate(theta)`.
//!
//! An expression is parsed once into a small syntax tree; names are looked up when it
//! is evaluated, so the same text can be checked early and evaluated later (for `t`).
//! A state quantity (`rate(theta)`, `x(P)`, `angle(crank)`, see [`STATE_ACCESSORS`])
//! is parsed as one name, `"rate(theta)"`, that the model resolves. Derivatives are
//! symbolic ([`Expr::derivative`]): the dynamics factor's Jacobians need ∂Q/∂q and
//! ∂Q/∂q̇ of a state-dependent load, and a tree gives them exactly.
//!
//! The parser and every walk over the tree recurse, so input size is bounded
//! ([`MAX_LEN`], [`MAX_NODES`], [`MAX_DEPTH`]): no text can overflow the stack.
//! Sums and products are flat lists, so a long sum is a wide tree, not a deep one.
//!
//! The public types are here; `functions` holds the functions an expression may
//! call, `parse` the parser, `eval` evaluation, name resolution and binding, and
//! `derivative` the symbolic derivatives.

mod derivative;
mod eval;
mod functions;
mod parse;

pub use derivative::MAX_DERIVATIVE_NODES;
pub use functions::STATE_ACCESSORS;

use functions::Func;
use std::cell::Cell;
use std::collections::HashSet;
use std::fmt;

/// Longest expression text accepted, in bytes.
pub const MAX_LEN: usize = 100_000;
/// Most numbers, names, operators and calls in one expression.
pub const MAX_NODES: usize = 10_000;
/// Deepest nesting of parentheses, function calls, unary signs and exponents. Each
/// level costs a few stack frames in the parser and in every walk over the tree;
/// 100 keeps all of them far inside a 256 kB stack.
pub const MAX_DEPTH: usize = 100;

/// Longest piece of the input (a name, a number) quoted in a message, in characters.
const QUOTE: usize = 40;

/// Why an expression could not be parsed or evaluated.
#[derive(Debug, Clone, PartialEq)]
pub enum ExprError {
    /// Malformed text; `at` is the character offset where parsing stopped.
    Syntax { at: usize, message: String },
    /// A name that is neither a parameter nor a known constant or function.
    Undefined(String),
    /// The value is NaN or infinite (for example `sqrt(-1)` or `1/0`).
    NotFinite,
    /// The text exceeds one of the size limits; the message names it.
    TooLarge(String),
}

impl fmt::Display for ExprError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            ExprError::Syntax { at, message } => write!(f, "{message} at character {}", at + 1),
            ExprError::Undefined(name) => write!(f, "undefined name '{}'", excerpt(name, QUOTE)),
            ExprError::NotFinite => write!(f, "evaluates to a non-finite number"),
            ExprError::TooLarge(message) => write!(f, "{message}"),
        }
    }
}

/// `text` cut to at most `max` characters (an ellipsis marks the cut), on one line:
/// messages quote user input, which may be huge or span lines.
pub fn excerpt(text: &str, max: usize) -> String {
    let mut out = String::new();
    let mut count = 0;
    for c in text.chars() {
        let piece = if c.is_control() {
            c.escape_default().to_string()
        } else {
            c.to_string()
        };
        let n = piece.chars().count();
        if count + n > max {
            // Room for the ellipsis: drop the last characters if needed.
            while count + 1 > max && out.pop().is_some() {
                count -= 1;
            }
            out.push('…');
            return out;
        }
        count += n;
        out.push_str(&piece);
    }
    out
}

/// Names joined with ", ", or for more than eight the first four, "…" and the last:
/// a list of dozens would fill a one-line message.
pub fn abbreviated<S: AsRef<str>>(names: &[S]) -> String {
    let all: Vec<&str> = names.iter().map(AsRef::as_ref).collect();
    match all.as_slice() {
        [first @ .., last] if all.len() > 8 => format!("{}, …, {last}", first[..4].join(", ")),
        _ => all.join(", "),
    }
}

#[derive(Debug, Clone, PartialEq)]
enum Node {
    Num(f64),
    Var(String),
    Neg(Box<Node>),
    /// `first op₁ x₁ op₂ x₂ …` with the operators of one precedence level (`+ -` or
    /// `* /`), evaluated left to right like the nested binary form it replaces.
    Chain(Box<Node>, Vec<(char, Node)>),
    Pow(Box<Node>, Box<Node>),
    Call(Func, Vec<Node>),
    /// A name resolved to a position in a slice of values ([`Expr::resolve`]).
    Slot(usize),
}

/// A parsed expression.
#[derive(Debug, Clone, PartialEq)]
pub struct Expr {
    root: Node,
}

impl Expr {
    /// Parses `text`; names stay unresolved until evaluation.
    pub fn parse(text: &str) -> Result<Expr, ExprError> {
        Ok(Expr {
            root: parse::syntax_tree(text)?,
        })
    }

    /// A constant expression.
    pub fn constant(value: f64) -> Expr {
        Expr {
            root: Node::Num(value),
        }
    }

    /// Evaluates with `lookup` giving the value of each name (`pi` is built in and
    /// may be shadowed by a parameter of that name).
    pub fn eval(&self, lookup: &dyn Fn(&str) -> Option<f64>) -> Result<f64, ExprError> {
        let v = eval::eval_node(&self.root, lookup, &[])?;
        if v.is_finite() {
            Ok(v)
        } else {
            Err(ExprError::NotFinite)
        }
    }

    /// Evaluates an expression whose names were all resolved to slots of `values`
    /// ([`Expr::resolve`]); the value may be non-finite, for the caller to name.
    pub fn eval_slots(&self, values: &[f64]) -> f64 {
        eval::eval_slots_node(&self.root, values).unwrap_or(f64::NAN)
    }

    /// Replaces every name by its slot from `slot_of` (a name without one is an
    /// error), for [`Expr::eval_slots`]: no string is compared in a hot loop.
    pub fn resolve(&self, slot_of: &dyn Fn(&str) -> Option<usize>) -> Result<Expr, ExprError> {
        Ok(Expr {
            root: eval::resolve_node(&self.root, slot_of)?,
        })
    }

    /// The symbolic derivative with respect to `name`, simplified where a factor is 0
    /// or 1 or every operand is a number. `abs`, `min` and `max` differentiate through
    /// `sign` (the mean of both sides at a kink). An expression whose derivative would
    /// copy more than [`MAX_DERIVATIVE_NODES`] nodes is refused.
    pub fn derivative(&self, name: &str) -> Result<Expr, ExprError> {
        self.derivative_by(&|n| matches!(n, Node::Var(v) if v == name))
    }

    /// [`Expr::derivative`] with respect to a resolved slot.
    pub fn derivative_slot(&self, slot: usize) -> Result<Expr, ExprError> {
        self.derivative_by(&|n| matches!(n, Node::Slot(k) if *k == slot))
    }

    fn derivative_by(&self, is_v: &dyn Fn(&Node) -> bool) -> Result<Expr, ExprError> {
        let budget = Cell::new(MAX_DERIVATIVE_NODES);
        Ok(Expr {
            root: derivative::derive(&self.root, is_v, &budget)?,
        })
    }

    /// Names the expression refers to (not functions), in order of appearance.
    pub fn names(&self) -> Vec<String> {
        let mut out = Vec::new();
        eval::collect_names(&self.root, &mut HashSet::new(), &mut out);
        out
    }

    /// Whether the expression jumps somewhere: it calls `sign` (abs, min and max only
    /// kink).
    pub fn jumps(&self) -> bool {
        eval::calls_sign(&self.root)
    }

    /// Whether the expression refers to `name`.
    pub fn uses(&self, name: &str) -> bool {
        self.names().iter().any(|n| n == name)
    }

    /// Replaces every name other than those in `keep` by its value from `lookup`, so
    /// the result depends on `keep` only (used to bind parameters, leaving `t`).
    pub fn bind(
        &self,
        keep: &dyn Fn(&str) -> bool,
        lookup: &dyn Fn(&str) -> Option<f64>,
    ) -> Result<Expr, ExprError> {
        Ok(Expr {
            root: eval::bind_node(&self.root, keep, lookup)?,
        })
    }

    /// The value if the expression has no free names.
    pub fn as_constant(&self) -> Option<f64> {
        match self.root {
            Node::Num(v) => Some(v),
            _ => None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn excerpt_cuts_and_escapes() {
        assert_eq!(excerpt("abc", 3), "abc");
        assert_eq!(excerpt("abcdef", 4), "abc…");
        assert_eq!(excerpt("a\nb", 10), "a\\nb");
        assert_eq!(excerpt("é€日本", 3), "é€…");
    }
}
