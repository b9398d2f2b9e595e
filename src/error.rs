//! The library's one error type.

use crate::convergence::SolveReport;
use std::fmt;

/// An error in a scene or mechanism file, located as precisely as the parser knows.
#[derive(Debug, Clone, PartialEq)]
pub struct SceneError {
    /// The file, as the user named it.
    pub file: String,
    /// 1-based line, when known.
    pub line: Option<u64>,
    /// The key or name at fault, as a path such as `bodies[1].mass`.
    pub key: String,
    pub message: String,
}

impl fmt::Display for SceneError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}", self.file)?;
        if let Some(line) = self.line {
            write!(f, ":{line}")?;
        }
        if self.key.is_empty() {
            write!(f, ": {}", self.message)
        } else {
            write!(f, ": {}: {}", self.key, self.message)
        }
    }
}

impl std::error::Error for SceneError {}

/// Everything that can go wrong in mbfg.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum Error {
    #[error("{0}")]
    Scene(#[from] SceneError),

    #[error("{path}: {source}")]
    Io {
        path: String,
        #[source]
        source: std::io::Error,
    },

    /// The position problem did not close: the named constraints stay violated.
    #[error("the position problem did not converge after {iterations} iterations; constraints left violated: {}",
        list_violated(.violated))]
    PositionProblem {
        violated: Vec<(String, f64)>,
        iterations: usize,
    },

    /// A linear system that should be regular is singular (a singular configuration,
    /// or independent coordinates that do not determine the motion): `what` says
    /// which, `step` and `t` locate it in a run where known.
    #[error("singular system: {}", located(.what, *.step, *.t))]
    Singular {
        what: String,
        step: Option<usize>,
        t: Option<f64>,
    },

    /// A solve that did not converge: `what` names it, `report` says how it ended.
    #[error("{what} did not converge: {report}")]
    NotConverged { what: String, report: SolveReport },

    /// A data file (CSV) that cannot be read or written, or whose content is
    /// malformed: the file and, where known, the line.
    #[error("{}", in_file(.file, *.line, .message))]
    Data {
        file: Option<String>,
        line: Option<u64>,
        message: String,
    },

    /// An estimate whose readings disagree with it by far more than their noise, step
    /// after step: it has left the motion (`why`), found at run step `step` (time `t`).
    #[error("the estimate diverged at step {step} (t = {t} s): {why}")]
    Diverged { step: usize, t: f64, why: String },

    /// An argument given to a library call is out of its domain.
    #[error("invalid argument: {0}")]
    InvalidArgument(String),
}

impl Error {
    /// A singular system not (yet) located in a run.
    pub fn singular(what: impl Into<String>) -> Error {
        Error::Singular {
            what: what.into(),
            step: None,
            t: None,
        }
    }

    /// Bad data not tied to a file (a stream, a writer).
    pub fn data(message: impl Into<String>) -> Error {
        Error::Data {
            file: None,
            line: None,
            message: message.into(),
        }
    }

    /// Bad data in `file`, at `line` where known.
    pub fn data_in(
        file: impl Into<String>,
        line: Option<u64>,
        message: impl Into<String>,
    ) -> Error {
        Error::Data {
            file: Some(file.into()),
            line,
            message: message.into(),
        }
    }
}

/// "what", or "what at step k (t = … s)".
fn located(what: &str, step: Option<usize>, t: Option<f64>) -> String {
    match (step, t) {
        (Some(k), Some(t)) => format!("{what} at step {k} (t = {t} s)"),
        (Some(k), None) => format!("{what} at step {k}"),
        _ => what.to_string(),
    }
}

/// "file:line: message", as far as the place is known.
fn in_file(file: &Option<String>, line: Option<u64>, message: &str) -> String {
    match (file, line) {
        (Some(f), Some(l)) => format!("{f}:{l}: {message}"),
        (Some(f), None) => format!("{f}: {message}"),
        _ => message.to_string(),
    }
}

/// The worst few violated constraints, for a one-line message.
fn list_violated(violated: &[(String, f64)]) -> String {
    const SHOWN: usize = 4;
    let mut text = violated
        .iter()
        .take(SHOWN)
        .map(|(n, v)| format!("{n} (|Φ| = {v:.3e})"))
        .collect::<Vec<_>>()
        .join(", ");
    if violated.len() > SHOWN {
        text += &format!(" and {} more", violated.len() - SHOWN);
    }
    text
}

pub type Result<T, E = Error> = std::result::Result<T, E>;
