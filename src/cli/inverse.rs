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
    /// Treat the prescribed samples as measurements with noise σ: smooth them (a
    /// motion whose fourth derivative is white noise, its intensity by maximum
    /// likelihood), solve from the smoothed motion, and write the standard deviations
    /// (`sd:q:<c>`, `sd:dq:<c>`, `sd:ddq:<c>`, `sd:Q:<c>`) after the standard
    /// columns. S: one σ for every column (`1e-4`), one per column
    /// (`theta=1e-4,phi=2e-4`, every prescribed column named once), or `auto`: σ
    /// chosen from the data (the samples' scatter about the smooth motion, or the
    /// rounding of their printed digits, whichever is likelier), printed in the
    /// summary. Without it, the samples are exact (fourth-order differences).
    #[arg(long = "sample-sigma", value_name = "S|auto|c=S,...")]
    sample_sigma: Option<String>,
    #[command(flatten)]
    written: WrittenArgs,
    /// Write the result of a solve that did not converge too, to
    /// `<out>.partial.csv` (or to standard output, ended by `# incomplete`).
    #[arg(long = "keep-unconverged")]
    keep_unconverged: bool,
    /// Print every iteration of the batch solve to standard error: the cost before
    /// and after the step, LM's damping, the predicted decrease and the step's size.
    #[arg(long = "trace-solver")]
    trace_solver: bool,
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
        sample_sigma,
        written,
        keep_unconverged,
        trace_solver,
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
    options.settings.trace = trace_solver;
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
        options,
        sample_sigma.as_deref(),
        output,
        keep_unconverged,
        &written,
    )
}

/// A sample this many of its σ's from the smoothed motion is warned about: a Gaussian
/// error goes that far once in about 10⁹ samples.
const OUTLIER: f64 = 6.0;

/// `--sample-sigma`'s value for the prescribed `columns`: `auto`, one σ, or
/// `c=σ,...` naming every column once.
fn sample_sigma(text: &str, columns: &[&str]) -> Result<mbfg::inverse::SampleSigma, String> {
    use mbfg::inverse::SampleSigma;
    let text = text.trim();
    let number = |v: &str, what: &str| -> Result<f64, String> {
        match v.trim().parse::<f64>() {
            Ok(x) if x.is_finite() && x > 0.0 => Ok(x),
            _ => Err(format!(
                "--sample-sigma: {what} must be a positive number, got `{}`",
                mbfg::expr::excerpt(v.trim(), 40)
            )),
        }
    };
    if text == "auto" {
        return Ok(SampleSigma::FromData);
    }
    if !text.contains('=') {
        return Ok(SampleSigma::Given(vec![number(text, "σ")?; columns.len()]));
    }
    let mut given: Vec<Option<f64>> = vec![None; columns.len()];
    for part in text.split(',') {
        let Some((name, value)) = part.split_once('=') else {
            return Err(format!(
                "--sample-sigma: `{}` is not `<coordinate>=<σ>`",
                mbfg::expr::excerpt(part.trim(), 40)
            ));
        };
        let name = name.trim();
        let Some(c) = columns.iter().position(|c| *c == name) else {
            return Err(format!(
                "--sample-sigma: `{}` is not a prescribed coordinate; the trajectory's are {}",
                mbfg::expr::excerpt(name, 40),
                columns.join(", ")
            ));
        };
        if given[c].is_some() {
            return Err(format!("--sample-sigma: `{name}` is given twice"));
        }
        given[c] = Some(number(value, &format!("the σ of `{name}`"))?);
    }
    SampleSigma::per_column(columns, given).map_err(|why| format!("--sample-sigma: {why}"))
}

/// The summary's words on the smoothing: per column its σ (given, from the scatter,
/// or from the rounding of the printed digits) and the samples' RMS residual.
fn smoothing_words(names: &[&str], fits: &[mbfg::inverse::ColumnFit], when: &str) -> String {
    let parts: Vec<String> = names
        .iter()
        .zip(fits)
        .map(|(name, f)| {
            let how = match (f.from_data, f.noise) {
                (false, _) => "given".to_string(),
                (true, mbfg::inverse::NoiseShape::Uniform) => "from the data".to_string(),
                (true, mbfg::inverse::NoiseShape::Rounding { digits }) => format!(
                    "from the data: rounding of {digits} significant digits, σ at the largest step"
                ),
            };
            format!(
                "{name} σ {:.3e} ({how}), residual RMS {:.3e}",
                f.sigma, f.residual_rms
            )
        })
        .collect();
    format!("; samples smoothed{when}: {}", parts.join(", "))
}

/// The standard deviations as columns `sd:q:<c>`…, `sd:dq:<c>`…, `sd:ddq:<c>`…,
/// `sd:Q:<c>`…, row-major steps × 4n.
fn sigma_columns(names: &[String], s: &mbfg::inverse::Sigmas) -> mbfg::derived::Columns {
    let n = names.len();
    let steps = s.q.len().checked_div(n).unwrap_or(0);
    let mut columns = Vec::with_capacity(4 * n);
    for part in ["q", "dq", "ddq", "Q"] {
        columns.extend(names.iter().map(|c| format!("sd:{part}:{c}")));
    }
    let mut values = Vec::with_capacity(steps * 4 * n);
    for k in 0..steps {
        for part in [&s.q, &s.dq, &s.ddq, &s.forces] {
            values.extend_from_slice(&part[k * n..(k + 1) * n]);
        }
    }
    mbfg::derived::Columns {
        names: columns,
        values,
    }
}

/// `mbfg inverse`: reads the prescription, solves, writes the CSV and the summary.
#[allow(clippy::too_many_arguments)] // the command's options, one each
fn inverse(
    model: Model,
    trajectory: &Path,
    mut options: mbfg::inverse::InverseOptions,
    sample_sigma_arg: Option<&str>,
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
    let written = Written::new(
        written,
        prescription.dt,
        mbfg::derived::WorkRule::Trapezoidal,
    )?;
    let columns: Vec<&str> = prescription
        .indices
        .iter()
        .map(|&i| model.names[i].as_str())
        .collect();
    if let Some(text) = sample_sigma_arg {
        options.sample_sigma = Some(sample_sigma(text, &columns).map_err(Failure::Input)?);
    } else {
        prescription.check_grid(&file).map_err(plain)?;
    }
    let smoothing_names: Vec<String> = columns.iter().map(|c| c.to_string()).collect();
    let model = Arc::new(model);
    let sol =
        mbfg::inverse::solve(model.clone(), &prescription, &options).map_err(|e| match e {
            Error::InvalidArgument(m) => Failure::Input(m),
            other => Failure::Run(plain(other)),
        })?;
    let s = &sol.summary;
    let mut line = format!(
        "{} steps (dt = {} s, batch) in {:.3} s; {} LM iterations ({}); worst tracking error {:.2e}; worst |Φ| {:.2e}",
        s.steps,
        super::seconds(prescription.dt),
        s.wall_time.as_secs_f64(),
        s.report.iterations,
        s.report.termination,
        s.worst_tracking,
        s.worst_phi
    );
    if let Some(fits) = &s.smoothing {
        let names: Vec<&str> = smoothing_names.iter().map(String::as_str).collect();
        let at_their_times = s.off_grid.map(|(shortest, longest)| {
            format!(
                " at their own times (intervals {} to {} s), read on the grid of their mean interval",
                mbfg::io::three_digits(shortest),
                mbfg::io::three_digits(longest)
            )
        });
        line += &smoothing_words(&names, fits, at_their_times.as_deref().unwrap_or(""));
        for (name, f) in names.iter().zip(fits) {
            let (z, k) = f.worst_residual;
            if z > OUTLIER {
                eprintln!(
                    "warning: the sample of {name} at t = {} (line {}) is {z:.0}σ from the smoothed motion: a glitch, an angle written wrapped, or a σ too small; the smoothing follows it only partly",
                    prescription.sample_time(k),
                    k + 2
                );
            }
        }
    }
    let to_file = output.to_file();
    // Computed only for what is written.
    let prepare = || {
        let prepared = written.prepare(&model, &sol.trajectory, Some(&sol.forces))?;
        Ok::<_, Failure>(match &sol.sigmas {
            Some(sd) => prepared.with_leading(sigma_columns(&model.names, sd)),
            None => prepared,
        })
    };
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
