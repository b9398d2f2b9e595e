//! The constant mass matrix of natural coordinates, from the kinetic energy.
//!
//! A material point of a body with body-frame coordinates (ξ, η) is at
//! r = r₁ + a e + b R e, with e = r₂ − r₁, a = ξ/L, b = η/L, L = |e| and R the
//! rotation by +90°. So r = C q_b with C = [(1−a)I − bR, aI + bR] over
//! q_b = [x₁, y₁, x₂, y₂], and T = ½ q̇_bᵀ (∫Cᵀ C dm) q̇_b. Using RᵀR = I and
//! R + Rᵀ = 0, the integral needs only the mass m, the centre (ξ_G, η_G) and the
//! polar moment I₀ about the first point:
//!
//! M₁₁ = (m − 2mξ_G/L + I₀/L²) I,  M₁₂ = (mξ_G/L − I₀/L²) I + (mη_G/L) R,
//! M₂₂ = (I₀/L²) I.
//!
//! A body on more than two points moves with its first two, which carry its mass.

use crate::scene::Body;

/// The 4×4 mass matrix of a body over [x₁, y₁, x₂, y₂] (row-major).
pub fn body_mass_matrix(body: &Body) -> [[f64; 4]; 4] {
    inertia_matrix(body, body.mass, body.i0)
}

/// [`body_mass_matrix`] of `body`'s geometry with mass `m` and polar moment `i0`:
/// linear in (m, i0), so that it gives ∂M/∂p from ∂m/∂p and ∂I₀/∂p too.
pub fn inertia_matrix(body: &Body, m: f64, i0: f64) -> [[f64; 4]; 4] {
    let l = body.length;
    let (xi, eta) = (body.cog[0], body.cog[1]);
    let j = i0 / (l * l);
    let d11 = m - 2.0 * m * xi / l + j;
    let d12 = m * xi / l - j;
    let r12 = m * eta / l;
    let d22 = j;
    // M₁₂ = d12·I + r12·R with R = [[0, −1], [1, 0]].
    [
        [d11, 0.0, d12, -r12],
        [0.0, d11, r12, d12],
        [d12, r12, d22, 0.0],
        [-r12, d12, 0.0, d22],
    ]
}

/// The generalized force of uniform gravity g on a body over [x₁, y₁, x₂, y₂]:
/// ∫Cᵀ g dm = m [(1−ā) g + b̄ R g ; ā g − b̄ R g] with ā = ξ_G/L, b̄ = η_G/L.
pub fn body_gravity_force(body: &Body, g: [f64; 2]) -> [f64; 4] {
    gravity_force(body, body.mass, g)
}

/// [`body_gravity_force`] of `body`'s geometry with mass `m`: bilinear in (m, g).
pub fn gravity_force(body: &Body, m: f64, g: [f64; 2]) -> [f64; 4] {
    let (a, b) = (body.cog[0] / body.length, body.cog[1] / body.length);
    let rg = [-g[1], g[0]];
    [
        m * ((1.0 - a) * g[0] + b * rg[0]),
        m * ((1.0 - a) * g[1] + b * rg[1]),
        m * (a * g[0] - b * rg[0]),
        m * (a * g[1] - b * rg[1]),
    ]
}

/// Global position of the centre of mass from the first two points' positions.
pub fn body_cog_position(body: &Body, r1: [f64; 2], r2: [f64; 2]) -> [f64; 2] {
    let (a, b) = (body.cog[0] / body.length, body.cog[1] / body.length);
    let e = [r2[0] - r1[0], r2[1] - r1[1]];
    [r1[0] + a * e[0] - b * e[1], r1[1] + a * e[1] + b * e[0]]
}
