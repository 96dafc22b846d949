//! The basic-mode point pass: every point is projected, culled and written to the point
//! framebuffer with an atomic minimum of (depth, color).
//!
//! Two variants render the same image: one 64-bit `atomicMin` per pixel where the adapter has
//! 64-bit atomics (`shaders/raster_atomic64.wgsl`), and a depth pass followed by a color pass
//! with 32-bit atomics where it has not (`shaders/raster_atomic32.wgsl`).
//!
//! The pass that writes depths runs in phases over the near-to-far batch table, with the
//! occlusion tiles built before each but the first, so that batches hidden behind what earlier
//! phases drew are skipped whole (`occlusion.rs`).

use pointfarm_shaders::Shader;

use super::culling::FrameBatches;
use super::occlusion::{OcclusionPass, MIN_POINTS_PER_PIXEL_FOR_FINAL_TILES};
use super::pipeline::{bind_resources, dispatch_grid, shader_module};
use super::point_pipelines::{PointPipelines, SplatShape};
use super::points::{GpuPointCloud, PointSegment};
use super::targets::FrameTargets;

/// Which atomics the point pass uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum AtomicsPath {
    /// One pass, one 64-bit atomicMin of (depth << 32 | color).
    Atomic64,
    /// Two passes with 32-bit atomics: depth, then color of the points at that depth.
    Atomic32,
}

pub(crate) struct BasicPass {
    /// Present when the device has 64-bit atomics.
    atomic64: Option<PointPipelines>,
    atomic32_depth: PointPipelines,
    atomic32_color: PointPipelines,
    occlusion: OcclusionPass,
}

impl BasicPass {
    pub fn new(device: &wgpu::Device, int64_atomics: bool, workgroup_size: u32) -> Self {
        let atomic64 = int64_atomics.then(|| {
            let module = shader_module(device, Shader::RasterAtomic64);
            PointPipelines::new(device, &module, "rasterize", workgroup_size)
        });
        let m32 = shader_module(device, Shader::RasterAtomic32);
        Self {
            atomic64,
            atomic32_depth: PointPipelines::new(device, &m32, "rasterize_depth", workgroup_size),
            atomic32_color: PointPipelines::new(device, &m32, "rasterize_color", workgroup_size),
            occlusion: OcclusionPass::new(device),
        }
    }

    /// `Atomic64` when the device can and the caller allows it.
    pub fn path(&self, allow_64: bool) -> AtomicsPath {
        if allow_64 && self.atomic64.is_some() {
            AtomicsPath::Atomic64
        } else {
            AtomicsPath::Atomic32
        }
    }

    /// Records the point dispatches for every segment of the frame's cloud into `pass`.
    pub fn record(
        &self,
        device: &wgpu::Device,
        pass: &mut wgpu::ComputePass<'_>,
        path: AtomicsPath,
        frame: PointFrame<'_>,
    ) {
        match (path, &self.atomic64) {
            (AtomicsPath::Atomic64, Some(pipelines)) => {
                self.record_phased(device, pass, pipelines, AtomicsPath::Atomic64, frame);
            }
            _ => {
                // The color pass needs every segment's final depths: it runs after the depth
                // pass over all of them, against the final tiles.
                self.record_depth(device, pass, frame);
                let pipeline = self.atomic32_color.get(device, frame.shape);
                pass.set_pipeline(&pipeline);
                // Phase by phase, as the accumulation (`hq_pass.rs`).
                for phase in 0..frame.batches.phase_count() {
                    for part in frame.batches.phase_parts(phase) {
                        dispatch_part(device, pass, &pipeline, AtomicsPath::Atomic32, frame, part);
                    }
                }
            }
        }
    }

    /// Records only the nearest-depth pass (the first pass of the high-quality mode), and
    /// builds the occlusion tiles from its final depths for the passes after it where points
    /// lie deep enough for that to pay.
    pub fn record_depth(
        &self,
        device: &wgpu::Device,
        pass: &mut wgpu::ComputePass<'_>,
        frame: PointFrame<'_>,
    ) {
        self.record_phased(
            device,
            pass,
            &self.atomic32_depth,
            AtomicsPath::Atomic32,
            frame,
        );
        if frame.batches.points_per_pixel() >= MIN_POINTS_PER_PIXEL_FOR_FINAL_TILES {
            self.build_tiles(device, pass, frame);
        }
    }

    /// The depth-writing pass over every segment, in phases with the occlusion tiles built
    /// before each but the first. A phase is the listed batches within a band of depths
    /// (`phases.rs`), the nearest first, segment after segment near to far.
    fn record_phased(
        &self,
        device: &wgpu::Device,
        pass: &mut wgpu::ComputePass<'_>,
        pipelines: &PointPipelines,
        path: AtomicsPath,
        frame: PointFrame<'_>,
    ) {
        self.occlusion
            .record_clear(device, pass, &frame.targets.occlusion);
        let pipeline = pipelines.get(device, frame.shape);
        for phase in 0..frame.batches.phase_count() {
            if phase > 0 {
                self.build_tiles(device, pass, frame);
            }
            pass.set_pipeline(&pipeline);
            for part in frame.batches.phase_parts(phase) {
                dispatch_part(device, pass, &pipeline, path, frame, part);
            }
        }
    }

    fn build_tiles(
        &self,
        device: &wgpu::Device,
        pass: &mut wgpu::ComputePass<'_>,
        frame: PointFrame<'_>,
    ) {
        let targets = frame.targets;
        self.occlusion.record_build(
            device,
            pass,
            (frame.uniforms, frame.batches.footprint()),
            &targets.framebuffer,
            &targets.occlusion,
        );
    }
}

/// What every point pass of a frame reads and writes: the frame's uniforms and splat shape,
/// the resident cloud with this frame's batch tables, and the frame's targets.
#[derive(Clone, Copy)]
pub(crate) struct PointFrame<'a> {
    pub uniforms: &'a wgpu::Buffer,
    pub shape: SplatShape,
    pub cloud: &'a GpuPointCloud,
    pub batches: &'a FrameBatches,
    pub targets: &'a FrameTargets,
}

/// Dispatches one workgroup per entry of a part of segment `segment`'s batch table; the pipeline
/// is set.
fn dispatch_part(
    device: &wgpu::Device,
    pass: &mut wgpu::ComputePass<'_>,
    pipeline: &wgpu::ComputePipeline,
    path: AtomicsPath,
    frame: PointFrame<'_>,
    (segment, (table, batches)): (usize, (wgpu::BufferBinding<'_>, u32)),
) {
    let bind_group = bind_group(
        device,
        pipeline,
        path,
        frame,
        (&frame.cloud.segments[segment], table),
    );
    pass.set_bind_group(0, &bind_group, &[]);
    let (x, y) = dispatch_grid(batches);
    pass.dispatch_workgroups(x, y, 1);
}

fn bind_group(
    device: &wgpu::Device,
    pipeline: &wgpu::ComputePipeline,
    path: AtomicsPath,
    frame: PointFrame<'_>,
    (segment, batch_table): (&PointSegment, wgpu::BufferBinding<'_>),
) -> wgpu::BindGroup {
    let framebuffer = &frame.targets.framebuffer;
    let mut resources = vec![
        (0, frame.uniforms.as_entire_binding()),
        (1, segment.positions.as_entire_binding()),
        (2, wgpu::BindingResource::Buffer(batch_table)),
        (8, segment.batches.as_entire_binding()),
        (3, framebuffer.as_entire_binding()),
        (5, segment.colors.as_entire_binding()),
        (6, frame.targets.occlusion.tiles.as_entire_binding()),
        (7, frame.targets.occlusion.skipped.as_entire_binding()),
    ];
    if path == AtomicsPath::Atomic64 {
        // The non-atomic view of the same framebuffer, for the early depth test.
        resources.push((4, framebuffer.as_entire_binding()));
    }
    bind_resources(device, pipeline, "point pass", resources)
}
