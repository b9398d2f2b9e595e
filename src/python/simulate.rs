//! `mbfg.simulate`: forward dynamics, its arguments checked, and its result (the
//! table, the summary, the failures and the warnings) as a dict.

use super::args::{arg_bool, arg_choice, arg_count, arg_real, arg_str, arg_values};
use super::effects::{arg_effects, interrupted, is_interrupted, raised, with_loads};
use super::errors::{arg_error, guard, invalid, SolveError};
use super::failure::{error_failure, step_failure, with_failure};
use super::model::study_model;
use super::run::{coordinates, interruptible, run_table, with_result};
use crate::forward::{
    self, DcIntegrators, ForwardOptions, Integrator, NoiseModels, RunSummary, Schedule, Trajectory,
};
use crate::smoother::Mode;
use crate::solver::Past;
use crate::Error;
use numpy::PyArray1;
use pyo3::exceptions::PyRuntimeError;
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};
use std::ops::ControlFlow;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

/// A forward run's result, complete or not: `requested` is the number of steps asked
/// for, so that a partial one says so in its summary.
fn forward_result<'py>(
    py: Python<'py>,
    tr: &Trajectory,
    s: &RunSummary,
    requested: usize,
) -> PyResult<Bound<'py, PyDict>> {
    let out = run_table(py, tr, None)?;
    let summary = PyDict::new(py);
    summary.set_item("steps", s.steps)?;
    summary.set_item("requested_steps", requested)?;
    summary.set_item("wall_time", s.wall_time.as_secs_f64())?;
    summary.set_item("mean_iterations", s.mean_iterations)?;
    summary.set_item("mean_factorizations", s.mean_factorizations)?;
    summary.set_item("max_iterations", s.max_iterations)?;
    summary.set_item("worst_phi", s.worst_phi)?;
    summary.set_item("worst_velocity_constraint", s.worst_velocity_constraint)?;
    summary.set_item("energy_drift", s.energy_drift)?;
    summary.set_item("conditioned_from", s.conditioned_from)?;
    // What ran: the schedule (one step at a time where a window or batch asked of
    // a square graph has that solution), the integrator factors, the solvers.
    let plan = PyDict::new(py);
    plan.set_item("schedule", schedule_name(s.plan.schedule))?;
    plan.set_item(
        "window",
        match s.plan.schedule {
            Schedule::FixedLag(n) => Some(n),
            Schedule::Stepwise => Some(1),
            Schedule::Batch => None,
        },
    )?;
    plan.set_item(
        "asked",
        match s.plan.asked {
            Mode::FixedLag(n) => format!("window {n}"),
            Mode::Batch => "batch".to_string(),
        },
    )?;
    plan.set_item("description", s.plan.describe())?;
    plan.set_item("square_step", s.plan.square_step)?;
    plan.set_item("dt", s.plan.dt)?;
    plan.set_item("integrator", s.plan.integrator.name())?;
    plan.set_item(
        "dc_integrators",
        s.plan
            .dc_integrators
            .map(|d| format!("{d:?}").to_lowercase()),
    )?;
    plan.set_item("past", format!("{:?}", s.plan.settings.past).to_lowercase())?;
    plan.set_item(
        "rescues",
        s.plan
            .rescues
            .iter()
            .map(|r| format!("{r:?}"))
            .collect::<Vec<_>>(),
    )?;
    summary.set_item("plan", plan)?;
    summary.set_item("square_steps", s.square_steps)?;
    summary.set_item("general_steps", s.general_steps)?;
    summary.set_item("paper_steps", s.paper_steps)?;
    let passages = PyDict::new(py);
    passages.set_item("count", s.passages.count)?;
    passages.set_item("first", s.passages.first.map(crate::trajectory::round_time))?;
    passages.set_item(
        "worst_velocity_constraint",
        s.passages.worst_velocity_constraint,
    )?;
    passages.set_item("energy_jump", s.passages.energy_jump.map(|(j, _)| j))?;
    passages.set_item(
        "energy_jump_t",
        s.passages
            .energy_jump
            .map(|(_, t)| crate::trajectory::round_time(t)),
    )?;
    summary.set_item("passages", passages)?;
    let error_control = match &s.error_control {
        Some(c) => {
            let d = PyDict::new(py);
            d.set_item("rtol", c.tolerance.rtol)?;
            d.set_item("atol", c.tolerance.atol)?;
            d.set_item("accepted", c.accepted)?;
            d.set_item("rejected", c.rejected)?;
            d.set_item("failed_solves", c.failed_solves)?;
            d.set_item("smallest_step", c.smallest)?;
            d.set_item("largest_step", c.largest)?;
            d.set_item("at_floor", c.at_floor)?;
            d.set_item("damped", c.damped)?;
            let check = c.check.as_ref();
            d.set_item("estimated_error", check.and_then(|k| k.estimated))?;
            d.set_item("step_rtols", check.map(|k| k.step_rtols.clone()))?;
            d.set_item("unchecked", check.and_then(|k| k.unchecked.clone()))?;
            Some(d)
        }
        None => None,
    };
    summary.set_item("error_control", error_control)?;
    // Kept for scripts that read them: no run is made again with other integrator
    // factors (a step the tangent ones fail is taken by the paper's, `paper_steps`).
    summary.set_item("tangent_after", py.None())?;
    summary.set_item("full_after", py.None())?;
    let refinement = match &s.refinement {
        Some(r) => {
            let d = PyDict::new(py);
            d.set_item("factor", r.factor)?;
            d.set_item("dt", r.dt)?;
            d.set_item("after", (r.after.step, r.after.t))?;
            d.set_item("message", r.after.message())?;
            Some(d)
        }
        None => None,
    };
    summary.set_item("refinement", refinement)?;
    let reselections = PyList::empty(py);
    for r in &s.reselections {
        let d = PyDict::new(py);
        d.set_item("step", r.step)?;
        d.set_item("t", r.t)?;
        d.set_item("from", &r.from)?;
        d.set_item("to", &r.to)?;
        reselections.append(d)?;
    }
    summary.set_item("reselections", reselections)?;
    let converged = s.failures.is_empty();
    summary.set_item("converged", converged)?;
    summary.set_item("interrupted", s.interrupted)?;
    summary.set_item(
        "complete",
        converged && s.interrupted.is_none() && tr.len() == requested,
    )?;
    out.set_item("summary", summary)?;
    let failures = PyList::empty(py);
    for f in &s.failures {
        let d = PyDict::new(py);
        d.set_item("step", f.step)?;
        d.set_item("t", f.t)?;
        let reason = match f.singular {
            Some(_) => "singular configuration".to_string(),
            None => f.report.termination.to_string(),
        };
        d.set_item("reason", reason)?;
        d.set_item("cost", f.report.cost)?;
        failures.append(d)?;
    }
    out.set_item("failures", failures)?;
    Ok(out)
}

/// Forward dynamics. Every argument is required (`mbfg.simulate` gives the defaults).
#[pyfunction]
#[pyo3(name = "simulate")]
#[allow(clippy::too_many_arguments)] // the CLI's options, one keyword each
pub(super) fn simulate_run<'py>(
    py: Python<'py>,
    scene: &Bound<'py, PyAny>,
    coords: &Bound<'py, PyAny>,
    dt: &Bound<'py, PyAny>,
    t_end: &Bound<'py, PyAny>,
    window: &Bound<'py, PyAny>,
    batch: &Bound<'py, PyAny>,
    max_iterations: &Bound<'py, PyAny>,
    integrator: &Bound<'py, PyAny>,
    noise: &Bound<'py, PyAny>,
    continue_on_failure: &Bound<'py, PyAny>,
    past: &Bound<'py, PyAny>,
    dc_integrators: &Bound<'py, PyAny>,
    refine: &Bound<'py, PyAny>,
    params: &Bound<'py, PyAny>,
    q0: &Bound<'py, PyAny>,
    dq0: &Bound<'py, PyAny>,
    effects: &Bound<'py, PyAny>,
    square_steps: &Bound<'py, PyAny>,
    columns: &Bound<'py, PyAny>,
    until: &Bound<'py, PyAny>,
    rtol: &Bound<'py, PyAny>,
    atol: &Bound<'py, PyAny>,
    tolerance_scope: &Bound<'py, PyAny>,
) -> PyResult<Bound<'py, PyDict>> {
    guard(|| {
        let tolerance = match rtol.is_none() {
            true if !atol.is_none() => return Err(invalid("atol is given without rtol")),
            true => None,
            false => {
                let atol = match atol.is_none() {
                    true => None,
                    false => Some(arg_real(atol, "atol")?),
                };
                Some(
                    forward::Tolerance::new(arg_real(rtol, "rtol")?, atol)
                        .map_err(|e| invalid(e.to_string()))?,
                )
            }
        };
        let scope = arg_str(tolerance_scope, "tolerance_scope")?;
        let scope = forward::ToleranceScope::parse(&scope).ok_or_else(|| {
            invalid(format!(
                "tolerance_scope must be \"run\" or \"steps\", got {scope:?}"
            ))
        })?;
        let until = match until.is_none() {
            true => None,
            false => Some(arg_str(until, "until")?),
        };
        // The CLI's optional column groups (`--columns`), as a list of names.
        let groups = match columns.is_none() {
            true => Vec::new(),
            false => {
                let names: Vec<String> = columns.extract().map_err(|_| {
                    invalid("columns must be a list of group names (bodies, energy, joints)")
                })?;
                crate::derived::Group::parse_list(&names.join(","))
                    .map_err(|e| invalid(e.replace("--columns", "columns")))?
            }
        };
        let loads = arg_effects(effects)?;
        let params = arg_values(Some(params), "params")?;
        let q0 = arg_values(Some(q0), "q0")?;
        let dq0 = arg_values(Some(dq0), "dq0")?;
        let coordinates = coordinates(coords)?;
        let dt = arg_real(dt, "dt")?;
        if dt <= 0.0 {
            return Err(invalid(format!(
                "dt: the time step must be positive, got {dt}"
            )));
        }
        let t_end = arg_real(t_end, "t_end")?;
        if t_end < dt {
            return Err(invalid(format!(
                "t_end must be at least one time step (dt = {dt}), got {t_end}"
            )));
        }
        let window = arg_count(window, "window", 1)?;
        let batch = arg_bool(batch, "batch")?;
        let max_iterations = arg_count(max_iterations, "max_iterations", 1)?;
        let integrators = Integrator::ALL.map(Integrator::name);
        let integrator = arg_choice(integrator, "integrator", &integrators)?;
        let noise = arg_choice(noise, "noise", &["default", "paper"])?;
        let continue_on_failure = arg_bool(continue_on_failure, "continue_on_failure")?;
        let refine = arg_bool(refine, "refine")?;
        let square_steps = arg_bool(square_steps, "square_steps")?;
        let past = arg_choice(past, "past", &["adaptive", "conditioned", "marginalized"])?;
        let dc_integrators = arg_choice(
            dc_integrators,
            "dc_integrators",
            &["auto", "tangent", "full"],
        )?;

        let mode = if batch {
            Mode::Batch
        } else {
            Mode::FixedLag(window)
        };
        let mut options = ForwardOptions::new(coordinates, dt, t_end, mode);
        options.integrator = Integrator::from_name(integrator).expect("a listed name");
        options.dc_integrators = match dc_integrators {
            "auto" => DcIntegrators::Auto,
            "tangent" => DcIntegrators::Tangent,
            _ => DcIntegrators::Full,
        };
        options.noise = match noise {
            "default" => NoiseModels::default(),
            _ => NoiseModels::paper(),
        };
        options.settings.max_iterations = max_iterations;
        options.settings.past = match past {
            "adaptive" => Past::Adaptive,
            "conditioned" => Past::Conditioned,
            _ => Past::Marginalized,
        };
        options.continue_on_failure = continue_on_failure;
        options.refine = refine;
        options.square_steps = square_steps;
        options.tolerance = tolerance;
        options.tolerance_scope = scope;
        let model = with_loads(study_model(scene, &params, &q0, &dq0)?, &loads)?;
        // What is left to refuse depends on the scene (its independent coordinates)
        // or on dt and t_end together (the number of steps).
        options.validate(&model).map_err(arg_error)?;
        // The result holds every step: a run whose rows cannot fit is refused here,
        // not aborted by the allocator (which would end the interpreter).
        options.check_memory(&model, true).map_err(arg_error)?;
        let mut requested = options.steps();
        let until = until
            .map(|text| crate::stop::StopCondition::new(&model, &text))
            .transpose()
            .map_err(|e| invalid(e.to_string().replace("--until", "until")))?;
        let step_warning: Vec<String> = crate::model::plausibility::idle_warning(&model)
            .into_iter()
            .chain(crate::model::plausibility::locked_warning(&model))
            .chain(crate::model::plausibility::inertia_warning(&model))
            .chain(crate::model::plausibility::units_warnings(&model))
            // (An error-controlled run's dt is the rows' spacing, not its steps'.)
            .chain(
                crate::model::plausibility::step_warning(&model, options.dt)
                    .filter(|_| options.tolerance.is_none()),
            )
            .chain(
                crate::limits::t_end_unmet(options.dt, options.t_end).map(|last| {
                    format!(
                        "t_end = {} s is not a whole number of steps: the run ends at t = {last} s, \
                         the whole step nearest it",
                        options.t_end
                    )
                }),
            )
            .collect();
        let model_for_checks = model.clone();
        let hit = Arc::new(AtomicBool::new(false));
        let (run, signal) = interruptible(
            py,
            || !loads.is_empty() && is_interrupted(&loads),
            |progress| {
                // The rows are held (and, for the columns, the steps between them).
                options.check_memory(&model, true)?;
                let mut steps = crate::derived::Steps::new(&model, !groups.is_empty());
                let Some(condition) = &until else {
                    return forward::simulate_streaming(model, &options, progress, &mut steps)
                        .map(|s| (steps, s, None));
                };
                let mut watch = crate::stop::Watch::new(&model, condition, &mut steps, hit.clone());
                let mut watched = |done, total| match hit.load(Ordering::Relaxed) {
                    true => ControlFlow::Break(()),
                    false => progress(done, total),
                };
                let s =
                    forward::simulate_streaming(model.clone(), &options, &mut watched, &mut watch)?;
                let stopped = watch.stopped;
                Ok((steps, s, stopped))
            },
        );
        // A Ctrl-C that a Python effect's call received is the run's signal.
        let signal = signal.or_else(|| interrupted(&loads));
        let (steps, mut s, stopped) = match run {
            Ok(run) => run,
            // No trajectory comes back from a library error; an interrupt came first.
            Err(e) => {
                let err = match (signal, raised(&loads), e) {
                    (Some(signal), _, _) => signal,
                    (None, Some(python), _) => python,
                    (None, None, e @ Error::InvalidArgument(_)) => return Err(arg_error(e)),
                    (None, None, e) => with_failure(
                        py,
                        SolveError::new_err(e.to_string()),
                        error_failure(py, &e)?,
                    ),
                };
                return Err(with_result(py, err, None));
            }
        };
        // The optional columns over every step taken (a refined run's between rows).
        let extra = match !groups.is_empty() && s.failures.is_empty() && signal.is_none() {
            true => Some(
                steps
                    .columns(
                        &model_for_checks,
                        &groups,
                        crate::derived::WorkRule::of(s.plan.integrator),
                    )
                    .map_err(arg_error)?,
            ),
            false => None,
        };
        let tr = steps.into_rows();
        if let Some((k, _)) = stopped {
            // The steps solved past the stop are not kept; the run is whole up to it.
            s.steps = s.steps.min(k + 1);
            s.interrupted = None;
            requested = tr.len();
        }
        let out = forward_result(py, &tr, &s, requested)?;
        if let Some((k, at)) = stopped {
            let d = PyDict::new(py);
            d.set_item("t", at)?;
            d.set_item("step", k)?;
            out.get_item("summary")?
                .ok_or_else(|| PyRuntimeError::new_err("a result without a summary"))?
                .set_item("until", d)?;
        }
        if let Some(extra) = extra {
            out.set_item("extra_columns", extra.names)?;
            out.set_item("extra", PyArray1::from_vec(py, extra.values))?;
        }
        // What converged but may not be right (mbfg simulate prints these as warnings).
        let warnings: Vec<String> = step_warning
            .iter()
            .cloned()
            .chain(s.load_jump.as_ref().map(|j| j.message()))
            .chain(crate::forward::energy_checks::energy_warning(&s))
            .chain(crate::forward::energy_checks::passage_warning(&s))
            .chain(crate::forward::energy_checks::tolerance_warning(&s))
            .chain(crate::forward::energy_checks::balance_warning(&s))
            .collect();
        out.get_item("summary")?
            .ok_or_else(|| PyRuntimeError::new_err("a result without a summary"))?
            .set_item("warnings", warnings)?;
        if let Some(signal) = signal {
            return Err(with_result(py, signal, Some(&out)));
        }
        // A singular configuration stops the run whatever continue_on_failure says; so
        // does a diverged solve, and then the trajectory ends short.
        let stopped = s.failures.iter().find(|f| f.singular.is_some());
        let short = (tr.len() < requested).then(|| s.failures.last()).flatten();
        let fatal = stopped
            .or(s.failures.first().filter(|_| !continue_on_failure))
            .or(short);
        if let Some(f) = fatal {
            let err = match raised(&loads) {
                Some(python) => python,
                None => with_failure(py, SolveError::new_err(f.message()), step_failure(py, f)?),
            };
            return Err(with_result(py, err, Some(&out)));
        }
        if tr.len() < requested {
            let m = format!(
                "the run ended after {} of {requested} steps without naming a failure",
                tr.len()
            );
            return Err(with_result(py, SolveError::new_err(m), Some(&out)));
        }
        // A Ctrl-C after the last look: raise it here, with the run, rather than lose
        // the run to it on the next Python instruction.
        py.check_signals()
            .map_err(|e| with_result(py, e, Some(&out)))?;
        Ok(out)
    })
}

/// A schedule's name in Python.
fn schedule_name(schedule: Schedule) -> &'static str {
    match schedule {
        Schedule::Stepwise => "stepwise",
        Schedule::FixedLag(_) => "fixed_lag",
        Schedule::Batch => "batch",
    }
}
