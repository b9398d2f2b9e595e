//! The `mbfg` command line. Every error is one line on stderr; the exit code says
//! which kind: 2 bad input, 1 a run that failed or ended early, 130 interrupted,
//! 70 a bug (a panic, caught here).

mod cli;

use clap::{Parser, Subcommand};
use cli::failure::{clap_line, shorten, Failure};
use std::process::ExitCode;

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
    Check(cli::check::CheckArgs),
    /// Forward dynamics: simulate the scene from its initial state and write the
    /// trajectory as CSV (to --out, or to standard output).
    #[command(allow_negative_numbers = true)]
    Simulate(cli::simulate::SimulateArgs),
    /// Draw a run: the mechanism's motion from a trajectory CSV, as a GIF or an MP4
    /// (matplotlib, through the mbfg Python module: `make python`; MBFG_PYTHON names
    /// the interpreter, default .venv/bin/python beside the current directory, then
    /// python3).
    Animate(cli::animate::AnimateArgs),
    /// Inverse dynamics: the forces on the prescribed coordinates that produce their
    /// motion, and the motion of all the others, solved over the whole horizon.
    Inverse(cli::inverse::InverseArgs),
    /// Simulated sensor readings: the scene's sensors read along a trajectory CSV,
    /// with seeded Gaussian noise and quantization, written as CSV (to --out, or
    /// to standard output).
    Measure(cli::measure::MeasureArgs),
    /// State estimation: the motion from the scene's model and noisy sensor readings, with the standard deviation of every estimate
    Estimate(cli::estimate::EstimateArgs),
}

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
            cli::tell(&format!("error: {}", clap_line(&e)));
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
    cli::tell(&format!("error: {}", shorten(&message)));
    ExitCode::from(code)
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
        Command::Check(args) => cli::check::run(args),
        Command::Simulate(args) => cli::simulate::run(args),
        Command::Animate(args) => cli::animate::run(args),
        Command::Inverse(args) => cli::inverse::run(args),
        Command::Measure(args) => cli::measure::run(args),
        Command::Estimate(args) => cli::estimate::run(args),
    }
}
