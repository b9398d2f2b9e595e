//! The `mbfg` command line. Every error is one line on stderr; the exit code says
//! which kind: 2 bad input, 1 a run that failed or ended early, 130 interrupted,
//! 70 a bug (a panic, caught here).

mod cli;

use clap::{Parser, Subcommand, ValueEnum};
use cli::output::Output;
use mbfg::check::CheckReport;
use mbfg::forward::{
    self, Coordinates, DcIntegrators, ForwardOptions, Integrator, NoiseModels, RunSummary,
};
use mbfg::smoother::Mode;
use mbfg::solver::Past;
use mbfg::{Error, Model, Scene};
use std::io::IsTerminal;
use std::ops::ControlFlow;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::Arc;
use std::time::{Duration, Instant};

#[derive(Parser)]
#[command(
    name = "mbfg",
    version,
    about = "Planar multibody dynamics as factor graphs"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Parse and assemble a scene; print its coordinates, constraints, degrees of
    /// freedom and effects.
    Check {
        /// Scene or MBSE mechanism file (YAML).
        scene: PathBuf,
    },
    /// Forward dynamics: simulate the scene from its initial state and write the
    /// trajectory as CSV (to --out, or to standard output).
    #[command(allow_negative_numbers = true)]
    Simulate {
        /// Scene or MBSE mechanism file (YAML).
        scene: PathBuf,
        /// Dependent (natural) or independent coordinates.
        #[arg(long, value_enum, default_value_t = CoordsArg::Dc)]
        coords: CoordsArg,
        /// Time step, in seconds.
        #[arg(long)]
        dt: f64,
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
        #[arg(long, value_enum, default_value_t = IntegratorArg::Trapezoidal)]
        integrator: IntegratorArg,
        /// In dependent coordinates, what the integrator factors ask: on all n
        /// coordinates as in the paper (`full`: a least-squares compromise), only along
        /// the directions the constraints leave free (`tangent`: one equation per
        /// unknown, all satisfied, every window and the batch give N_w = 1's
        /// solution), or `full` with the run made again with `tangent` where a solve
        /// fails (`auto`)
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
        /// Make the plausibility warnings errors: a time step too coarse for the
        /// stiffest spring or damper (refused before the run), and the energy drift
        /// of a conservative scene beyond 1 % of its largest kinetic energy (the
        /// trajectory is then not written).
        #[arg(long)]
        strict: bool,
    },
    /// Draw a run: the mechanism's motion from a trajectory CSV, as a GIF or an MP4
    /// (matplotlib, through the mbfg Python module: `make python`; MBFG_PYTHON names
    /// the interpreter, default .venv/bin/python beside the current directory, then
    /// python3).
    Animate {
        /// Trajectory CSV written by `mbfg simulate` (.csv or .csv.gz).
        run: PathBuf,
        /// The scene the run was made from.
        #[arg(long)]
        scene: PathBuf,
        /// GIF or MP4 to write [default: the run's name with .gif].
        #[arg(long, value_name = "FILE.gif")]
        out: Option<PathBuf>,
        /// Frames per second of video.
        #[arg(long, default_value_t = 25)]
        fps: u32,
        /// Seconds of motion per second of video.
        #[arg(long, default_value_t = 1.0)]
        speed: f64,
        /// Draw the path of this point.
        #[arg(long, value_name = "POINT")]
        trail: Option<String>,
    },
    /// Inverse dynamics: the forces on the prescribed coordinates that produce their
    /// motion, and the motion of all the others, solved over the whole horizon.
    Inverse {
        /// Scene or MBSE mechanism file (YAML).
        scene: PathBuf,
        /// CSV with header `t,<coordinate>,...`: the prescribed coordinates at uniformly
        /// spaced times (at least 5 rows).
        #[arg(long, value_name = "FILE.csv")]
        trajectory: PathBuf,
        /// Dependent (natural) or independent coordinates.
        #[arg(long, value_enum, default_value_t = InverseCoords::Dc)]
        coords: InverseCoords,
        /// Linear solves allowed.
        #[arg(long = "max-iterations", value_name = "K", default_value_t = 50)]
        max_iterations: usize,
        /// How the batch solve starts: the classical kinematic solution, or the
        /// paper's four stages from the scene's configuration.
        #[arg(long, value_enum, default_value_t = StartArg::Kinematic)]
        start: StartArg,
        /// Output CSV (trajectory plus `Q:<c>` columns; gzip-compressed when it ends
        /// in `.gz`); the summary then goes to standard output.
        #[arg(long, value_name = "FILE.csv")]
        out: Option<PathBuf>,
        #[command(flatten)]
        written: WrittenArgs,
        /// Write the result of a solve that did not converge too, to
        /// `<out>.partial.csv` (or to standard output, ended by `# incomplete`).
        #[arg(long = "keep-unconverged")]
        keep_unconverged: bool,
    },
}

/// What the CSV holds beyond the standard columns, and which rows.
#[derive(clap::Args)]
struct WrittenArgs {
    /// Write the rows at t = 0, S, 2S, … only (and the last); S must be a whole
    /// number of time steps. The solve is unchanged.
    #[arg(long = "sample-dt", value_name = "S")]
    sample_dt: Option<f64>,
    /// Optional columns after the standard ones, comma-separated: `bodies` (angle,
    /// centre of mass position and velocity of every body), `energy` (kinetic,
    /// potential, work of every non-conservative effect, energy_balance).
    #[arg(long, value_name = "LIST")]
    columns: Option<String>,
}

/// [`WrittenArgs`] checked: the sample stride in steps and the column groups.
struct Written {
    stride: usize,
    groups: Vec<mbfg::derived::Group>,
}

impl Written {
    /// Checks the options against the time step; errors are bad input.
    fn new(args: &WrittenArgs, dt: f64) -> Result<Self, String> {
        let stride = match args.sample_dt {
            Some(s) => mbfg::io::sample_stride(dt, s)?,
            None => 1,
        };
        let groups = match &args.columns {
            Some(list) => mbfg::derived::Group::parse_list(list)?,
            None => Vec::new(),
        };
        Ok(Written { stride, groups })
    }

    /// The optional columns over every step (the work integrals need them all), and
    /// the rows to write.
    fn prepare(
        &self,
        model: &Model,
        trajectory: &forward::Trajectory,
        actuators: Option<&[f64]>,
    ) -> Result<Prepared, Failure> {
        let extra = if self.groups.is_empty() {
            None
        } else {
            let c = mbfg::derived::columns(model, trajectory, &self.groups, actuators)
                .map_err(|e| Failure::Run(plain(e)))?;
            Some(c)
        };
        let rows = (self.stride > 1).then(|| mbfg::io::sampled_rows(trajectory.len(), self.stride));
        Ok(Prepared { extra, rows })
    }
}

/// The optional columns and rows of one trajectory, ready to write.
struct Prepared {
    extra: Option<mbfg::derived::Columns>,
    rows: Option<Vec<usize>>,
}

impl Prepared {
    fn csv<'a>(&'a self, forces: Option<&'a [f64]>) -> mbfg::io::CsvOptions<'a> {
        mbfg::io::CsvOptions {
            forces,
            extra: self
                .extra
                .as_ref()
                .map(|c| (c.names.as_slice(), c.values.as_slice())),
            rows: self.rows.as_deref(),
        }
    }
}

#[derive(Clone, Copy, ValueEnum)]
enum StartArg {
    Kinematic,
    Staged,
}

#[derive(Clone, Copy, ValueEnum)]
enum InverseCoords {
    Dc,
    Ic,
}

#[derive(Clone, Copy, ValueEnum)]
enum CoordsArg {
    Dc,
    Ic,
}

#[derive(Clone, Copy, ValueEnum)]
enum IntegratorArg {
    /// The paper's trapezoidal rule, second order.
    Trapezoidal,
    /// Explicit Euler, first order.
    Euler,
    /// Hermite–Simpson collocation, fourth order (the dynamics also at each step's middle).
    HermiteSimpson,
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

/// Why a command failed: bad input (exit 2), a run that failed or ended early
/// (exit 1), or a run the user interrupted (exit 130).
enum Failure {
    Input(String),
    Run(String),
    Interrupted(String),
}

impl From<String> for Failure {
    fn from(m: String) -> Self {
        Failure::Input(m)
    }
}

/// The longest error message: with `error: `, a line of 300 characters at most;
/// longer messages are cut with an ellipsis.
const MAX_MESSAGE_CHARS: usize = 300 - "error: ".len();

fn main() -> ExitCode {
    cli::panic::install_hook();
    let cli = match Cli::try_parse_from(join_negative_values(std::env::args_os())) {
        Ok(cli) => cli,
        Err(e) if !e.use_stderr() => {
            // --help and --version.
            let _ = e.print();
            return ExitCode::SUCCESS;
        }
        Err(e) => {
            eprintln!("error: {}", clap_line(&e));
            return ExitCode::from(2);
        }
    };
    let (code, message) = match std::panic::catch_unwind(|| run(cli)) {
        Ok(Ok(())) => return ExitCode::SUCCESS,
        Ok(Err(Failure::Input(m))) => (2, m),
        Ok(Err(Failure::Run(m))) => (1, m),
        Ok(Err(Failure::Interrupted(m))) => (130, m),
        Err(_) => (
            70,
            format!(
                "internal error (a bug in mbfg; please report it with the command): {}",
                cli::panic::last_message()
            ),
        ),
    };
    eprintln!("error: {}", shorten(&message));
    ExitCode::from(code)
}

/// One line of at most [`MAX_MESSAGE_CHARS`] characters.
fn shorten(message: &str) -> String {
    let line = message.replace(['\n', '\r'], " ");
    if line.chars().count() <= MAX_MESSAGE_CHARS {
        return line;
    }
    let mut cut: String = line.chars().take(MAX_MESSAGE_CHARS - 1).collect();
    cut.push('…');
    cut
}

/// clap's error as one line: its first line without the `error: ` prefix, and where
/// to read more.
fn clap_line(e: &clap::Error) -> String {
    let text = e.render().to_string();
    // The first paragraph (a list of missing arguments runs over several lines).
    let first: Vec<&str> = text
        .lines()
        .map(str::trim)
        .skip_while(|l| l.is_empty())
        .take_while(|l| !l.is_empty())
        .collect();
    let first = first.join(" ");
    let first = first.strip_prefix("error: ").unwrap_or(&first);
    shorten(&format!("{first} (mbfg --help lists the arguments)"))
}

/// `--dt -inf` as `--dt=-inf`: clap takes a value that starts with `-` and is not a
/// plain number for a flag; the value is then checked like any other.
fn join_negative_values(args: impl Iterator<Item = std::ffi::OsString>) -> Vec<std::ffi::OsString> {
    let mut out: Vec<std::ffi::OsString> = Vec::new();
    for arg in args {
        let joined = match (out.last().and_then(|p| p.to_str()), arg.to_str()) {
            (Some(prev), Some(value))
                if prev.starts_with("--")
                    && !prev.contains('=')
                    && value.starts_with('-')
                    && value.parse::<f64>().is_ok() =>
            {
                Some(format!("{prev}={value}"))
            }
            _ => None,
        };
        match joined {
            Some(j) => *out.last_mut().expect("a previous argument") = j.into(),
            None => out.push(arg),
        }
    }
    out
}

/// Runs a command; the error is the one line to print.
fn run(cli: Cli) -> Result<(), Failure> {
    match cli.command {
        Command::Check { scene } => {
            let (scene, model) = load(&scene)?;
            let report = CheckReport::new(&scene, &model);
            let numbers = [
                ("max |Φ|", report.initial_residual),
                ("kinetic energy", report.kinetic_energy),
                ("potential energy", report.potential_energy),
            ];
            if let Some((what, v)) = numbers.iter().find(|(_, v)| !v.is_finite()) {
                return Err(Failure::Input(format!(
                    "{}: the initial state's {what} is {v}: a value in the scene is out of range",
                    scene.file
                )));
            }
            println!("{report}");
            Ok(())
        }
        Command::Simulate {
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
            strict,
        } => {
            let (_, model) = load(&scene)?;
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
            options.integrator = match integrator {
                IntegratorArg::Trapezoidal => Integrator::Trapezoidal,
                IntegratorArg::Euler => Integrator::Euler,
                IntegratorArg::HermiteSimpson => Integrator::HermiteSimpson,
            };
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
            options.settings.past = match past {
                PastArg::Adaptive => Past::Adaptive,
                PastArg::Conditioned => Past::Conditioned,
                PastArg::Marginalized => Past::Marginalized,
            };
            options.continue_on_failure = continue_on_failure;
            options.refine = !no_refine;
            options.validate(&model).map_err(plain)?;
            if let Mode::FixedLag(w) = options.mode {
                // A window longer than the run is the whole run.
                options.mode = Mode::FixedLag(w.min(options.steps()));
            }
            let written = Written::new(&written, dt)?;
            simulate(model, &options, out.as_deref(), &scene, strict, &written)
        }
        Command::Animate {
            run,
            scene,
            out,
            fps,
            speed,
            trail,
        } => animate(&run, &scene, out.as_deref(), fps, speed, trail.as_deref()),
        Command::Inverse {
            scene,
            trajectory,
            coords,
            max_iterations,
            start,
            out,
            written,
            keep_unconverged,
        } => {
            let (_, model) = load(&scene)?;
            if max_iterations == 0 {
                return Err(Failure::Input("--max-iterations must be at least 1".into()));
            }
            let start = match start {
                StartArg::Kinematic => mbfg::inverse::Start::Kinematic,
                StartArg::Staged => mbfg::inverse::Start::Staged,
            };
            let mut options = mbfg::inverse::InverseOptions::default();
            options.settings.max_iterations = max_iterations;
            options.start = start;
            options.coordinates = match coords {
                InverseCoords::Dc => Coordinates::Dependent,
                InverseCoords::Ic => Coordinates::Independent,
            };
            let output = Output::open(out.as_deref(), &[&scene, &trajectory])?;
            inverse(
                model,
                &trajectory,
                &options,
                output,
                keep_unconverged,
                &written,
            )
        }
    }
}

/// `mbfg inverse`: reads the prescription, solves, writes the CSV and the summary.
fn inverse(
    model: Model,
    trajectory: &Path,
    options: &mbfg::inverse::InverseOptions,
    output: Output,
    keep_unconverged: bool,
    written: &WrittenArgs,
) -> Result<(), Failure> {
    let file = trajectory.display().to_string();
    let table = mbfg::io::read_table_with(
        trajectory,
        &mbfg::io::TableLimits::default(),
        &mut |columns| mbfg::inverse::Prescription::check_header(&model, columns, &file).map(drop),
    )
    .map_err(plain)?;
    let prescription =
        mbfg::inverse::Prescription::from_table(&model, &table, &trajectory.display().to_string())
            .map_err(plain)?;
    let written = Written::new(written, prescription.dt)?;
    let model = Arc::new(model);
    let sol = mbfg::inverse::solve(model.clone(), &prescription, options).map_err(|e| match e {
        Error::InvalidArgument(m) => Failure::Input(m),
        other => Failure::Run(plain(other)),
    })?;
    let s = &sol.summary;
    let line = format!(
        "{} steps (dt = {} s, batch) in {:.3} s; {} LM iterations ({}); worst tracking error {:.2e}; worst |Φ| {:.2e}",
        s.steps,
        prescription.dt,
        s.wall_time.as_secs_f64(),
        s.report.iterations,
        s.report.termination,
        s.worst_tracking,
        s.worst_phi
    );
    let to_file = output.to_file();
    // Computed only for what is written.
    let prepare = || written.prepare(&model, &sol.trajectory, Some(&sol.forces));
    let forces = Some(sol.forces.as_slice());
    if s.report.termination != mbfg::solver::Termination::Converged {
        let why = format!(
            "the inverse solve did not converge: {}, cost {:.3e} after {} iterations",
            s.report.termination, s.report.cost, s.report.iterations
        );
        let what = if keep_unconverged {
            output
                .keep_partial(&sol.trajectory, &prepare()?.csv(forces), &why)
                .map_err(Failure::Run)?
                .replacen(" steps ", " unconverged steps ", 1)
        } else {
            output.discard();
            "nothing was written (--keep-unconverged writes it, marked)".into()
        };
        print_summary(to_file, &line);
        return Err(Failure::Run(format!(
            "{why}; {what}; --max-iterations allows more"
        )));
    }
    output
        .commit(&sol.trajectory, &prepare()?.csv(forces))
        .map_err(Failure::Run)?;
    print_summary(to_file, &line);
    Ok(())
}

/// The summary line goes to standard output beside a CSV file, to standard error
/// beside CSV on standard output.
fn print_summary(to_file: bool, line: &str) {
    if to_file {
        println!("{line}");
    } else {
        eprintln!("{line}");
    }
}

/// The message of a library error without the variant's prefix for bad arguments.
fn plain(e: Error) -> String {
    match e {
        Error::InvalidArgument(m) => m,
        other => other.to_string(),
    }
}

/// `mbfg simulate`: runs, writes the CSV, prints the summary.
fn simulate(
    model: Model,
    options: &ForwardOptions,
    out: Option<&Path>,
    scene: &Path,
    strict: bool,
    written: &Written,
) -> Result<(), Failure> {
    // Open the output first: an unwritable path is bad input, found before the run.
    let output = Output::open(out, &[scene])?;
    if let Some(w) = mbfg::plausibility::idle_warning(&model) {
        eprintln!("warning: {w}");
    }
    if let Some(w) = mbfg::plausibility::step_warning(&model, options.dt) {
        if strict {
            return Err(Failure::Input(format!("{w} (--strict)")));
        }
        eprintln!("warning: {w}");
    }
    cli::interrupt::install();
    let mut bar = Progress::new();
    let model = Arc::new(model);
    let result = forward::simulate_interruptible(model.clone(), options, &mut |done, total| {
        bar.update(done, total);
        if cli::interrupt::requested() {
            ControlFlow::Break(())
        } else {
            ControlFlow::Continue(())
        }
    });
    bar.finish();
    let (trajectory, summary) = result.map_err(|e| Failure::Run(plain(e)))?;
    let to_file = output.to_file();
    let line = summary_line(options, &summary);
    // Computed only for what is written.
    let prepare = || written.prepare(&model, &trajectory, None);
    if let Some(k) = summary.interrupted {
        let why = format!("interrupted after step {k}");
        let what = if trajectory.is_empty() {
            output.discard();
            "nothing was written".to_string()
        } else {
            output
                .keep_partial(&trajectory, &prepare()?.csv(None), &why)
                .map_err(Failure::Run)?
        };
        print_summary(to_file, &line);
        return Err(Failure::Interrupted(format!("{why}; {what}")));
    }
    let first_failure = summary.failures.first().cloned();
    let stopped = match options.mode {
        // A batch that did not converge has no trustworthy step.
        Mode::Batch => first_failure.is_some(),
        Mode::FixedLag(_) => trajectory.len() < options.steps(),
    };
    for f in summary.failures.iter().skip(usize::from(stopped)).take(10) {
        eprintln!("warning: {}", shorten(&f.message()));
    }
    if stopped {
        let Some(f) = first_failure else {
            return Err(Failure::Run(format!(
                "the run ended after {} of {} steps",
                trajectory.len(),
                options.steps()
            )));
        };
        let what = if options.mode == Mode::Batch || trajectory.is_empty() {
            output.discard();
            "nothing was written".to_string()
        } else {
            output
                .keep_partial(&trajectory, &prepare()?.csv(None), &f.message())
                .map_err(Failure::Run)?
        };
        print_summary(to_file, &line);
        // More iterations do not help the solves that stall (they crawl along a
        // direction the cost barely sees), so --max-iterations is not suggested.
        let hint = if f.cause.is_some() {
            "an effect must be finite over the whole run"
        } else if options.mode == Mode::Batch && !f.warm_start {
            "the fixed-lag smoother (--window N) or a smaller dt may converge"
        } else if f.singular.is_some() {
            "--coords dc does not stop there"
        } else if f.warm_start {
            "--window 1 writes the run up to there"
        } else if f.report.termination == mbfg::solver::Termination::Diverged {
            "a diverged solve ends the run, --continue-on-failure too"
        } else {
            "--continue-on-failure goes on past it"
        };
        return Err(Failure::Run(format!("{}; {what} ({hint})", f.message())));
    }
    let euler =
        mbfg::plausibility::euler_warning(&model, &trajectory, &summary, options.integrator);
    if let Some(w) = mbfg::plausibility::energy_warning(&summary).or(euler) {
        if strict {
            output.discard();
            print_summary(to_file, &line);
            return Err(Failure::Run(format!("{w}; nothing was written (--strict)")));
        }
        eprintln!("warning: {w}");
    }
    output
        .commit(&trajectory, &prepare()?.csv(None))
        .map_err(Failure::Run)?;
    print_summary(to_file, &line);
    Ok(())
}

fn summary_line(options: &ForwardOptions, s: &RunSummary) -> String {
    let mode = match options.mode {
        Mode::Batch => "batch".to_string(),
        Mode::FixedLag(n) => format!("window {n}"),
    };
    let mut line = format!(
        "{} steps (dt = {} s, {mode}) in {:.3} s; LM iterations per solve: mean {:.2}, max {}; \
         worst |Φ| {:.2e}, worst |Φq q̇| {:.2e}",
        s.steps,
        options.dt,
        s.wall_time.as_secs_f64(),
        s.mean_iterations,
        s.max_iterations,
        s.worst_phi,
        s.worst_velocity_constraint
    );
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
    if let Some(f) = &s.tangent_after {
        line += &format!(
            "; tangent integrators (the paper's did not converge at step {}, t = {} s)",
            f.step,
            forward::round_time(f.t)
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
    line
}

/// A progress bar on stderr, shown only when stderr is a terminal and the run has
/// lasted over a second. Its clock runs from the start of the run, and its ETA is
/// the mean time per step so far times the steps left ([`eta`]): indicatif's own
/// estimator, first fed at the bar's creation with every step done in the first
/// second at once, saw a near-infinite rate and said 0 s.
struct Progress {
    start: Instant,
    bar: Option<indicatif::ProgressBar>,
    enabled: bool,
}

impl Progress {
    fn new() -> Self {
        Progress {
            start: Instant::now(),
            bar: None,
            enabled: std::io::stderr().is_terminal(),
        }
    }

    fn update(&mut self, done: usize, total: usize) {
        if !self.enabled {
            return;
        }
        let elapsed = self.start.elapsed();
        if self.bar.is_none() && elapsed > Duration::from_secs(1) {
            let bar = indicatif::ProgressBar::new(total as u64).with_elapsed(elapsed);
            bar.set_style(
                indicatif::ProgressStyle::with_template(
                    "{elapsed_precise} [{bar:40}] {pos}/{len} steps, eta {left}",
                )
                .expect("a valid template")
                .with_key(
                    "left",
                    |state: &indicatif::ProgressState, w: &mut dyn std::fmt::Write| {
                        let left = eta(state.elapsed(), state.pos(), state.len().unwrap_or(0));
                        let _ = match left {
                            Some(d) => write!(w, "{:#}", indicatif::HumanDuration(d)),
                            None => write!(w, "?"),
                        };
                    },
                )
                .progress_chars("=> "),
            );
            self.bar = Some(bar);
        }
        if let Some(bar) = &self.bar {
            bar.set_position(done as u64);
        }
    }

    fn finish(&mut self) {
        if let Some(bar) = self.bar.take() {
            bar.finish_and_clear();
        }
    }
}

/// The time left at the mean pace so far: `elapsed` for `done` of `total` steps;
/// None before the first step.
fn eta(elapsed: Duration, done: u64, total: u64) -> Option<Duration> {
    if done == 0 {
        return None;
    }
    let left = total.saturating_sub(done) as f64;
    Some(elapsed.mul_f64(left / done as f64))
}

/// Reads and assembles a scene; errors name the file.
fn load(path: &Path) -> Result<(Scene, Model), String> {
    let scene = Scene::load(path).map_err(|e| e.to_string())?;
    let model = Model::new(&scene).map_err(|e| match e {
        Error::Scene(s) => s.to_string(),
        other => format!("{}: {other}", path.display()),
    })?;
    Ok((scene, model))
}

/// `mbfg animate`: hands the drawing to the Python module's `mbfg.animate`.
fn animate(
    run: &Path,
    scene: &Path,
    out: Option<&Path>,
    fps: u32,
    speed: f64,
    trail: Option<&str>,
) -> Result<(), Failure> {
    let python = std::env::var_os("MBFG_PYTHON")
        .map(PathBuf::from)
        .or_else(|| Some(PathBuf::from(".venv/bin/python")).filter(|p| p.exists()))
        .unwrap_or_else(|| PathBuf::from("python3"));
    let mut cmd = std::process::Command::new(&python);
    cmd.args(["-m", "mbfg.animation"])
        .arg(run)
        .arg("--scene")
        .arg(scene)
        .args(["--fps", &fps.to_string(), "--speed", &speed.to_string()]);
    if let Some(out) = out {
        cmd.arg("--out").arg(out);
    }
    if let Some(p) = trail {
        cmd.args(["--trail", p]);
    }
    let done = cmd
        .stderr(std::process::Stdio::piped())
        .output()
        .map_err(|e| {
            Failure::Input(format!(
                "mbfg animate runs {} (the mbfg Python module and matplotlib; MBFG_PYTHON names another interpreter): {e}",
                python.display()
            ))
        })?;
    if done.status.success() {
        return Ok(());
    }
    // One line: the module's own error line, or what stopped the interpreter.
    let err = String::from_utf8_lossy(&done.stderr);
    let last = err
        .lines()
        .rev()
        .find(|l| !l.trim().is_empty())
        .unwrap_or("");
    Err(match last.strip_prefix("error: ") {
        Some(m) => Failure::Input(m.to_string()),
        None if last.contains("No module named") => Failure::Input(format!(
            "{} cannot import the mbfg Python module ({last}): make python builds it into .venv; MBFG_PYTHON names another interpreter",
            python.display()
        )),
        None => Failure::Run(format!("drawing the run failed: {last}")),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn eta_is_the_mean_pace_times_the_steps_left() {
        let s = Duration::from_secs;
        assert_eq!(eta(s(2), 0, 100), None);
        assert_eq!(eta(s(2), 50, 100), Some(s(2)));
        assert_eq!(eta(s(2), 25, 100), Some(s(6)));
        assert_eq!(eta(s(2), 100, 100), Some(s(0)));
        // A position past the length (never expected) is not negative time.
        assert_eq!(eta(s(2), 120, 100), Some(s(0)));
    }

    #[test]
    fn sample_and_column_options_are_checked() {
        let args = |sample_dt, columns: Option<&str>| WrittenArgs {
            sample_dt,
            columns: columns.map(str::to_string),
        };
        let w = Written::new(&args(Some(0.01), Some("energy")), 0.001).unwrap();
        assert_eq!(w.stride, 10);
        assert_eq!(w.groups, [mbfg::derived::Group::Energy]);
        assert!(Written::new(&args(Some(0.0015), None), 0.001).is_err());
        assert!(Written::new(&args(None, Some("nope")), 0.001).is_err());
    }
}
