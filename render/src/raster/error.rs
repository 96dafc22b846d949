use thiserror::Error;

use super::settings::{
    MAX_FILL_KERNEL, MAX_IMAGE_SIDE, MAX_PINTUS_LEVELS, MAX_POINT_SIZE, MAX_SUPERSAMPLE,
    MIN_FILL_KERNEL,
};
use crate::camera::CameraError;
use crate::gpu::GpuError;

#[derive(Debug, Error)]
pub enum RenderError {
    #[error(
        "image size {width}x{height} is invalid: each side must be 1 to {MAX_IMAGE_SIDE} pixels"
    )]
    ImageSize { width: u32, height: u32 },
    #[error(
        "image size {width}x{height} needs a {needed_mib} MiB framebuffer, more than this \
         adapter's {limit_mib} MiB storage binding limit"
    )]
    ImageTooLarge {
        width: u32,
        height: u32,
        needed_mib: u64,
        limit_mib: u64,
    },
    #[error("depth band {0} is invalid: it must be a finite number from 0 to 1")]
    DepthBand(f32),
    #[error("Eye-Dome Lighting strength {strength} and radius {radius} are invalid: the strength must be 0 to 100, the radius 0.5 to 16 pixels")]
    Edl { strength: f32, radius: f32 },
    #[error(
        "fill kernel {0} is invalid: it must be an odd number of pixels from {MIN_FILL_KERNEL} to {MAX_FILL_KERNEL}"
    )]
    FillKernel(u32),
    #[error("Pintus shading with {levels} levels and exponent {exponent} is invalid: levels must be 1 to {MAX_PINTUS_LEVELS}, the exponent 0 to 4")]
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
