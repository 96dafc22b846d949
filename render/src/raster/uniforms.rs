//! The frame's uniforms (`FrameUniforms` in common.wgsl) from its camera transform and
//! settings, the rows the resolve visits and the frame's footprint.

use super::gpu_data::FrameUniforms;
use super::occlusion;
use super::pixel_rect::PixelRect;
use super::resolve_pass::PixelRun;
use super::{FrameSettings, Quality, Shading};
use crate::camera::{CameraTransform, ImageWindow};

/// The uniforms of a frame seen through `t` with `settings`, whose resolve visits
/// `resolve_run`, whose points can touch `footprint` and whose statistics count `counted`.
pub(crate) fn frame_uniforms(
    t: &CameraTransform,
    settings: &FrameSettings,
    resolve_run: PixelRun,
    footprint: PixelRect,
    counted: ImageWindow,
) -> FrameUniforms {
    FrameUniforms {
        view_proj: t.view_proj.as_mat4().to_cols_array_2d(),
        depth_row: t.depth_row.as_vec4().to_array(),
        depth_band: match settings.quality {
            Quality::High { depth_band } => depth_band,
            Quality::Basic => 0.0,
        },
        near: t.near as f32,
        far: t.far as f32,
        width: settings.width,
        height: settings.height,
        background: u32::from_le_bytes(settings.background),
        edl_strength: match settings.shading {
            Shading::Edl { strength, .. } => strength,
            _ => 0.0,
        },
        edl_radius: match settings.shading {
            Shading::Edl { radius, .. } => radius,
            _ => 0.0,
        },
        // Image sides are at most MAX_IMAGE_SIDE: a run's length fits.
        resolve_pixels: resolve_run.count as u32,
        occlusion_tile_x0: footprint.x0 / occlusion::TILE,
        occlusion_tile_y0: footprint.y0 / occlusion::TILE,
        point_size_scale: settings.adaptive_size.unwrap_or(0.0),
        counted_min: [counted.x0, counted.y0],
        counted_end: [counted.x0 + counted.width, counted.y0 + counted.height],
    }
}
