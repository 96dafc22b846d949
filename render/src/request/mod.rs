//! One render request: the image size, the camera path with its lens, and the render
//! options, with their defaults and ranges, one validation naming the field at fault, and the
//! per-frame [`Camera`] and [`FrameSettings`] they describe. The CLI renders it here, the
//! daemon stores it and its workers render it: nothing else re-states a default or a range.

mod camera_path;
mod options;
mod point_size;
mod validate;

use serde::{Deserialize, Serialize};

pub use camera_path::{
    camera_for_frame, CameraPath, Interpolation, Keyframe, Lens, Point3, StillCamera, Turntable,
    DEFAULT_TURNTABLE_DEGREES, DEFAULT_UP, FOV_Y_DEG_RANGE, MIN_KEYFRAMES, TURNTABLE_DEGREES_RANGE,
    TURNTABLE_ELEVATION_RANGE, VIEW_ELEVATION_RANGE,
};
pub use options::{PointSize, RenderOptions, DEFAULT_SUPERSAMPLE};
pub use validate::RequestError;

use crate::camera::Camera;
use crate::extent::Framed;
use crate::raster::{AtomicsMode, Exposure, FrameSettings, DEFAULT_POINT_SIZE};

/// Everything that decides the frames of a render, apart from the cloud.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RenderRequest {
    pub width: u32,
    pub height: u32,
    pub camera_path: CameraPath,
    /// Absent in jobs stored before lenses could be chosen: a fitted perspective lens.
    #[serde(default)]
    pub lens: Lens,
    pub render: RenderOptions,
}

impl RenderRequest {
    /// `frames` frames of a turntable around the cloud, `width` by `height` pixels, through
    /// the default lens with the default render options.
    pub fn turntable(width: u32, height: u32, frames: u32) -> Self {
        Self {
            width,
            height,
            camera_path: CameraPath::Turntable(Turntable::around_the_cloud(frames)),
            lens: Lens::default(),
            render: RenderOptions::default(),
        }
    }

    pub fn frames(&self) -> u32 {
        self.camera_path.frames()
    }

    /// Width over height.
    pub fn aspect(&self) -> f64 {
        self.width as f64 / self.height.max(1) as f64
    }

    /// The camera of frame `index` for a cloud whose points lie in `extent` (its bounds, or
    /// an [`Extent`](crate::extent::Extent) with the robust box the automatic camera frames).
    pub fn camera(&self, index: u32, extent: &impl Framed) -> Camera {
        let extent = extent.extent();
        camera_for_frame(&self.camera_path, &self.lens, index, &extent, self.aspect())
    }

    /// The renderer's settings of frame `index` for a cloud whose points lie in `extent` (as
    /// [`RenderRequest::camera`] takes it) and `spacing` apart (world units; `None` when
    /// unknown), which sizes adaptive points.
    pub fn frame_settings(
        &self,
        index: u32,
        extent: &impl Framed,
        spacing: Option<f64>,
    ) -> FrameSettings {
        let extent = extent.extent();
        let RenderOptions {
            point_size,
            round_points,
            quality,
            shading,
            color_mode: _, // applied to the cloud's colors before upload
            color_range: _,
            color_ramp: _,
            background,
            fill,
            supersample,
            depth,
            lod_error: _, // chooses what is drawn, not how (`cut/`)
            filter: _,    // applied to the points before upload
        } = self.render;
        FrameSettings {
            width: self.width,
            height: self.height,
            camera: self.camera(index, &extent),
            point_size: DEFAULT_POINT_SIZE,
            adaptive_size: None,
            round_points,
            background,
            atomics: AtomicsMode::Auto,
            quality,
            fill,
            shading,
            // Measured here; a frame source holds its first frame's gain for the others.
            exposure: Exposure::Measured,
            supersample,
            read_depth: depth,
        }
        // The largest side at every point's box, as a camera placed by hand always had it.
        .with_point_size(point_size, &extent.all, spacing)
    }
}

#[cfg(test)]
mod tests;
