//! Per-size GPU buffers of a frame: the point framebuffer and the resolved images.
//! Reused from frame to frame while the size stays the same.

use crate::gpu::staging_buffer;

pub(crate) struct FrameTargets {
    pub width: u32,
    pub height: u32,
    /// One (colour, depth-bits) pair of u32 words per pixel; a u64 to the 64-bit pass. The
    /// resolve pass empties it as it reads it.
    pub framebuffer: wgpu::Buffer,
    /// True until the framebuffer was first cleared (a new buffer holds zeros, not "empty").
    pub needs_clear: bool,
    /// RGBA8 per pixel.
    pub colour: wgpu::Buffer,
    /// Linear depth per pixel as f32, +infinity where no point landed.
    pub depth: wgpu::Buffer,
    /// Host-mappable copies of `colour` and `depth`, for readback.
    pub colour_staging: wgpu::Buffer,
    pub depth_staging: wgpu::Buffer,
    /// High-quality mode: per pixel the sums of red, green, blue and a count (4 x u32).
    /// Created (zeroed) on the first high-quality frame of this size; `resolve_average`
    /// zeroes it again as it reads it.
    pub accumulator: Option<wgpu::Buffer>,
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
            needs_clear: true,
            colour: storage("colour image", pixels * 4),
            depth: storage("depth image", pixels * 4),
            colour_staging: staging_buffer(device, "colour image readback", pixels * 4),
            depth_staging: staging_buffer(device, "depth image readback", pixels * 4),
            accumulator: None,
        }
    }

    pub fn ensure_accumulator(&mut self, device: &wgpu::Device) {
        let pixels = self.pixels();
        self.accumulator.get_or_insert_with(|| {
            device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("colour accumulator"),
                size: pixels * 16,
                usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            })
        });
    }

    pub fn pixels(&self) -> u64 {
        self.width as u64 * self.height as u64
    }
}
