//! The dynamics kernel of the factors ([`DynamicsKernel`]): what it computes, and
//! the constants of its regularization near a singular configuration. Its
//! evaluation is in `augmented`, its singularity measure in `regularization`, its
//! directional products in `along`.

/// Forward dynamics q̈(q, q̇, t) by the augmented system, and optionally its exact
/// Jacobians, without allocating.
///
/// With K = [M Aᵀ; A −E] (A: the active rows of Φ_q, E = diag(εₖ), see below) and
/// [q̈; λ] = K⁻¹[Q; c]:
///   K [∂q̈/∂q; ∂λ/∂q] = [∂Q/∂q − ∂(Φ_qᵀλ)/∂q; −∂(Φ̇_q q̇)/∂q − Φ_qq q̈ + E_q λ]
///   K [∂q̈/∂q̇; ∂λ/∂q̇] = [∂Q/∂q̇; −2 Φ̇_q]
/// (rows of the right-hand sides restricted to the active constraints; row k of
/// E_q λ is λₖ ∂εₖ/∂q).
///
/// **Singular configurations.** Where Φ_q is regular, E = 0: the KKT system of the
/// paper (eq. "qDynSys"), computed exactly. Where Φ_q loses a rank (the
/// parallelogram's flat configurations) K is singular, and near it the KKT q̈
/// answers a velocity off the constraint manifold by round-off with an acceleration
/// 1/σ larger (σ the smallest singular value of Φ_q); the hard constraints cannot
/// remove that round-off there (they fix the velocity along the lost rank only to
/// ε_mach/σ²), ∂q̈/∂q grows like 1/σ, and K no longer factors below σ ≈ 1e-8. So
/// near rank loss the bottom block is −E with εₖ = w(s) ε_rel ‖aₖ‖²/m̄ (aₖ row k of
/// A, m̄ the largest diagonal entry of M): the Tikhonov-regularized (penalty) form
/// (M + AᵀE⁻¹A) q̈ = Q + AᵀE⁻¹c, regular at every configuration, with a bounded
/// response to such velocities, and within O(ε/σ²) of the KKT q̈ where σ² ≫ ε.
/// s = (tr G⁻¹)^(−1/2), G = ÂÂᵀ with Â the rows of A normalized, measures the
/// distance to rank loss (√λ_min(G/m) ≤ s ≤ √λ_min(G)); w = 0 above
/// [`DynamicsKernel::REGULAR_ABOVE`], 1 below [`DynamicsKernel::SINGULAR_BELOW`] and
/// the cubic 1 − x²(3 − 2x) of x = log(s/below)/log(above/below) between, so q̈ is C¹
/// and the Jacobians above exact everywhere.
pub struct DynamicsKernel;

impl DynamicsKernel {
    /// ε_rel: εₖ = w ε_rel ‖aₖ‖²/m̄, in the middle of the range that passes the
    /// parallelogram's flat points (`docs/dc-stall.md`, "9. How much regularization,
    /// and from where").
    pub const REGULARIZATION: f64 = 1e-6;
    /// Below this s the regularization is full (w = 1).
    pub const SINGULAR_BELOW: f64 = 1e-4;
    /// At or above this s the system is the plain KKT system (w = 0). With the
    /// damped corrections of [`crate::linalg::nullspace::NullSpace`] the KKT system
    /// serves down to s ≈ 1e-4; the top stays below the regular motion of every
    /// scene, so that regularization never changes a regular run (`docs/dc-stall.md`,
    /// "9. How much regularization, and from where").
    pub const REGULAR_ABOVE: f64 = 1e-3;
}
