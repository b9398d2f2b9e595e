//! The progress bar of a long run.

use std::io::IsTerminal;
use std::time::{Duration, Instant};

/// A progress bar on stderr, shown only when stderr is a terminal and the run has
/// lasted over a second. Its clock runs from the start of the run, and its ETA is
/// the mean time per step so far times the steps left ([`eta`]): indicatif's own
/// estimator, first fed at the bar's creation with every step done in the first
/// second at once, saw a near-infinite rate and said 0 s.
pub struct Progress {
    start: Instant,
    bar: Option<indicatif::ProgressBar>,
    enabled: bool,
}

impl Progress {
    pub fn new() -> Self {
        Progress {
            start: Instant::now(),
            bar: None,
            enabled: std::io::stderr().is_terminal(),
        }
    }

    pub fn update(&mut self, done: usize, total: usize) {
        if !self.enabled {
            return;
        }
        let elapsed = self.start.elapsed();
        if self.bar.is_none() && elapsed > Duration::from_secs(1) {
            let bar = indicatif::ProgressBar::new(total as u64).with_elapsed(elapsed);
            bar.set_style(
                indicatif::ProgressStyle::with_template(
                    "{elapsed_precise} [{bar:40}] {pos}/{len} steps, eta {left}",
                )
                .expect("a valid template")
                .with_key(
                    "left",
                    |state: &indicatif::ProgressState, w: &mut dyn std::fmt::Write| {
                        let left = eta(state.elapsed(), state.pos(), state.len().unwrap_or(0));
                        let _ = match left {
                            Some(d) => write!(w, "{:#}", indicatif::HumanDuration(d)),
                            None => write!(w, "?"),
                        };
                    },
                )
                .progress_chars("=> "),
            );
            self.bar = Some(bar);
        }
        if let Some(bar) = &self.bar {
            bar.set_position(done as u64);
        }
    }

    pub fn finish(&mut self) {
        if let Some(bar) = self.bar.take() {
            bar.finish_and_clear();
        }
    }
}

/// The time left at the mean pace so far: `elapsed` for `done` of `total` steps;
/// None before the first step.
fn eta(elapsed: Duration, done: u64, total: u64) -> Option<Duration> {
    if done == 0 {
        return None;
    }
    let left = total.saturating_sub(done) as f64;
    Some(elapsed.mul_f64(left / done as f64))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn eta_is_the_mean_pace_times_the_steps_left() {
        let s = Duration::from_secs;
        assert_eq!(eta(s(2), 0, 100), None);
        assert_eq!(eta(s(2), 50, 100), Some(s(2)));
        assert_eq!(eta(s(2), 25, 100), Some(s(6)));
        assert_eq!(eta(s(2), 100, 100), Some(s(0)));
        // A position past the length (never expected) is not negative time.
        assert_eq!(eta(s(2), 120, 100), Some(s(0)));
    }
}
