//! The functions an expression may call (`sqrt`, `sin`, `atan2`, `min`, …) with their
//! arity and value, and the accessors of the mechanism's state (`rate(theta)`, …).

#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) enum Func {
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
    pub(super) fn lookup(name: &str) -> Option<(Func, usize)> {
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

    pub(super) fn apply(self, a: &[f64]) -> f64 {
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
