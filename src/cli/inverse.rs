//! `mbfg inverse`: its arguments, the prescription read from CSV, the batch solve,
//! the CSV with the forces and the summary line.

use super::failure::{plain, Failure};
use super::output::Output;
use super::written::{Written, WrittenArgs};
use super::{load, print_summary};
use clap::ValueEnum;
use mbfg::forward::Coordinates;
use mbfg::{Error, Model};
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// The arguments of `mbfg inverse`.
#[derive(clap::Args)]
pub struct InverseArgs {
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

/// `mbfg inverse`: the options from the arguments; the output is opened before the
/// solve.
pub fn run(args: InverseArgs) -> Result<(), Failure> {
    let InverseArgs {
        scene,
        trajectory,
        coords,
        max_iterations,
        start,
        out,
        written,
        keep_unconverged,
    } = args;
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
    let output = Output::open(
        out.as_deref(),
        &super::inputs(&scene, &model, &[&trajectory]),
    )?;
    inverse(
        model,
        &trajectory,
        &options,
        output,
        keep_unconverged,
        &written,
    )
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
        super::seconds(prescription.dt),
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
        let why = mbfg::Error::NotConverged {
            what: "the inverse solve".into(),
            report: s.report.clone(),
        }
        .to_string();
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
