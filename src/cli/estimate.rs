//! `mbfg estimate`: the motion of a mechanism from its scene's model and a record of
//! noisy sensor readings, by the fixed-lag smoother or a batch solve, with the
//! standard deviation of every estimate and the consistency of the readings.

use super::failure::{plain, Failure};
use super::output::Output;
use super::progress::Progress;
use super::{load, print_summary, seconds};
use mbfg::coordinates::Coordinates;
use mbfg::estimate::options::DEFAULT_PROCESS_STEP;
use mbfg::estimate::{
    estimate_with_progress, EstimateOptions, EstimateSummary, Estimates, ProcessSource, Record,
    Smoothing,
};
use mbfg::factors::Integrator;
use std::cell::RefCell;
use std::path::PathBuf;
use std::sync::Arc;

/// The arguments of `mbfg estimate`.
#[derive(clap::Args)]
pub struct EstimateArgs {
    /// Scene file (YAML) with a `sensors:` section (and optionally `estimation:`).
    scene: PathBuf,
    /// The readings: CSV with `t`, then one column per sensor reading (as `mbfg
    /// measure` writes it); an empty cell is no reading at that time.
    #[arg(long, value_name = "FILE.csv")]
    measurements: PathBuf,
    /// Fixed-lag smoother over the N newest steps: a step's estimate is final when it
    /// leaves the window [default: 20].
    #[arg(long, value_name = "N", conflicts_with = "batch")]
    window: Option<usize>,
    /// Estimate every step at once from the whole record (started from a fixed-lag
    /// pass).
    #[arg(long)]
    batch: bool,
    /// Coordinates of the estimate's graph: dependent (natural; the process noise on
    /// every q̈) or independent (the scene's `independent:`; the process noise on
    /// their z̈).
    #[arg(long, default_value = "dc", value_parser = ["dc", "ic"])]
    coords: String,
    /// The step, in seconds; a reading between steps is compared with the motion's
    /// expansion about its nearest step. Smaller than the readings' period, it follows
    /// motions too fast for that period [default: the readings' period].
    #[arg(long, value_name = "S")]
    dt: Option<f64>,
    /// The rule between consecutive steps: the paper's trapezoidal rule (second
    /// order), or Hermite–Simpson (fourth order, the dynamics also at each step's
    /// middle). [default: hermite-simpson where the scene identifies parameters,
    /// whose fit to a whole record would keep the trapezoidal rule's error as a bias;
    /// trapezoidal otherwise]
    #[arg(long, value_parser = ["trapezoidal", "hermite-simpson"])]
    integrator: Option<String>,
    /// Linear solves allowed per window solve.
    #[arg(long, value_name = "K", default_value_t = 200)]
    max_iterations: usize,
    /// Print every iteration of every window solve to standard error: the window,
    /// the cost before and after the step, LM's damping, the predicted decrease and
    /// the step's size (for diagnosing an estimate that crawls or stops).
    #[arg(long = "trace-solver")]
    trace_solver: bool,
    /// Output CSV (gzip-compressed when it ends in `.gz`); the summary then goes to
    /// standard output.
    #[arg(long, value_name = "FILE.csv")]
    out: Option<PathBuf>,
    /// Write the identified parameters (`estimation: parameters:`) to this CSV: name,
    /// estimate, sigma, prior, prior_sigma, identifiable (yes/no), reason, and their
    /// correlation matrix (corr:<name>), one row a parameter.
    #[arg(long = "parameters-out", value_name = "FILE.csv")]
    parameters_out: Option<PathBuf>,
}

pub fn run(args: EstimateArgs) -> Result<(), Failure> {
    let (_, model) = load(&args.scene)?;
    let model = Arc::new(model);
    if model.sensors.is_empty() {
        return Err(Failure::Input(format!(
            "scene {} has no sensors: declare them in a `sensors:` section (docs/scene-format.md)",
            args.scene.display()
        )));
    }
    if let Some(dt) = args.dt {
        if !(dt > 0.0 && dt.is_finite()) {
            return Err(Failure::Input(format!(
                "--dt must be a positive number of seconds, got {dt}"
            )));
        }
    }
    if args.window == Some(0) {
        return Err(Failure::Input("--window must be at least 1".into()));
    }
    let mut options = EstimateOptions {
        coordinates: if args.coords == "ic" {
            Coordinates::Independent
        } else {
            Coordinates::Dependent
        },
        smoothing: match (args.batch, args.window) {
            (true, _) => Smoothing::Batch,
            (false, Some(w)) => Smoothing::Window(w),
            (false, None) => EstimateOptions::default().smoothing,
        },
        dt: args.dt,
        integrator: args
            .integrator
            .as_deref()
            .map(|name| Integrator::from_name(name).expect("clap checked the name")),
        ..EstimateOptions::default()
    };
    if args.max_iterations == 0 {
        return Err(Failure::Input("--max-iterations must be at least 1".into()));
    }
    options.settings.max_iterations = args.max_iterations;
    options.settings.trace = args.trace_solver;
    if args.parameters_out.is_some() && model.parameters.is_none() {
        return Err(Failure::Input(format!(
            "--parameters-out: scene {} identifies no parameter; name them in \
             `estimation: parameters:` (docs/estimation.md)",
            args.scene.display()
        )));
    }
    let output = Output::open(
        args.out.as_deref(),
        &super::inputs(&args.scene, &model, &[&args.measurements]),
    )?;
    let parameters_out = match &args.parameters_out {
        Some(p) => Some(Output::open(
            Some(p),
            &super::inputs(&args.scene, &model, &[&args.measurements]),
        )?),
        None => None,
    };
    let record =
        Record::read(&model, &args.measurements, args.dt).map_err(|e| Failure::Input(plain(e)))?;
    let table = RefCell::new(Estimates::for_model(&model));
    let started = std::time::Instant::now();
    let mut bar = Progress::new(options.smoothing == Smoothing::Batch);
    let result = estimate_with_progress(
        model.clone(),
        &record,
        &options,
        &mut |e| {
            table.borrow_mut().push(e);
            Ok(())
        },
        &mut |done, total| bar.update(done, total),
    );
    bar.finish();
    let elapsed = started.elapsed().as_secs_f64();
    let table = table.into_inner();
    let to_file = output.to_file();
    match result {
        Ok(summary) => {
            output
                .commit_with(&|w| table.write_csv(w))
                .map_err(Failure::Run)?;
            if let Some(out) = parameters_out {
                out.commit_with(&|w| {
                    summary
                        .identification
                        .write_csv(w)
                        .map_err(|e| mbfg::Error::Io {
                            path: "the parameters' CSV".into(),
                            source: e,
                        })
                })
                .map_err(Failure::Run)?;
            }
            print_summary(to_file, &summary_line(&summary, elapsed));
            for line in parameter_lines(&summary) {
                print_summary(to_file, &line);
            }
            if summary.unsettled > 0 {
                super::tell(&format!(
                    "warning: {} window solves reached the iteration limit ({}) still improving \
                     and were kept, the next step's solve going on from them; \
                     --max-iterations raises the limit",
                    summary.unsettled, options.settings.max_iterations
                ));
            }
            if let Some(w) = consistency_warning(&summary) {
                super::tell(&format!("warning: {w}"));
            }
            for u in &summary.undetermined {
                super::tell(&format!("warning: {}", undetermined_warning(&model, u)));
            }
            Ok(())
        }
        Err(e) => {
            let advice = mbfg::estimate::finer_step_advice(&e, &options, record.dt);
            // Input the run cannot take (no sensors, a batch beyond the memory) exits
            // as bad input; a run that failed, as a failure.
            let input = matches!(e, mbfg::Error::InvalidArgument(_));
            let why = plain(e);
            let kept = if table.rows == 0 || options.smoothing == Smoothing::Batch {
                output.discard();
                "nothing was written".to_string()
            } else {
                output
                    .keep_partial_with(&|w| table.write_csv(w), table.rows, &why)
                    .map_err(Failure::Run)?
            };
            let message = match advice {
                Some(a) => format!("{why}; {kept}; {a}"),
                None => format!("{why}; {kept}"),
            };
            Err(match input {
                true => Failure::Input(message),
                false => Failure::Run(message),
            })
        }
    }
}

/// What ran, in one line.
pub fn summary_line(s: &EstimateSummary, elapsed: f64) -> String {
    let how = match s.smoothing {
        Smoothing::Window(w) if s.longest_window > w => format!(
            "window {w}, grown to {} at most and {:.0} on average while its oldest step was \
             less certain than its newest{}",
            s.longest_window,
            s.mean_window,
            if s.misfit_holds > 0 {
                " or its cost far from a fit's"
            } else {
                ""
            }
        ),
        Smoothing::Window(w) => format!("window {w}"),
        Smoothing::Batch => "batch".to_string(),
    };
    // The paper's trapezoidal rule goes unnamed, as in every summary before it.
    let how = match s.integrator {
        Integrator::Trapezoidal => how,
        other => format!("{}, {how}", other.name()),
    };
    let how = match s.coordinates {
        Coordinates::Dependent => format!("DC, {how}"),
        Coordinates::Independent => format!("IC, {how}"),
    };
    let nis = &s.nis;
    let (lo, hi) = nis.bounds();
    let verdict = if nis.consistent() {
        "consistent"
    } else {
        "NOT consistent"
    };
    format!(
        "{} steps (dt = {} s, {how}) from {} readings{} in {:.3} s ({:.0} µs a step); \
         linear solves per step: mean {:.2}{}; mean NIS {:.3} against {:.3} expected, \
         95 % bounds [{lo:.3}, {hi:.3}]: {verdict}; process σ {}",
        s.steps,
        seconds(s.dt),
        s.readings,
        match s.between_steps {
            (0, _) => String::new(),
            (n, most) => format!(
                " ({n} between steps, up to {} s from their nearest, compared with the \
                 motion's expansion about it)",
                mbfg::io::three_digits(most)
            ),
        },
        elapsed,
        elapsed / s.steps.max(1) as f64 * 1e6,
        s.iterations as f64 / s.steps.max(1) as f64,
        match s.refits {
            0 => String::new(),
            r => format!(
                ", the start solved again from the filter's path {r} time{} (its window's \
                 cost far from a fit's)",
                if r == 1 { "" } else { "s" }
            ),
        },
        nis.mean(),
        nis.expected(),
        process(s)
    )
}

/// One line per identified parameter: its estimate and σ against its prior, or why
/// the readings do not determine it.
pub fn parameter_lines(s: &EstimateSummary) -> Vec<String> {
    let id = &s.identification;
    let mut lines: Vec<String> = id
        .parameters
        .iter()
        .map(|p| {
            let lowered = p.sigma_lowered.map_or(String::new(), |l| {
                format!(", ± {l:.2e} at the lowered process σ")
            });
            let head = format!(
                "parameter {} = {} ± {:.2e}{lowered} (prior {} ± {})",
                p.name,
                significant(p.estimate, p.sigma.min(p.sigma_lowered.unwrap_or(p.sigma))),
                p.sigma,
                short(p.prior),
                short(p.prior_sigma)
            );
            match &p.undetermined {
                None => head,
                Some(why) => format!("{head}: NOT identified, {why}"),
            }
        })
        .collect();
    let np = id.parameters.len();
    let strong: Vec<String> = (0..np)
        .flat_map(|i| (i + 1..np).map(move |j| (i, j)))
        .filter(|&(i, j)| id.correlation[i * np + j].abs() >= STRONG_CORRELATION)
        .map(|(i, j)| {
            format!(
                "{}–{} {:+.3}",
                id.parameters[i].name,
                id.parameters[j].name,
                id.correlation[i * np + j]
            )
        })
        .collect();
    if !strong.is_empty() {
        lines.push(format!(
            "parameters correlated by {STRONG_CORRELATION} or more: {}",
            strong.join(", ")
        ));
    }
    lines
}

/// A correlation the summary points out (the whole matrix is in --parameters-out).
const STRONG_CORRELATION: f64 = 0.9;

/// `v` to six significant digits, without trailing zeros.
fn short(v: f64) -> String {
    let s = format!("{v:.6e}");
    match s.parse::<f64>() {
        Ok(r) => format!("{r}"),
        Err(_) => s,
    }
}

/// `v` to two significant digits of its σ.
fn significant(v: f64, sigma: f64) -> String {
    let digits = if sigma > 0.0 && sigma.is_finite() {
        (1.0 - sigma.log10().floor()).clamp(0.0, 15.0) as usize
    } else {
        6
    };
    format!("{v:.digits$}")
}

/// The process σ and where it came from.
fn process(s: &EstimateSummary) -> String {
    let sigma = mbfg::io::three_digits(s.process_sigma);
    match s.process_source {
        ProcessSource::Scene => format!("{sigma} (the scene's)"),
        ProcessSource::Default => format!("{sigma} (the default{})", at_step(s)),
        ProcessSource::Unresponsive { tried, then, .. } => format!(
            "{sigma} (the default{}; at {} a filter pass's mean NIS was still {then:.3})",
            at_step(s),
            mbfg::io::three_digits(tried)
        ),
        ProcessSource::Correlated { tried, lag_one, .. } => format!(
            "{sigma} (the default{}; at {}, where a filter pass's mean NIS was inside its \
             bounds, its innovations' lag-one autocorrelation was {lag_one:.2}: not white)",
            at_step(s),
            mbfg::io::three_digits(tried)
        ),
        ProcessSource::Identified { from, used } => format!(
            "{sigma} (lowered after identification: at the default {} the batch's dynamics \
             residuals used {:.2e} of their expected χ²)",
            mbfg::io::three_digits(from),
            used
        ),
        ProcessSource::Readings {
            nis,
            bounds,
            default,
        } => format!(
            "{sigma} (from the readings: the default {} left a filter pass's mean NIS at \
             {nis:.3}, outside [{:.3}, {:.3}])",
            mbfg::io::three_digits(default),
            bounds.0,
            bounds.1
        ),
    }
}

/// How the default process σ was scaled to the run's step, where it was.
fn at_step(s: &EstimateSummary) -> String {
    if (s.dt - DEFAULT_PROCESS_STEP).abs() <= 1e-12 * DEFAULT_PROCESS_STEP {
        String::new()
    } else {
        format!(
            ", scaled to the {} s step from its value at {DEFAULT_PROCESS_STEP} s",
            seconds(s.dt)
        )
    }
}

/// The mean NIS, as a multiple of its expected value, beyond which an identification's
/// warning says the model does not describe the readings: misfits of √10 ≈ 3.2 σ on
/// average (a four-bar estimated on the other assembly than its readings' gave 31).
const FAR_FROM_THE_READINGS: f64 = 10.0;

/// What a mean NIS outside its bounds says, and what to change.
pub fn consistency_warning(s: &EstimateSummary) -> Option<String> {
    let nis = &s.nis;
    if nis.count == 0 || nis.consistent() {
        return None;
    }
    let (lo, hi) = nis.bounds();
    let unresponsive = matches!(s.process_source, ProcessSource::Unresponsive { .. });
    // The NIS is the fixed-lag pass's, at the σ before any lowering.
    let now = match s.process_source {
        ProcessSource::Identified { from, .. } => {
            format!("{from}, the default, in the fixed-lag pass the NIS comes from")
        }
        _ => process(s),
    };
    Some(if nis.mean() > hi && unresponsive {
        format!(
            "the mean NIS {:.3} is above its 95 % bound {hi:.3}: the readings disagree with \
             the model more than the σ's allow, and a larger process σ does not change \
             that (process σ {}): look at the sensors' `sigma` (noise, quantization) and at \
             the model",
            nis.mean(),
            now
        )
    } else if nis.mean() > hi {
        let ratio = nis.mean() / nis.expected();
        let far = if ratio > FAR_FROM_THE_READINGS && !s.identification.is_empty() {
            format!(
                ". At {ratio:.0} times its expected value the misfits are {:.1} times their σ's (RMS): \
                 unless the sensors' σ's are that much too small, the model does not describe \
                 these readings (a start on the other assembly, a wrong constant left fixed), \
                 and the parameters are the best fit of a wrong model, not an identification",
                ratio.sqrt()
            )
        } else {
            String::new()
        };
        format!(
            "the mean NIS {:.3} is above its 95 % bound {hi:.3}: the readings disagree with \
             the model more than the σ's allow; the reported σ's are too small. Raise \
             `estimation: process_sigma` (now {}) or the sensors' `sigma`{far}",
            nis.mean(),
            now
        )
    } else if let ProcessSource::Correlated { tried, lag_one, .. } = s.process_source {
        format!(
            "the mean NIS {:.3} is below its 95 % bound {lo:.3}, but a smaller process σ \
             leaves the innovations correlated (lag-one {lag_one:.2} at σ {}): a bias in the \
             model or in a sensor's model that white process noise does not describe; the σ's \
             stay large (`inputs:` or `parameters:` can carry the bias)",
            nis.mean(),
            mbfg::io::three_digits(tried)
        )
    } else if unresponsive {
        format!(
            "the mean NIS {:.3} is below its 95 % bound {lo:.3}: the readings agree with \
             the model better than the σ's say, and a smaller process σ does not change \
             that (process σ {}): the sensors' `sigma` may be too large",
            nis.mean(),
            process(s)
        )
    } else {
        format!(
            "the mean NIS {:.3} is below its 95 % bound {lo:.3}: the readings agree with the \
             model better than the σ's say; the reported σ's are too large. Lower \
             `estimation: process_sigma` (now {}) or the sensors' `sigma`",
            nis.mean(),
            now
        )
    })
}

/// A coordinate the readings leave undetermined, named with what to do.
pub fn undetermined_warning(model: &mbfg::Model, u: &mbfg::estimate::Undetermined) -> String {
    let name = &model.names[u.coordinate];
    let mean = mbfg::io::three_digits(u.mean_sd);
    if u.prior < u.against {
        format!(
            "the readings leave '{name}' undetermined: its σ averages {mean} over the run, \
             from a start known to {}, so its estimate is that start carried by the model; \
             add a sensor that observes it (directly or through the dynamics)",
            u.prior
        )
    } else {
        format!(
            "the readings leave '{name}' undetermined: its σ averages {mean} over the run \
             against {} for the prior on its start, so its estimate is that prior's guess \
             carried by the model; add a sensor that observes it (directly or through the \
             dynamics), or give its start in `estimation: initial_sigma` if it is known",
            u.prior
        )
    }
}
