//! Ctrl-C (SIGINT) and SIGTERM end a run after its current step, so that the steps
//! solved so far are kept; a second signal ends the process at once.

use std::sync::atomic::{AtomicBool, Ordering};

static REQUESTED: AtomicBool = AtomicBool::new(false);

#[cfg(unix)]
mod os {
    const SIGINT: i32 = 2;
    const SIGTERM: i32 = 15;
    const SIG_DFL: usize = 0;

    extern "C" {
        // POSIX signal(2); the handler is passed as an address.
        fn signal(signum: i32, handler: usize) -> usize;
    }

    extern "C" fn on_signal(signum: i32) {
        super::REQUESTED.store(true, std::sync::atomic::Ordering::SeqCst);
        // Only async-signal-safe calls here: restoring the default makes a second
        // signal end the process.
        unsafe {
            signal(signum, SIG_DFL);
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

/// Whether a signal asked the run to stop.
pub fn requested() -> bool {
    REQUESTED.load(Ordering::SeqCst)
}
