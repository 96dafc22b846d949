//! The process's resident memory, from `/proc/self/status` (Linux; 0 elsewhere): its size now
//! and its peak (`VmHWM`) since the peak was last reset.

fn status_kib(field: &str) -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|status| {
            status
                .lines()
                .find(|l| l.starts_with(field))
                .and_then(|l| l.split_whitespace().nth(1))
                .and_then(|kib| kib.parse().ok())
        })
        .unwrap_or(0)
}

pub(crate) fn resident_bytes() -> u64 {
    status_kib("VmRSS:") * 1024
}

/// The peak resident set size since the last [`reset_peak`] (or the start).
pub(crate) fn peak_resident_bytes() -> u64 {
    status_kib("VmHWM:") * 1024
}

/// Held across a measurement from its size before to its peak: a reset of the process's one
/// peak by another measurement running meanwhile (tests run on threads) would cut it short.
pub(crate) fn measuring() -> std::sync::MutexGuard<'static, ()> {
    static MEASURING: std::sync::Mutex<()> = std::sync::Mutex::new(());
    MEASURING
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner)
}

/// Resets the peak to the current size (Linux 4.0 and later); false where that was refused,
/// when the next peak is the process's since its start.
pub(crate) fn reset_peak() -> bool {
    std::fs::write("/proc/self/clear_refs", "5").is_ok()
}
