//! Structs shared with WGSL (`shaders/common.wgsl`), byte for byte.
//!
//! WGSL layout rules: a `vec3<f32>` is 16-byte aligned but 12 bytes long, so a scalar placed
//! right after it fills the gap; uniform structs round up to 16 bytes.

use bytemuck::{Pod, Zeroable};

/// `FrameUniforms` in common.wgsl.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct FrameUniforms {
    pub view_proj: [[f32; 4]; 4],
    pub depth_row: [f32; 4],
    pub near: f32,
    pub far: f32,
    pub width: u32,
    pub height: u32,
    pub background: u32,
    pub depth_band: f32,
    pub edl_strength: f32,
    pub edl_radius: f32,
    /// Pixels the resolve visits, from the first of its bindings (`PixelRun`).
    pub resolve_pixels: u32,
    /// The first occlusion tile of the frame's footprint (`occlusion.rs`).
    pub occlusion_tile_x0: u32,
    pub occlusion_tile_y0: u32,
    /// Adaptive point size: a point's side in pixels times its depth (0 when fixed).
    pub point_size_scale: f32,
    /// The pixels frame-wide statistics count, from `counted_min` to before `counted_end`
    /// (`FrameWindow::counted`).
    pub counted_min: [u32; 2],
    pub counted_end: [u32; 2],
}

/// A point's position as two u32 words, laid out as `pointfarm_shaders::layout::POSITION_BITS`
/// says: each axis is the position's fraction of its batch's box in steps of
/// `extent / (2^bits - 1)` (see `points::quantise`).
pub type QuantisedPosition = [u32; 2];

/// Bytes of one point's color on the GPU: RGB, 8 bits each, packed back to back (points are
/// opaque; the shaders put alpha 255 back).
pub const COLOR_BYTES: u64 = 3;

/// `Batch` in common.wgsl: a run of points in one segment, with their bounding box.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Pod, Zeroable)]
pub struct GpuBatch {
    pub min: [f32; 3],
    /// Index of the batch's first point within its segment.
    pub first: u32,
    pub max: [f32; 3],
    pub count: u32,
}

impl GpuBatch {
    /// This batch as a batch table on the GPU holds it with its points drawn `factor` times
    /// the frame's adaptive size (`batch_size_factor` in common.wgsl): the factor in 8.8
    /// fixed point in the high 16 bits of `count`, where 0 means 1. A level-of-detail cut
    /// sizes each node's batches by its spacing; the host's copy keeps the plain count.
    pub fn with_size_factor(self, factor: f32) -> GpuBatch {
        let code = (factor * SIZE_FACTOR_ONE as f32)
            .round()
            .clamp(1.0, f32::from(u16::MAX)) as u32;
        GpuBatch {
            count: self.count | code << 16,
            ..self
        }
    }
}

/// A size factor of 1 in `GpuBatch::with_size_factor`'s fixed point.
const SIZE_FACTOR_ONE: u32 = 256;

// The point count shares its word with the size factor.
const _: () = assert!(crate::raster::BATCH_POINTS < 1 << 16);
const _: () = assert!(std::mem::size_of::<FrameUniforms>() == 144);
const _: () = assert!(std::mem::size_of::<QuantisedPosition>() == 8);
const _: () = assert!(std::mem::size_of::<GpuBatch>() == 32);
