//! Per-size GPU buffers of a frame: the point framebuffer and the resolved images.
//! Reused from frame to frame while the size stays the same.
//!
//! They also remember where the last frame's points could have landed, so that the next
//! resolve visits only that and its own footprint: a cloud that covers a corner of the image
//! does not pay for resolving the rest of it every frame.

use super::occlusion::OcclusionTiles;
use super::pixel_rect::PixelRect;
use super::FrameSettings;
use crate::gpu::staging_buffer;

pub(crate) struct FrameTargets {
    pub width: u32,
    pub height: u32,
    /// One (color, depth-bits) pair of u32 words per pixel; a u64 to the 64-bit pass. The
    /// resolve pass empties it as it reads it.
    pub framebuffer: wgpu::Buffer,
    /// True until the framebuffer was first cleared (a new buffer holds zeros, not "empty").
    pub needs_clear: bool,
    /// The point passes' occlusion culling of whole batches (`occlusion.rs`).
    pub occlusion: OcclusionTiles,
    /// RGBA8 per pixel.
    pub color: wgpu::Buffer,
    /// Linear depth per pixel as f32, +infinity where no point landed.
    pub depth: wgpu::Buffer,
    /// Host-mappable copies of `color` and `depth`, for readback.
    pub color_staging: wgpu::Buffer,
    pub depth_staging: wgpu::Buffer,
    /// High-quality mode: per pixel the sums of red, green, blue and a count (4 x u32).
    /// Created (zeroed) on the first high-quality frame of this size; `resolve_average`
    /// zeroes it again as it reads it.
    pub accumulator: Option<wgpu::Buffer>,
    /// High-quality mode with 64-bit atomics: per pixel the sums of red, green, blue and the
    /// count, 16 bits each, packed in a u64 (`shaders/hq_sums_atomic64.wgsl`); the
    /// `accumulator` then holds only what overflows them. Created and zeroed like it.
    pub packed_sums: Option<wgpu::Buffer>,
    /// Filling: created on the first filled frame of this size.
    pub fill: Option<FillTargets>,
    /// Pintus shading: created on the first such frame of this size.
    pub shading: Option<ShadingTargets>,
    /// What the images hold outside the last frame's footprint, when that is known.
    clean_outside: Option<CleanOutside>,
}

/// Outside `footprint` the color image holds `background`, the depth image (where `depth`)
/// "no surface", and the framebuffer and accumulator are empty: no point landed there since
/// a resolve that covered those pixels.
#[derive(Debug, Clone, Copy)]
struct CleanOutside {
    footprint: PixelRect,
    background: [u8; 4],
    depth: bool,
}

/// The visibility pass's output and the other half of the filling's ping-pong.
pub(crate) struct FillTargets {
    pub depth: wgpu::Buffer,
    pub color: wgpu::Buffer,
    /// The pixels the filling may change, `(y << 16) | x` each, in no particular order; the
    /// others are fixed. Written by the visibility pass, which counts them in `list_args`.
    pub mutable: wgpu::Buffer,
    /// The filling's indirect dispatch over `mutable` (workgroups x, y, z) and the number of
    /// mutable pixels (`shaders/fill.wgsl`, `FillArgs`).
    pub list_args: wgpu::Buffer,
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
            occlusion: OcclusionTiles::new(device, width, height),
            color: storage("color image", pixels * 4),
            depth: storage("depth image", pixels * 4),
            color_staging: staging_buffer(device, "color image readback", pixels * 4),
            depth_staging: staging_buffer(device, "depth image readback", pixels * 4),
            accumulator: None,
            packed_sums: None,
            fill: None,
            shading: None,
            clean_outside: None,
        }
    }

    /// The pixels the resolve of a frame with `settings`, whose points can land in
    /// `footprint`, must visit: this footprint and the last one (to erase the last frame's
    /// points), or the whole image unless the rest is known to be clean for this frame.
    /// Forgets what it knew until [`FrameTargets::record_resolved`], in case the frame fails.
    pub fn begin_resolve(&mut self, footprint: PixelRect, settings: &FrameSettings) -> PixelRect {
        let known = self.clean_outside.take().filter(|clean| {
            !settings.rewrites_resolved_images()
                && clean.background == settings.background
                && (clean.depth || !settings.needs_depth_image())
        });
        match known {
            Some(clean) => footprint.union(clean.footprint),
            None => PixelRect::full(self.width, self.height),
        }
    }

    /// Records what the images hold after a frame with `settings`, whose points could land in
    /// `footprint`, was resolved over the area [`FrameTargets::begin_resolve`] gave.
    pub fn record_resolved(&mut self, footprint: PixelRect, settings: &FrameSettings) {
        // Filling and shading write pixels anywhere in the images.
        if settings.rewrites_resolved_images() {
            return;
        }
        self.clean_outside = Some(CleanOutside {
            footprint,
            background: settings.background,
            // A frame that writes depth had it clean outside its area (`begin_resolve`), and
            // wrote "no surface" inside it wherever no point landed.
            depth: settings.needs_depth_image(),
        });
    }

    pub fn ensure_fill(&mut self, device: &wgpu::Device) {
        let bytes = self.pixels() * 4;
        self.fill.get_or_insert_with(|| FillTargets {
            depth: scratch(device, "fill depth", bytes),
            color: scratch(device, "fill color", bytes),
            mutable: scratch(device, "fill mutable pixels", bytes),
            list_args: device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("fill dispatch arguments"),
                size: 16,
                usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::INDIRECT,
                mapped_at_creation: false,
            }),
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

    /// The high-quality accumulator, and the packed sums where `packed_sums`.
    pub fn ensure_accumulator(&mut self, device: &wgpu::Device, packed_sums: bool) {
        let pixels = self.pixels();
        let zeroed = |label, bytes_per_pixel| {
            device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size: pixels * bytes_per_pixel,
                usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            })
        };
        self.accumulator
            .get_or_insert_with(|| zeroed("color accumulator", 16));
        if packed_sums {
            self.packed_sums
                .get_or_insert_with(|| zeroed("packed color sums", 8));
        }
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::Camera;
    use crate::cloud::WorldBounds;
    use crate::raster::{FillSettings, Shading};
    use glam::DVec3;

    fn rect(x0: u32, y0: u32, x1: u32, y1: u32) -> PixelRect {
        PixelRect { x0, y0, x1, y1 }
    }

    #[test]
    fn the_resolve_visits_the_last_and_this_footprint_once_the_rest_is_known_clean() {
        let gpu = crate::testing::gpu();
        let bounds = WorldBounds {
            min: DVec3::ZERO,
            max: DVec3::ONE,
        };
        let basic = FrameSettings::new(64, 48, Camera::auto(&bounds, 4.0 / 3.0));
        let full = PixelRect::full(64, 48);
        let mut targets = FrameTargets::new(&gpu.device, 64, 48);
        let (a, b) = (rect(0, 0, 10, 10), rect(30, 20, 40, 48));

        // One frame: the area its resolve visits.
        let mut frame = |footprint: PixelRect, settings: &FrameSettings| {
            let area = targets.begin_resolve(footprint, settings);
            targets.record_resolved(footprint, settings);
            area
        };

        // Nothing is known of new images.
        assert_eq!(frame(a, &basic), full);
        // The last frame's points and this frame's.
        assert_eq!(frame(b, &basic), rect(0, 0, 40, 48));
        // A frame with no point in view erases the last one's; the next has nothing to do.
        assert_eq!(frame(PixelRect::EMPTY, &basic), b);
        assert!(frame(PixelRect::EMPTY, &basic).is_empty());

        // A new background repaints everything.
        let grey = FrameSettings {
            background: [90, 90, 90, 255],
            ..basic
        };
        assert_eq!(frame(a, &grey), full);
        assert_eq!(frame(a, &basic), full);

        // The depth image was not written outside the footprints of color-only frames.
        let depth = FrameSettings {
            read_depth: true,
            ..basic
        };
        assert_eq!(frame(a, &depth), full);
        assert_eq!(frame(b, &depth), a.union(b));
        assert_eq!(frame(a, &basic), a.union(b));

        // Filling and shading write anywhere: the frame after them starts over too.
        for rewrites in [
            FrameSettings {
                fill: Some(FillSettings::default()),
                ..basic
            },
            FrameSettings {
                shading: Shading::EDL,
                ..basic
            },
        ] {
            assert_eq!(frame(a, &rewrites), full);
            assert_eq!(frame(a, &basic), full);
        }
    }
}
