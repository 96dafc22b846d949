//! The process's CPU time, all threads together, from `/proc/self/stat` (Linux; 0 elsewhere):
//! on a host shared with other work a build's CPU time against the decoding's says what its
//! wall time cannot, how much work it adds to the decoding.

/// Clock ticks a second of `/proc`'s times (`USER_HZ`, 100 on every Linux architecture).
const TICKS_PER_S: f64 = 100.0;

/// Seconds of CPU (user and system) the process has used so far.
pub(crate) fn process_cpu_s() -> f64 {
    let Ok(stat) = std::fs::read_to_string("/proc/self/stat") else {
        return 0.0;
    };
    // The command name, in parentheses, may hold spaces: fields are counted after it.
    let Some((_, after)) = stat.rsplit_once(')') else {
        return 0.0;
    };
    let fields: Vec<&str> = after.split_whitespace().collect();
    // utime and stime are the 14th and 15th fields; the state, after the name, the 3rd.
    let ticks = |i: usize| {
        fields
            .get(i)
            .and_then(|v| v.parse::<u64>().ok())
            .unwrap_or(0)
    };
    (ticks(11) + ticks(12)) as f64 / TICKS_PER_S
}
