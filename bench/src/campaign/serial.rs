//! The counting pass's own threads in a campaign build: each one's CPU seconds, and the rate
//! the largest of them bounds the pass at on any number of cores (points / its CPU seconds).

use pointfarm_render::lod::thread_cpu::CountingThreadsCpu;
use serde::Serialize;

/// CPU seconds of each thread of the counting pass that does its share of every point alone.
#[derive(Debug, Clone, Serialize)]
pub struct SerialThreads {
    pub walker_cpu_s: f64,
    pub scatterer_cpu_s: f64,
    pub spill_writer_cpu_s: f64,
    pub checkpoint_recorder_cpu_s: f64,
    pub source_reader_cpu_s: f64,
    /// The thread that took the most CPU.
    pub largest: &'static str,
    /// Points over the largest thread's CPU seconds, in millions a second: the counting pass
    /// cannot go faster on any number of cores (0 where nothing was measured).
    pub ceiling_mpoints_per_s: f64,
}

impl SerialThreads {
    /// The figures of `cpu`, of a pass over `points`.
    pub fn of(cpu: &CountingThreadsCpu, points: u64) -> Self {
        Self {
            walker_cpu_s: cpu.walker.as_secs_f64(),
            scatterer_cpu_s: cpu.scatterer.as_secs_f64(),
            spill_writer_cpu_s: cpu.spill_writer.as_secs_f64(),
            checkpoint_recorder_cpu_s: cpu.checkpoint_recorder.as_secs_f64(),
            source_reader_cpu_s: cpu.source_reader.as_secs_f64(),
            largest: cpu.largest().0,
            ceiling_mpoints_per_s: cpu.ceiling_points_per_s(points).unwrap_or(0.0) / 1e6,
        }
    }

    /// One line of the figures, for the bench's log.
    pub fn line(&self) -> String {
        format!(
            "counting threads' CPU: walker {:.2} s, scatterer {:.2} s, spill writer {:.2} s, \
             checkpoint recorder {:.2} s, source reader {:.2} s; ceiling {:.1} M points/s \
             (the {})",
            self.walker_cpu_s,
            self.scatterer_cpu_s,
            self.spill_writer_cpu_s,
            self.checkpoint_recorder_cpu_s,
            self.source_reader_cpu_s,
            self.ceiling_mpoints_per_s,
            self.largest
        )
    }
}
