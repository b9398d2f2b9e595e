//! The guess of a new step from the steps before it, shared by the forward run and
//! the estimator: a Taylor step of each (x, ẋ, ẍ) triple of the step's block.

/// Fills the triples `(offset, size)` of step k of `values` (steps of `s` unknowns,
/// step-major) from step k − 1 by x + Δt ẋ + Δt²/2 ẍ + Δt³/6 j, ẋ + Δt ẍ + Δt²/2 j,
/// ẍ + Δt j, with the jerk j from the last two accelerations (0 at step 1). A cubic
/// guess lands the first Newton step within the tolerance more often than a
/// quadratic one. The rest of the block is left as it is.
pub(crate) fn taylor_step(
    values: &mut [f64],
    k: usize,
    s: usize,
    dt: f64,
    triples: &[(usize, usize)],
) {
    let (prev, next) = values.split_at_mut(k * s);
    let older = (k >= 2).then(|| &prev[(k - 2) * s..(k - 1) * s]);
    let prev = &prev[(k - 1) * s..];
    let next = &mut next[..s];
    for &(off, d) in triples {
        for i in 0..d {
            let (x, v, a) = (prev[off + i], prev[off + d + i], prev[off + 2 * d + i]);
            let j = older.map_or(0.0, |o| (a - o[off + 2 * d + i]) / dt);
            next[off + i] = x + dt * v + 0.5 * dt * dt * a + dt * dt * dt / 6.0 * j;
            next[off + d + i] = v + dt * a + 0.5 * dt * dt * j;
            next[off + 2 * d + i] = a + dt * j;
        }
    }
}
