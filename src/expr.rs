//! Arithmetic expressions in scene files: `2*L`, `sqrt(13)`, `(1/3)*mass*length^2`,
//! `pi`, and functions of time such as `5*sin(2*t)`.
//!
//! An expression is parsed once into a small syntax tree; names are looked up when it
//! is evaluated, so the same text can be checked early and evaluated later (for `t`).
//!
//! The parser and every walk over the tree recurse, so input size is bounded
//! ([`MAX_LEN`], [`MAX_NODES`], [`MAX_DEPTH`]): no text can overflow the stack.
//! Sums and products are flat lists, so a long sum is a wide tree, not a deep one.

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
}

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
        let v = eval_node(&self.root, lookup)?;
        if v.is_finite() {
            Ok(v)
        } else {
            Err(ExprError::NotFinite)
        }
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
        keep: &[&str],
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
        Node::Num(_) => {}
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

fn eval_node(n: &Node, lookup: &dyn Fn(&str) -> Option<f64>) -> Result<f64, ExprError> {
    Ok(match n {
        Node::Num(v) => *v,
        Node::Var(name) => lookup(name)
            .or_else(|| builtin(name))
            .ok_or_else(|| ExprError::Undefined(name.clone()))?,
        Node::Neg(a) => -eval_node(a, lookup)?,
        Node::Chain(first, rest) => {
            let mut acc = eval_node(first, lookup)?;
            for (op, x) in rest {
                acc = apply_op(*op, acc, eval_node(x, lookup)?);
            }
            acc
        }
        Node::Pow(a, b) => eval_node(a, lookup)?.powf(eval_node(b, lookup)?),
        Node::Call(f, args) => {
            let mut vals = [0.0; 2];
            for (slot, a) in vals.iter_mut().zip(args) {
                *slot = eval_node(a, lookup)?;
            }
            f.apply(&vals[..args.len().min(2)])
        }
    })
}

fn bind_node(
    n: &Node,
    keep: &[&str],
    lookup: &dyn Fn(&str) -> Option<f64>,
) -> Result<Node, ExprError> {
    let bind = |a: &Node| bind_node(a, keep, lookup);
    let folded = match n {
        Node::Var(name) if keep.contains(&name.as_str()) => return Ok(n.clone()),
        Node::Num(_) | Node::Var(_) => return Ok(Node::Num(eval_node(n, lookup)?)),
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
        Node::Num(_) | Node::Var(_) => false,
    };
    if constant {
        let v = eval_node(&folded, &|_| None)?;
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
            .bind(&["t"], &|n| (n == "L").then_some(2.0).or(Some(3.0)))
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
            .bind(&["t"], &|n| if n == "L" { Some(2.0) } else { Some(3.0) })
            .unwrap();
        assert_eq!(b.names(), vec!["t".to_string()]);
        let v = b.eval(&|n| (n == "t").then_some(0.25)).unwrap();
        assert!((v - (2.0 * 0.5f64.sin() + 3.0)).abs() < 1e-15);
        let c = Expr::parse("2*L")
            .unwrap()
            .bind(&["t"], &|_| Some(1.5))
            .unwrap();
        assert_eq!(c.as_constant(), Some(3.0));
    }
}
