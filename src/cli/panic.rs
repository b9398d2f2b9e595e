//! The last line of defence: a panic is a bug, reported in one line with exit code 70
//! (EX_SOFTWARE), never an abort with a backtrace dump.

use std::sync::Mutex;

static LAST: Mutex<Option<String>> = Mutex::new(None);

/// Records a panic's message and place instead of printing them.
pub fn install_hook() {
    std::panic::set_hook(Box::new(|info| {
        let message = info
            .payload()
            .downcast_ref::<&str>()
            .map(|s| s.to_string())
            .or_else(|| info.payload().downcast_ref::<String>().cloned())
            .unwrap_or_else(|| "unknown panic".into());
        let place = info
            .location()
            .map(|l| format!(" at {}:{}", l.file(), l.line()))
            .unwrap_or_default();
        let line = message.lines().next().unwrap_or("").chars().take(200);
        if let Ok(mut last) = LAST.lock() {
            *last = Some(format!("{}{place}", line.collect::<String>()));
        }
    }));
}

/// The message of the last panic, for the error line.
pub fn last_message() -> String {
    LAST.lock()
        .ok()
        .and_then(|l| l.clone())
        .unwrap_or_else(|| "unknown panic".into())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_caught_panic_leaves_its_message_and_place() {
        install_hook();
        let caught = std::panic::catch_unwind(|| panic!("boom {}", 42));
        let _ = std::panic::take_hook();
        assert!(caught.is_err());
        let m = last_message();
        assert!(
            m.starts_with("boom 42 at ") && m.contains("panic.rs"),
            "{m}"
        );
    }
}
