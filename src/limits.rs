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

/// Bytes of memory this process may plan to use: the least of what the system reports
/// available (Linux `/proc/meminfo`, 8 GiB where that cannot be read), what the
/// process's own limits leave (its address-space limit, `ulimit -v`, less the address
/// space it already maps; its cgroup's memory limit less the cgroup's usage) and
/// `MBFG_MEMORY_LIMIT` (bytes), which lowers the bound for tests and shared machines.
pub fn available_memory() -> f64 {
    let system = std::fs::read_to_string("/proc/meminfo")
        .ok()
        .and_then(|text| status_field(&text, "MemAvailable:"))
        .unwrap_or(8.0 * 1024.0 * 1024.0 * 1024.0);
    let requested = std::env::var("MBFG_MEMORY_LIMIT")
        .ok()
        .and_then(|s| s.trim().parse::<f64>().ok())
        .filter(|v| *v > 0.0);
    [Some(system), address_space_left(), cgroup_left(), requested]
        .into_iter()
        .flatten()
        .fold(f64::INFINITY, f64::min)
}

/// `Name:   123456 kB` → bytes, from a `/proc` status-like text.
fn status_field(text: &str, name: &str) -> Option<f64> {
    let line = text.lines().find(|l| l.starts_with(name))?;
    let kb: f64 = line[name.len()..].split_whitespace().next()?.parse().ok()?;
    Some(kb * 1024.0)
}

/// What RLIMIT_AS (`ulimit -v`) leaves: the limit less the address space mapped now.
/// Allocations past it fail, and Rust aborts on a failed allocation.
fn address_space_left() -> Option<f64> {
    let limits = std::fs::read_to_string("/proc/self/limits").ok()?;
    let limit = rlimit_as(&limits)?;
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let mapped = status_field(&status, "VmSize:").unwrap_or(0.0);
    Some((limit - mapped).max(0.0))
}

/// The soft address-space limit from `/proc/self/limits`, None when unlimited.
fn rlimit_as(limits: &str) -> Option<f64> {
    let line = limits
        .lines()
        .find(|l| l.starts_with("Max address space"))?;
    let soft = line["Max address space".len()..]
        .split_whitespace()
        .next()?;
    soft.parse::<f64>().ok()
}

/// What this process's memory cgroup leaves: its limit less its usage, for cgroup v2
/// (`memory.max`, `memory.current`) or v1 (`memory.limit_in_bytes`,
/// `memory.usage_in_bytes`). None without a limit.
fn cgroup_left() -> Option<f64> {
    let membership = std::fs::read_to_string("/proc/self/cgroup").ok()?;
    let read = |path: &str| -> Option<f64> {
        let text = std::fs::read_to_string(path).ok()?;
        text.trim().parse::<f64>().ok()
    };
    for (dir, limit, usage) in cgroup_files(&membership) {
        // Inside a container the cgroup's own directory is often mounted as the root.
        for base in [dir.as_str(), ""] {
            let root = if base.is_empty() || base == "/" {
                String::new()
            } else {
                base.to_string()
            };
            let prefix = format!("/sys/fs/cgroup{}", cgroup_mount(limit, &root));
            if let Some(max) = read(&format!("{prefix}/{limit}")) {
                // v1 writes "no limit" as a page-rounded i64::MAX, v2 as "max".
                if max >= 1e18 {
                    break;
                }
                let used = read(&format!("{prefix}/{usage}")).unwrap_or(0.0);
                return Some((max - used).max(0.0));
            }
        }
    }
    None
}

/// The directory of a cgroup file below /sys/fs/cgroup: v1 keeps memory under `memory/`.
fn cgroup_mount(limit_file: &str, path: &str) -> String {
    if limit_file == "memory.limit_in_bytes" {
        format!("/memory{path}")
    } else {
        path.to_string()
    }
}

/// The (cgroup path, limit file, usage file) triples of `/proc/self/cgroup`: the v2
/// line `0::/path` and the v1 line `N:memory:/path` (or with `memory` among others).
fn cgroup_files(membership: &str) -> Vec<(String, &'static str, &'static str)> {
    let mut files = Vec::new();
    for line in membership.lines() {
        let mut parts = line.splitn(3, ':');
        let (Some(_), Some(controllers), Some(path)) = (parts.next(), parts.next(), parts.next())
        else {
            continue;
        };
        if controllers.is_empty() {
            files.push((path.to_string(), "memory.max", "memory.current"));
        } else if controllers.split(',').any(|c| c == "memory") {
            files.push((
                path.to_string(),
                "memory.limit_in_bytes",
                "memory.usage_in_bytes",
            ));
        }
    }
    files
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
    fn the_address_space_limit_is_read_unless_unlimited() {
        let header =
            "Limit                     Soft Limit           Hard Limit           Units     \n";
        let capped = format!("{header}Max address space         4096000000           unlimited            bytes     \n");
        assert_eq!(rlimit_as(&capped), Some(4096000000.0));
        let free = format!("{header}Max address space         unlimited            unlimited            bytes     \n");
        assert_eq!(rlimit_as(&free), None);
    }

    #[test]
    fn both_cgroup_versions_name_their_memory_files() {
        let v1 = "6:cpu,cpuacct:/\n4:memory:/job/7\n0::/\n";
        let files = cgroup_files(v1);
        assert_eq!(
            files[0],
            (
                "/job/7".to_string(),
                "memory.limit_in_bytes",
                "memory.usage_in_bytes"
            )
        );
        assert_eq!(files[1], ("/".to_string(), "memory.max", "memory.current"));
        assert_eq!(
            cgroup_mount("memory.limit_in_bytes", "/job/7"),
            "/memory/job/7"
        );
        assert_eq!(cgroup_mount("memory.max", "/a"), "/a");
    }

    #[test]
    fn sizes_read_as_people_write_them() {
        assert_eq!(human(512.0), "512 B");
        assert_eq!(human(9.6e11), "960.0 GB");
    }
}
