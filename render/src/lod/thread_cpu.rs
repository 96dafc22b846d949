//! CPU time of single threads, and the counting pass's account of its own: a thread that does
//! its share of every point alone bounds the pass at points / its CPU seconds, however many
//! cores the others have (docs/perf/lod-build-decode-bound.md).
//!
//! A source that reads on a thread of its own (`ingest/source.rs`) takes a [`ThreadAccount`]
//! on the thread that visits its batches before it starts that thread; while the counting pass
//! reads, the account adds the reader's CPU to the pass's.

use std::cell::RefCell;
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// CPU time (user and system) the calling thread has used since it started; `None` where the
/// system does not say (Linux's `/proc/thread-self/schedstat`, in nanoseconds, or its `stat`
/// in clock ticks where the scheduler's statistics are off).
pub fn thread_cpu() -> Option<Duration> {
    schedstat_cpu().or_else(stat_cpu)
}

fn schedstat_cpu() -> Option<Duration> {
    let text = std::fs::read_to_string("/proc/thread-self/schedstat").ok()?;
    let nanos = text.split_whitespace().next()?.parse::<u64>().ok()?;
    Some(Duration::from_nanos(nanos))
}

/// `utime` and `stime` of `/proc/thread-self/stat`, in ticks of 1/100 s (`USER_HZ`).
fn stat_cpu() -> Option<Duration> {
    let text = std::fs::read_to_string("/proc/thread-self/stat").ok()?;
    // The command name, in parentheses, may hold spaces: fields are counted after it.
    let (_, after) = text.rsplit_once(')')?;
    let mut fields = after.split_whitespace().skip(11);
    let user = fields.next()?.parse::<u64>().ok()?;
    let system = fields.next()?.parse::<u64>().ok()?;
    Some(Duration::from_millis((user + system) * 10))
}

/// The calling thread's CPU time since `start` (a [`thread_cpu`] of the same thread).
pub fn thread_cpu_since(start: Option<Duration>) -> Duration {
    thread_cpu()
        .zip(start)
        .map_or(Duration::ZERO, |(now, start)| now.saturating_sub(start))
}

/// CPU time of each thread of the counting pass that does its share of every point alone.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct CountingThreadsCpu {
    /// The thread that walks the source's batches: checks them, hands each block of points
    /// to the pool to make its records, and sends the blocks on.
    pub walker: Duration,
    /// The thread that appends each record to its bucket's buffer.
    pub scatterer: Duration,
    /// The threads that append the buffers to the buckets' files, one set at a time.
    pub spill_writer: Duration,
    /// The thread that syncs the buckets' files and records each checkpoint.
    pub checkpoint_recorder: Duration,
    /// The source's own reading thread, where it has one (decoding LAZ in the pool, filling
    /// columns).
    pub source_reader: Duration,
}

impl CountingThreadsCpu {
    /// Each thread's name and CPU time.
    pub fn threads(&self) -> [(&'static str, Duration); 5] {
        [
            ("walker", self.walker),
            ("scatterer", self.scatterer),
            ("spill writer", self.spill_writer),
            ("checkpoint recorder", self.checkpoint_recorder),
            ("source reader", self.source_reader),
        ]
    }

    /// The thread that took the most CPU, with its time.
    pub fn largest(&self) -> (&'static str, Duration) {
        self.threads()
            .into_iter()
            .max_by_key(|&(_, cpu)| cpu)
            .unwrap_or(("walker", Duration::ZERO))
    }

    /// Points a second the pass cannot pass on any number of cores: `points` over the
    /// largest thread's CPU seconds; `None` where no thread's time was measured.
    pub fn ceiling_points_per_s(&self, points: u64) -> Option<f64> {
        let (_, cpu) = self.largest();
        (!cpu.is_zero()).then(|| points as f64 / cpu.as_secs_f64())
    }
}

thread_local! {
    /// Where a source's reading thread started from this thread adds its CPU time.
    static READERS: RefCell<Option<Arc<Mutex<Duration>>>> = const { RefCell::new(None) };
}

/// Runs `read` with the CPU time of the reading threads a source starts from this thread
/// meanwhile (through [`ThreadAccount::reader`]) counted, and returns it beside its result.
pub(crate) fn with_readers_counted<T>(read: impl FnOnce() -> T) -> (T, Duration) {
    let counted = Arc::new(Mutex::new(Duration::ZERO));
    let outer = READERS.with(|readers| readers.replace(Some(Arc::clone(&counted))));
    let result = read();
    READERS.with(|readers| readers.replace(outer));
    let cpu = *counted
        .lock()
        .unwrap_or_else(|poisoned| poisoned.into_inner());
    (result, cpu)
}

/// Adds the CPU time of the thread that drops it to an account, if one was open where it was
/// taken.
pub struct ThreadAccount(Option<Arc<Mutex<Duration>>>);

impl ThreadAccount {
    /// Taken on the thread that visits a source's batches, then moved to the thread that reads
    /// them, which holds it until it ends.
    pub fn reader() -> Self {
        Self(READERS.with(|readers| readers.borrow().clone()))
    }
}

impl Drop for ThreadAccount {
    fn drop(&mut self) {
        if let Some(counted) = &self.0 {
            let cpu = thread_cpu().unwrap_or_default();
            *counted
                .lock()
                .unwrap_or_else(|poisoned| poisoned.into_inner()) += cpu;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A thread's time grows with its own work, and a reader's account reaches the thread that
    /// opened it, not another.
    #[test]
    fn a_readers_time_is_counted_where_its_account_was_taken() {
        // Spins until the thread has taken 20 ms of CPU (or 20 s have passed on a busy host).
        let spin = || {
            let start = std::time::Instant::now();
            let cpu = thread_cpu();
            let mut x = 0u64;
            while thread_cpu_since(cpu) < Duration::from_millis(20)
                && start.elapsed() < Duration::from_secs(20)
            {
                for _ in 0..10_000 {
                    x = std::hint::black_box(x.wrapping_mul(31).wrapping_add(7));
                }
            }
            x
        };
        let before = thread_cpu();
        spin();
        assert!(thread_cpu_since(before) > Duration::ZERO);
        let ((), counted) = with_readers_counted(|| {
            let account = ThreadAccount::reader();
            std::thread::scope(|scope| {
                scope.spawn(move || {
                    let _account = account;
                    spin();
                });
            });
        });
        assert!(counted >= Duration::from_millis(20), "{counted:?}");
        let stray = ThreadAccount::reader();
        assert!(stray.0.is_none(), "no account open outside a count");
    }
}
