//! Per-frame stage timings, from GPU timestamp queries where the adapter has them and from
//! host clocks otherwise.

use std::fmt;

/// A stage of producing a frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Stage {
    /// Levels of detail: the frame's cut chosen from the hierarchy (`cut/select.rs`).
    Select,
    /// Levels of detail: the cut's missing nodes read from the store or the host cache,
    /// decoded, colored and quantised for the GPU (their transfer is "upload").
    Load,
    /// Host-to-GPU transfers: per-frame uniforms, and the points on the first frame of a cloud.
    Upload,
    /// On the host: the batches that can be in view, culled against the frustum and put in
    /// draw order, and their table sent to the GPU. Part of the frame's work: a baseline that
    /// draws every point does none of it.
    Cull,
    /// The point pass(es), in high-quality mode the depth pass (and the clear of a new
    /// framebuffer).
    Rasterize,
    /// High-quality mode: colors of the points near the front surface summed per pixel.
    Accumulate,
    /// Framebuffer to RGBA8 and depth images (emptying the framebuffer for the next frame).
    Resolve,
    /// Screen-space visibility: points seen through holes of nearer surfaces removed.
    Visibility,
    /// Anisotropic filling of the holes' depth and color.
    Fill,
    /// Screen-space shading of the resolved image (Eye-Dome Lighting, Pintus).
    Shade,
    /// Supersampling: averaging blocks of the larger image.
    Downsample,
    /// After Eye-Dome Lighting, on the host: the surface's median brightness brought back to
    /// the unshaded one (`exposure.rs`).
    Expose,
    /// GPU-to-host copy of the images.
    Readback,
    /// Image file encoding (PNG).
    Encode,
}

impl Stage {
    pub fn name(self) -> &'static str {
        match self {
            Stage::Select => "select",
            Stage::Load => "load",
            Stage::Upload => "upload",
            Stage::Cull => "cull",
            Stage::Rasterize => "rasterize",
            Stage::Accumulate => "accumulate",
            Stage::Resolve => "resolve",
            Stage::Visibility => "visibility",
            Stage::Fill => "fill",
            Stage::Shade => "shade",
            Stage::Downsample => "downsample",
            Stage::Expose => "expose",
            Stage::Readback => "readback",
            Stage::Encode => "encode",
        }
    }
}

/// How a stage was timed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Clock {
    /// GPU timestamp queries around the pass.
    Gpu,
    /// Host wall clock around the work and a wait for its completion.
    Host,
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StageTiming {
    pub stage: Stage,
    pub ms: f64,
    pub clock: Clock,
}

/// The timings of one frame, in the order the stages ran.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct StageTimings {
    pub stages: Vec<StageTiming>,
}

impl StageTimings {
    pub fn push(&mut self, stage: Stage, ms: f64, clock: Clock) {
        self.stages.push(StageTiming { stage, ms, clock });
    }

    /// Adds `ms` to `stage`'s entry, or appends one: a frame drawn in tiles reports each stage
    /// once, summed over its tiles.
    pub(crate) fn add_ms(&mut self, stage: Stage, ms: f64, clock: Clock) {
        match self.stages.iter_mut().find(|t| t.stage == stage) {
            Some(timing) => timing.ms += ms,
            None => self.push(stage, ms, clock),
        }
    }

    /// Adds each stage of `other` ([`StageTimings::add_ms`]).
    pub(crate) fn add(&mut self, other: &StageTimings) {
        for timing in &other.stages {
            self.add_ms(timing.stage, timing.ms, timing.clock);
        }
    }

    /// Milliseconds spent in `stage` (summed if it ran more than once), if it ran.
    pub fn get(&self, stage: Stage) -> Option<f64> {
        let mut found = None;
        for t in self.stages.iter().filter(|t| t.stage == stage) {
            *found.get_or_insert(0.0) += t.ms;
        }
        found
    }

    pub fn total_ms(&self) -> f64 {
        self.stages.iter().map(|t| t.ms).sum()
    }
}

impl fmt::Display for StageTimings {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for (i, t) in self.stages.iter().enumerate() {
            if i > 0 {
                f.write_str("  ")?;
            }
            let clock = match t.clock {
                Clock::Gpu => " (gpu)",
                Clock::Host => "",
            };
            write!(f, "{} {:.2} ms{}", t.stage.name(), t.ms, clock)?;
        }
        write!(f, "  | total {:.2} ms", self.total_ms())
    }
}

/// Timestamp queries around the compute passes of a frame.
pub(crate) struct GpuTimer {
    pub query_set: wgpu::QuerySet,
    pub resolved: wgpu::Buffer,
    pub staging: wgpu::Buffer,
    period_ns: f32,
}

/// Most compute passes in one frame.
const MAX_PASSES: u32 = 6;
/// Query slots: begin and end of each pass.
const QUERY_COUNT: u32 = 2 * MAX_PASSES;

impl GpuTimer {
    pub fn new(device: &wgpu::Device, queue: &wgpu::Queue) -> Self {
        Self {
            query_set: device.create_query_set(&wgpu::QuerySetDescriptor {
                label: Some("frame timestamps"),
                ty: wgpu::QueryType::Timestamp,
                count: QUERY_COUNT,
            }),
            resolved: device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("frame timestamps resolved"),
                size: QUERY_COUNT as u64 * 8,
                usage: wgpu::BufferUsages::QUERY_RESOLVE | wgpu::BufferUsages::COPY_SRC,
                mapped_at_creation: false,
            }),
            staging: crate::gpu::staging_buffer(
                device,
                "frame timestamps readback",
                QUERY_COUNT as u64 * 8,
            ),
            period_ns: queue.get_timestamp_period(),
        }
    }

    pub fn writes(&self, pass: u32) -> wgpu::ComputePassTimestampWrites<'_> {
        wgpu::ComputePassTimestampWrites {
            query_set: &self.query_set,
            beginning_of_pass_write_index: Some(2 * pass),
            end_of_pass_write_index: Some(2 * pass + 1),
        }
    }

    /// Milliseconds of pass `pass` from the resolved raw timestamps.
    pub fn pass_ms(&self, raw: &[u64], pass: u32) -> f64 {
        let (begin, end) = (raw[2 * pass as usize], raw[2 * pass as usize + 1]);
        end.saturating_sub(begin) as f64 * self.period_ns as f64 / 1e6
    }
}
