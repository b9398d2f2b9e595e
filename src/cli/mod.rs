//! The `mbfg` subcommands, one file each with its arguments and its body, and the
//! pieces they share: what a command's failure turns into, where outputs go, the
//! optional columns and rows, the progress bar, and what Ctrl-C and panics turn into.

pub mod animate;
pub mod check;
pub mod estimate;
pub mod failure;
pub mod interrupt;
pub mod inverse;
pub mod measure;
pub mod memory;
pub mod output;
pub mod panic;
pub mod progress;
pub mod simulate;
pub mod written;

use mbfg::{Error, Model, Scene};
use std::path::Path;

/// Reads and assembles a scene; errors name the file.
pub fn load(path: &Path) -> Result<(Scene, Model), String> {
    let scene = Scene::load(path).map_err(|e| e.to_string())?;
    let model = Model::new(&scene).map_err(|e| match e {
        Error::Scene(s) => s.to_string(),
        // Messages that name the file already (a model too large to assemble).
        Error::InvalidArgument(m) if m.starts_with(&*path.to_string_lossy()) => m,
        other => format!("{}: {other}", path.display()),
    })?;
    Ok((scene, model))
}

/// The files a command reads: the scene, the mechanism file it names, and `others`
/// (a trajectory, measurements). `--out` may name none of them.
pub fn inputs<'a>(scene: &'a Path, model: &'a Model, others: &[&'a Path]) -> Vec<&'a Path> {
    let mut all = vec![scene];
    all.extend(model.scene.mechanism.as_deref().map(Path::new));
    all.extend_from_slice(others);
    all
}

/// The summary line goes to standard output beside a CSV file, to standard error
/// beside CSV on standard output.
pub fn print_summary(to_file: bool, line: &str) {
    if to_file {
        say(line);
    } else {
        tell(line);
    }
}

/// A line on standard output. A consumer that stopped reading (`mbfg check S | head`)
/// is not an error: what it wanted went out.
pub fn say(line: &str) {
    use std::io::Write;
    let mut out = std::io::stdout().lock();
    let _ = writeln!(out, "{line}").and_then(|()| out.flush());
}

/// A line on standard error (warnings, summaries, the error line). An unwritable
/// standard error loses the line, never the run.
pub fn tell(line: &str) {
    use std::io::Write;
    let _ = writeln!(std::io::stderr().lock(), "{line}");
}

/// Whether a write error means that the reader of a pipe went away.
pub fn consumer_gone(error: &str) -> bool {
    error.contains("Broken pipe") || error.contains("os error 32")
}

/// A time in seconds as the summary lines print it: as Rust writes it, except far
/// outside any mechanism's time scales, where that would be hundreds of digits
/// (dt = 1e-300 s).
pub fn seconds(v: f64) -> String {
    if v != 0.0 && !(1e-9..1e9).contains(&v.abs()) {
        format!("{v:e}")
    } else {
        format!("{v}")
    }
}

#[cfg(test)]
mod tests {
    #[test]
    fn seconds_stay_short() {
        assert_eq!(super::seconds(0.001), "0.001");
        assert_eq!(super::seconds(0.00001), "0.00001");
        assert_eq!(super::seconds(1e-300), "1e-300");
        assert_eq!(super::seconds(0.0), "0");
    }
}
