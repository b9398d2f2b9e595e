//! Walks over the syntax tree: evaluation, the names it refers to, names resolved to
//! slots, and parameters bound to their values.

use super::{ExprError, Node};
use std::collections::HashSet;

pub(super) fn collect_names<'a>(n: &'a Node, seen: &mut HashSet<&'a str>, out: &mut Vec<String>) {
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

/// Whether the tree calls `sign`, the one function that jumps.
pub(super) fn calls_sign(n: &Node) -> bool {
    match n {
        Node::Num(_) | Node::Slot(_) | Node::Var(_) => false,
        Node::Neg(a) => calls_sign(a),
        Node::Chain(first, rest) => calls_sign(first) || rest.iter().any(|(_, x)| calls_sign(x)),
        Node::Pow(a, b) => calls_sign(a) || calls_sign(b),
        Node::Call(f, args) => *f == super::functions::Func::Sign || args.iter().any(calls_sign),
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

pub(super) fn eval_node(
    n: &Node,
    lookup: &dyn Fn(&str) -> Option<f64>,
    slots: &[f64],
) -> Result<f64, ExprError> {
    walk(n, slots, &|name: &String| {
        lookup(name)
            .or_else(|| builtin(name))
            .ok_or_else(|| ExprError::Undefined(name.clone()))
    })
}

/// [`eval_node`] with no names to look up, as [`super::Expr::eval_slots`] evaluates
/// a resolved tree, an unknown name `None`. It runs inside every step's Newton
/// iteration, where an error payload in the result costs more than the arithmetic:
/// the walk is the same, its error type `()`.
pub(super) fn eval_slots_node(n: &Node, slots: &[f64]) -> Option<f64> {
    walk(n, slots, &|name: &String| builtin(name).ok_or(())).ok()
}

/// The tree's value, names by `var`.
fn walk<E>(n: &Node, slots: &[f64], var: &impl Fn(&String) -> Result<f64, E>) -> Result<f64, E> {
    // Most operands are numbers and slots: read in place, not through a call.
    let eval = |a: &Node| match a {
        Node::Num(v) => Ok(*v),
        Node::Slot(k) => Ok(slots[*k]),
        _ => walk(a, slots, var),
    };
    Ok(match n {
        Node::Num(v) => *v,
        Node::Slot(k) => slots[*k],
        Node::Var(name) => var(name)?,
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

pub(super) fn resolve_node(
    n: &Node,
    slot_of: &dyn Fn(&str) -> Option<usize>,
) -> Result<Node, ExprError> {
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

pub(super) fn bind_node(
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

#[cfg(test)]
mod tests {
    use crate::expr::Expr;

    #[test]
    fn bind_folds_partly_constant_chains() {
        let e = Expr::parse("t + 2*L - -mass^2").unwrap();
        let b = e
            .bind(&|n| n == "t", &|n| (n == "L").then_some(2.0).or(Some(3.0)))
            .unwrap();
        assert_eq!(b.eval(&|_| Some(1.0)).unwrap(), 1.0 + 4.0 + 9.0);
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
