//! What the benchmarks report about the machine they ran on: the CPU model,
//! the load average (these VMs are shared and noisy, so every table carries
//! it) and the process's own CPU time (to tell "slow" from "starved").
//! Linux `/proc` only; elsewhere the fallbacks say so.

/// The CPU model from `/proc/cpuinfo` (the architecture name elsewhere).
pub fn cpu_model() -> String {
    std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split(':').nth(1))
                .map(|m| m.trim().to_string())
        })
        .unwrap_or_else(|| std::env::consts::ARCH.to_string())
}

/// `/proc/loadavg`'s 1, 5 and 15 minute averages, or `"unknown"`.
pub fn load_average() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .map(|s| s.split_whitespace().take(3).collect::<Vec<_>>().join(" "))
        .unwrap_or_else(|_| "unknown".into())
}

/// User + system CPU seconds of this process so far (`/proc/self/stat`,
/// 100 clock ticks per second), or `None` where it cannot be read.
pub fn process_cpu_seconds() -> Option<f64> {
    parse_cpu_seconds(&std::fs::read_to_string("/proc/self/stat").ok()?)
}

/// The utime + stime fields of a `/proc/<pid>/stat` line, in seconds. The
/// command name may contain spaces and parentheses, so fields are counted
/// after its last `)`.
fn parse_cpu_seconds(stat: &str) -> Option<f64> {
    let fields: Vec<&str> = stat.rsplit_once(')')?.1.split_whitespace().collect();
    let ticks: u64 = fields.get(11)?.parse::<u64>().ok()? + fields.get(12)?.parse::<u64>().ok()?;
    Some(ticks as f64 / 100.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cpu_seconds_are_read_after_the_command_name() {
        let stat = "42 (a (weird) name) S 1 42 42 0 -1 4194560 100 0 0 0 250 50 0 0 20 0 1 0";
        assert_eq!(parse_cpu_seconds(stat), Some(3.0));
        assert_eq!(parse_cpu_seconds("garbage"), None);
        assert!(process_cpu_seconds().is_some_and(|s| s >= 0.0));
        assert!(!cpu_model().is_empty());
        assert!(!load_average().is_empty());
    }
}
