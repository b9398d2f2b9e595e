//! The progress bar of a long run.

use std::io::IsTerminal;
use std::time::{Duration, Instant};

/// A progress bar on stderr, shown only when stderr is a terminal and the run has
/// lasted over a second. Its clock runs from the start of the run, and its ETA is
/// the mean time per step of the current attempt times the steps left ([`eta`]):
/// indicatif's own estimator, fed the first second's steps at once, reads 0 s.
///
/// A run made again (at a finer step: more steps)
/// starts a new attempt: the bar's length becomes the new count and the pace is
/// measured afresh, so that the first attempt's time does not count against the
/// second's steps.
///
/// A batch run reports the steps of its one-step start (the fixed-lag smoother
/// with N_w = 1 over the horizon); the solve of all steps at once follows, for as
/// many iterations as it takes, which no count of steps foretells: once the start
/// is done the bar says so, its clock keeps running and its ETA is `?`.
pub struct Progress {
    batch: bool,
    start: Instant,
    bar: Option<indicatif::ProgressBar>,
    enabled: bool,
    /// The current attempt: its total, when it started and the steps done then;
    /// shared with the bar's ETA.
    attempt: Attempt,
    shared: Option<std::sync::Arc<std::sync::Mutex<Attempt>>>,
}

#[derive(Clone, Copy)]
struct Attempt {
    total: usize,
    start: Instant,
    done: usize,
    last: usize,
}

impl Progress {
    /// A bar for a run solved step by step, or in one `batch`.
    pub fn new(batch: bool) -> Self {
        let now = Instant::now();
        Progress {
            batch,
            start: now,
            bar: None,
            enabled: std::io::stderr().is_terminal(),
            attempt: Attempt {
                total: 0,
                start: now,
                done: 0,
                last: 0,
            },
            shared: None,
        }
    }

    pub fn update(&mut self, done: usize, total: usize) {
        if !self.enabled {
            return;
        }
        let now = Instant::now();
        if self.attempt.next(done, total, now) {
            if let Some(bar) = &self.bar {
                bar.set_length(total as u64);
            }
        }
        let elapsed = now - self.start;
        if self.bar.is_none() && elapsed > Duration::from_secs(1) {
            let bar = indicatif::ProgressBar::new(total as u64).with_elapsed(elapsed);
            let attempt = std::sync::Arc::new(std::sync::Mutex::new(self.attempt));
            let shared = attempt.clone();
            let batch = self.batch;
            bar.set_style(
                indicatif::ProgressStyle::with_template(
                    "{elapsed_precise} [{bar:40}] {pos}/{len} steps, eta {left}{msg}",
                )
                .expect("a valid template")
                .with_key(
                    "left",
                    move |state: &indicatif::ProgressState, w: &mut dyn std::fmt::Write| {
                        let a = *shared.lock().expect("not poisoned");
                        if batch && state.pos() >= state.len().unwrap_or(0) {
                            let _ = write!(w, "?");
                            return;
                        }
                        let left = eta(
                            a.start.elapsed(),
                            state.pos().saturating_sub(a.done as u64),
                            state.len().unwrap_or(0).saturating_sub(a.done as u64),
                        );
                        let _ = match left {
                            Some(d) => write!(w, "{:#}", indicatif::HumanDuration(d)),
                            None => write!(w, "?"),
                        };
                    },
                )
                .progress_chars("=> "),
            );
            self.bar = Some(bar);
            self.shared = Some(attempt);
        }
        if let Some(shared) = &self.shared {
            *shared.lock().expect("not poisoned") = self.attempt;
        }
        if let Some(bar) = &self.bar {
            bar.set_position(done as u64);
            if self.batch {
                if done >= total {
                    bar.set_message(" (one-step start done; solving all steps at once)");
                    bar.enable_steady_tick(Duration::from_millis(500));
                } else {
                    bar.set_message(" (one-step start; the batch solve follows)");
                }
            }
        }
    }

    pub fn finish(&mut self) {
        if let Some(bar) = self.bar.take() {
            bar.finish_and_clear();
        }
    }
}

impl Attempt {
    /// Takes the next report; true when it starts a new attempt (another total, or
    /// fewer steps done than before: the run was made again).
    fn next(&mut self, done: usize, total: usize, now: Instant) -> bool {
        let new = total != self.total || done < self.last;
        if new {
            // Its first report is one step in: the pace counts from the step before.
            *self = Attempt {
                total,
                start: now,
                done,
                last: done,
            };
        }
        self.last = done;
        new
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

    #[test]
    fn a_run_made_again_is_a_new_attempt() {
        let t = Instant::now();
        let mut a = Attempt {
            total: 0,
            start: t,
            done: 0,
            last: 0,
        };
        assert!(a.next(1, 100, t));
        assert!(!a.next(50, 100, t));
        // Made again with tangent integrators: the same total, from the start.
        assert!(a.next(1, 100, t));
        assert_eq!(a.done, 1);
        // At a finer step: four times the steps.
        assert!(!a.next(100, 100, t));
        assert!(a.next(1, 400, t));
        assert_eq!((a.total, a.done), (400, 1));
    }
}
