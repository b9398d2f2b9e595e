//! `mbfg animate`: the drawing of a run, handed to the Python module.

use super::failure::Failure;
use std::path::{Path, PathBuf};

/// The arguments of `mbfg animate`.
#[derive(clap::Args)]
pub struct AnimateArgs {
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
    /// Draw the ground's reaction at every fixed point as an arrow.
    #[arg(long)]
    forces: bool,
}

/// `mbfg animate`: the arguments passed on.
pub fn run(args: AnimateArgs) -> Result<(), Failure> {
    let AnimateArgs {
        run,
        scene,
        out,
        fps,
        speed,
        trail,
        forces,
    } = args;
    animate(
        &run,
        &scene,
        out.as_deref(),
        fps,
        speed,
        trail.as_deref(),
        forces,
    )
}

/// The Python that draws: `MBFG_PYTHON`; else the active virtual environment's;
/// else the `.venv` of the checkout this binary was built in (it sits in
/// `<checkout>/target/release/`), wherever the command runs from; else `python3`.
fn interpreter() -> PathBuf {
    if let Some(p) = std::env::var_os("MBFG_PYTHON") {
        return PathBuf::from(p);
    }
    let active = std::env::var_os("VIRTUAL_ENV").map(|v| PathBuf::from(v).join("bin/python"));
    let checkout = std::env::current_exe()
        .ok()
        .and_then(|exe| exe.canonicalize().ok())
        .and_then(|exe| Some(exe.parent()?.parent()?.parent()?.join(".venv/bin/python")));
    active
        .into_iter()
        .chain(checkout)
        .find(|p| p.exists())
        .unwrap_or_else(|| PathBuf::from("python3"))
}

/// `mbfg animate`: hands the drawing to the Python module's `mbfg.animate`.
fn animate(
    run: &Path,
    scene: &Path,
    out: Option<&Path>,
    fps: u32,
    speed: f64,
    trail: Option<&str>,
    forces: bool,
) -> Result<(), Failure> {
    let python = interpreter();
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
    if forces {
        cmd.arg("--forces");
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
