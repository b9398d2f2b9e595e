//! The process's peak memory, as the system measures it.

/// The peak resident set size of this process in bytes (the high-water mark the
/// kernel keeps, `VmHWM` in `/proc/self/status`), or None where the system does
/// not report it.
pub fn peak() -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    parse_hwm(&status)
}

/// `VmHWM:   123456 kB` → bytes.
fn parse_hwm(status: &str) -> Option<u64> {
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let mut fields = line["VmHWM:".len()..].split_whitespace();
    let value: u64 = fields.next()?.parse().ok()?;
    match fields.next()? {
        "kB" => Some(value * 1024),
        _ => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_high_water_mark_is_read_in_bytes() {
        let status = "Name:\tmbfg\nVmPeak:\t  20000 kB\nVmHWM:\t    1536 kB\nVmRSS:\t 1024 kB\n";
        assert_eq!(parse_hwm(status), Some(1536 * 1024));
        assert_eq!(parse_hwm("VmRSS:\t 1024 kB\n"), None);
    }

    #[test]
    fn this_process_has_a_peak_where_linux_reports_one() {
        if cfg!(target_os = "linux") {
            let before = peak().expect("Linux reports VmHWM");
            // Touch 64 MiB: the high-water mark rises by about as much.
            let big = vec![1u8; 64 << 20];
            std::hint::black_box(&big);
            let after = peak().unwrap();
            assert!(after >= before, "{after} < {before}");
            assert!(after >= 64 << 20, "{after} bytes after touching 64 MiB");
        }
    }
}
