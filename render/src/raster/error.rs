use thiserror::Error;

use super::exposure::GAIN_RANGE;
use super::settings::{
    DEPTH_BAND_RANGE, EDL_RADIUS_RANGE, EDL_STRENGTH_RANGE, MAX_FILL_KERNEL, MAX_IMAGE_SIDE,
    MAX_PINTUS_LEVELS, MAX_POINT_SIZE, MAX_SUPERSAMPLE, MIN_FILL_KERNEL, PINTUS_EXPONENT_RANGE,
};
use crate::camera::CameraError;
use crate::gpu::GpuError;

#[derive(Debug, Error)]
pub enum RenderError {
    #[error(
        "image size {width}x{height} is invalid: each side must be 1 to {MAX_IMAGE_SIDE} pixels"
    )]
    ImageSize { width: u32, height: u32 },
    /// Even the smallest tile (one pixel and the overlap its passes read around it) exceeds
    /// the adapter's binding limit; larger frames are otherwise drawn in tiles.
    #[error(
        "image size {width}x{height} cannot be drawn in tiles on this adapter: even the \
         smallest tile needs a {needed_mib} MiB framebuffer, more than its {limit_mib} MiB \
         storage binding limit"
    )]
    ImageTooLarge {
        width: u32,
        height: u32,
        needed_mib: u64,
        limit_mib: u64,
    },
    #[error("adaptive point size scale {0} is invalid: it must be a positive finite number")]
    AdaptivePointSize(f32),
    #[error(
        "depth band {0} is invalid: it must be a finite number from {low} to {high}",
        low = DEPTH_BAND_RANGE.start(),
        high = DEPTH_BAND_RANGE.end()
    )]
    DepthBand(f32),
    #[error(
        "Eye-Dome Lighting strength {strength} and radius {radius} are invalid: the strength \
         must be {s_low} to {s_high}, the radius {r_low} to {r_high} pixels",
        s_low = EDL_STRENGTH_RANGE.start(),
        s_high = EDL_STRENGTH_RANGE.end(),
        r_low = EDL_RADIUS_RANGE.start(),
        r_high = EDL_RADIUS_RANGE.end()
    )]
    Edl { strength: f32, radius: f32 },
    #[error(
        "held exposure gain {0} is invalid: it must be a finite number from {low} to {high}",
        low = GAIN_RANGE.start(),
        high = GAIN_RANGE.end()
    )]
    ExposureGain(f32),
    #[error(
        "fill kernel {0} is invalid: it must be an odd number of pixels from {MIN_FILL_KERNEL} to {MAX_FILL_KERNEL}"
    )]
    FillKernel(u32),
    #[error(
        "Pintus shading with {levels} levels and exponent {exponent} is invalid: levels must \
         be 1 to {MAX_PINTUS_LEVELS}, the exponent {low} to {high}",
        low = PINTUS_EXPONENT_RANGE.start(),
        high = PINTUS_EXPONENT_RANGE.end()
    )]
    Pintus { levels: u32, exponent: f32 },
    #[error("supersampling factor {0} is invalid: it must be 1 to {MAX_SUPERSAMPLE}")]
    Supersample(u32),
    #[error("point size {0} is invalid: it must be 1 to {MAX_POINT_SIZE} pixels")]
    PointSize(u32),
    #[cfg(feature = "pointlist-baseline")]
    #[error("point size {0} is not supported by the PointList baseline: it draws 1-pixel points")]
    PointListPointSize(u32),
    #[error(transparent)]
    Camera(#[from] CameraError),
    #[error("the point cloud is empty")]
    EmptyCloud,
    #[error("GPU error: {0}")]
    Gpu(String),
}

impl From<GpuError> for RenderError {
    fn from(e: GpuError) -> Self {
        RenderError::Gpu(e.to_string())
    }
}
