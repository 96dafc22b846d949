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
    /// Filling: created on the first filled frame of this size.
    pub fill: Option<FillTargets>,
    /// Pintus shading: created on the first such frame of this size.
    pub shading: Option<ShadingTargets>,
}

/// The visibility pass's output and the other half of the filling's ping-pong.
pub(crate) struct FillTargets {
    pub depth: wgpu::Buffer,
    pub colour: wgpu::Buffer,
    /// 1 where the filling may change the pixel, 0 where it is fixed.
    pub mutable: wgpu::Buffer,
}

/// Pintus shading's smoothed depth levels (ping-pong) and per-pixel weighted sum.
pub(crate) struct ShadingTargets {
    pub depth: [wgpu::Buffer; 2],
    pub sum: wgpu::Buffer,
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
            fill: None,
            shading: None,
        }
    }

    pub fn ensure_fill(&mut self, device: &wgpu::Device) {
        let bytes = self.pixels() * 4;
        self.fill.get_or_insert_with(|| FillTargets {
            depth: scratch(device, "fill depth", bytes),
            colour: scratch(device, "fill colour", bytes),
            mutable: scratch(device, "fill mutable pixels", bytes),
        });
    }

    pub fn ensure_shading(&mut self, device: &wgpu::Device) {
        let bytes = self.pixels() * 4;
        self.shading.get_or_insert_with(|| ShadingTargets {
            depth: [
                scratch(device, "shading depth level a", bytes),
                scratch(device, "shading depth level b", bytes),
            ],
            sum: scratch(device, "shading sum", bytes),
        });
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

/// A storage buffer only the GPU reads and writes.
fn scratch(device: &wgpu::Device, label: &str, size: u64) -> wgpu::Buffer {
    device.create_buffer(&wgpu::BufferDescriptor {
        label: Some(label),
        size,
        usage: wgpu::BufferUsages::STORAGE,
        mapped_at_creation: false,
    })
}
