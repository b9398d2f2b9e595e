//! `mbfg simulate`: its arguments, the forward options they make, the run with its
//! progress bar, the CSV and the summary line.

use super::failure::{plain, shorten, Failure};
use super::output::Output;
use super::progress::Progress;
use super::written::{Written, WrittenArgs};
use super::{load, print_summary};
use clap::ValueEnum;
use mbfg::forward::{
    self, Coordinates, DcIntegrators, ForwardOptions, Integrator, NoiseModels, RunSummary, Schedule,
};
use mbfg::smoother::Mode;
use mbfg::solver::Past;
use mbfg::Model;
use std::ops::ControlFlow;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

/// The arguments of `mbfg simulate`.
#[derive(clap::Args)]
pub struct SimulateArgs {
    /// Scene or MBSE mechanism file (YAML).
    scene: PathBuf,
    /// Dependent (natural) or independent coordinates.
    #[arg(long, value_enum, default_value_t = CoordsArg::Dc)]
    coords: CoordsArg,
    /// Time step, in seconds. With --rtol, the spacing of the rows written (the
    /// steps taken are chosen by the error control); then optional: --sample-dt,
    /// else t_end/1000.
    #[arg(long, required_unless_present = "rtol")]
    dt: Option<f64>,
    /// End time, in seconds (the run starts at 0).
    #[arg(long = "t-end")]
    t_end: f64,
    /// Fixed-lag smoother over the N newest steps [default: 1].
    #[arg(long, value_name = "N", conflicts_with = "batch")]
    window: Option<usize>,
    /// Solve the whole horizon at once.
    #[arg(long)]
    batch: bool,
    /// Linear solves allowed per window solve.
    #[arg(long = "max-iterations", value_name = "K", default_value_t = 50)]
    max_iterations: usize,
    /// Trajectory CSV to write (gzip-compressed when it ends in `.gz`); the
    /// summary then goes to standard output.
    #[arg(long, value_name = "FILE.csv")]
    out: Option<PathBuf>,
    #[command(flatten)]
    written: WrittenArgs,
    /// Integrator factor between steps.
    #[arg(long, value_enum, default_value_t = IntegratorArg(Integrator::Trapezoidal))]
    integrator: IntegratorArg,
    /// In dependent coordinates, what the integrator factors ask: only along the
    /// directions the constraints leave free (`tangent`: one equation per unknown,
    /// all satisfied, every window and the batch give N_w = 1's solution), on all n
    /// coordinates as in the paper (`full`: a least-squares compromise), or
    /// `tangent` with a step they fail taken by `full`, that step only (`auto`).
    #[arg(long = "dc-integrators", value_enum, default_value_t = DcIntegratorsArg::Auto)]
    dc_integrators: DcIntegratorsArg,
    /// Noise models: mbfg's defaults, or the paper's Table 2.
    #[arg(long, value_enum, default_value_t = NoiseArg::Default)]
    noise: NoiseArg,
    /// What a step leaving the window leaves behind: the paper's Gaussian marginal
    /// until a window solve fails, then the factors to the next step with it held
    /// at its estimate (adaptive); always one or always the other.
    #[arg(long, value_enum, default_value_t = PastArg::Adaptive)]
    past: PastArg,
    /// Keep going after a step whose solve did not converge (it is reported).
    #[arg(long = "continue-on-failure")]
    continue_on_failure: bool,
    /// Fail where the step is too coarse for the motion, instead of integrating
    /// the run again at a finer step (dt/K, K up to 1024) and writing every K-th
    /// state, on the grid of --dt.
    #[arg(long = "no-refine")]
    no_refine: bool,
    /// Send every step through the general solver with the window or batch asked,
    /// instead of taking the steps of IC and tangent DC runs (trapezoidal rule or
    /// Euler; Hermite–Simpson in DC) one at a time as sparse square systems: the same
    /// solution to the step tolerance, for comparison.
    #[arg(long = "no-square-steps")]
    no_square_steps: bool,
    /// Make the plausibility warnings errors: a time step too coarse for the
    /// stiffest spring or damper (refused before the run), the energy drift of a
    /// conservative scene beyond 1 % of its largest kinetic energy, and its energy
    /// changing by more than 1e-4 of it across a passage through a singular
    /// configuration (the trajectory is then not written).
    #[arg(long)]
    strict: bool,
    /// Print every iteration of every window solve to standard error: the window,
    /// the cost before and after the step, LM's damping, the predicted decrease and
    /// the step's size (for diagnosing a run that does not converge).
    #[arg(long = "trace-solver")]
    trace_solver: bool,
    /// End the run where an expression of the time and the state crosses zero, e.g.
    /// `x(ram) - 0.3` or `theta - 1.5` (names as in effects' values: coordinates by
    /// name, rate(c), x(P), y(P), vx(P), vy(P), angle(B), omega(B), t). The time of the
    /// zero is located within the step and stated in the summary; the rows end with the
    /// step after it.
    #[arg(long, value_name = "EXPR")]
    until: Option<String>,
    /// Relative tolerance of error-controlled steps: each step's size is chosen so
    /// that its estimated local error stays within atol + rtol·|x| per coordinate
    /// and per second simulated; the rows are interpolated onto the grid of --dt.
    /// The rows are then checked against a run at a coarser tolerance, and the run
    /// made again at a tighter one where their estimated error exceeds it (see
    /// --tolerance-scope). One step at a time (no --window or --batch);
    /// hermite-simpson takes the fewest.
    #[arg(long, value_name = "TOL")]
    rtol: Option<f64>,
    /// Absolute tolerance of error-controlled steps (in the coordinates' units, m
    /// and rad) [default: rtol].
    #[arg(long, value_name = "TOL", requires = "rtol")]
    atol: Option<f64>,
    /// What --rtol bounds: `run`, the rows written (the run checked, and made again
    /// at a tighter step tolerance where the motion amplified its steps' errors past
    /// the tolerance), or `steps`, each step's local error only (one run, about 1.7
    /// times faster, its rows' error unchecked).
    #[arg(long, value_name = "SCOPE", default_value = "run", requires = "rtol")]
    tolerance_scope: ToleranceScopeArg,
}

#[derive(Clone, Copy, ValueEnum)]
enum ToleranceScopeArg {
    Run,
    Steps,
}

#[derive(Clone, Copy, ValueEnum)]
enum CoordsArg {
    Dc,
    Ic,
}

/// `--integrator`: every [`Integrator`], by its name and description.
#[derive(Clone, Copy)]
struct IntegratorArg(Integrator);

impl IntegratorArg {
    const ALL: [IntegratorArg; Integrator::ALL.len()] = {
        let mut all = [IntegratorArg(Integrator::Trapezoidal); Integrator::ALL.len()];
        let mut i = 0;
        while i < all.len() {
            all[i] = IntegratorArg(Integrator::ALL[i]);
            i += 1;
        }
        all
    };
}

impl ValueEnum for IntegratorArg {
    fn value_variants<'a>() -> &'a [Self] {
        &IntegratorArg::ALL
    }
    fn to_possible_value(&self) -> Option<clap::builder::PossibleValue> {
        Some(clap::builder::PossibleValue::new(self.0.name()).help(self.0.description()))
    }
}

#[derive(Clone, Copy, ValueEnum)]
enum DcIntegratorsArg {
    Auto,
    Tangent,
    Full,
}

#[derive(Clone, Copy, ValueEnum)]
enum PastArg {
    Adaptive,
    Conditioned,
    Marginalized,
}

#[derive(Clone, Copy, ValueEnum)]
enum NoiseArg {
    Default,
    Paper,
}

/// `mbfg simulate`: the options from the arguments, checked against the scene.
pub fn run(args: SimulateArgs) -> Result<(), Failure> {
    let SimulateArgs {
        scene,
        coords,
        dt,
        t_end,
        window,
        batch,
        max_iterations,
        out,
        written,
        integrator,
        dc_integrators,
        noise,
        past,
        continue_on_failure,
        no_refine,
        no_square_steps,
        strict,
        trace_solver,
        until,
        rtol,
        atol,
        tolerance_scope,
    } = args;
    let tolerance = rtol
        .map(|rtol| forward::Tolerance::new(rtol, atol))
        .transpose()
        .map_err(|e| Failure::Input(format!("--{}", plain(e))))?;
    if tolerance.is_some() && (window.is_some() || batch) {
        return Err(Failure::Input(
            "--rtol takes its error-controlled steps one at a time: not with --window or --batch"
                .into(),
        ));
    }
    let args_dt = dt;
    let dt = match (dt, tolerance) {
        (Some(dt), _) => dt,
        // The rows of an error-controlled run: --sample-dt's, else a thousand.
        (None, Some(_)) => match written.sample_dt() {
            Some(sample) => sample,
            None => t_end / 1000.0,
        },
        (None, None) => return Err(Failure::Input("--dt is required (or --rtol)".into())),
    };
    let (_, model) = load(&scene)?;
    let until = until
        .map(|text| mbfg::stop::StopCondition::new(&model, &text))
        .transpose()
        .map_err(|e| Failure::Input(plain(e)))?;
    let mode = if batch {
        Mode::Batch
    } else {
        Mode::FixedLag(window.unwrap_or(1))
    };
    let coordinates = match coords {
        CoordsArg::Dc => Coordinates::Dependent,
        CoordsArg::Ic => Coordinates::Independent,
    };
    let mut options = ForwardOptions::new(coordinates, dt, t_end, mode);
    options.integrator = integrator.0;
    options.dc_integrators = match dc_integrators {
        DcIntegratorsArg::Auto => DcIntegrators::Auto,
        DcIntegratorsArg::Tangent => DcIntegrators::Tangent,
        DcIntegratorsArg::Full => DcIntegrators::Full,
    };
    options.noise = match noise {
        NoiseArg::Default => NoiseModels::default(),
        NoiseArg::Paper => NoiseModels::paper(),
    };
    options.settings.max_iterations = max_iterations;
    options.settings.trace = trace_solver;
    options.settings.past = match past {
        PastArg::Adaptive => Past::Adaptive,
        PastArg::Conditioned => Past::Conditioned,
        PastArg::Marginalized => Past::Marginalized,
    };
    options.continue_on_failure = continue_on_failure;
    options.refine = !no_refine;
    options.square_steps = !no_square_steps;
    options.tolerance = tolerance;
    options.tolerance_scope = match tolerance_scope {
        ToleranceScopeArg::Run => forward::ToleranceScope::Run,
        ToleranceScopeArg::Steps => forward::ToleranceScope::Steps,
    };
    options.validate(&model).map_err(plain)?;
    if tolerance.is_some() && args_dt.is_none() && written.sample_dt().is_none() {
        super::tell(&format!(
            "note: --rtol without --dt: rows written every {} s (t_end/1000)",
            super::seconds(dt)
        ));
    }
    if let Mode::FixedLag(w) = options.mode {
        // A window longer than the run is the whole run.
        options.mode = Mode::FixedLag(w.min(options.steps()));
    }
    let written = Written::new(
        &written,
        dt,
        mbfg::derived::WorkRule::of(options.integrator),
    )?;
    simulate(
        model,
        &options,
        out.as_deref(),
        &scene,
        strict,
        &written,
        until.as_ref(),
    )
}

/// `mbfg simulate`: runs, writes the CSV, prints the summary.
fn simulate(
    model: Model,
    options: &ForwardOptions,
    out: Option<&Path>,
    scene: &Path,
    strict: bool,
    written: &Written,
    until: Option<&mbfg::stop::StopCondition>,
) -> Result<(), Failure> {
    // Open the output first: an unwritable path is bad input, found before the run.
    let output = Output::open(out, &super::inputs(scene, &model, &[]))?;
    for w in mbfg::model::plausibility::idle_warning(&model)
        .into_iter()
        .chain(mbfg::model::plausibility::locked_warning(&model))
        .chain(mbfg::model::plausibility::inertia_warning(&model))
        .chain(mbfg::model::plausibility::units_warnings(&model))
    {
        super::tell(&format!("warning: {w}"));
    }
    // (An error-controlled run's dt is the rows' spacing, not its steps'.)
    let step_warning = match options.tolerance {
        Some(_) => None,
        None => mbfg::model::plausibility::step_warning(&model, options.dt),
    };
    if let Some(w) = step_warning {
        if strict {
            return Err(Failure::Input(format!("{w} (--strict)")));
        }
        super::tell(&format!("warning: {w}"));
    }
    super::interrupt::install();
    let batch = forward::Plan::new(&model, options)
        .map_err(|e| Failure::Input(plain(e)))?
        .schedule
        == Schedule::Batch;
    let mut bar = Progress::new(batch);
    let model = Arc::new(model);
    // The rows go to the file as the steps become final where nothing needs the
    // whole run first: the optional columns (work integrals over every step) do,
    // and standard output cannot take back the rows of a run made again.
    let stream = written.streams();
    let mut streamed = match stream {
        true => output
            .stream(&model.names, written.stride())
            .map_err(Failure::Run)?,
        false => None,
    };
    if streamed.is_none() {
        // The rows are held until the run ends: refused before it starts if they
        // cannot be (bad input, as the other limits).
        options
            .check_memory(&model, true)
            .map_err(|e| Failure::Input(plain(e)))?;
    }
    let hit = Arc::new(AtomicBool::new(false));
    let watched = hit.clone();
    let mut progress = |done, total| {
        bar.update(done, total);
        if super::interrupt::requested() || watched.load(Ordering::Relaxed) {
            ControlFlow::Break(())
        } else {
            ControlFlow::Continue(())
        }
    };
    let mut until_stop = None;
    // The rows go to the file, or are held (the memory was checked above; for the
    // columns, the steps between them too).
    let mut held = streamed
        .is_none()
        .then(|| mbfg::derived::Steps::new(&model, !written.streams()));
    let sink: &mut dyn forward::StepSink = match (streamed.as_mut(), held.as_mut()) {
        (Some(sink), _) => sink,
        (None, Some(held)) => held,
        (None, None) => unreachable!("held when not streamed"),
    };
    let result = match until {
        Some(condition) => {
            let mut watch = mbfg::stop::Watch::new(&model, condition, sink, hit.clone());
            let run =
                forward::simulate_streaming(model.clone(), options, &mut progress, &mut watch);
            until_stop = watch.stopped;
            run
        }
        None => forward::simulate_streaming(model.clone(), options, &mut progress, sink),
    }
    .map(|summary| (held, summary));
    bar.finish();
    let (trajectory, mut summary) = result.map_err(|e| Failure::Run(plain(e)))?;
    if let Some((k, _)) = until_stop {
        // The steps solved past the stop are not kept.
        summary.steps = summary.steps.min(k + 1);
    }
    let run = match (trajectory, streamed) {
        (Some(trajectory), _) => Run::Held(trajectory),
        (None, Some(streamed)) => Run::Streamed(Box::new(streamed)),
        (None, None) => unreachable!("a run without a trajectory was streamed"),
    };
    let steps = summary.steps;
    let to_file = output.to_file();
    let mut line = summary_line(options, &summary, super::memory::peak());
    if let (Some(condition), Some((k, at))) = (until, until_stop) {
        line += &format!(
            "; stopped by --until '{}' at t = {} s (its zero, within step {k})",
            condition.text,
            forward::round_time(at)
        );
    }
    // What was kept of a run that ended early (its rows written, held or streamed).
    let keep_partial = |output: Output, run: Run, why: &str| -> Result<String, Failure> {
        match run {
            Run::Held(steps) => {
                let (trajectory, prepared) = written.prepare_steps(&model, steps)?;
                output
                    .keep_partial(&trajectory, &prepared.csv(None), why)
                    .map_err(Failure::Run)
            }
            Run::Streamed(streamed) => output
                .keep_partial_streamed(*streamed)
                .map_err(Failure::Run),
        }
    };
    if let (Some(k), None) = (summary.interrupted, until_stop) {
        let why = format!("interrupted after step {k}");
        let what = if steps == 0 {
            output.discard();
            "nothing was written".to_string()
        } else {
            keep_partial(output, run, &why)?
        };
        print_summary(to_file, &line);
        return Err(Failure::Interrupted(format!("{why}; {what}")));
    }
    let first_failure = summary.failures.first().cloned();
    let batch = summary.plan.schedule == Schedule::Batch;
    // A batch that did not converge has no trustworthy step.
    let stopped = match batch {
        true => first_failure.is_some(),
        false => steps < options.steps() && until_stop.is_none(),
    };
    for f in summary.failures.iter().skip(usize::from(stopped)).take(10) {
        super::tell(&format!("warning: {}", shorten(&f.message())));
    }
    if stopped {
        let Some(f) = first_failure else {
            return Err(Failure::Run(format!(
                "the run ended after {} of {} steps",
                steps,
                options.steps()
            )));
        };
        let what = if batch || steps == 0 {
            output.discard();
            "nothing was written".to_string()
        } else {
            keep_partial(output, run, &f.message())?
        };
        print_summary(to_file, &line);
        // More iterations do not help the solves that stall (they crawl along a
        // direction the cost barely sees), so --max-iterations is not suggested.
        let jumping: Vec<&str> = model
            .scene
            .effects
            .iter()
            .filter(|e| e.jumps())
            .filter_map(|e| e.name())
            .collect();
        let jump_hint;
        let fast_hint;
        let too_fast = mbfg::model::plausibility::too_fast(&model, options.dt);
        let hint = if f
            .cause
            .as_deref()
            .is_some_and(|c| c.starts_with("singular system"))
        {
            "a singular configuration of the mechanism, or a dt far from its time scales: a smaller dt, or check the constraints"
        } else if f.cause.as_deref().is_some_and(|c| !no_step_converged(c)) {
            "an effect must be finite over the whole run"
        } else if f.singular.is_none() && !jumping.is_empty() {
            // A step across a jump of the load (Coulomb friction as sign(v)) has no
            // implicit solution when the load's jump reverses the motion that made it.
            jump_hint = format!(
                "{} jumps with sign(): smooth it, e.g. tanh(x/1e-3) for sign(x)",
                jumping
                    .iter()
                    .map(|n| format!("effect '{n}'"))
                    .collect::<Vec<_>>()
                    .join(", ")
            );
            &jump_hint
        } else if let (true, Some(fast)) = (f.singular.is_none(), &too_fast) {
            // The warning before the run named it; the failure is where it shows.
            fast_hint = format!(
                "dt is too coarse for effect {}: dt ≤ {:.2e} s resolves it",
                fast.name,
                mbfg::model::plausibility::MAX_OMEGA_DT / fast.speed()
            );
            &fast_hint
        } else if f.is_too_coarse() {
            "without --no-refine the run is integrated again at a finer step"
        } else if f.singular.is_some() && options.coordinates == Coordinates::Independent {
            // Ill-posed ahead: no window or dt passes it in IC.
            "--coords dc does not stop there"
        } else if batch && !f.warm_start && f.singular.is_none() {
            "the fixed-lag smoother (--window N) or a smaller dt may converge"
        } else if f.warm_start {
            "--window 1 writes the run up to there"
        } else if f.report.termination == mbfg::solver::Termination::Diverged {
            "a diverged solve ends the run, --continue-on-failure too"
        } else if f.cause.as_deref().is_some_and(no_step_converged) {
            "a run of fixed steps (--dt without --rtol) names what stops it"
        } else {
            "--continue-on-failure goes on past it"
        };
        return Err(Failure::Run(format!("{}; {what} ({hint})", f.message())));
    }
    let warnings: Vec<String> = summary
        .load_jump
        .as_ref()
        .map(|j| j.message())
        .into_iter()
        .chain(mbfg::forward::energy_checks::energy_warning(&summary))
        .chain(mbfg::forward::energy_checks::balance_warning(&summary))
        .chain(mbfg::forward::energy_checks::passage_warning(&summary))
        .chain(mbfg::forward::energy_checks::tolerance_warning(&summary))
        .collect();
    if let (true, Some(w)) = (strict, warnings.first()) {
        output.discard();
        print_summary(to_file, &line);
        return Err(Failure::Run(format!("{w}; nothing was written (--strict)")));
    }
    for w in &warnings {
        super::tell(&format!("warning: {w}"));
    }
    match run {
        Run::Held(steps) => {
            let (trajectory, prepared) = written.prepare_steps(&model, steps)?;
            output
                .commit(&trajectory, &prepared.csv(None))
                .map_err(Failure::Run)?
        }
        Run::Streamed(streamed) => output.commit_streamed(*streamed).map_err(Failure::Run)?,
    }
    print_summary(to_file, &line);
    Ok(())
}

/// A run's rows: held until it ends, or already in the output's temporary file.
enum Run {
    Held(mbfg::derived::Steps),
    Streamed(Box<super::output::Streamed>),
}

/// Whether a failure's cause is an error-controlled run's steps shrinking to the
/// smallest size without converging (not an effect that cannot be evaluated).
fn no_step_converged(cause: &str) -> bool {
    cause.starts_with(forward::NO_STEP_CONVERGED)
}

/// The summary's words on the check of a run's rows against its tolerance (empty
/// where there was none).
fn check_description(c: &forward::ErrorControl) -> String {
    let Some(check) = &c.check else {
        return String::new();
    };
    let runs = match check.step_rtols.len() {
        1 => String::new(),
        k => format!(
            " after {k} runs at step rtol {}",
            check
                .step_rtols
                .iter()
                .map(|r| format!("{r:.1e}"))
                .collect::<Vec<_>>()
                .join(", ")
        ),
    };
    match (check.estimated, &check.unchecked) {
        (Some(e), _) => format!("; the rows' estimated error {e:.2} × the tolerance{runs}"),
        (None, Some(why)) => format!("; the rows' error unchecked: {why}"),
        (None, None) => String::new(),
    }
}

/// The summary line; `peak_memory`, the process's peak resident memory in bytes,
/// where the system reports it.
fn summary_line(options: &ForwardOptions, s: &RunSummary, peak_memory: Option<u64>) -> String {
    let (what, mode) = match s.error_control {
        // The steps are the error control's; the rows are on the grid.
        Some(_) => ("rows", "error-controlled steps".to_string()),
        None => ("steps", s.plan.describe()),
    };
    let mut line = format!(
        "{} {what} (dt = {} s, {mode}) in {:.3} s; iterations per solve: mean {:.2}, max {} \
         (factorizations: mean {:.2}); worst |Φ| {:.2e}, worst |Φq q̇| {:.2e}",
        s.steps,
        super::seconds(options.dt),
        s.wall_time.as_secs_f64(),
        s.mean_iterations,
        s.max_iterations,
        s.mean_factorizations,
        s.worst_phi,
        s.worst_velocity_constraint
    );
    if let Some(t_last) = mbfg::limits::t_end_unmet(options.dt, options.t_end) {
        line += &format!(
            "; ends at t = {} s, the whole step nearest t_end = {} s",
            super::seconds(t_last),
            super::seconds(options.t_end)
        );
    }
    if let Some(d) = s.energy_drift {
        line += &format!("; energy drift {d:.2e} J");
    }
    for r in &s.reselections {
        line += &format!(
            "; independent coordinates [{}] replaced by [{}] at step {} (t = {} s)",
            r.from.join(", "),
            r.to.join(", "),
            r.step,
            r.t
        );
    }
    let p = &s.passages;
    if let Some(first) = p.first {
        line += &format!(
            "; {} passage(s) through a singular configuration (the first at t = {} s): \
             max |Φq q̇| {:.2e} around them",
            p.count,
            forward::round_time(first),
            p.worst_velocity_constraint
        );
        if let Some((jump, _)) = p.energy_jump {
            line += &format!(", largest energy change across one {jump:.2e} J");
        }
    }
    if s.general_steps > 0 {
        line += &format!(
            "; {} of {} steps by the general solver (the square step declined them)",
            s.general_steps,
            s.general_steps + s.square_steps
        );
    }
    if let Some(c) = &s.error_control {
        line += &format!(
            "; error control rtol {:.1e}, atol {:.1e}: {} steps taken, {} rejected{}, h from \
             {:.3e} to {:.3e} s",
            c.tolerance.rtol,
            c.tolerance.atol,
            c.accepted,
            c.rejected,
            match c.failed_solves {
                0 => String::new(),
                k => format!(", {k} failed solve(s) taken again smaller"),
            } + &match c.at_floor {
                0 => String::new(),
                k => format!(
                    ", {k} kept above the tolerance at the smallest step (the estimate \
                     there is the noise of the solves, not the step's error)"
                ),
            } + &match c.damped {
                0 => String::new(),
                k => format!(
                    ", {k} kept unestimated at the size that reached a rank loss (damped \
                     projections, where the estimate reads the lost direction)"
                ),
            },
            c.smallest,
            c.largest
        );
        line += &check_description(c);
    }
    if s.paper_steps > 0 {
        line += &format!(
            "; {} step(s) by the paper's integrators (the tangent ones failed there)",
            s.paper_steps
        );
    }
    if let Some(r) = &s.refinement {
        let (body, turn) = r.after.fast_body.clone().unwrap_or_default();
        line += &format!(
            "; integrated at dt = {:.3e} s ({} steps per step written): at dt = {:.3e} s body \
             {body} turns about {turn:.2} rad a step at t = {} s, too coarse for the motion \
             (steps and failures named here are the finer ones)",
            r.dt,
            r.factor,
            r.after.dt(),
            forward::round_time(r.after.t)
        );
    }
    if let Some((k, t)) = s.conditioned_from {
        line += &format!(
            "; past conditioned from step {k} (t = {} s)",
            forward::round_time(t)
        );
    }
    let unconverged = s.failures.iter().filter(|f| f.singular.is_none()).count();
    if unconverged > 0 {
        line += &format!("; {unconverged} step(s) did not converge");
    }
    if s.failures.iter().any(|f| f.singular.is_some()) {
        line += "; stopped ahead of a singular configuration";
    }
    if let Some(bytes) = peak_memory {
        line += &format!("; peak memory {:.1} MiB", bytes as f64 / (1024.0 * 1024.0));
    }
    line
}
