//! The `mbfg` command line. Errors end with exit code 2 and one line on stderr.

use clap::{Parser, Subcommand};
use mbfg::check::CheckReport;
use mbfg::{Error, Model, Scene};
use std::path::PathBuf;
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
    Check {
        /// Scene or MBSE mechanism file (YAML).
        scene: PathBuf,
    },
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
        Err(message) => {
            eprintln!("error: {message}");
            ExitCode::from(2)
        }
    }
}

/// Runs a command; the error is the one line to print.
fn run(cli: Cli) -> Result<(), String> {
    match cli.command {
        Command::Check { scene } => {
            let (scene, model) = load(&scene)?;
            println!("{}", CheckReport::new(&scene, &model));
            Ok(())
        }
    }
}

/// Reads and assembles a scene; errors name the file.
fn load(path: &std::path::Path) -> Result<(Scene, Model), String> {
    let scene = Scene::load(path).map_err(|e| e.to_string())?;
    let model = Model::new(&scene).map_err(|e| match e {
        Error::Scene(s) => s.to_string(),
        other => format!("{}: {other}", path.display()),
    })?;
    Ok((scene, model))
}
