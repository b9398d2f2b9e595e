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

#[derive(Debug, Clone, Copy, PartialEq)]
enum Func {
    Sqrt,
    Sin,
    Cos,
    Tan,
    Asin,
    Acos,
    Atan,
    Atan2,
    Exp,
    Ln,
    Abs,
    Min,
    Max,
    Pow,
    Sinh,
    Cosh,
    Tanh,
    Sign,
}

/// Functions of the state an expression may call on one name: a coordinate's rate,
/// a point's position and velocity, a body's angle and angular velocity.
pub const STATE_ACCESSORS: [&str; 7] = ["rate", "x", "y", "vx", "vy", "angle", "omega"];

impl Func {
    fn lookup(name: &str) -> Option<(Func, usize)> {
        Some(match name {
            "sqrt" => (Func::Sqrt, 1),
            "sin" => (Func::Sin, 1),
            "cos" => (Func::Cos, 1),
            "tan" => (Func::Tan, 1),
            "asin" => (Func::Asin, 1),
            "acos" => (Func::Acos, 1),
            "atan" => (Func::Atan, 1),
            "atan2" => (Func::Atan2, 2),
            "exp" => (Func::Exp, 1),
            "log" | "ln" => (Func::Ln, 1),
            "abs" => (Func::Abs, 1),
            "min" => (Func::Min, 2),
            "max" => (Func::Max, 2),
            "pow" => (Func::Pow, 2),
            "sinh" => (Func::Sinh, 1),
            "cosh" => (Func::Cosh, 1),
            "tanh" => (Func::Tanh, 1),
            "sign" => (Func::Sign, 1),
            _ => return None,
        })
    }

    fn apply(self, a: &[f64]) -> f64 {
        match self {
            Func::Sqrt => a[0].sqrt(),
            Func::Sin => a[0].sin(),
            Func::Cos => a[0].cos(),
            Func::Tan => a[0].tan(),
            Func::Asin => a[0].asin(),
            Func::Acos => a[0].acos(),
            Func::Atan => a[0].atan(),
            Func::Atan2 => a[0].atan2(a[1]),
            Func::Exp => a[0].exp(),
            Func::Ln => a[0].ln(),
            Func::Abs => a[0].abs(),
            Func::Min => a[0].min(a[1]),
            Func::Max => a[0].max(a[1]),
            Func::Pow => a[0].powf(a[1]),
            Func::Sinh => a[0].sinh(),
            Func::Cosh => a[0].cosh(),
            Func::Tanh => a[0].tanh(),
            // 0 at 0 (f64::signum gives ±1 there): the derivative of abs and of
            // min/max at a tie is then the mean of both sides.
            Func::Sign => {
                if a[0] > 0.0 {
                    1.0
                } else if a[0] < 0.0 {
                    -1.0
                } else {
                    a[0]
                }
            }
        }
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
        if text.len() > MAX_LEN {
            return Err(ExprError::TooLarge(format!(
                "expression too long: {} bytes, the limit is {MAX_LEN}",
                text.len()
            )));
        }
        let mut p = Parser {
            chars: text.chars().collect(),
            pos: 0,
            depth: 0,
            nodes: 0,
        };
        let root = p.expr()?;
        p.skip_ws();
        if p.pos < p.chars.len() {
            return Err(p.error(format!("unexpected '{}'", p.chars[p.pos].escape_default())));
        }
        Ok(Expr { root })
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
        let v = eval_node(&self.root, lookup, &[])?;
        if v.is_finite() {
            Ok(v)
        } else {
            Err(ExprError::NotFinite)
        }
    }

    /// Evaluates an expression whose names were all resolved to slots of `values`
    /// ([`Expr::resolve`]); the value may be non-finite, for the caller to name.
    pub fn eval_slots(&self, values: &[f64]) -> f64 {
        eval_node(&self.root, &|_| None, values).unwrap_or(f64::NAN)
    }

    /// Replaces every name by its slot from `slot_of` (a name without one is an
    /// error), for [`Expr::eval_slots`]: no string is compared in a hot loop.
    pub fn resolve(&self, slot_of: &dyn Fn(&str) -> Option<usize>) -> Result<Expr, ExprError> {
        Ok(Expr {
            root: resolve_node(&self.root, slot_of)?,
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
            root: derive(&self.root, is_v, &budget)?,
        })
    }

    /// Names the expression refers to (not functions), in order of appearance.
    pub fn names(&self) -> Vec<String> {
        let mut out = Vec::new();
        collect_names(&self.root, &mut HashSet::new(), &mut out);
        out
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
            root: bind_node(&self.root, keep, lookup)?,
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

fn collect_names<'a>(n: &'a Node, seen: &mut HashSet<&'a str>, out: &mut Vec<String>) {
    match n {
        Node::Num(_) | Node::Slot(_) => {}
        Node::Var(v) => {
            if seen.insert(v) {
                out.push(v.clone())
            }
        }
        Node::Neg(a) => collect_names(a, seen, out),
        Node::Chain(first, rest) => {
            collect_names(first, seen, out);
            rest.iter().for_each(|(_, x)| collect_names(x, seen, out));
        }
        Node::Pow(a, b) => {
            collect_names(a, seen, out);
            collect_names(b, seen, out);
        }
        Node::Call(_, args) => args.iter().for_each(|a| collect_names(a, seen, out)),
    }
}

fn builtin(name: &str) -> Option<f64> {
    match name {
        "pi" => Some(std::f64::consts::PI),
        _ => None,
    }
}

fn apply_op(op: char, x: f64, y: f64) -> f64 {
    match op {
        '+' => x + y,
        '-' => x - y,
        '*' => x * y,
        _ => x / y,
    }
}

fn eval_node(
    n: &Node,
    lookup: &dyn Fn(&str) -> Option<f64>,
    slots: &[f64],
) -> Result<f64, ExprError> {
    let eval = |a: &Node| eval_node(a, lookup, slots);
    Ok(match n {
        Node::Num(v) => *v,
        Node::Slot(k) => slots[*k],
        Node::Var(name) => lookup(name)
            .or_else(|| builtin(name))
            .ok_or_else(|| ExprError::Undefined(name.clone()))?,
        Node::Neg(a) => -eval(a)?,
        Node::Chain(first, rest) => {
            let mut acc = eval(first)?;
            for (op, x) in rest {
                acc = apply_op(*op, acc, eval(x)?);
            }
            acc
        }
        Node::Pow(a, b) => eval(a)?.powf(eval(b)?),
        Node::Call(f, args) => {
            let mut vals = [0.0; 2];
            for (slot, a) in vals.iter_mut().zip(args) {
                *slot = eval(a)?;
            }
            f.apply(&vals[..args.len().min(2)])
        }
    })
}

fn resolve_node(n: &Node, slot_of: &dyn Fn(&str) -> Option<usize>) -> Result<Node, ExprError> {
    let r = |a: &Node| resolve_node(a, slot_of);
    Ok(match n {
        Node::Num(_) | Node::Slot(_) => n.clone(),
        Node::Var(name) => match (slot_of(name), builtin(name)) {
            (Some(k), _) => Node::Slot(k),
            (None, Some(v)) => Node::Num(v),
            (None, None) => return Err(ExprError::Undefined(name.clone())),
        },
        Node::Neg(a) => Node::Neg(Box::new(r(a)?)),
        Node::Chain(first, rest) => Node::Chain(
            Box::new(r(first)?),
            rest.iter()
                .map(|(op, x)| Ok((*op, r(x)?)))
                .collect::<Result<_, ExprError>>()?,
        ),
        Node::Pow(a, b) => Node::Pow(Box::new(r(a)?), Box::new(r(b)?)),
        Node::Call(f, args) => Node::Call(*f, args.iter().map(r).collect::<Result<_, _>>()?),
    })
}

// Builders that fold numbers and drop factors of 0 and 1, so that a derivative stays
// about as small as the expression it came from.

fn num(n: &Node) -> Option<f64> {
    match n {
        Node::Num(v) => Some(*v),
        _ => None,
    }
}

fn add(a: Node, b: Node) -> Node {
    match (num(&a), num(&b)) {
        (Some(x), Some(y)) => Node::Num(x + y),
        (Some(0.0), _) => b,
        (_, Some(0.0)) => a,
        _ => Node::Chain(Box::new(a), vec![('+', b)]),
    }
}

fn sub(a: Node, b: Node) -> Node {
    match (num(&a), num(&b)) {
        (Some(x), Some(y)) => Node::Num(x - y),
        (Some(0.0), _) => neg(b),
        (_, Some(0.0)) => a,
        _ => Node::Chain(Box::new(a), vec![('-', b)]),
    }
}

fn neg(a: Node) -> Node {
    match a {
        Node::Num(x) => Node::Num(-x),
        Node::Neg(inner) => *inner,
        a => Node::Neg(Box::new(a)),
    }
}

fn mul(a: Node, b: Node) -> Node {
    match (num(&a), num(&b)) {
        (Some(x), Some(y)) => Node::Num(x * y),
        (Some(0.0), _) | (_, Some(0.0)) => Node::Num(0.0),
        (Some(1.0), _) => b,
        (_, Some(1.0)) => a,
        _ => Node::Chain(Box::new(a), vec![('*', b)]),
    }
}

fn div(a: Node, b: Node) -> Node {
    match (num(&a), num(&b)) {
        (Some(0.0), _) => Node::Num(0.0),
        (_, Some(1.0)) => a,
        _ => Node::Chain(Box::new(a), vec![('/', b)]),
    }
}

fn call(f: Func, args: Vec<Node>) -> Node {
    Node::Call(f, args)
}

/// Most nodes a derivative may copy from its expression: a product of k factors that
/// depend on the variable copies O(k²) of them, and without a bound a long one would
/// take seconds and gigabytes.
pub const MAX_DERIVATIVE_NODES: usize = 200_000;

fn size(n: &Node) -> usize {
    1 + match n {
        Node::Num(_) | Node::Var(_) | Node::Slot(_) => 0,
        Node::Neg(a) => size(a),
        Node::Chain(first, rest) => size(first) + rest.iter().map(|(_, x)| size(x)).sum::<usize>(),
        Node::Pow(a, b) => size(a) + size(b),
        Node::Call(_, args) => args.iter().map(size).sum(),
    }
}

/// A copy of `n` for a derivative, paid from `budget`.
fn copy(n: &Node, budget: &Cell<usize>) -> Result<Node, ExprError> {
    let s = size(n);
    if s > budget.get() {
        return Err(ExprError::TooLarge(format!(
            "expression too large to differentiate: its derivative would copy more than {MAX_DERIVATIVE_NODES} nodes (a long product of factors that depend on the state; give it fewer)"
        )));
    }
    budget.set(budget.get() - s);
    Ok(n.clone())
}

/// d n / d v, where `is_v` recognises the variable.
fn derive(n: &Node, is_v: &dyn Fn(&Node) -> bool, budget: &Cell<usize>) -> Result<Node, ExprError> {
    let d = |a: &Node| derive(a, is_v, budget);
    let c = |a: &Node| copy(a, budget);
    Ok(match n {
        Node::Num(_) => Node::Num(0.0),
        Node::Var(_) | Node::Slot(_) => Node::Num(if is_v(n) { 1.0 } else { 0.0 }),
        Node::Neg(a) => neg(d(a)?),
        Node::Chain(first, rest) => {
            // Every chain holds one precedence level, so its operands are terms of a
            // sum (± x_j) or factors of a product (x₀ · x₁ / x₂ …). The derivative is
            // kept flat, one level deeper than the chain at most: a sum of the ± x_j',
            // or a sum of products, one per factor in the variable — x_j replaced by
            // x_j' for a factor, −(P / x_j) x_j' for a divisor.
            let items: Vec<(char, &Node)> = std::iter::once(('+', &**first))
                .chain(rest.iter().map(|(op, x)| (*op, x)))
                .collect();
            let product = matches!(rest.first(), Some(('*' | '/', _)));
            let mut terms: Vec<(char, Node)> = Vec::new();
            for (j, &(op, x)) in items.iter().enumerate() {
                let dx = d(x)?;
                if num(&dx) == Some(0.0) {
                    continue;
                }
                if !product {
                    terms.push((op, dx));
                    continue;
                }
                let mut factors: Vec<(char, Node)> = Vec::with_capacity(items.len() + 2);
                for (i, &(o, xi)) in items.iter().enumerate() {
                    let o = if i == 0 { '*' } else { o };
                    if i != j {
                        factors.push((o, c(xi)?));
                    } else if o == '/' {
                        factors.push(('/', c(xi)?));
                        factors.push(('/', c(xi)?));
                    }
                }
                if num(&dx) != Some(1.0) {
                    factors.push(('*', dx));
                }
                terms.push((if op == '/' { '-' } else { '+' }, flat_product(factors)));
            }
            flat_sum(terms)
        }
        Node::Pow(a, b) => power_derivative(a, b, d(a)?, d(b)?, budget)?,
        Node::Call(f, args) => {
            let a = &args[0];
            let da = d(a)?;
            if *f == Func::Sign {
                return Ok(Node::Num(0.0));
            }
            if num(&da) == Some(0.0) && args.len() == 1 {
                return Ok(Node::Num(0.0));
            }
            let one = || Node::Num(1.0);
            let sq = |x: &Node| -> Result<Node, ExprError> { Ok(mul(c(x)?, c(x)?)) };
            match f {
                Func::Sqrt => div(da, mul(Node::Num(2.0), c(n)?)),
                Func::Sin => mul(call(Func::Cos, vec![c(a)?]), da),
                Func::Cos => neg(mul(call(Func::Sin, vec![c(a)?]), da)),
                Func::Tan => mul(add(one(), sq(n)?), da),
                Func::Asin => div(da, call(Func::Sqrt, vec![sub(one(), sq(a)?)])),
                Func::Acos => neg(div(da, call(Func::Sqrt, vec![sub(one(), sq(a)?)]))),
                Func::Atan => div(da, add(one(), sq(a)?)),
                Func::Exp => mul(c(n)?, da),
                Func::Ln => div(da, c(a)?),
                Func::Abs => mul(call(Func::Sign, vec![c(a)?]), da),
                Func::Sinh => mul(call(Func::Cosh, vec![c(a)?]), da),
                Func::Cosh => mul(call(Func::Sinh, vec![c(a)?]), da),
                Func::Tanh => mul(sub(one(), sq(n)?), da),
                Func::Sign => Node::Num(0.0),
                Func::Atan2 => {
                    // atan2(y, x)' = (x y' − y x') / (x² + y²)
                    let (y, x) = (a, &args[1]);
                    let dx = d(x)?;
                    div(sub(mul(c(x)?, da), mul(c(y)?, dx)), add(sq(x)?, sq(y)?))
                }
                Func::Min | Func::Max => {
                    // min(a, b) = (a + b − |a − b|)/2, max with +|a − b|.
                    let b = &args[1];
                    let db = d(b)?;
                    let s = call(Func::Sign, vec![sub(c(a)?, c(b)?)]);
                    let kink = mul(s, sub(c(&da)?, c(&db)?));
                    let mean = add(da, db);
                    let sum = if *f == Func::Min {
                        sub(mean, kink)
                    } else {
                        add(mean, kink)
                    };
                    mul(Node::Num(0.5), sum)
                }
                Func::Pow => power_derivative(a, &args[1], da, d(&args[1])?, budget)?,
            }
        }
    })
}

/// x₀ op₁ x₁ … as one chain (ops `*`, `/`; the first operand's op is ignored as `*`, a
/// leading divisor becomes 1/x).
fn flat_product(mut factors: Vec<(char, Node)>) -> Node {
    if factors.is_empty() {
        return Node::Num(1.0);
    }
    if factors[0].0 == '/' {
        factors.insert(0, ('*', Node::Num(1.0)));
    }
    let mut it = factors.into_iter();
    let (_, first) = it.next().expect("not empty");
    let rest: Vec<(char, Node)> = it.collect();
    if rest.is_empty() {
        first
    } else {
        Node::Chain(Box::new(first), rest)
    }
}

/// ± t₀ ± t₁ … as one chain (0 when empty; a leading − as a negation).
fn flat_sum(terms: Vec<(char, Node)>) -> Node {
    let mut it = terms.into_iter();
    let Some((sign, first)) = it.next() else {
        return Node::Num(0.0);
    };
    let first = if sign == '-' { neg(first) } else { first };
    let rest: Vec<(char, Node)> = it.collect();
    if rest.is_empty() {
        first
    } else {
        Node::Chain(Box::new(first), rest)
    }
}

/// (aᵇ)' = b aᵇ⁻¹ a' for a constant exponent, aᵇ (b' ln a + b a'/a) otherwise.
fn power_derivative(
    a: &Node,
    b: &Node,
    da: Node,
    db: Node,
    budget: &Cell<usize>,
) -> Result<Node, ExprError> {
    let c = |x: &Node| copy(x, budget);
    if num(&db) == Some(0.0) {
        if num(&da) == Some(0.0) {
            return Ok(Node::Num(0.0));
        }
        let lowered = match num(b) {
            Some(e) => Node::Num(e - 1.0),
            None => sub(c(b)?, Node::Num(1.0)),
        };
        let p = match num(&lowered) {
            Some(1.0) => c(a)?,
            _ => Node::Pow(Box::new(c(a)?), Box::new(lowered)),
        };
        return Ok(mul(mul(c(b)?, p), da));
    }
    let ab = Node::Pow(Box::new(c(a)?), Box::new(c(b)?));
    Ok(mul(
        ab,
        add(
            mul(db, call(Func::Ln, vec![c(a)?])),
            div(mul(c(b)?, da), c(a)?),
        ),
    ))
}

fn bind_node(
    n: &Node,
    keep: &dyn Fn(&str) -> bool,
    lookup: &dyn Fn(&str) -> Option<f64>,
) -> Result<Node, ExprError> {
    let bind = |a: &Node| bind_node(a, keep, lookup);
    let folded = match n {
        Node::Var(name) if keep(name) => return Ok(n.clone()),
        Node::Slot(_) => return Ok(n.clone()),
        Node::Num(_) | Node::Var(_) => return Ok(Node::Num(eval_node(n, lookup, &[])?)),
        Node::Neg(a) => Node::Neg(Box::new(bind(a)?)),
        Node::Chain(first, rest) => Node::Chain(
            Box::new(bind(first)?),
            rest.iter()
                .map(|(op, x)| Ok((*op, bind(x)?)))
                .collect::<Result<_, ExprError>>()?,
        ),
        Node::Pow(a, b) => Node::Pow(Box::new(bind(a)?), Box::new(bind(b)?)),
        Node::Call(f, args) => Node::Call(*f, args.iter().map(bind).collect::<Result<_, _>>()?),
    };
    // A subtree whose children all folded to numbers no longer depends on a kept
    // name: fold it too.
    let constant = match &folded {
        Node::Neg(a) => matches!(**a, Node::Num(_)),
        Node::Chain(first, rest) => {
            matches!(**first, Node::Num(_)) && rest.iter().all(|(_, x)| matches!(x, Node::Num(_)))
        }
        Node::Pow(a, b) => matches!(**a, Node::Num(_)) && matches!(**b, Node::Num(_)),
        Node::Call(_, args) => args.iter().all(|a| matches!(a, Node::Num(_))),
        Node::Num(_) | Node::Var(_) | Node::Slot(_) => false,
    };
    if constant {
        let v = eval_node(&folded, &|_| None, &[])?;
        if !v.is_finite() {
            return Err(ExprError::NotFinite);
        }
        return Ok(Node::Num(v));
    }
    Ok(folded)
}

struct Parser {
    chars: Vec<char>,
    pos: usize,
    /// Current nesting (active `unary` calls, through which every recursion passes).
    depth: usize,
    /// Nodes built so far.
    nodes: usize,
}

impl Parser {
    fn error(&self, message: String) -> ExprError {
        ExprError::Syntax {
            at: self.pos,
            message,
        }
    }

    /// Counts one more node against [`MAX_NODES`].
    fn node(&mut self, n: Node) -> Result<Node, ExprError> {
        self.nodes += 1;
        if self.nodes > MAX_NODES {
            return Err(ExprError::TooLarge(format!(
                "expression too large: more than {MAX_NODES} numbers, names and operators"
            )));
        }
        Ok(n)
    }

    fn skip_ws(&mut self) {
        while self.pos < self.chars.len() && self.chars[self.pos].is_whitespace() {
            self.pos += 1;
        }
    }

    fn peek(&mut self) -> Option<char> {
        self.skip_ws();
        self.chars.get(self.pos).copied()
    }

    /// One precedence level of left-associative operators `ops` over `operand`.
    fn chain(
        &mut self,
        ops: [char; 2],
        operand: fn(&mut Parser) -> Result<Node, ExprError>,
    ) -> Result<Node, ExprError> {
        let first = operand(self)?;
        let mut rest = Vec::new();
        while let Some(op) = self.peek().filter(|c| ops.contains(c)) {
            self.pos += 1;
            let x = operand(self)?;
            rest.push((op, self.node(x)?));
        }
        if rest.is_empty() {
            Ok(first)
        } else {
            Ok(Node::Chain(Box::new(first), rest))
        }
    }

    fn expr(&mut self) -> Result<Node, ExprError> {
        self.chain(['+', '-'], Parser::term)
    }

    fn term(&mut self) -> Result<Node, ExprError> {
        self.chain(['*', '/'], Parser::unary)
    }

    fn unary(&mut self) -> Result<Node, ExprError> {
        self.depth += 1;
        if self.depth > MAX_DEPTH {
            return Err(ExprError::TooLarge(format!(
                "expression nested too deeply at character {}: more than {MAX_DEPTH} levels of parentheses, calls, signs and powers",
                self.pos + 1
            )));
        }
        let n = match self.peek() {
            Some('-') => {
                self.pos += 1;
                let a = self.unary()?;
                self.node(Node::Neg(Box::new(a)))
            }
            Some('+') => {
                self.pos += 1;
                self.unary()
            }
            _ => self.power(),
        };
        self.depth -= 1;
        n
    }

    /// `a^b^c` is `a^(b^c)`, and `-a^2` is `-(a^2)`, as in mathematics.
    fn power(&mut self) -> Result<Node, ExprError> {
        let base = self.atom()?;
        if self.peek() == Some('^') {
            self.pos += 1;
            let exp = self.unary()?;
            return self.node(Node::Pow(Box::new(base), Box::new(exp)));
        }
        Ok(base)
    }

    fn atom(&mut self) -> Result<Node, ExprError> {
        match self.peek() {
            None => Err(self.error("expression ends too early".into())),
            Some('(') => {
                self.pos += 1;
                let inner = self.expr()?;
                if self.peek() != Some(')') {
                    return Err(self.error("missing ')'".into()));
                }
                self.pos += 1;
                Ok(inner)
            }
            Some(c) if c.is_ascii_digit() || c == '.' => self.number(),
            Some(c) if c.is_alphabetic() || c == '_' => {
                let start = self.pos;
                while self.pos < self.chars.len()
                    && (self.chars[self.pos].is_alphanumeric() || self.chars[self.pos] == '_')
                {
                    self.pos += 1;
                }
                let name: String = self.chars[start..self.pos].iter().collect();
                if self.peek() == Some('(') && STATE_ACCESSORS.contains(&name.as_str()) {
                    return self.state_quantity(name);
                }
                if self.peek() == Some('(') {
                    let Some((func, arity)) = Func::lookup(&name) else {
                        self.pos = start;
                        return Err(
                            self.error(format!("unknown function '{}'", excerpt(&name, QUOTE)))
                        );
                    };
                    self.pos += 1;
                    let mut args = vec![self.expr()?];
                    while self.peek() == Some(',') {
                        self.pos += 1;
                        if args.len() == arity {
                            return Err(self.error(format!("{name} takes {arity} argument(s)")));
                        }
                        args.push(self.expr()?);
                    }
                    if self.peek() != Some(')') {
                        return Err(self.error("missing ')' after function arguments".into()));
                    }
                    self.pos += 1;
                    if args.len() != arity {
                        return Err(self.error(format!(
                            "{name} takes {arity} argument(s), got {}",
                            args.len()
                        )));
                    }
                    return self.node(Node::Call(func, args));
                }
                self.node(Node::Var(name))
            }
            Some(c) => Err(self.error(format!("unexpected '{}'", c.escape_default()))),
        }
    }

    /// `rate(theta)`: one name in parentheses, kept whole as the name `"rate(theta)"`.
    fn state_quantity(&mut self, accessor: String) -> Result<Node, ExprError> {
        self.pos += 1; // '('
        self.skip_ws();
        let start = self.pos;
        while self.pos < self.chars.len()
            && (self.chars[self.pos].is_alphanumeric() || self.chars[self.pos] == '_')
        {
            self.pos += 1;
        }
        if self.pos == start {
            return Err(self.error(format!(
                "{accessor}(…) takes the name of a {}",
                match accessor.as_str() {
                    "rate" => "coordinate",
                    "angle" | "omega" => "body",
                    _ => "point",
                }
            )));
        }
        let arg: String = self.chars[start..self.pos].iter().collect();
        if self.peek() != Some(')') {
            return Err(self.error(format!("missing ')' after {accessor}({arg}")));
        }
        self.pos += 1;
        self.node(Node::Var(format!("{accessor}({arg})")))
    }

    fn number(&mut self) -> Result<Node, ExprError> {
        let start = self.pos;
        let at = |p: &Parser, i: usize| p.chars.get(i).copied();
        while matches!(at(self, self.pos), Some(c) if c.is_ascii_digit() || c == '.') {
            self.pos += 1;
        }
        if matches!(at(self, self.pos), Some('e' | 'E')) {
            let mut k = self.pos + 1;
            if matches!(at(self, k), Some('+' | '-')) {
                k += 1;
            }
            if matches!(at(self, k), Some(c) if c.is_ascii_digit()) {
                self.pos = k;
                while matches!(at(self, self.pos), Some(c) if c.is_ascii_digit()) {
                    self.pos += 1;
                }
            }
        }
        let text: String = self.chars[start..self.pos].iter().collect();
        match text.parse::<f64>() {
            Ok(v) => self.node(Node::Num(v)),
            Err(_) => Err(ExprError::Syntax {
                at: start,
                message: format!("malformed number '{}'", excerpt(&text, QUOTE)),
            }),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ev(s: &str) -> Result<f64, ExprError> {
        Expr::parse(s)?.eval(&|n| match n {
            "L" => Some(2.0),
            "mass" => Some(3.0),
            _ => None,
        })
    }

    #[test]
    fn arithmetic_and_precedence() {
        assert_eq!(ev("1+2*3").unwrap(), 7.0);
        assert_eq!(ev("(1+2)*3").unwrap(), 9.0);
        assert_eq!(ev("2^3^2").unwrap(), 512.0);
        assert_eq!(ev("-2^2").unwrap(), -4.0);
        assert_eq!(ev("2*L").unwrap(), 4.0);
        assert!((ev("(1/3)*mass*L^2").unwrap() - 4.0).abs() < 1e-15);
        assert!((ev("sqrt(13)").unwrap() - 13f64.sqrt()).abs() < 1e-15);
        assert!((ev("pi").unwrap() - std::f64::consts::PI).abs() < 1e-15);
        assert_eq!(ev("1.5e-3*2").unwrap(), 3e-3);
        assert_eq!(ev("atan2(0, -1)").unwrap(), std::f64::consts::PI);
        // Flat chains keep left associativity.
        assert_eq!(ev("1-2-3").unwrap(), -4.0);
        assert_eq!(ev("8/4/2").unwrap(), 1.0);
        assert_eq!(
            ev("2*3/4*5-1+L").unwrap(),
            ((2.0 * 3.0) / 4.0) * 5.0 - 1.0 + 2.0
        );
    }

    #[test]
    fn excerpt_cuts_and_escapes() {
        assert_eq!(excerpt("abc", 3), "abc");
        assert_eq!(excerpt("abcdef", 4), "abc…");
        assert_eq!(excerpt("a\nb", 10), "a\\nb");
        assert_eq!(excerpt("é€日本", 3), "é€…");
    }

    #[test]
    fn bind_folds_partly_constant_chains() {
        let e = Expr::parse("t + 2*L - -mass^2").unwrap();
        let b = e
            .bind(&|n| n == "t", &|n| (n == "L").then_some(2.0).or(Some(3.0)))
            .unwrap();
        assert_eq!(b.eval(&|_| Some(1.0)).unwrap(), 1.0 + 4.0 + 9.0);
    }

    #[test]
    fn errors_name_the_problem() {
        assert_eq!(ev("2*W"), Err(ExprError::Undefined("W".into())));
        assert!(matches!(ev("2*(L"), Err(ExprError::Syntax { .. })));
        assert!(matches!(ev("2 L"), Err(ExprError::Syntax { .. })));
        assert!(matches!(ev("foo(2)"), Err(ExprError::Syntax { .. })));
        assert!(matches!(ev("sqrt(1,2)"), Err(ExprError::Syntax { .. })));
        assert!(matches!(ev(""), Err(ExprError::Syntax { .. })));
        assert_eq!(ev("sqrt(-1)"), Err(ExprError::NotFinite));
        assert_eq!(ev("1/0"), Err(ExprError::NotFinite));
    }

    #[test]
    fn bind_keeps_time() {
        let e = Expr::parse("L*sin(2*t) + mass").unwrap();
        let b = e
            .bind(&|n| n == "t", &|n| {
                if n == "L" {
                    Some(2.0)
                } else {
                    Some(3.0)
                }
            })
            .unwrap();
        assert_eq!(b.names(), vec!["t".to_string()]);
        let v = b.eval(&|n| (n == "t").then_some(0.25)).unwrap();
        assert!((v - (2.0 * 0.5f64.sin() + 3.0)).abs() < 1e-15);
        let c = Expr::parse("2*L")
            .unwrap()
            .bind(&|n| n == "t", &|_| Some(1.5))
            .unwrap();
        assert_eq!(c.as_constant(), Some(3.0));
    }

    /// Central differences of `e` in `name` at `at` (other names from `values`).
    fn numeric(e: &Expr, name: &str, values: &[(&str, f64)]) -> f64 {
        let at = |shift: f64| {
            e.eval(&|n| {
                values
                    .iter()
                    .find(|(k, _)| *k == n)
                    .map(|(k, v)| if *k == name { v + shift } else { *v })
            })
            .unwrap()
        };
        let x = values.iter().find(|(k, _)| *k == name).unwrap().1;
        let h = 1e-6 * x.abs().max(1.0);
        (at(h) - at(-h)) / (2.0 * h)
    }

    #[test]
    fn derivatives_match_finite_differences() {
        let values = [("a", 0.7), ("b", -1.3), ("t", 0.4)];
        let texts = [
            "3*a - 2*b + 5",
            "a*b/(1 + a^2) - b/a",
            "sqrt(a^2 + b^2) * sin(3*a) * cos(b - t)",
            "tan(a) + asin(a/2) + acos(b/3) + atan(a*b)",
            "atan2(b, a) + atan2(a, b*t)",
            "exp(-a*b) + ln(a) + log(a*a + 1)",
            "abs(b) * abs(a - 2) + sign(b)*a",
            "min(a, b) + max(a^2, b) + min(2*a, 1)",
            "a^b + pow(a, 3) + 2^a + b^2 + a^(1/2)",
            "sinh(a) + cosh(b) + tanh(a*b)",
            "-(a - b)^3 / (a + 2) - -a",
            "1/a/b*a*b - t",
        ];
        for text in texts {
            let e = Expr::parse(text).unwrap();
            for name in ["a", "b", "t"] {
                let exact = e
                    .derivative(name)
                    .unwrap()
                    .eval(&|n| values.iter().find(|(k, _)| *k == n).map(|(_, v)| *v))
                    .unwrap();
                let fd = numeric(&e, name, &values);
                assert!(
                    (exact - fd).abs() <= 1e-7 * (1.0 + fd.abs()),
                    "d({text})/d{name}: {exact} against {fd}"
                );
            }
        }
    }

    #[test]
    fn derivatives_stay_small() {
        // Constants vanish, and a term without the name costs nothing.
        let e = Expr::parse("5*sin(2*t) + 3*a").unwrap();
        assert_eq!(e.derivative("a").unwrap().as_constant(), Some(3.0));
        assert_eq!(e.derivative("b").unwrap().as_constant(), Some(0.0));
        assert_eq!(
            Expr::parse("a*a")
                .unwrap()
                .derivative("c")
                .unwrap()
                .as_constant(),
            Some(0.0)
        );
        // A long product of factors in the variable is refused, not built for seconds.
        let long = vec!["a"; 3000].join("*");
        assert!(matches!(
            Expr::parse(&long).unwrap().derivative("a"),
            Err(ExprError::TooLarge(_))
        ));
        // Factors without the variable cost one node each, and the derivative stays as
        // flat as the expression: it evaluates on a small stack.
        let wide = format!("a*{}*a", vec!["b"; 3000].join("*"));
        let d = Expr::parse(&wide).unwrap().derivative("a").unwrap();
        let v = std::thread::Builder::new()
            .stack_size(64 * 1024)
            .spawn(move || d.eval(&|n| Some(if n == "a" { 3.0 } else { 1.0 })))
            .unwrap()
            .join()
            .unwrap();
        assert_eq!(v, Ok(6.0));
    }

    #[test]
    fn state_quantities_are_names() {
        let e = Expr::parse("20 - 0.8*rate(theta) + x( P1 ) * angle(crank)").unwrap();
        assert_eq!(e.names(), vec!["rate(theta)", "x(P1)", "angle(crank)"]);
        assert!(matches!(
            Expr::parse("rate()"),
            Err(ExprError::Syntax { .. })
        ));
        assert!(matches!(
            Expr::parse("rate(a b)"),
            Err(ExprError::Syntax { .. })
        ));
        assert!(matches!(
            Expr::parse("vx(1+2)"),
            Err(ExprError::Syntax { .. })
        ));
        // A parameter may still be called x.
        assert_eq!(
            Expr::parse("2*x")
                .unwrap()
                .eval(&|n| (n == "x").then_some(4.0)),
            Ok(8.0)
        );
    }

    #[test]
    fn resolved_slots_evaluate_and_differentiate() {
        let e = Expr::parse("k*(1 - rate(theta)/w) + t")
            .unwrap()
            .bind(&|n| n == "t" || n == "rate(theta)", &|n| match n {
                "k" => Some(2.0),
                "w" => Some(4.0),
                _ => None,
            })
            .unwrap();
        let slot = |n: &str| match n {
            "t" => Some(0),
            "rate(theta)" => Some(1),
            _ => None,
        };
        let r = e.resolve(&slot).unwrap();
        assert_eq!(r.eval_slots(&[0.5, 2.0]), 2.0 * 0.5 + 0.5);
        assert_eq!(r.derivative_slot(1).unwrap().eval_slots(&[0.5, 2.0]), -0.5);
        assert!(e.resolve(&|_| None).is_err());
    }
}
