//! Per-size GPU buffers of a frame: the point framebuffer and the resolved images.
//! Reused from frame to frame while the size stays the same.

use crate::gpu::staging_buffer;

pub(crate) struct FrameTargets {
    pub width: u32,
    pub height: u32,
    /// One (colour, depth-bits) pair of u32 words per pixel; a u64 to the 64-bit pass.
    pub framebuffer: wgpu::Buffer,
    /// RGBA8 per pixel.
    pub colour: wgpu::Buffer,
    /// Linear depth per pixel as f32, +infinity where no point landed.
    pub depth: wgpu::Buffer,
    /// Host-mappable copies of `colour` and `depth`, for readback.
    pub colour_staging: wgpu::Buffer,
    pub depth_staging: wgpu::Buffer,
}

impl FrameTargets {
    pub fn new(device: &wgpu::Device, width: u32, height: u32) -> Self {
        let pixels = width as u64 * height as u64;
        let storage = |label: &str, size: u64| {
            device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size,
                usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
                mapped_at_creation: false,
            })
        };
        Self {
            width,
            height,
            framebuffer: storage("point framebuffer", pixels * 8),
            colour: storage("colour image", pixels * 4),
            depth: storage("depth image", pixels * 4),
            colour_staging: staging_buffer(device, "colour image readback", pixels * 4),
            depth_staging: staging_buffer(device, "depth image readback", pixels * 4),
        }
    }

    pub fn pixels(&self) -> u64 {
        self.width as u64 * self.height as u64
    }
}
