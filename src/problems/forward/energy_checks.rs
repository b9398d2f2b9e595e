//! Checks on a run's result, beyond convergence, each reported with its numbers:
//! energy that a conservative scene should keep but did not, a passage through a
//! singular configuration that moved it, and a run with non-conservative effects
//! off its energy balance, and a run whose rows' estimated error exceeds the
//! tolerance asked. `mbfg simulate --strict` makes them errors. The checks
//! on the model before a run are in [`crate::model::plausibility`].

use crate::forward::{Integrator, Passages, RunSummary};

/// The largest energy drift of a conservative scene, as a fraction of the largest
/// kinetic energy along the run, that is still taken as integration error.
pub const ENERGY_DRIFT_TOLERANCE: f64 = 0.01;

/// The drift, in J, below which no energy warning is given (round-off).
pub const ENERGY_DRIFT_FLOOR: f64 = 1e-12;

/// A warning when a conservative scene's energy drifted beyond
/// [`ENERGY_DRIFT_TOLERANCE`] of its largest kinetic energy.
pub fn energy_warning(summary: &RunSummary) -> Option<String> {
    let drift = summary.energy_drift?;
    let scale = summary.peak_kinetic_energy;
    // Below a picojoule the drift is round-off of a mechanism barely moving.
    if !(drift > ENERGY_DRIFT_TOLERANCE * scale && drift > ENERGY_DRIFT_FLOOR) {
        return None;
    }
    Some(format!(
        "the energy of this conservative scene drifted by {drift:.3e} J, {:.1} % of its \
         largest kinetic energy {scale:.3e} J (tolerance {} %): the step is too coarse \
         for the motion",
        100.0 * drift / scale.max(f64::MIN_POSITIVE),
        100.0 * ENERGY_DRIFT_TOLERANCE
    ))
}

/// A warning when a conservative scene's energy changed across a passage through a
/// singular configuration by more than [`Passages::ENERGY_JUMP_TOLERANCE`] of its
/// largest kinetic energy: the motion after it is not the one before it continued.
pub fn passage_warning(summary: &RunSummary) -> Option<String> {
    let (jump, t) = summary.passages.energy_jump?;
    let scale = summary.peak_kinetic_energy;
    if !(jump > Passages::ENERGY_JUMP_TOLERANCE * scale && jump > ENERGY_DRIFT_FLOOR) {
        return None;
    }
    Some(format!(
        "the energy changed by {jump:.3e} J ({:.2e} of the largest kinetic energy \
         {scale:.3e} J, tolerance {:.0e}) across the passage through a singular \
         configuration at t = {} s: the step is too coarse for the passage",
        jump / scale.max(f64::MIN_POSITIVE),
        Passages::ENERGY_JUMP_TOLERANCE,
        crate::trajectory::round_time(t)
    ))
}

/// A warning when a run with non-conservative effects did not keep its energy
/// balance: kinetic + potential energy against the work of those effects
/// ([`RunSummary::energy_balance`]) off by more than [`ENERGY_DRIFT_TOLERANCE`] of
/// the largest kinetic energy or work, with every integrator and in both coordinate
/// kinds. Every step converges all the same: the equations are solved, and the
/// integrator's are wrong by that much (`docs/cli.md` shows Andrews' squeezer with
/// explicit Euler). Conservative scenes get the energy drift warning.
pub fn balance_warning(summary: &RunSummary) -> Option<String> {
    let off = summary.energy_balance?;
    let scale = summary.peak_kinetic_energy.max(off.peak_work);
    if !(off.worst > ENERGY_DRIFT_TOLERANCE * scale && off.worst > ENERGY_DRIFT_FLOOR) {
        return None;
    }
    let fix = match summary.plan.integrator {
        Integrator::Euler => "the trapezoidal rule or a smaller dt keeps it",
        Integrator::Trapezoidal => "a smaller dt, or --integrator hermite-simpson, keeps it",
        Integrator::HermiteSimpson => "a smaller dt keeps it",
    };
    Some(format!(
        "the energy balance (integrator {}) is off by {:.3e} J at t = {} s, {:.1} % of the \
         largest kinetic energy or work {scale:.3e} J (tolerance {} %): the motion may be \
         wrong though every step converged ({fix})",
        summary.plan.integrator.name(),
        off.worst,
        crate::trajectory::round_time(off.t),
        100.0 * off.worst / scale.max(f64::MIN_POSITIVE),
        100.0 * ENERGY_DRIFT_TOLERANCE
    ))
}

/// A warning when a run with a tolerance on its rows ended with their estimated
/// error above it: the runs made again at tighter step tolerances, as many as are
/// made, did not bring it down (the motion amplifies the steps' errors more than
/// that, or the run's own rounding is the error).
pub fn tolerance_warning(summary: &RunSummary) -> Option<String> {
    let c = summary.error_control.as_ref()?;
    let check = c.check.as_ref()?;
    let estimated = check.estimated?;
    if estimated <= 1.0 {
        return None;
    }
    Some(format!(
        "the rows' estimated error is {estimated:.1} times the tolerance (rtol {:.1e}, atol \
         {:.1e}) after {} run(s) down to a step rtol of {:.1e}: the motion amplifies the \
         steps' errors more than a tighter step tolerance makes up for; a fixed --dt, \
         checked against one twice as fine, says how accurate its rows are",
        c.tolerance.rtol,
        c.tolerance.atol,
        check.step_rtols.len(),
        check.step_rtols.last().copied().unwrap_or(c.tolerance.rtol)
    ))
}
