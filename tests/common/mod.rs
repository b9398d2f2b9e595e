//! Helpers shared by the integration tests.
#![allow(dead_code)]

use std::path::PathBuf;

/// A scene of the suite by file name.
pub fn scene_path(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("scenes")
        .join(name)
}

/// A small deterministic generator (no dependency for a few random numbers).
pub struct Rng(pub u64);

impl Rng {
    /// Uniform in [−1, 1).
    pub fn uniform(&mut self) -> f64 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((self.0 >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0
    }

    /// n values uniform in [−scale, scale).
    pub fn values(&mut self, n: usize, scale: f64) -> Vec<f64> {
        (0..n).map(|_| scale * self.uniform()).collect()
    }
}

/// Runs the `mbfg` binary in the crate's directory with extra environment variables.
pub fn mbfg_env(args: &[&str], env: &[(&str, &str)]) -> std::process::Output {
    let mut c = std::process::Command::new(env!("CARGO_BIN_EXE_mbfg"));
    c.args(args).current_dir(env!("CARGO_MANIFEST_DIR"));
    for (k, v) in env {
        c.env(k, v);
    }
    c.output().expect("run mbfg")
}

/// Runs the `mbfg` binary in the crate's directory.
pub fn mbfg(args: &[&str]) -> std::process::Output {
    mbfg_env(args, &[])
}

/// A fresh, empty directory for one test's files.
pub fn scratch(group: &str, name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("mbfg-{group}-{}-{name}", std::process::id()));
    std::fs::remove_dir_all(&dir).ok();
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// A process's standard error as text.
pub fn stderr(out: &std::process::Output) -> String {
    String::from_utf8_lossy(&out.stderr).into_owned()
}

/// A failing call: the exit code, and exactly one line `error: …` on stderr.
pub fn one_error_line(out: &std::process::Output, code: i32) -> String {
    let err = stderr(out);
    assert_eq!(out.status.code(), Some(code), "stderr: {err}");
    let text = err.strip_suffix('\n').unwrap_or(&err);
    assert!(!text.contains('\n'), "one line expected, got:\n{err}");
    assert!(text.starts_with("error: "), "{text}");
    text.to_string()
}
