//! Constraint equations of planar mechanisms in closed form (paper, Appendix III).
//!
//! Each constraint is one scalar equation Φᵏ(u) = 0 over a small local vector u of the
//! coordinates it involves (fixed points enter u as constants). For each one we give
//! Φᵏ, its gradient Φᵏ_q, the directional second derivative Φᵏ_qq·v (which is Φ̇ᵏ_q
//! for v = q̇, ∂(Φᵏ_q q̇)/∂q likewise, and Φᵏ_qq q̈ for v = q̈) and the third-order
//! term ∂(Φ̇ᵏ_q q̇)/∂q = ∂(q̇ᵀ Φᵏ_qq q̇)/∂q. None of the constraints depends on time.

use std::cell::Cell;

/// Most coordinates one constraint involves (four points and an angle).
pub const MAX_LOCAL: usize = 9;

/// The scalar equation of one constraint, over its local coordinates.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Equation {
    /// u = [xi, yi, xj, yj]: (xj−xi)² + (yj−yi)² − L² = 0.
    Distance { length: f64 },
    /// u = [x, y, xi, yi, xj, yj]: (xj−xi)(y−yi) − (yj−yi)(x−xi) = 0; the fixed and
    /// the mobile pinned slider (their line points fixed or not).
    PointOnLine,
    /// u = [xi, yi, xj, yj, θ], d = rj−ri: d × (cos θ, sin θ) = 0, i.e.
    /// (xj−xi) sin θ − (yj−yi) cos θ = 0 (the segment points along θ).
    ///
    /// Appendix III pairs xj−xi − L cos θ and yj−yi − L sin θ and switches between them
    /// at |sin θ| = 1/√2. Both vanish on the same motion, but the switch makes Φ_q and
    /// its derivatives jump off the manifold, and a step whose iterates straddle it
    /// stalls (a crank spun through π/4 at speed). The cross-product form is one smooth
    /// equation whose derivative in θ, d·(cos θ, sin θ) = |d|, never vanishes near the
    /// solution; the anti-parallel root θ + π is a half turn away.
    AbsoluteAngle,
    /// u = [ri, rj, rk, rl, φ], a = rj−ri, b = rl−rk:
    /// (a×b) cos φ − (a·b) sin φ = 0, i.e. |a||b| sin(∠(a, b) − φ) = 0: one smooth
    /// equation instead of Appendix III's switched pair, for the reason given above;
    /// its derivative in φ is −|a||b| on the solution.
    RelativeAngle,
    /// u = [rp, ri, rj, s], e = rj−ri of length L: (rp−ri)·e − s L = 0.
    DistanceAlong { length: f64 },
}

/// sin and cos of an angle, the last angle's kept: a step's evaluations ask them of
/// the same angle many times over (Φ, its gradient, its second and third
/// derivatives, in every factor at that step). The same bits in, the same out.
fn sin_cos(x: f64) -> (f64, f64) {
    thread_local! {
        static LAST: Cell<(u64, f64, f64)> = const { Cell::new((0, 0.0, 1.0)) };
    }
    LAST.with(|last| {
        let (bits, s, c) = last.get();
        if bits == x.to_bits() {
            return (s, c);
        }
        let (s, c) = x.sin_cos();
        last.set((x.to_bits(), s, c));
        (s, c)
    })
}

impl Equation {
    /// Number of local coordinates.
    #[allow(clippy::len_without_is_empty)] // never empty: every equation has coordinates
    pub fn len(&self) -> usize {
        match self {
            Equation::Distance { .. } => 4,
            Equation::PointOnLine => 6,
            Equation::AbsoluteAngle => 5,
            Equation::RelativeAngle => 9,
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
            Equation::AbsoluteAngle => {
                let (s, c) = sin_cos(u[4]);
                (u[2] - u[0]) * s - (u[3] - u[1]) * c
            }
            Equation::RelativeAngle => {
                let (a, b) = segments(u);
                let (s, c) = sin_cos(u[8]);
                cross(a, b) * c - dot(a, b) * s
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
            Equation::AbsoluteAngle => {
                let (s, c) = sin_cos(u[4]);
                let d = [u[2] - u[0], u[3] - u[1]];
                g[..5].copy_from_slice(&[-s, c, s, -c, d[0] * c + d[1] * s]);
            }
            Equation::RelativeAngle => {
                let (a, b) = segments(u);
                let (s, c) = sin_cos(u[8]);
                relative_angle_bilinear(s, c, a, b, g);
                g[8] = -cross(a, b) * s - dot(a, b) * c;
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
            Equation::AbsoluteAngle => {
                let (s, c) = sin_cos(u[4]);
                let d = [u[2] - u[0], u[3] - u[1]];
                let dv = [v[2] - v[0], v[3] - v[1]];
                let w = v[4];
                out[..5].copy_from_slice(&[
                    -c * w,
                    -s * w,
                    c * w,
                    s * w,
                    c * dv[0] + s * dv[1] + (d[1] * c - d[0] * s) * w,
                ]);
            }
            Equation::RelativeAngle => {
                // Φ = c·X(a, b) − s·D(a, b) with X = a×b, D = a·b bilinear: the
                // (a, b) block applied to v is the gradient's bilinear part at (va, b)
                // and (a, vb); the φ column is the gradient's derivative in φ.
                let (a, b) = segments(u);
                let (va, vb) = segments(v);
                let (s, c) = sin_cos(u[8]);
                let w = v[8];
                let mut along_a = [0.0; MAX_LOCAL];
                let mut along_b = [0.0; MAX_LOCAL];
                let mut turned = [0.0; MAX_LOCAL];
                relative_angle_bilinear(s, c, a, vb, &mut along_b);
                relative_angle_bilinear(s, c, va, b, &mut along_a);
                // ∂/∂φ of the gradient's (a, b) part: (−s, −c) in place of (s, c).
                relative_angle_bilinear(c, -s, a, b, &mut turned);
                for i in 0..4 {
                    // ∂/∂a rows take b-directions, ∂/∂b rows take a-directions.
                    out[i] = along_b[i] + turned[i] * w;
                    out[4 + i] = along_a[4 + i] + turned[4 + i] * w;
                }
                let (x1, d1) = (cross(va, b) + cross(a, vb), dot(va, b) + dot(a, vb));
                out[8] = -s * x1 - c * d1 + (-c * cross(a, b) + s * dot(a, b)) * w;
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
            Equation::AbsoluteAngle => {
                // vᵀΦ_qq v = 2w (c Δv_x + s Δv_y) + (d_y c − d_x s) w².
                let (s, c) = sin_cos(u[4]);
                let d = [u[2] - u[0], u[3] - u[1]];
                let dv = [v[2] - v[0], v[3] - v[1]];
                let (w, w2) = (v[4], v[4] * v[4]);
                out[..5].copy_from_slice(&[
                    s * w2,
                    -c * w2,
                    -s * w2,
                    c * w2,
                    2.0 * w * (c * dv[1] - s * dv[0]) - (d[0] * c + d[1] * s) * w2,
                ]);
            }
            Equation::RelativeAngle => {
                // vᵀΦ_qq v = 2(c X(va, vb) − s D(va, vb)) + 2w(−s X₁ − c D₁)
                //          + w²(−c X + s D), X = a×b, D = a·b, X₁ = X(va, b) + X(a, vb),
                // D₁ likewise. Each bracket is a bilinear form c′X − s′D whose gradient
                // relative_angle_bilinear gives.
                let (a, b) = segments(u);
                let (va, vb) = segments(v);
                let (s, c) = sin_cos(u[8]);
                let (w, w2) = (v[8], v[8] * v[8]);
                let mut first = [0.0; MAX_LOCAL];
                relative_angle_bilinear(c, -s, va, vb, &mut first);
                let mut second = [0.0; MAX_LOCAL];
                relative_angle_bilinear(-s, -c, a, b, &mut second);
                for i in 0..8 {
                    out[i] = 2.0 * w * first[i] + w2 * second[i];
                }
                let (x1, d1) = (cross(va, b) + cross(a, vb), dot(va, b) + dot(a, vb));
                out[8] = 2.0 * (-s * cross(va, vb) - c * dot(va, vb))
                    + 2.0 * w * (-c * x1 + s * d1)
                    + w2 * (s * cross(a, b) + c * dot(a, b));
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

fn cross(a: [f64; 2], b: [f64; 2]) -> f64 {
    a[0] * b[1] - a[1] * b[0]
}

fn dot(a: [f64; 2], b: [f64; 2]) -> f64 {
    a[0] * b[0] + a[1] * b[1]
}

/// Gradient of the bilinear form c (a×b) − s (a·b) over the four points [ri, rj, rk,
/// rl]: the a-rows from b, the b-rows from a.
fn relative_angle_bilinear(s: f64, c: f64, a: [f64; 2], b: [f64; 2], g: &mut [f64]) {
    // ∂/∂a and ∂/∂b of the form; ri, rk enter with a minus sign.
    let da = [c * b[1] - s * b[0], -c * b[0] - s * b[1]];
    let db = [-c * a[1] - s * a[0], c * a[0] - s * a[1]];
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
    /// central finite differences at random points (angles over several quadrants).
    #[test]
    fn derivatives_match_finite_differences() {
        let eqs = [
            Equation::Distance { length: 1.3 },
            Equation::PointOnLine,
            Equation::AbsoluteAngle,
            Equation::RelativeAngle,
            Equation::DistanceAlong { length: 2.1 },
        ];
        let mut seed = 7;
        for eq in eqs {
            let n = eq.len();
            for _ in 0..200 {
                let mut u: Vec<f64> = (0..n).map(|_| 3.0 * rng(&mut seed)).collect();
                let v: Vec<f64> = (0..n).map(|_| 2.0 * rng(&mut seed)).collect();
                let angle = match eq {
                    Equation::AbsoluteAngle => Some(4),
                    Equation::RelativeAngle => Some(8),
                    _ => None,
                };
                if let Some(a) = angle {
                    u[a] *= 2.0;
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
