//! Why a run failed at a step ([`StepFailure`]): its solve did not converge, its
//! cost went non-finite, or a singular configuration lies ahead; and the message
//! that says so.

use crate::error::{Error, Result};
use crate::kinematics::SingularConfiguration;
use crate::model::Model;
use crate::solver::{SolveReport, Termination};
use crate::trajectory::round_time;

/// A step at which the run failed: its solve did not converge, or (independent
/// coordinates) the motion approached a configuration where they stop determining
/// the other coordinates.
#[derive(Debug, Clone, PartialEq)]
pub struct StepFailure {
    pub step: usize,
    pub t: f64,
    pub report: SolveReport,
    /// σ_r/σ₁ of Φ_q at the step's configuration, scaled by the coordinates' scales and
    /// row-normalized, r the constraints' rank at the start: near 0 where the
    /// mechanism approaches a singular configuration.
    pub constraint_conditioning: f64,
    /// Set when the run stopped because the independent coordinates approach a
    /// configuration where they do not determine the others (the step's own solve
    /// converged; `report` is its report).
    pub singular: Option<SingularConfiguration>,
    /// Set when the step failed in the one-step run that starts a batch solve.
    pub warm_start: bool,
    /// Set when the batch solve of the whole horizon failed (`step` is its last).
    pub batch: bool,
    /// Where the cost went non-finite: the effect that cannot be evaluated there.
    pub cause: Option<String>,
    /// The body that turns fastest over this step, from the velocities and
    /// accelerations of the step before: its name and its turn per step (rad). The
    /// message names it when the turn is more than [`StepFailure::LARGE_TURN`].
    pub fast_body: Option<(String, f64)>,
}

impl StepFailure {
    /// A turn per step (rad) beyond which a failure names the fastest body: the
    /// integrators relate positions by straight chords, and past about one radian a
    /// step the implicit equations of a coarse step stop having a nearby solution.
    pub const LARGE_TURN: f64 = 0.5;

    /// A failure found outside a window solve (a state that is not finite, a step no
    /// size converged, a stop ahead of a singular configuration): its `report`, the
    /// constraints' conditioning there, and why where that is a cause of its own.
    pub(super) fn outside_solve(
        step: usize,
        t: f64,
        report: SolveReport,
        constraint_conditioning: f64,
        cause: Option<String>,
    ) -> Self {
        StepFailure {
            step,
            t,
            report,
            constraint_conditioning,
            singular: None,
            warm_start: false,
            batch: false,
            cause,
            fast_body: None,
        }
    }

    /// Whether the step's solve converged but a body turned more than
    /// [`StepFailure::LARGE_TURN`] over it: the run is not to be trusted from there
    /// (a failure only with refinement off; by default such a run is refined).
    pub fn is_too_coarse(&self) -> bool {
        self.report.termination == Termination::Converged
            && self
                .fast_body
                .as_ref()
                .is_some_and(|(_, turn)| *turn > Self::LARGE_TURN)
    }

    /// The run's time step: t_k = k·Δt for every step of a run.
    pub fn dt(&self) -> f64 {
        self.t / self.step.max(1) as f64
    }

    /// The reason for the failure, naming the step and the time (not what was
    /// written).
    pub fn message(&self) -> String {
        let t = round_time(self.t);
        match &self.singular {
            Some(c) => format!(
                "singular configuration at t ≈ {:.6} s (extrapolated): independent coordinates \
                 [{}] stop determining [{}] (rank {} < {}); stopped at step {} (t = {t} s), \
                 distance to rank loss {:.1e}",
                c.t_singular,
                c.independent.join(", "),
                crate::expr::abbreviated(&c.dependent),
                c.rank,
                c.full_rank,
                self.step,
                c.distance
            ),
            None => {
                let singular = if self.constraint_conditioning < 1e-2 {
                    format!(
                        "; Φ_q is close to losing rank there (σ_r/σ₁ = {:.1e}): a singular \
                         configuration",
                        self.constraint_conditioning
                    )
                } else {
                    String::new()
                };
                let stage = if self.warm_start {
                    "in the one-step run that starts the batch solve, "
                } else {
                    ""
                };
                if self.batch && self.cause.is_none() {
                    return format!(
                        "the batch solve of {} steps (t = 0 to {t} s) did not converge: {}{singular}",
                        self.step + 1,
                        self.report
                    );
                }
                if let Some(cause) = &self.cause {
                    return format!(
                        "{stage}step {} (t = {t} s) cannot be solved: {cause}",
                        self.step
                    );
                }
                if let Some((body, per_step)) =
                    self.fast_body.as_ref().filter(|_| self.is_too_coarse())
                {
                    return format!(
                        "step {} (t = {t} s) is too coarse for the motion: body {body} turns \
                         about {per_step:.2} rad over it, where the integrators' chords no \
                         longer follow the motion (dt below {:.2e} s keeps it under {} rad)",
                        self.step,
                        self.dt() * Self::LARGE_TURN / per_step,
                        Self::LARGE_TURN
                    );
                }
                let turn = match &self.fast_body {
                    Some((body, per_step)) if *per_step > Self::LARGE_TURN => format!(
                        "; body {body} turns about {per_step:.2} rad over the step: the step is \
                         too coarse for the motion (dt below {:.2e} s keeps it under {} rad)",
                        self.dt() * Self::LARGE_TURN / per_step,
                        Self::LARGE_TURN
                    ),
                    _ => String::new(),
                };
                format!(
                    "{stage}step {} (t = {t} s) did not converge: {}{singular}{turn}",
                    self.step, self.report
                )
            }
        }
    }
}

/// Whether step k's state (`row`, at time t) is not finite (a solve that "converged"
/// on an overflowing force): a failure naming the cause, found with the state of the
/// step before (`before`); an error when it is the initial state.
pub(super) fn non_finite_at(
    model: &Model,
    k: usize,
    t: f64,
    row: (&[f64], &[f64], &[f64]),
    before: (&[f64], &[f64]),
) -> Result<Option<StepFailure>> {
    let (q, dq, ddq) = row;
    if q.iter().chain(dq).chain(ddq).all(|v| v.is_finite()) {
        return Ok(None);
    }
    let (q, dq) = if k > 0 { before } else { (q, dq) };
    let cause = model.effect_fault(q, dq, t).unwrap_or_else(|| {
        "the state is not finite: the forces or the accelerations overflow".into()
    });
    if k == 0 {
        return Err(Error::singular(format!(
            "{}: the initial state cannot be used: {cause}",
            model.scene.file
        )));
    }
    Ok(Some(StepFailure::outside_solve(
        k,
        t,
        SolveReport::new(Termination::Diverged, 0, f64::INFINITY),
        1.0,
        Some(cause),
    )))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn failure(batch: bool, cause: Option<&str>) -> StepFailure {
        StepFailure {
            step: 100,
            t: 1.0000000000000002,
            report: SolveReport::new(Termination::IterationLimit, 50, 3.3),
            constraint_conditioning: 0.5,
            singular: None,
            warm_start: false,
            batch,
            cause: cause.map(str::to_string),
            fast_body: None,
        }
    }

    #[test]
    fn failures_say_what_failed() {
        assert_eq!(
            failure(false, None).message(),
            "step 100 (t = 1 s) did not converge: iteration limit, cost 3.300e0 after 50 iterations"
        );
        assert_eq!(
            failure(true, None).message(),
            "the batch solve of 101 steps (t = 0 to 1 s) did not converge: iteration limit, \
             cost 3.300e0 after 50 iterations"
        );
        assert_eq!(
            failure(false, Some("effect e is not finite")).message(),
            "step 100 (t = 1 s) cannot be solved: effect e is not finite"
        );
    }
}
