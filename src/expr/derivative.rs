//! Symbolic derivatives: d/dv of a syntax tree, kept flat and folded where a factor
//! is 0 or 1, and bounded in size.

use super::functions::Func;
use super::{ExprError, Node};
use std::cell::Cell;

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
pub(super) fn derive(
    n: &Node,
    is_v: &dyn Fn(&Node) -> bool,
    budget: &Cell<usize>,
) -> Result<Node, ExprError> {
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

#[cfg(test)]
mod tests {
    use crate::expr::{Expr, ExprError};

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
}
