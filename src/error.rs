//! The library's one error type.

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
    /// or independent coordinates that do not determine the motion).
    #[error("singular system: {0}")]
    Singular(String),

    /// A data file (CSV) that cannot be read or written, or whose content is
    /// malformed; the message names the file and, where possible, the line.
    #[error("{0}")]
    Data(String),

    /// An argument given to a library call is out of its domain.
    #[error("invalid argument: {0}")]
    InvalidArgument(String),
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
