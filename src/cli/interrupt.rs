//! Ctrl-C (SIGINT) and SIGTERM end a run after its current step, so that the steps
//! solved so far are kept; a second signal ends the process at once, and so does the
//! first while the process waits on an output's reader (a FIFO nobody reads).

use std::sync::atomic::{AtomicBool, Ordering};

static REQUESTED: AtomicBool = AtomicBool::new(false);
/// Set while the process may block on an output: a signal then ends it at once.
static BLOCKED: AtomicBool = AtomicBool::new(false);

#[cfg(unix)]
mod os {
    const SIGINT: i32 = 2;
    const SIGTERM: i32 = 15;
    const SIG_DFL: usize = 0;

    extern "C" {
        // POSIX signal(2); the handler is passed as an address.
        fn signal(signum: i32, handler: usize) -> usize;
        fn raise(signum: i32) -> i32;
    }

    extern "C" fn on_signal(signum: i32) {
        super::REQUESTED.store(true, std::sync::atomic::Ordering::SeqCst);
        // Only async-signal-safe calls here: restoring the default makes a second
        // signal end the process, and raising it again ends a blocked one now.
        unsafe {
            signal(signum, SIG_DFL);
            if super::BLOCKED.load(std::sync::atomic::Ordering::SeqCst) {
                raise(signum);
            }
        }
    }

    pub fn install() {
        let handler = on_signal as extern "C" fn(i32) as usize;
        unsafe {
            signal(SIGINT, handler);
            signal(SIGTERM, handler);
        }
    }
}

/// Catches the signals from here on.
pub fn install() {
    #[cfg(unix)]
    os::install();
}

/// Runs `io`, which may block on a reader (opening or writing a FIFO): a signal that
/// arrives meanwhile ends the process rather than wait for the next step.
pub fn while_blocked<T>(io: impl FnOnce() -> T) -> T {
    BLOCKED.store(true, Ordering::SeqCst);
    let out = io();
    BLOCKED.store(false, Ordering::SeqCst);
    out
}

/// Whether a signal asked the run to stop.
pub fn requested() -> bool {
    REQUESTED.load(Ordering::SeqCst)
}
