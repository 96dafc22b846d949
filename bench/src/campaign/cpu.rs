//! CPU time, all threads together, from `/proc/*/stat` (Linux; 0 or None elsewhere): on a host
//! shared with other work a build's CPU time against the decoding's says what its wall time
//! cannot, how much work it adds to the decoding.

/// Clock ticks a second of `/proc`'s times (`USER_HZ`, 100 on every Linux architecture).
const TICKS_PER_S: f64 = 100.0;

/// Index of `utime` (then `stime`) among the fields after the command's name.
const OWN_TIMES: usize = 11;
/// Index of `cutime` (then `cstime`): the children that ended and were waited for.
const CHILDREN_TIMES: usize = 13;

/// Seconds of CPU (user and system) the process has used so far.
pub(crate) fn process_cpu_s() -> f64 {
    stat_cpu_s("/proc/self/stat", OWN_TIMES).unwrap_or(0.0)
}

/// Seconds of CPU (user and system) of this process's children that ended and were waited
/// for, as `getrusage(RUSAGE_CHILDREN)` counts them: a child killed by a signal included, once
/// reaped.
pub fn children_cpu_s() -> f64 {
    stat_cpu_s("/proc/self/stat", CHILDREN_TIMES).unwrap_or(0.0)
}

/// Seconds of CPU (user and system) process `pid` has used so far, while it runs.
pub fn pid_cpu_s(pid: u32) -> Option<f64> {
    stat_cpu_s(&format!("/proc/{pid}/stat"), OWN_TIMES)
}

/// The sum of the two tick counts at `first` and after it among the fields of the stat file
/// `path`, in seconds.
fn stat_cpu_s(path: &str, first: usize) -> Option<f64> {
    let stat = std::fs::read_to_string(path).ok()?;
    // The command name, in parentheses, may hold spaces: fields are counted after it.
    let (_, after) = stat.rsplit_once(')')?;
    let fields: Vec<&str> = after.split_whitespace().collect();
    let ticks = |i: usize| fields.get(i)?.parse::<u64>().ok();
    Some((ticks(first)? + ticks(first + 1)?) as f64 / TICKS_PER_S)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::process::Command;
    use std::time::{Duration, Instant};

    /// A child killed by SIGKILL while it spins counts in the children's time once reaped, as
    /// much as `/proc/PID/stat` showed just before the kill.
    #[test]
    fn a_killed_childs_time_counts_once_reaped() {
        let before = children_cpu_s();
        let mut child = Command::new("sh")
            .args(["-c", "while :; do :; done"])
            .spawn()
            .expect("start sh");
        let started = Instant::now();
        let mut seen = 0.0;
        while seen < 0.3 && started.elapsed() < Duration::from_secs(30) {
            std::thread::sleep(Duration::from_millis(50));
            seen = pid_cpu_s(child.id()).expect("the child's stat");
        }
        child.kill().expect("SIGKILL");
        child.wait().expect("reap");
        let counted = children_cpu_s() - before;
        assert!(seen >= 0.3, "the child spun {seen} s");
        assert!(
            counted >= seen,
            "{counted} s counted, {seen} s seen before the kill"
        );
    }
}
