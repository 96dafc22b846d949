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
    pub point_size: u32,
    pub background: u32,
    pub depth_band: f32,
    pub edl_strength: f32,
    pub edl_radius: f32,
    pub _pad: [u32; 3],
}

/// `GpuPoint` in common.wgsl: position relative to the dataset origin, RGBA8 colour.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Pod, Zeroable)]
pub struct GpuPoint {
    pub position: [f32; 3],
    pub colour: u32,
}

/// `Batch` in common.wgsl: a run of points in one chunk, with their bounding box.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Pod, Zeroable)]
pub struct GpuBatch {
    pub min: [f32; 3],
    /// Index of the batch's first point within its chunk.
    pub first: u32,
    pub max: [f32; 3],
    pub count: u32,
}

const _: () = assert!(std::mem::size_of::<FrameUniforms>() == 128);
const _: () = assert!(std::mem::size_of::<GpuPoint>() == 16);
const _: () = assert!(std::mem::size_of::<GpuBatch>() == 32);
