//! Occlusion culling of whole batches (`shaders/occlusion.wgsl`): the tiles of largest depth
//! that the point passes test a batch's box against, and the dispatches that build them.
//!
//! Where points lie deep enough for it to pay (see the constants below), a depth-writing point
//! pass runs in phases by depth (`phases.rs`): the nearest batches, then the tiles are built
//! from the framebuffer, then the next, and so on. A workgroup skips its batch when the box
//! lies behind the tiles it can reach. The high-quality accumulation and the 32-bit color
//! pass test against tiles built after the depth pass, which are final. Elsewhere the tiles stay "unknown" and nothing is skipped.
//!
//! On lavapipe every memory access of a shader costs a loop over the SIMD lanes whether or not
//! a lane is active, so the tiles are built between dispatches from the framebuffer rather
//! than updated by each point (that cost more than culling saved:
//! docs/perf/occlusion-culling.md).

use pointfarm_shaders::layout::{OCCLUSION_BUILD_WORKGROUP_SIDE, OCCLUSION_CLEAR_WORKGROUP};
use pointfarm_shaders::Shader;

use super::pipeline::{bind_buffers, compute_pipeline, shader_module};
use super::pixel_rect::PixelRect;
use crate::gpu::{read_buffer, staging_buffer, GpuContext, GpuError};

/// Side of a tile in pixels.
pub(crate) use pointfarm_shaders::layout::OCCLUSION_TILE as TILE;

/// A deep frame's depth-writing pass is split in phases of equal shares of its listed
/// batches by depth (`phases.rs`): one phase per this many points per footprint pixel, within
/// [`MIN_PHASES`] and [`MAX_PHASES`]. Each phase after the first costs a build of the tiles
/// and skips more. On lavapipe the best counts were 3 for the 10M-point cube (12.6 points a
/// pixel), 5 to 7 for 30M (39) and 7 for 100M (about 130; 10 phases were slower).
pub(crate) const POINTS_PER_PIXEL_PER_PHASE: f64 = 5.0;
pub(crate) const MIN_PHASES: usize = 3;
pub(crate) const MAX_PHASES: usize = 7;

/// Fewest listed batches for which a depth pass is split in phases.
pub(crate) const MIN_BATCHES_FOR_PHASES: u32 = 64;

/// Building the tiles reads every pixel of the footprint, while skipping a batch saves work on
/// each of its points, so the tiles are built only where points lie deep on the footprint's
/// pixels (`FrameBatches::points_per_pixel`). On lavapipe a build costs about 1.7 ns per
/// pixel and a point 5 to 10 ns. Between the phases of the depth pass, from this depth on
/// (only the points after the first phase can be skipped, and few of them are hidden in a
/// shallow cloud):
pub(crate) const MIN_POINTS_PER_PIXEL_FOR_PHASES: f64 = 8.0;
/// After the depth pass, for the passes that read the final depths (every point can be
/// skipped there, and each costs more), from this depth on.
pub(crate) const MIN_POINTS_PER_PIXEL_FOR_FINAL_TILES: f64 = 2.0;

/// Per tile of one image size, the bits of the largest depth of its pixels; and the counts of
/// batches skipped this frame.
pub(crate) struct OcclusionTiles {
    pub tiles: wgpu::Buffer,
    /// [batches skipped by the pass that writes depths, by the passes that read them]: u32s.
    pub skipped: wgpu::Buffer,
    pub skipped_staging: wgpu::Buffer,
    count: u32,
}

/// Batches a frame skipped whole because they were hidden (`Renderer::occlusion_skipped`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct OcclusionSkipped {
    /// By the pass that writes depths (the basic mode's, or the depth pass of the 32-bit path
    /// and of the high-quality mode).
    pub depth_pass: u32,
    /// By the passes that read the final depths: the 32-bit path's color pass and the
    /// high-quality accumulation.
    pub later_passes: u32,
}

impl OcclusionTiles {
    pub fn new(device: &wgpu::Device, width: u32, height: u32) -> Self {
        let count = width.div_ceil(TILE) * height.div_ceil(TILE);
        Self {
            tiles: device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("occlusion tiles"),
                size: u64::from(count) * 4,
                usage: wgpu::BufferUsages::STORAGE,
                mapped_at_creation: false,
            }),
            skipped: device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("occlusion skipped batches"),
                size: SKIPPED_BYTES,
                usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
                mapped_at_creation: false,
            }),
            skipped_staging: staging_buffer(device, "occlusion skipped readback", SKIPPED_BYTES),
            count,
        }
    }
}

const SKIPPED_BYTES: u64 = 8;

/// Reads back the counts of the last frame drawn with `tiles`.
pub(crate) fn read_skipped(
    gpu: &GpuContext,
    tiles: &OcclusionTiles,
) -> Result<OcclusionSkipped, GpuError> {
    let bytes = read_buffer(gpu, &tiles.skipped, &tiles.skipped_staging, SKIPPED_BYTES)?;
    let counts: Vec<u32> = bytemuck::pod_collect_to_vec(&bytes);
    Ok(OcclusionSkipped {
        depth_pass: counts[0],
        later_passes: counts[1],
    })
}

/// The pipelines that mark the tiles unknown and build them.
pub(crate) struct OcclusionPass {
    clear: wgpu::ComputePipeline,
    build: wgpu::ComputePipeline,
}

impl OcclusionPass {
    pub fn new(device: &wgpu::Device) -> Self {
        let module = shader_module(device, Shader::OcclusionTiles);
        Self {
            clear: compute_pipeline(device, &module, "clear_tiles", &[]),
            build: compute_pipeline(device, &module, "build_tiles", &[]),
        }
    }

    /// Marks every tile unknown: before a frame's first point dispatch.
    pub fn record_clear(
        &self,
        device: &wgpu::Device,
        pass: &mut wgpu::ComputePass<'_>,
        tiles: &OcclusionTiles,
    ) {
        let bind_group = bind_buffers(
            device,
            &self.clear,
            "occlusion tiles",
            &[(2, &tiles.tiles), (3, &tiles.skipped)],
        );
        pass.set_pipeline(&self.clear);
        pass.set_bind_group(0, &bind_group, &[]);
        pass.dispatch_workgroups(tiles.count.div_ceil(OCCLUSION_CLEAR_WORKGROUP), 1, 1);
    }

    /// Builds the tiles of `footprint` (the frame's, whose first tile the uniforms hold) from
    /// `framebuffer` as the dispatches before left it.
    pub fn record_build(
        &self,
        device: &wgpu::Device,
        pass: &mut wgpu::ComputePass<'_>,
        (uniforms, footprint): (&wgpu::Buffer, PixelRect),
        framebuffer: &wgpu::Buffer,
        tiles: &OcclusionTiles,
    ) {
        if footprint.is_empty() {
            return;
        }
        let bind_group = bind_buffers(
            device,
            &self.build,
            "occlusion tiles",
            &[(0, uniforms), (1, framebuffer), (2, &tiles.tiles)],
        );
        pass.set_pipeline(&self.build);
        pass.set_bind_group(0, &bind_group, &[]);
        let across = footprint.x1.div_ceil(TILE) - footprint.x0 / TILE;
        let down = footprint.y1.div_ceil(TILE) - footprint.y0 / TILE;
        let side = OCCLUSION_BUILD_WORKGROUP_SIDE;
        pass.dispatch_workgroups(across.div_ceil(side), down.div_ceil(side), 1);
    }
}

/// Where a depth pass over `batches` listed batches, `depth` points per footprint pixel, is
/// split in phases, as ascending shares of the batches near to far (none: one phase); the
/// tiles are built before every phase but the first.
pub(crate) fn phase_cuts(batches: u32, depth: f64) -> Vec<f64> {
    if batches < MIN_BATCHES_FOR_PHASES || depth < MIN_POINTS_PER_PIXEL_FOR_PHASES {
        return Vec::new();
    }
    let phases =
        ((depth / POINTS_PER_PIXEL_PER_PHASE).round() as usize).clamp(MIN_PHASES, MAX_PHASES);
    (1..phases).map(|k| k as f64 / phases as f64).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_deep_tables_of_many_batches_are_drawn_in_phases() {
        assert_eq!(phase_cuts(2441, 12.6), [1.0 / 3.0, 2.0 / 3.0]);
        assert_eq!(phase_cuts(7325, 25.0).len(), 4);
        assert_eq!(phase_cuts(24414, 130.0).len(), MAX_PHASES - 1);
        assert!(phase_cuts(2441, 0.7).is_empty());
        assert!(phase_cuts(20, 50.0).is_empty());
    }
}
