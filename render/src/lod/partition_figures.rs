//! What the partitions stage did, unit by unit: when each partition was built or split and on
//! how much CPU, so that the stage's parallelism can be measured (how many partitions were in
//! memory at once, the longest one against the whole stage) on any host, a pool larger than
//! its cores included. One small record a unit: the plan bounds how many there are.

use std::sync::Mutex;
use std::time::{Duration, Instant};

use super::key::NodeKey;
use super::thread_cpu::{thread_cpu, thread_cpu_since};

/// One unit of the partitions stage.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PartitionSpan {
    pub key: NodeKey,
    pub points: u64,
    /// Split on disk into its children rather than built.
    pub split: bool,
    /// From the stage's start to when the unit held its memory and began, and to its end.
    pub start: Duration,
    pub end: Duration,
    /// CPU time of the thread that ran the unit, from its start to its end (work it helped
    /// with while waiting for its own subtasks included).
    pub cpu: Duration,
    /// CPU time of the unit's steps that no other thread can share: reading its points, their
    /// order and storing its nodes.
    pub serial_cpu: Duration,
    /// Wall time of storing the unit's nodes and recording it (waiting for the journal's
    /// turn included).
    pub store: Duration,
}

/// The partitions stage's figures.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct PartitionsFigures {
    /// Every unit, in the order they ended.
    pub spans: Vec<PartitionSpan>,
    pub wall: Duration,
    /// CPU time of the whole process during the stage, every thread (`None` where unknown).
    pub process_cpu: Option<Duration>,
    /// Of that, the kernel's: page faults, reads and writes, syncs.
    pub process_system_cpu: Option<Duration>,
    /// Minor page faults of the whole process during the stage: pages it touched first.
    pub process_minor_faults: Option<u64>,
    /// Threads of the pool the stage ran on.
    pub threads: usize,
    /// The most threads one partition's build can keep busy.
    pub threads_per_partition: usize,
}

impl PartitionsFigures {
    /// The partitions built (not split).
    pub fn built(&self) -> impl Iterator<Item = &PartitionSpan> {
        self.spans.iter().filter(|s| !s.split)
    }

    /// The most partitions built at once, and their time-weighted mean over the stage's wall.
    pub fn in_flight(&self) -> (usize, f64) {
        let mut events: Vec<(Duration, i32)> = self
            .built()
            .flat_map(|s| [(s.start, 1), (s.end, -1)])
            .collect();
        // An end before a start at the same instant: touching units do not overlap.
        events.sort_unstable();
        let (mut now, mut max, mut weighted) = (0i32, 0i32, 0.0);
        let mut last = Duration::ZERO;
        for (at, step) in events {
            weighted += f64::from(now) * (at - last).as_secs_f64();
            last = at;
            now += step;
            max = max.max(now);
        }
        let wall = self.wall.as_secs_f64();
        let mean = if wall > 0.0 { weighted / wall } else { 0.0 };
        (max as usize, mean)
    }

    /// The CPU time of every unit, built and split.
    pub fn units_cpu(&self) -> Duration {
        self.spans.iter().map(|s| s.cpu).sum()
    }

    /// The built partition of the most points.
    pub fn largest(&self) -> Option<&PartitionSpan> {
        self.built().max_by_key(|s| (s.points, s.cpu))
    }

    /// The least wall time the stage could take on `threads` cores, from its units' CPU: no
    /// less than the largest partition's indivisible CPU (all of it where a partition runs on
    /// one thread, else its serial steps), nor than all the units' CPU spread over as many
    /// threads as partitions were in memory at once, each keeping as many busy as it can.
    pub fn ceiling(&self, threads: usize) -> Duration {
        let (max, _) = self.in_flight();
        let per_partition = self.threads_per_partition.max(1);
        let busy = (max.max(1) * per_partition).min(threads.max(1));
        let largest = self
            .largest()
            .map_or(Duration::ZERO, |s| match per_partition {
                1 => s.cpu,
                _ => s.serial_cpu,
            });
        largest.max(self.units_cpu() / busy as u32)
    }
}

/// Collects the spans while the stage runs.
pub(super) struct PartitionsTrace {
    start: Instant,
    process: Option<ProcessUsage>,
    spans: Mutex<Vec<PartitionSpan>>,
}

impl PartitionsTrace {
    pub fn new() -> Self {
        Self {
            start: Instant::now(),
            process: ProcessUsage::now(),
            spans: Mutex::new(Vec::new()),
        }
    }

    /// Starts timing a unit on this thread.
    pub fn unit(&self, key: NodeKey, points: u64, split: bool) -> UnitTimer<'_> {
        UnitTimer {
            trace: self,
            key,
            points,
            split,
            start: self.start.elapsed(),
            cpu: thread_cpu(),
            serial: Duration::ZERO,
            store: Duration::ZERO,
        }
    }

    /// The figures of a stage on `threads` threads, `threads_per_partition` of them at most
    /// on one partition.
    pub fn finish(self, threads: usize, threads_per_partition: usize) -> PartitionsFigures {
        let wall = self.start.elapsed();
        let used = self.process.zip(ProcessUsage::now());
        let process_cpu = used.map(|(start, end)| end.cpu.saturating_sub(start.cpu));
        let process_system_cpu = used.map(|(start, end)| end.system.saturating_sub(start.system));
        let process_minor_faults =
            used.map(|(start, end)| end.minor_faults.saturating_sub(start.minor_faults));
        PartitionsFigures {
            spans: self
                .spans
                .into_inner()
                .unwrap_or_else(|poisoned| poisoned.into_inner()),
            wall,
            process_cpu,
            process_system_cpu,
            process_minor_faults,
            threads,
            threads_per_partition,
        }
    }
}

/// A unit being timed; recorded by [`UnitTimer::end`].
pub(super) struct UnitTimer<'t> {
    trace: &'t PartitionsTrace,
    key: NodeKey,
    points: u64,
    split: bool,
    start: Duration,
    cpu: Option<Duration>,
    serial: Duration,
    store: Duration,
}

impl UnitTimer<'_> {
    /// Runs `step`, one of the unit's serial steps, counting its CPU (and its wall as the
    /// store's when `store`).
    pub fn serial<T>(&mut self, store: bool, step: impl FnOnce() -> T) -> T {
        let (cpu, wall) = (thread_cpu(), Instant::now());
        let out = step();
        self.serial += thread_cpu_since(cpu);
        if store {
            self.store += wall.elapsed();
        }
        out
    }

    pub fn end(self) {
        let cpu = thread_cpu_since(self.cpu);
        let span = PartitionSpan {
            key: self.key,
            points: self.points,
            split: self.split,
            start: self.start,
            end: self.trace.start.elapsed(),
            cpu,
            serial_cpu: self.serial,
            store: self.store,
        };
        self.trace
            .spans
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner())
            .push(span);
    }
}

/// What the process has used so far, every thread.
#[derive(Debug, Clone, Copy)]
struct ProcessUsage {
    /// User and system CPU time.
    cpu: Duration,
    system: Duration,
    minor_faults: u64,
}

impl ProcessUsage {
    /// From `/proc/self/stat` (times in the kernel's clock ticks of 1/100 s).
    fn now() -> Option<Self> {
        let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
        let (_, after) = stat.rsplit_once(')')?;
        let fields: Vec<&str> = after.split_whitespace().collect();
        let number = |i: usize| fields.get(i)?.parse::<u64>().ok();
        let (user, system) = (number(11)?, number(12)?);
        Some(Self {
            cpu: Duration::from_millis(10 * (user + system)),
            system: Duration::from_millis(10 * system),
            minor_faults: number(7)?,
        })
    }
}

#[cfg(test)]
mod tests {
    use glam::UVec3;

    use super::*;

    fn span(start: u64, end: u64, points: u64, cpu: u64) -> PartitionSpan {
        PartitionSpan {
            key: NodeKey::new(3, UVec3::new(start as u32, 0, 0)),
            points,
            split: false,
            start: Duration::from_secs(start),
            end: Duration::from_secs(end),
            cpu: Duration::from_secs(cpu),
            serial_cpu: Duration::from_secs(cpu / 2),
            store: Duration::ZERO,
        }
    }

    #[test]
    fn in_flight_counts_overlaps_weighted_by_time() {
        let figures = PartitionsFigures {
            // Two at once for 2 s, one for 6 s, none for 2 s, of 10 s.
            spans: vec![span(0, 4, 10, 4), span(2, 4, 5, 2), span(4, 8, 8, 4)],
            wall: Duration::from_secs(10),
            process_cpu: None,
            process_system_cpu: None,
            process_minor_faults: None,
            threads: 4,
            threads_per_partition: 1,
        };
        let (max, mean) = figures.in_flight();
        assert_eq!(max, 2);
        assert!((mean - 1.0).abs() < 1e-9, "{mean}");
        assert_eq!(figures.largest().map(|s| s.points), Some(10));
        // 10 s of CPU over two at once, against the largest's 4 s.
        assert_eq!(figures.ceiling(16), Duration::from_secs(5));
        // Each of the two on up to four threads: the largest's serial 2 s against 10 / 8.
        let shared = PartitionsFigures {
            threads_per_partition: 4,
            ..figures
        };
        assert_eq!(shared.ceiling(16), Duration::from_secs(2));
    }

    #[test]
    fn a_unit_counts_its_threads_cpu() {
        let trace = PartitionsTrace::new();
        let mut unit = trace.unit(NodeKey::ROOT, 1, false);
        let sum = unit.serial(false, || {
            (0..20_000_000u64).fold(0u64, |a, b| std::hint::black_box(a.wrapping_add(b)))
        });
        assert!(sum > 0);
        // Fresh pages, each touched once: the kernel counts a fault for each first touch.
        // Above glibc's largest mmap threshold (32 MiB), so the allocation is always a new
        // mapping, never heap pages an earlier test in the process touched already.
        let touched = std::hint::black_box(vec![1u8; 64 << 20]);
        unit.end();
        let figures = trace.finish(1, 1);
        drop(touched);
        assert_eq!(figures.spans.len(), 1);
        let s = figures.spans[0];
        assert!(s.cpu > Duration::ZERO && s.serial_cpu <= s.cpu);
        assert!(s.end >= s.start && figures.wall >= s.end);
        assert!(figures.process_minor_faults.is_some_and(|f| f > 0));
        assert!(figures.process_system_cpu <= figures.process_cpu);
    }
}
