//! What a run may ask of the machine: refused before allocating, with the estimate in
//! the message, rather than aborted by the allocator halfway through.

use crate::error::{Error, Result};

/// The most steps a run may have (t_end/dt + 1): beyond it the step count itself
/// stops being exact in f64 arithmetic long before memory runs out.
pub const MAX_STEPS: f64 = 1e9;

/// The largest coordinate magnitude a scene may place a point at, in metres: the
/// constraint equations square lengths, and beyond this their residuals lose every
/// digit a millimetre-scale link needs (and overflow near 1e154).
pub const MAX_COORDINATE: f64 = 1e6;

/// Bytes of memory this process may plan to use: what the system reports available
/// (Linux `/proc/meminfo`), or 8 GiB where that cannot be read. `MBFG_MEMORY_LIMIT`
/// (bytes) overrides it, for tests and for sharing a machine.
pub fn available_memory() -> f64 {
    if let Some(v) = std::env::var("MBFG_MEMORY_LIMIT")
        .ok()
        .and_then(|s| s.trim().parse::<f64>().ok())
        .filter(|v| *v > 0.0)
    {
        return v;
    }
    std::fs::read_to_string("/proc/meminfo")
        .ok()
        .and_then(|text| {
            text.lines()
                .find(|l| l.starts_with("MemAvailable:"))
                .and_then(|l| l.split_whitespace().nth(1))
                .and_then(|kb| kb.parse::<f64>().ok())
        })
        .map(|kb| kb * 1024.0)
        .unwrap_or(8.0 * 1024.0 * 1024.0 * 1024.0)
}

/// Refuses `what` when its estimated `bytes` exceed the available memory.
pub fn ensure_fits(what: &str, bytes: f64) -> Result<()> {
    let available = available_memory();
    if bytes > available {
        return Err(Error::InvalidArgument(format!(
            "{what} needs about {} of memory, more than the {} available",
            human(bytes),
            human(available)
        )));
    }
    Ok(())
}

/// The number of steps t = 0, dt, …, t_end (dt and t_end already checked positive and
/// finite), refused beyond [`MAX_STEPS`].
pub fn step_count(dt: f64, t_end: f64) -> Result<usize> {
    let steps = (t_end / dt).round() + 1.0;
    if !(steps <= MAX_STEPS) {
        return Err(Error::InvalidArgument(format!(
            "t_end/dt = {t_end:e}/{dt:e} makes {steps:.3e} steps, more than the {MAX_STEPS:e} a run may have"
        )));
    }
    Ok(steps as usize)
}

/// The run's last time when t_end is not a whole number of steps (runs end on the
/// step grid, at the step nearest t_end), `None` when it is, to rounding.
pub fn t_end_unmet(dt: f64, t_end: f64) -> Option<f64> {
    let last = (t_end / dt).round() * dt;
    // Rounded for printing, as the CSV's times are, where that keeps the step.
    let printed = match dt >= 1e-6 {
        true => crate::trajectory::round_time(last),
        false => last,
    };
    // A millionth of a step: t_end given in single precision (0.01 as 0.0099999998)
    // is on the grid.
    ((last - t_end).abs() > 1e-6 * dt).then_some(printed)
}

/// A byte count for messages.
pub fn human(bytes: f64) -> String {
    const UNITS: [&str; 5] = ["B", "kB", "MB", "GB", "TB"];
    let mut v = bytes;
    let mut u = 0;
    while v >= 1000.0 && u + 1 < UNITS.len() {
        v /= 1000.0;
        u += 1;
    }
    if u == 0 {
        format!("{v:.0} B")
    } else {
        format!("{v:.1} {}", UNITS[u])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_end_time_off_the_step_grid_is_named() {
        assert_eq!(super::t_end_unmet(1e-3, 2.0005), Some(2.001));
        assert_eq!(super::t_end_unmet(3e-3, 1.0), Some(0.999));
        assert_eq!(super::t_end_unmet(1e-3, 5.0), None);
        assert_eq!(super::t_end_unmet(0.1, 0.3), None);
        assert_eq!(super::t_end_unmet(1e-3, 0.01f32 as f64), None);
    }

    #[test]
    fn step_counts_beyond_the_limit_are_refused() {
        assert_eq!(step_count(1e-3, 1.0).unwrap(), 1001);
        for (dt, t_end) in [(1e-300, 1.0), (1.0, 1e300), (1.0, 1e18)] {
            let e = step_count(dt, t_end).unwrap_err().to_string();
            assert!(e.contains("steps, more than"), "{e}");
        }
    }

    #[test]
    fn sizes_read_as_people_write_them() {
        assert_eq!(human(512.0), "512 B");
        assert_eq!(human(9.6e11), "960.0 GB");
    }
}
