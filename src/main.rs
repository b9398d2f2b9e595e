//! The `mbfg` command line. Errors end with exit code 2 and one line on stderr.

use clap::{Parser, Subcommand, ValueEnum};
use mbfg::check::CheckReport;
use mbfg::forward::{
    self, Coordinates, ForwardOptions, Integrator, NoiseModels, RunSummary, Trajectory,
};
use mbfg::smoother::Mode;
use mbfg::solver::Past;
use mbfg::{Error, Model, Scene};
use std::io::IsTerminal;
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
        /// Trajectory CSV to write; the summary then goes to standard output.
        #[arg(long, value_name = "FILE.csv")]
        out: Option<PathBuf>,
        /// Integrator factor between steps.
        #[arg(long, value_enum, default_value_t = IntegratorArg::Trapezoidal)]
        integrator: IntegratorArg,
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
        /// Output CSV (trajectory plus `Q:<c>` columns); the summary then goes to
        /// standard output.
        #[arg(long, value_name = "FILE.csv")]
        out: Option<PathBuf>,
    },
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
    Trapezoidal,
    Euler,
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

/// Why a command failed: bad input (exit 2) or a run that did not converge (exit 1).
enum Failure {
    Input(String),
    Run(String),
}

impl From<String> for Failure {
    fn from(m: String) -> Self {
        Failure::Input(m)
    }
}

fn main() -> ExitCode {
    let cli = match Cli::try_parse() {
        Ok(cli) => cli,
        Err(e) => {
            let code = if e.use_stderr() { 2 } else { 0 };
            let _ = e.print();
            return ExitCode::from(code);
        }
    };
    match run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(Failure::Input(message)) => {
            eprintln!("error: {message}");
            ExitCode::from(2)
        }
        Err(Failure::Run(message)) => {
            eprintln!("error: {message}");
            ExitCode::from(1)
        }
    }
}

/// Runs a command; the error is the one line to print.
fn run(cli: Cli) -> Result<(), Failure> {
    match cli.command {
        Command::Check { scene } => {
            let (scene, model) = load(&scene)?;
            println!("{}", CheckReport::new(&scene, &model));
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
            integrator,
            noise,
            past,
            continue_on_failure,
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
            options.validate(&model).map_err(plain)?;
            simulate(model, &options, out.as_deref())
        }
        Command::Inverse {
            scene,
            trajectory,
            coords,
            max_iterations,
            start,
            out,
        } => {
            let (_, model) = load(&scene)?;
            if max_iterations == 0 {
                return Err(Failure::Input("--max-iterations must be at least 1".into()));
            }
            let start = match start {
                StartArg::Kinematic => mbfg::inverse::Start::Kinematic,
                StartArg::Staged => mbfg::inverse::Start::Staged,
            };
            inverse(
                model,
                &trajectory,
                coords,
                max_iterations,
                start,
                out.as_deref(),
            )
        }
    }
}

/// `mbfg inverse`: reads the prescription, solves, writes the CSV and the summary.
fn inverse(
    model: Model,
    trajectory: &Path,
    coords: InverseCoords,
    max_iterations: usize,
    start: mbfg::inverse::Start,
    out: Option<&Path>,
) -> Result<(), Failure> {
    let table = mbfg::io::read_table(trajectory).map_err(plain)?;
    let prescription =
        mbfg::inverse::Prescription::from_table(&model, &table, &trajectory.display().to_string())
            .map_err(plain)?;
    let mut output = Output::open(out)?;
    let mut options = mbfg::inverse::InverseOptions::default();
    options.settings.max_iterations = max_iterations;
    options.start = start;
    options.coordinates = match coords {
        InverseCoords::Dc => Coordinates::Dependent,
        InverseCoords::Ic => Coordinates::Independent,
    };
    let model = Arc::new(model);
    let sol = mbfg::inverse::solve(model, &prescription, &options).map_err(|e| match e {
        Error::InvalidArgument(m) => Failure::Input(m),
        other => Failure::Run(plain(other)),
    })?;
    output.write(&sol.trajectory, Some(&sol.forces))?;
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
    output.summary(&line);
    if s.report.termination != mbfg::solver::Termination::Converged {
        return Err(Failure::Run(format!(
            "the inverse solve did not converge: {}, cost {:.3e} after {} iterations (--max-iterations allows more)",
            s.report.termination, s.report.cost, s.report.iterations
        )));
    }
    Ok(())
}

/// Where a command's CSV goes: the `--out` file (opened before the run, so that an
/// unwritable path is refused as bad input) or standard output. The summary line goes
/// to standard output beside a file, to standard error beside CSV on standard output.
struct Output {
    file: Option<std::fs::File>,
    to_file: bool,
}

impl Output {
    fn open(out: Option<&Path>) -> Result<Self, Failure> {
        let file = match out {
            Some(p) => Some(
                std::fs::File::create(p)
                    .map_err(|e| format!("cannot write {}: {e}", p.display()))?,
            ),
            None => None,
        };
        Ok(Output {
            to_file: file.is_some(),
            file,
        })
    }

    fn write(&mut self, trajectory: &Trajectory, forces: Option<&[f64]>) -> Result<(), Failure> {
        let written = match self.file.take() {
            Some(f) => mbfg::io::write_trajectory(std::io::BufWriter::new(f), trajectory, forces),
            None => mbfg::io::write_trajectory(std::io::stdout().lock(), trajectory, forces),
        };
        written.map_err(|e| Failure::Run(plain(e)))
    }

    fn summary(&self, line: &str) {
        if self.to_file {
            println!("{line}");
        } else {
            eprintln!("{line}");
        }
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
fn simulate(model: Model, options: &ForwardOptions, out: Option<&Path>) -> Result<(), Failure> {
    // Open the output first: an unwritable path is bad input, found before the run.
    let mut output = Output::open(out)?;
    let mut bar = Progress::new();
    let result = forward::simulate(Arc::new(model), options, &mut |done, total| {
        bar.update(done, total)
    });
    bar.finish();
    let (trajectory, summary) = result.map_err(|e| Failure::Run(plain(e)))?;
    let first_failure = summary.failures.first().cloned();
    let stopped = first_failure.is_some() && !options.continue_on_failure;
    // A batch that did not converge has no trustworthy step to write.
    let writable = !(stopped && options.mode == Mode::Batch);
    if writable {
        output.write(&trajectory, None)?;
    }
    let line = summary_line(options, &summary);
    output.summary(&line);
    for f in summary.failures.iter().skip(usize::from(stopped)).take(10) {
        eprintln!("warning: {}", f.message());
    }
    if let (true, Some(f)) = (stopped, first_failure) {
        let what = if writable {
            format!("the {} steps before it were written", trajectory.len())
        } else {
            "nothing was written".into()
        };
        // More iterations do not help the solves that stall (they crawl along a
        // direction the cost barely sees), so --max-iterations is not suggested.
        let hint = if f.singular.is_some() {
            "dependent coordinates (--coords dc) do not depend on that choice"
        } else if f.warm_start {
            "--window 1 writes the run up to there"
        } else if f.report.termination == mbfg::solver::Termination::Diverged {
            "a diverged solve ends the run, --continue-on-failure too"
        } else {
            "--continue-on-failure goes on past it"
        };
        return Err(Failure::Run(format!("{}; {what} ({hint})", f.message())));
    }
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
/// lasted over a second.
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
        if self.bar.is_none() && self.start.elapsed() > Duration::from_secs(1) {
            let bar = indicatif::ProgressBar::new(total as u64);
            bar.set_style(
                indicatif::ProgressStyle::with_template(
                    "{elapsed_precise} [{bar:40}] {pos}/{len} steps, eta {eta}",
                )
                .expect("a valid template")
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

/// Reads and assembles a scene; errors name the file.
fn load(path: &Path) -> Result<(Scene, Model), String> {
    let scene = Scene::load(path).map_err(|e| e.to_string())?;
    let model = Model::new(&scene).map_err(|e| match e {
        Error::Scene(s) => s.to_string(),
        other => format!("{}: {other}", path.display()),
    })?;
    Ok((scene, model))
}
