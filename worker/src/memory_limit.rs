//! The worker process's limit on its own memory (`pointfarm worker --max-memory-mib`): its
//! data (heap and other private writable memory, `RLIMIT_DATA`) is capped with `setrlimit`, so
//! a frame whose data does not fit fails its allocation and aborts the worker process (whose
//! supervisor counts the attempt) instead of pushing the machine into swap or the kernel's
//! out-of-memory killer. Mapped files and reserved address space do not count.

/// Caps this process's data at `max_bytes` (the soft limit; the hard one stays).
#[cfg(unix)]
pub fn apply(max_bytes: u64) -> anyhow::Result<()> {
    use anyhow::Context;
    use rustix::process::{getrlimit, setrlimit, Resource, Rlimit};

    let hard = getrlimit(Resource::Data).maximum;
    if hard.is_some_and(|hard| hard < max_bytes) {
        anyhow::bail!(
            "the memory limit of {max_bytes} bytes is above this process's hard limit of {} bytes",
            hard.unwrap_or_default()
        );
    }
    setrlimit(
        Resource::Data,
        Rlimit {
            current: Some(max_bytes),
            maximum: hard,
        },
    )
    .with_context(|| format!("limiting the process's data to {max_bytes} bytes"))
}

#[cfg(not(unix))]
pub fn apply(_max_bytes: u64) -> anyhow::Result<()> {
    anyhow::bail!("a memory limit is only supported on Unix")
}
