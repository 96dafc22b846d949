//! The uniforms of the passes on the resolved images (`shaders/screen_common.wgsl`): one
//! buffer of 256-byte slots, slot 0 for visibility and filling, slot 1 + k for level k of the
//! Pintus shading.

use bytemuck::{Pod, Zeroable};

use super::pipeline::bind_resources;
use super::pixel_rect::PixelRect;
use super::targets::FrameTargets;
use super::tiles::FrameWindow;
use super::{FrameSettings, Shading, MAX_PINTUS_LEVELS};
use crate::camera::Projection;

/// Mirrors `ScreenParams` in screen_common.wgsl.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub(crate) struct ScreenParams {
    pub width: u32,
    pub height: u32,
    pub kernel_radius: u32,
    pub perspective: u32,
    pub unproject: [f32; 2],
    pub min_solid_angle: f32,
    pub depth_tolerance: f32,
    pub background: u32,
    pub first_level: u32,
    pub level_weight: f32,
    pub inverse_total_weight: f32,
    /// The pixels the visibility pass classifies (`x0, y0, x1, y1`); all others are fixed.
    pub visibility_area: [u32; 4],
    /// Where these images lie in their frame: the first pixel's position, the frame's size.
    pub frame_offset: [u32; 2],
    pub frame_size: [u32; 2],
}

/// Uniform buffer offsets must be multiples of this (wgpu's default limit).
const SLOT: u64 = 256;
const SLOTS: u64 = 1 + MAX_PINTUS_LEVELS as u64;

pub(crate) struct ScreenUniforms {
    pub buffer: wgpu::Buffer,
}

impl ScreenUniforms {
    pub fn new(device: &wgpu::Device) -> Self {
        Self {
            buffer: device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("screen-space pass parameters"),
                size: SLOT * SLOTS,
                usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            }),
        }
    }

    /// Writes the frame's parameters (before the frame's passes are submitted); the frame's
    /// points can land only in `footprint`; its images are `view` of the whole frame.
    pub fn write(
        &self,
        queue: &wgpu::Queue,
        settings: &FrameSettings,
        footprint: PixelRect,
        view: FrameWindow,
    ) {
        let base = ScreenParams::new(settings, footprint, view);
        queue.write_buffer(&self.buffer, 0, bytemuck::bytes_of(&base));
        if let Shading::Pintus { levels, exponent } = settings.shading {
            let levels = levels.min(MAX_PINTUS_LEVELS);
            let total: f32 = (0..levels).map(|k| level_weight(k, exponent)).sum();
            for k in 0..levels {
                let params = ScreenParams {
                    first_level: (k == 0) as u32,
                    level_weight: level_weight(k, exponent),
                    inverse_total_weight: 1.0 / total,
                    ..base
                };
                queue.write_buffer(
                    &self.buffer,
                    Self::offset(1 + k),
                    bytemuck::bytes_of(&params),
                );
            }
        }
    }

    fn offset(slot: u32) -> u64 {
        slot as u64 * SLOT
    }

    /// Slot 0: visibility and filling.
    pub fn fill(&self) -> wgpu::BindingResource<'_> {
        self.slot(0)
    }

    /// The parameters of Pintus shading level `k`.
    pub fn pintus_level(&self, k: u32) -> wgpu::BindingResource<'_> {
        self.slot(1 + k)
    }

    fn slot(&self, slot: u32) -> wgpu::BindingResource<'_> {
        wgpu::BindingResource::Buffer(wgpu::BufferBinding {
            buffer: &self.buffer,
            offset: Self::offset(slot),
            size: wgpu::BufferSize::new(std::mem::size_of::<ScreenParams>() as u64),
        })
    }
}

/// What every pass on the resolved images binds from: the frame's buffers and these uniforms.
#[derive(Clone, Copy)]
pub(crate) struct ScreenFrame<'a> {
    pub device: &'a wgpu::Device,
    pub params: &'a ScreenUniforms,
    pub targets: &'a FrameTargets,
}

impl ScreenFrame<'_> {
    pub fn bind(
        &self,
        pipeline: &wgpu::ComputePipeline,
        label: &str,
        resources: Vec<(u32, wgpu::BindingResource<'_>)>,
    ) -> wgpu::BindGroup {
        bind_resources(self.device, pipeline, label, resources)
    }
}

/// Equation 3's weight of level k: 1 / (k + 1)^xi.
pub(crate) fn level_weight(k: u32, exponent: f32) -> f32 {
    1.0 / ((k + 1) as f32).powf(exponent)
}

impl ScreenParams {
    /// `settings` at the size of `view`'s window, which the projection's aspect is not.
    pub fn new(settings: &FrameSettings, footprint: PixelRect, view: FrameWindow) -> Self {
        let aspect = f64::from(view.frame_width) / f64::from(view.frame_height);
        let (perspective, half_height) = match settings.camera.projection {
            Projection::Perspective { fov_y_deg } => (1, (fov_y_deg.to_radians() * 0.5).tan()),
            Projection::Orthographic { height } => (0, height * 0.5),
        };
        let fill = settings.fill.unwrap_or_default();
        let area = visibility_area(settings, footprint);
        Self {
            width: settings.width,
            height: settings.height,
            kernel_radius: fill.kernel / 2,
            perspective,
            unproject: [(half_height * aspect) as f32, half_height as f32],
            min_solid_angle: super::VISIBILITY_MIN_SOLID_ANGLE,
            depth_tolerance: super::FILL_DEPTH_TOLERANCE,
            background: u32::from_le_bytes(settings.background),
            first_level: 0,
            level_weight: 0.0,
            inverse_total_weight: 0.0,
            visibility_area: [area.x0, area.y0, area.x1, area.y1],
            frame_offset: [view.window.x0, view.window.y0],
            frame_size: [view.frame_width, view.frame_height],
        }
    }
}

/// The pixels the visibility pass classifies when the frame's points can land only in
/// `footprint`. A pixel farther than the kernel's radius from every point sees no point: it
/// stays background, fixed. One pixel more holds the neighbours the filling reads around the
/// mutable pixels, which the visibility pass must have written.
pub(crate) fn visibility_area(settings: &FrameSettings, footprint: PixelRect) -> PixelRect {
    let kernel = settings.fill.unwrap_or_default().kernel;
    footprint.grown(kernel / 2 + 1, settings.width, settings.height)
}
