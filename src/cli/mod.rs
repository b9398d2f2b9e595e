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
        other => format!("{}: {other}", path.display()),
    })?;
    Ok((scene, model))
}

/// The summary line goes to standard output beside a CSV file, to standard error
/// beside CSV on standard output.
pub fn print_summary(to_file: bool, line: &str) {
    if to_file {
        println!("{line}");
    } else {
        eprintln!("{line}");
    }
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
