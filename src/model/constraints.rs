//! Constraint equations of planar mechanisms in closed form (paper, Appendix III).
//!
//! Each constraint is one scalar equation Φᵏ(u) = 0 over a small local vector u of the
//! coordinates it involves (fixed points enter u as constants). For each one we give
//! Φᵏ, its gradient Φᵏ_q, the directional second derivative Φᵏ_qq·v (which is Φ̇ᵏ_q
//! for v = q̇, ∂(Φᵏ_q q̇)/∂q likewise, and Φᵏ_qq q̈ for v = q̈) and the third-order
//! term ∂(Φ̇ᵏ_q q̇)/∂q = ∂(q̇ᵀ Φᵏ_qq q̇)/∂q. None of the constraints depends on time.

/// Most coordinates one constraint involves (four points and an angle).
pub const MAX_LOCAL: usize = 9;

/// The switch between the two equation sets of an angle (Appendix III): the cosine
/// form is used where |sin| > 1/√2, so that the derivative in the angle stays large.
fn use_cos_form(angle: f64) -> bool {
    angle.sin().abs() > std::f64::consts::FRAC_1_SQRT_2
}

/// The scalar equation of one constraint, over its local coordinates.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Equation {
    /// u = [xi, yi, xj, yj]: (xj−xi)² + (yj−yi)² − L² = 0.
    Distance { length: f64 },
    /// u = [x, y, xi, yi, xj, yj]: (xj−xi)(y−yi) − (yj−yi)(x−xi) = 0; the fixed and
    /// the mobile pinned slider (their line points fixed or not).
    PointOnLine,
    /// u = [xi, yi, xj, yj, θ]: xj−xi − L cos θ = 0 where |sin θ| > 1/√2, else
    /// yj−yi − L sin θ = 0.
    AbsoluteAngle { length: f64 },
    /// u = [ri, rj, rk, rl, φ], a = rj−ri, b = rl−rk, K = |a||b|:
    /// a·b − K cos φ = 0 where |sin φ| > 1/√2, else a×b − K sin φ = 0.
    RelativeAngle { k: f64 },
    /// u = [rp, ri, rj, s], e = rj−ri of length L: (rp−ri)·e − s L = 0.
    DistanceAlong { length: f64 },
}

impl Equation {
    /// Number of local coordinates.
    #[allow(clippy::len_without_is_empty)] // never empty: every equation has coordinates
    pub fn len(&self) -> usize {
        match self {
            Equation::Distance { .. } => 4,
            Equation::PointOnLine => 6,
            Equation::AbsoluteAngle { .. } => 5,
            Equation::RelativeAngle { .. } => 9,
            Equation::DistanceAlong { .. } => 7,
        }
    }

    /// Φᵏ(u).
    pub fn phi(&self, u: &[f64]) -> f64 {
        match *self {
            Equation::Distance { length } => {
                let (dx, dy) = (u[2] - u[0], u[3] - u[1]);
                dx * dx + dy * dy - length * length
            }
            Equation::PointOnLine => (u[4] - u[2]) * (u[1] - u[3]) - (u[5] - u[3]) * (u[0] - u[2]),
            Equation::AbsoluteAngle { length } => {
                let th = u[4];
                if use_cos_form(th) {
                    u[2] - u[0] - length * th.cos()
                } else {
                    u[3] - u[1] - length * th.sin()
                }
            }
            Equation::RelativeAngle { k } => {
                let (a, b) = segments(u);
                let phi = u[8];
                if use_cos_form(phi) {
                    a[0] * b[0] + a[1] * b[1] - k * phi.cos()
                } else {
                    a[0] * b[1] - a[1] * b[0] - k * phi.sin()
                }
            }
            Equation::DistanceAlong { length } => {
                let d = [u[0] - u[2], u[1] - u[3]];
                let e = [u[4] - u[2], u[5] - u[3]];
                d[0] * e[0] + d[1] * e[1] - u[6] * length
            }
        }
    }

    /// ∂Φᵏ/∂u into `g` (first `len()` entries).
    pub fn gradient(&self, u: &[f64], g: &mut [f64]) {
        match *self {
            Equation::Distance { .. } => {
                let (dx, dy) = (u[2] - u[0], u[3] - u[1]);
                g[..4].copy_from_slice(&[-2.0 * dx, -2.0 * dy, 2.0 * dx, 2.0 * dy]);
            }
            Equation::PointOnLine => point_on_line_linear(u, g),
            Equation::AbsoluteAngle { length } => {
                let th = u[4];
                if use_cos_form(th) {
                    g[..5].copy_from_slice(&[-1.0, 0.0, 1.0, 0.0, length * th.sin()]);
                } else {
                    g[..5].copy_from_slice(&[0.0, -1.0, 0.0, 1.0, -length * th.cos()]);
                }
            }
            Equation::RelativeAngle { k } => {
                let (a, b) = segments(u);
                let phi = u[8];
                let cos_form = use_cos_form(phi);
                relative_angle_bilinear(cos_form, a, b, g);
                g[8] = if cos_form {
                    k * phi.sin()
                } else {
                    -k * phi.cos()
                };
            }
            Equation::DistanceAlong { length } => {
                distance_along_bilinear(u, g);
                g[6] = -length;
            }
        }
    }

    /// Φᵏ_qq(u)·v into `out`: the derivative of the gradient in direction v.
    pub fn hessian_times(&self, u: &[f64], v: &[f64], out: &mut [f64]) {
        match *self {
            Equation::Distance { .. } => {
                let (dx, dy) = (v[2] - v[0], v[3] - v[1]);
                out[..4].copy_from_slice(&[-2.0 * dx, -2.0 * dy, 2.0 * dx, 2.0 * dy]);
            }
            // The gradient is linear in u, so the Hessian applied to v is the
            // gradient's formula evaluated at v.
            Equation::PointOnLine => point_on_line_linear(v, out),
            Equation::AbsoluteAngle { length } => {
                let th = u[4];
                out[..4].fill(0.0);
                out[4] = if use_cos_form(th) {
                    length * th.cos() * v[4]
                } else {
                    length * th.sin() * v[4]
                };
            }
            Equation::RelativeAngle { k } => {
                let (va, vb) = segments(v);
                let phi = u[8];
                let cos_form = use_cos_form(phi);
                relative_angle_bilinear(cos_form, va, vb, out);
                out[8] = if cos_form {
                    k * phi.cos() * v[8]
                } else {
                    k * phi.sin() * v[8]
                };
            }
            Equation::DistanceAlong { .. } => {
                distance_along_bilinear(v, out);
                out[6] = 0.0;
            }
        }
    }

    /// ∂(vᵀ Φᵏ_qq(u) v)/∂u into `out`: nonzero only for angle coordinates, whose
    /// equations are not quadratic.
    pub fn third_order(&self, u: &[f64], v: &[f64], out: &mut [f64]) {
        out[..self.len()].fill(0.0);
        match *self {
            Equation::AbsoluteAngle { length } => {
                let (th, w) = (u[4], v[4]);
                out[4] = if use_cos_form(th) {
                    -length * th.sin() * w * w
                } else {
                    length * th.cos() * w * w
                };
            }
            Equation::RelativeAngle { k } => {
                let (phi, w) = (u[8], v[8]);
                out[8] = if use_cos_form(phi) {
                    -k * phi.sin() * w * w
                } else {
                    k * phi.cos() * w * w
                };
            }
            _ => {}
        }
    }
}

/// The two segments a = rj − ri, b = rl − rk of a relative angle.
fn segments(u: &[f64]) -> ([f64; 2], [f64; 2]) {
    ([u[2] - u[0], u[3] - u[1]], [u[6] - u[4], u[7] - u[5]])
}

/// Gradient of (xj−xi)(y−yi) − (yj−yi)(x−xi) over [x, y, xi, yi, xj, yj].
fn point_on_line_linear(u: &[f64], g: &mut [f64]) {
    let (x, y, xi, yi, xj, yj) = (u[0], u[1], u[2], u[3], u[4], u[5]);
    g[..6].copy_from_slice(&[yi - yj, xj - xi, yj - y, x - xj, y - yi, xi - x]);
}

/// Gradient of a·b (cos form) or a×b over the four points, for segments a and b.
fn relative_angle_bilinear(cos_form: bool, a: [f64; 2], b: [f64; 2], g: &mut [f64]) {
    // ∂/∂a and ∂/∂b of the product; ri, rk enter with a minus sign.
    let (da, db) = if cos_form {
        (b, a)
    } else {
        ([b[1], -b[0]], [-a[1], a[0]])
    };
    g[..8].copy_from_slice(&[-da[0], -da[1], da[0], da[1], -db[0], -db[1], db[0], db[1]]);
}

/// Gradient of (rp−ri)·(rj−ri) over [rp, ri, rj].
fn distance_along_bilinear(u: &[f64], g: &mut [f64]) {
    let d = [u[0] - u[2], u[1] - u[3]];
    let e = [u[4] - u[2], u[5] - u[3]];
    g[..6].copy_from_slice(&[e[0], e[1], -e[0] - d[0], -e[1] - d[1], d[0], d[1]]);
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Central differences of `f` at u in every direction.
    fn fd(f: &dyn Fn(&[f64]) -> f64, u: &[f64], n: usize) -> Vec<f64> {
        let h = 1e-6;
        (0..n)
            .map(|i| {
                let (mut up, mut dn) = (u.to_vec(), u.to_vec());
                up[i] += h;
                dn[i] -= h;
                (f(&up) - f(&dn)) / (2.0 * h)
            })
            .collect()
    }

    fn rng(seed: &mut u64) -> f64 {
        *seed = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((*seed >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0
    }

    fn close(a: &[f64], b: &[f64], what: &str) {
        let scale = b.iter().fold(1.0f64, |m, x| m.max(x.abs()));
        for (i, (x, y)) in a.iter().zip(b).enumerate() {
            assert!(
                (x - y).abs() <= 1e-6 * scale,
                "{what}[{i}]: closed form {x} vs finite differences {y}"
            );
        }
    }

    /// Every equation's gradient, Hessian product and third-order term against
    /// central finite differences at random points, away from the angle switch.
    #[test]
    fn derivatives_match_finite_differences() {
        let eqs = [
            Equation::Distance { length: 1.3 },
            Equation::PointOnLine,
            Equation::AbsoluteAngle { length: 0.8 },
            Equation::RelativeAngle { k: 1.7 },
            Equation::DistanceAlong { length: 2.1 },
        ];
        let mut seed = 7;
        for eq in eqs {
            let n = eq.len();
            for _ in 0..200 {
                let mut u: Vec<f64> = (0..n).map(|_| 3.0 * rng(&mut seed)).collect();
                let v: Vec<f64> = (0..n).map(|_| 2.0 * rng(&mut seed)).collect();
                let angle = match eq {
                    Equation::AbsoluteAngle { .. } => Some(4),
                    Equation::RelativeAngle { .. } => Some(8),
                    _ => None,
                };
                if let Some(a) = angle {
                    u[a] *= 2.0;
                    // Keep the finite-difference stencil on one side of the switch.
                    let s = u[a].sin().abs();
                    if (s - std::f64::consts::FRAC_1_SQRT_2).abs() < 1e-3 {
                        continue;
                    }
                }
                let mut g = vec![0.0; MAX_LOCAL];
                eq.gradient(&u, &mut g);
                close(
                    &g[..n],
                    &fd(&|x| eq.phi(x), &u, n),
                    &format!("{eq:?} gradient"),
                );

                let mut hv = vec![0.0; MAX_LOCAL];
                eq.hessian_times(&u, &v, &mut hv);
                let gv = |x: &[f64]| {
                    let mut g = vec![0.0; MAX_LOCAL];
                    eq.gradient(x, &mut g);
                    g[..n].iter().zip(&v).map(|(a, b)| a * b).sum::<f64>()
                };
                close(&hv[..n], &fd(&gv, &u, n), &format!("{eq:?} hessian·v"));

                let mut t = vec![0.0; MAX_LOCAL];
                eq.third_order(&u, &v, &mut t);
                let vhv = |x: &[f64]| {
                    let mut h = vec![0.0; MAX_LOCAL];
                    eq.hessian_times(x, &v, &mut h);
                    h[..n].iter().zip(&v).map(|(a, b)| a * b).sum::<f64>()
                };
                close(&t[..n], &fd(&vhv, &u, n), &format!("{eq:?} third order"));
            }
        }
    }
}
