//! The parser: expression text to syntax tree, recursive descent over the precedence
//! levels, bounded by the size limits.

use super::functions::{Func, STATE_ACCESSORS};
use super::{excerpt, ExprError, Node, MAX_DEPTH, MAX_LEN, MAX_NODES, QUOTE};

/// The syntax tree of `text`, checked against the size limits.
pub(super) fn syntax_tree(text: &str) -> Result<Node, ExprError> {
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
    Ok(root)
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
            // The name quoted at most QUOTE characters long: a message is one short line.
            let arg = excerpt(&arg, QUOTE);
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
    use crate::expr::{Expr, ExprError};

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
    fn a_long_name_in_an_unclosed_accessor_is_quoted_short() {
        let text = format!("rate({}", "M".repeat(500));
        let msg = Expr::parse(&text).unwrap_err().to_string();
        assert!(msg.contains("missing ')' after rate("), "{msg}");
        assert!(msg.chars().count() <= 120, "{msg}");
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
}
