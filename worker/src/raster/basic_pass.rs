//! The basic-mode point pass: every point is projected, culled and written to the point
//! framebuffer with an atomic minimum of (depth, colour).
//!
//! Two variants render the same image: one 64-bit `atomicMin` per pixel where the adapter has
//! 64-bit atomics (`shaders/raster_atomic64.wgsl`), and a depth pass followed by a colour pass
//! with 32-bit atomics where it has not (`shaders/raster_atomic32.wgsl`).

use pointfarm_shaders::Shader;

use super::culling::FrameBatches;
use super::pipeline::{bind_resources, shader_module};
use super::point_pipelines::PointPipelines;
use super::points::{GpuPointCloud, PointChunk};
use super::targets::FrameTargets;

/// Which atomics the point pass uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum AtomicsPath {
    /// One pass, one 64-bit atomicMin of (depth << 32 | colour).
    Atomic64,
    /// Two passes with 32-bit atomics: depth, then colour of the points at that depth.
    Atomic32,
}

pub(crate) struct BasicPass {
    /// Present when the device has 64-bit atomics.
    atomic64: Option<PointPipelines>,
    atomic32_depth: PointPipelines,
    atomic32_colour: PointPipelines,
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
            atomic32_colour: PointPipelines::new(device, &m32, "rasterize_colour", workgroup_size),
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

    /// Records the point dispatches for every chunk of the frame's cloud into `pass`.
    pub fn record(
        &self,
        device: &wgpu::Device,
        pass: &mut wgpu::ComputePass<'_>,
        path: AtomicsPath,
        frame: PointFrame<'_>,
    ) {
        let stages: Vec<&PointPipelines> = match (path, &self.atomic64) {
            (AtomicsPath::Atomic64, Some(p)) => vec![p],
            _ => vec![&self.atomic32_depth, &self.atomic32_colour],
        };
        // The 32-bit colour pass needs every chunk's depths, so stages run outermost.
        for pipelines in stages {
            let pipeline = pipelines.get(device, frame.point_size);
            dispatch_chunks(device, pass, &pipeline, path, frame);
        }
    }

    /// Records only the nearest-depth pass (the first pass of the high-quality mode).
    pub fn record_depth(
        &self,
        device: &wgpu::Device,
        pass: &mut wgpu::ComputePass<'_>,
        frame: PointFrame<'_>,
    ) {
        let pipeline = self.atomic32_depth.get(device, frame.point_size);
        dispatch_chunks(device, pass, &pipeline, AtomicsPath::Atomic32, frame);
    }
}

/// What every point pass of a frame reads and writes: the frame's uniforms and point size,
/// the resident cloud with this frame's batch tables, and the frame's targets.
#[derive(Clone, Copy)]
pub(crate) struct PointFrame<'a> {
    pub uniforms: &'a wgpu::Buffer,
    pub point_size: u32,
    pub cloud: &'a GpuPointCloud,
    pub batches: &'a FrameBatches,
    pub targets: &'a FrameTargets,
}

fn dispatch_chunks(
    device: &wgpu::Device,
    pass: &mut wgpu::ComputePass<'_>,
    pipeline: &wgpu::ComputePipeline,
    path: AtomicsPath,
    frame: PointFrame<'_>,
) {
    pass.set_pipeline(pipeline);
    for (index, chunk) in frame.cloud.chunks.iter().enumerate() {
        // A chunk with no batch in view is skipped.
        let Some(table) = frame.batches.binding(index) else {
            continue;
        };
        let bind_group = bind_group(device, pipeline, path, frame, (chunk, table));
        pass.set_bind_group(0, &bind_group, &[]);
        let (x, y) = super::dispatch_grid(frame.batches.count(index));
        pass.dispatch_workgroups(x, y, 1);
    }
}

fn bind_group(
    device: &wgpu::Device,
    pipeline: &wgpu::ComputePipeline,
    path: AtomicsPath,
    frame: PointFrame<'_>,
    (chunk, batch_table): (&PointChunk, wgpu::BufferBinding<'_>),
) -> wgpu::BindGroup {
    let framebuffer = &frame.targets.framebuffer;
    let mut resources = vec![
        (0, frame.uniforms.as_entire_binding()),
        (1, chunk.positions.as_entire_binding()),
        (2, wgpu::BindingResource::Buffer(batch_table)),
        (3, framebuffer.as_entire_binding()),
        (5, chunk.colours.as_entire_binding()),
    ];
    if path == AtomicsPath::Atomic64 {
        // The non-atomic view of the same framebuffer, for the early depth test.
        resources.push((4, framebuffer.as_entire_binding()));
    }
    bind_resources(device, pipeline, "point pass", resources)
}
