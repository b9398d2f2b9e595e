//! A step that ends next to a rank loss of Φ_q (a flat configuration of the N
//! four-bar, a parallelogram's crossing point), taken by a longer step that
//! clears it.
//!
//! Near a rank loss the step's multipliers grow like 1/σ (σ the smallest singular
//! value of Φ_q: the constraint forces that keep a loop on its branch act through
//! nearly parallel rows) and the step system's condition like 1/σ². A step whose
//! end lands within [`near`] of the rank loss is solved only to that rounding
//! amplified: a jump in the energy, and a shift of the phase after it, whatever
//! the step size. The motion itself is smooth there. So the run takes the
//! shortest step longer than Δt whose end lies clear (of r·Δt, r from
//! [`LENGTHS`]) and, where that end is off the grid, a second step back onto it;
//! the states at the grid times in between are Hermite interpolants of the
//! steps' ends ([`hermite`]), and are not stepped from. The shortest such step
//! keeps the passage's error that of about one step: a step of 2Δt or more made
//! with Hermite–Simpson errs 2⁵ = 32 times one of Δt, and at 8Δt 32,768 times.

use super::system::System;
use super::{SquareStep, StepLimits, StepWork};
use crate::dynamics::DynamicsKernel;

/// The distance to a rank loss of the rows nearest one, (max (G⁻¹)ᵢᵢ)^(−1/2), below
/// which a step's end is stepped over, by the step's integrator. Closer, the step
/// system's condition grows like the inverse square of that distance: Newton's
/// iteration ends at a residual at rounding whose updates are still large along the
/// lost rank, and the energy moves by an amount that does not fall with Δt. A step
/// over errs like its length to the power of its order, so the zone is as wide as
/// the coarse steps' passages allow: wider for Hermite–Simpson, whose steps err
/// least and whose landings err most; far narrower where the step damps its
/// projections (`damps`: a Hermite–Simpson DC step), whose landings
/// are resolved.
pub(super) fn near(system: &System, damps: bool) -> f64 {
    if damps {
        return NEAR_DAMPED;
    }
    match system.staged() {
        true => NEAR_HERMITE_SIMPSON,
        false => NEAR_TRAPEZOIDAL,
    }
}

/// [`near`] of a step with damped projections ([`System::row_damping`]): they
/// leave the lost rank to the integrators, so that a landing is resolved however
/// near it lies, except for its accelerations, whose constraint stays exact and
/// whose lost component is the drift of q̇ divided by the distance.
const NEAR_DAMPED: f64 = 1e-5;

/// [`near`] of a Hermite–Simpson step.
const NEAR_HERMITE_SIMPSON: f64 = 2e-4;
/// [`near`] of a trapezoidal or Euler step.
const NEAR_TRAPEZOIDAL: f64 = 1e-4;

/// The lengths tried for the step over a rank loss, in steps, shortest first: at
/// coarse steps the zone within 2·[`near`] is a small part of one step, at 0.1 ms
/// the N four-bar's measure moves by 1e-4 (40 loops) to 4e-4 (one) a step (the
/// longest, 64, clears far more). An off-grid length is followed by a step of at
/// least Δt/2 back onto the grid.
const LENGTHS: [f64; 20] = [
    1.5, 2.0, 2.5, 3.0, 3.5, 4.0, 5.0, 6.0, 7.0, 8.0, 10.0, 12.0, 16.0, 20.0, 24.0, 32.0, 40.0,
    48.0, 56.0, 64.0,
];

/// The steps of a passage: a square step (the sparse analysis of the run's) whose
/// length is set for each; and the long step under way.
#[derive(Default)]
pub(super) struct Passage {
    over: Option<Box<SquareStep>>,
    /// The long step under way: its pieces (one, or the step over and the one back
    /// onto the grid), each from its start (time, state) over its length to its end.
    under_way: Option<LongStep>,
    /// The state handed out last (q, q̇, q̈): the next step is the long step's
    /// only where it is given this state as the step before.
    last: Vec<f64>,
}

struct LongStep {
    pieces: Vec<Piece>,
    /// Whether its steps are Hermite–Simpson's (how its rows' q̇ is interpolated:
    /// [`hermite`]).
    staged: bool,
}

struct Piece {
    t0: f64,
    start: Vec<f64>,
    h: f64,
    /// The whole block at the piece's end.
    end: Vec<f64>,
}

impl LongStep {
    fn t0(&self) -> f64 {
        self.pieces[0].t0
    }

    fn length(&self) -> f64 {
        let last = &self.pieces[self.pieces.len() - 1];
        last.t0 + last.h - self.t0()
    }
}

/// What a passage did with a step.
pub(super) enum Passed {
    /// The step was interpolated within a long step, or is its end.
    Taken(StepWork),
    /// No long step is under way for this step.
    NotUnderWay,
}

impl Passage {
    /// Whether a long step is under way: the next steps it spans are its
    /// interpolants, and its end.
    pub(super) fn under_way(&self) -> bool {
        self.under_way.is_some()
    }

    /// Step `block` at time `t`, given `before`, where a long step under way
    /// spans it: interpolated, or at its end, that end.
    pub(super) fn resume(&mut self, t: f64, before: &[f64], block: &mut [f64], n: usize) -> Passed {
        let Some(long) = self.under_way.as_ref() else {
            return Passed::NotUnderWay;
        };
        let (t0, length) = (long.t0(), long.length());
        let tau = t - t0;
        let spanned = tau > 0.0 && tau <= length * (1.0 + 1e-9);
        if !spanned || before[..3 * n] != self.last[..] {
            self.under_way = None;
            return Passed::NotUnderWay;
        }
        let last = long.pieces.len() - 1;
        if tau >= length * (1.0 - 1e-9) {
            block.copy_from_slice(&long.pieces[last].end);
            self.under_way = None;
        } else {
            // The piece that spans τ (a grid time on the seam between two takes the
            // first's end).
            let piece = long
                .pieces
                .iter()
                .find(|p| t - p.t0 <= p.h * (1.0 + 1e-9))
                .unwrap_or(&long.pieces[last]);
            block.copy_from_slice(&long.pieces[last].end);
            let local = (t - piece.t0).min(piece.h);
            let ends = (&piece.start[..], &piece.end[..3 * n]);
            hermite(ends, piece.h, local, n, long.staged, block);
        }
        self.last.clear();
        self.last.extend_from_slice(&block[..3 * n]);
        Passed::Taken(StepWork {
            iterations: 0,
            factorizations: 0,
        })
    }

    /// Step `block` at time `t` given `before` (Δt earlier), within the shortest
    /// step of [`LENGTHS`] from `before` that converges and ends at least 2·[`near`]
    /// from a rank loss, then back onto the grid (kept to hand out the steps they
    /// span); the work of the steps tried, or `None` where none does.
    pub(super) fn start(
        &mut self,
        square: &SquareStep,
        t: f64,
        before: &[f64],
        block: &mut [f64],
        limits: StepLimits,
    ) -> Option<StepWork> {
        let system = &square.equations.system;
        let n = system.model.n();
        let dt = system.dt;
        let t0 = t - dt;
        let near = near(system, square.may_damp());
        let mut total = StepWork {
            iterations: 0,
            factorizations: 0,
        };
        let mut add = |work: StepWork| {
            total.iterations += work.iterations;
            total.factorizations += work.factorizations;
        };
        let mut far = block.to_vec();
        for r in LENGTHS {
            let h = r * dt;
            let Some((work, clearance)) = self.step(square, t0, h, before, &mut far, limits) else {
                continue;
            };
            add(work);
            if clearance < 2.0 * near {
                continue;
            }
            let mut pieces = vec![Piece {
                t0,
                start: before[..3 * n].to_vec(),
                h,
                end: far.clone(),
            }];
            let steps = r.ceil();
            if steps > r {
                // Back onto the grid, from the end of the step over.
                let back = (steps - r) * dt;
                let mut grid = far.clone();
                let Some((work, clearance)) =
                    self.step(square, t0 + h, back, &far, &mut grid, limits)
                else {
                    continue;
                };
                add(work);
                if clearance < 2.0 * near {
                    continue;
                }
                pieces.push(Piece {
                    t0: t0 + h,
                    start: far[..3 * n].to_vec(),
                    h: back,
                    end: grid,
                });
            }
            self.under_way = Some(LongStep {
                pieces,
                staged: system.staged(),
            });
            self.last.clear();
            self.last.extend_from_slice(&before[..3 * n]);
            if let Passed::NotUnderWay = self.resume(t, before, block, n) {
                return None;
            }
            return Some(total);
        }
        None
    }

    /// One step of length `h` from `from` at `t0` into `to` (its guess the Taylor
    /// one), by the passage's square step set to that length: its work and its
    /// end's distance to a rank loss (0 where, within
    /// [`DynamicsKernel::REGULAR_ABOVE`] of one, its solution is not resolved to the
    /// step tolerance), or `None` where it does not converge.
    fn step(
        &mut self,
        square: &SquareStep,
        t0: f64,
        h: f64,
        from: &[f64],
        to: &mut [f64],
        limits: StepLimits,
    ) -> Option<(StepWork, f64)> {
        let n = square.equations.system.model.n();
        let over = match &mut self.over {
            Some(over) => over,
            none => none.insert(Box::new(square.at_dt(h)?)),
        };
        over.set_dt(h);
        // A step over lands near a rank loss: damped where its system damps.
        over.work.near_rank_loss = over.may_damp();
        taylor(&from[..3 * n], &mut to[..3 * n], n, h);
        let work = over.solve_plain(t0 + h, from, to, limits)?;
        let clearance = over.clearance(from, to);
        if clearance < DynamicsKernel::REGULAR_ABOVE && !over.resolved(t0 + h, from, limits) {
            return Some((work, 0.0));
        }
        Some((work, clearance))
    }
}

/// The Taylor guess of the state h after `before` (q, q̇, q̈ of n coordinates).
fn taylor(before: &[f64], out: &mut [f64], n: usize, h: f64) {
    for i in 0..n {
        let (x, v, a) = (before[i], before[n + i], before[2 * n + i]);
        out[i] = x + h * v + 0.5 * h * h * a;
        out[n + i] = v + h * a;
        out[2 * n + i] = a;
    }
}

/// q, q̇, q̈ at τ after `start`, into `out[..3n]`, from the long step's two ends
/// (`start`, `end`): q on the quintic that matches q, q̇, q̈ at both, q̈ on the
/// cubic q̇ that matches q̇ and q̈ at both, and q̇ on that cubic, or with
/// Hermite–Simpson (`staged`) the quintic's derivative. (A trapezoidal tangent
/// step holds its integrators along the tangent space only: its q and q̇ agree
/// with the rule per coordinate only to ~1e-7 of q̇ near a rank loss, which a
/// quintic's q̇ carries into |Φ_q q̇| (3.5e-10 against 5.6e-11 on five loops at
/// 0.1 ms). Hermite–Simpson's ends agree to its order, and there the cubic's q̇,
/// built on accelerations solved next to the rank loss, is the worse: |Φ_q q̇|
/// 1.6e-8 at 2.5 ms and 5.8e-10 at 0.1 ms against 1e-11 for the quintic's.)
fn hermite(ends: (&[f64], &[f64]), h: f64, tau: f64, n: usize, staged: bool, out: &mut [f64]) {
    let (start, end) = ends;
    let (h2, h3) = (h * h, h * h * h);
    let (t1, t2, t3) = (tau, tau * tau, tau * tau * tau);
    for i in 0..n {
        let (p0, v0, a0) = (start[i], start[n + i], start[2 * n + i]);
        let (p1, v1, a1) = (end[i], end[n + i], end[2 * n + i]);
        // p(τ) = p0 + v0 τ + a0 τ²/2 + c3 τ³ + c4 τ⁴ + c5 τ⁵, with the end conditions
        // on the remainders A (position), B = h·(velocity), C = h²·(acceleration).
        let a = p1 - (p0 + v0 * h + 0.5 * a0 * h2);
        let b = (v1 - (v0 + a0 * h)) * h;
        let c = (a1 - a0) * h2;
        let c3 = (10.0 * a - 4.0 * b + 0.5 * c) / h3;
        let c4 = (-15.0 * a + 7.0 * b - c) / (h3 * h);
        let c5 = (6.0 * a - 3.0 * b + 0.5 * c) / (h3 * h2);
        out[i] = p0 + v0 * t1 + 0.5 * a0 * t2 + c3 * t3 + c4 * t3 * t1 + c5 * t3 * t2;
        // v(τ) = v0 + a0 τ + d2 τ² + d3 τ³ through v1, a1 at h.
        let (dv, da) = (v1 - v0 - a0 * h, (a1 - a0) * h);
        let d2 = (3.0 * dv - da) / h2;
        let d3 = (da - 2.0 * dv) / h3;
        out[n + i] = match staged {
            true => v0 + a0 * t1 + 3.0 * c3 * t2 + 4.0 * c4 * t3 + 5.0 * c5 * t3 * t1,
            false => v0 + a0 * t1 + d2 * t2 + d3 * t3,
        };
        out[2 * n + i] = a0 + 2.0 * d2 * t1 + 3.0 * d3 * t2;
    }
}

#[cfg(test)]
mod tests {
    use super::hermite;

    /// q through a quintic's ends is that quintic and q̈ through a cubic q̇'s ends
    /// that cubic's derivative, at every τ; q̇ is the cubic for a two-point rule's
    /// steps, and the quintic's derivative for Hermite–Simpson's.
    #[test]
    fn hermite_reproduces_a_quintic_and_a_cubic() {
        let p = |t: f64| {
            0.3 - 1.1 * t + 0.7 * t * t + 2.0 * t.powi(3) - 0.4 * t.powi(4) + 0.9 * t.powi(5)
        };
        let v = |t: f64| -1.1 + 1.4 * t + 6.0 * t * t - 1.6 * t.powi(3) + 4.5 * t.powi(4);
        let a = |t: f64| 1.4 + 12.0 * t - 4.8 * t * t + 18.0 * t.powi(3);
        let w = |t: f64| 0.5 - 2.0 * t + 3.0 * t * t - 0.7 * t.powi(3);
        let dw = |t: f64| -2.0 + 6.0 * t - 2.1 * t * t;
        let h = 0.8;
        // Coordinate 0 moves on the quintic, coordinate 1's speed on the cubic.
        let start = [p(0.0), 0.0, v(0.0), w(0.0), a(0.0), dw(0.0)];
        let end = [p(h), 0.0, v(h), w(h), a(h), dw(h)];
        for tau in [0.0, 0.1, 0.35, 0.8] {
            for staged in [false, true] {
                let mut out = [0.0; 6];
                hermite((&start, &end), h, tau, 2, staged, &mut out);
                assert!((out[0] - p(tau)).abs() < 1e-13, "q at {tau}");
                assert!((out[5] - dw(tau)).abs() < 1e-12, "q̈ at {tau}");
                match staged {
                    true => assert!((out[2] - v(tau)).abs() < 1e-12, "q̇ at {tau}"),
                    false => assert!((out[3] - w(tau)).abs() < 1e-13, "q̇ at {tau}"),
                }
            }
        }
    }
}
