//! How a request's points become pixels: size, colours, quality, filling, shading,
//! supersampling and the depth output, with their defaults (the ranges are in
//! [`crate::raster`]'s settings, shared with the renderer's own checks).

use serde::{Deserialize, Serialize};

use crate::color::{ColorMode, ColorRamp, ColorRange, Coloring};
use crate::filter::PointFilter;
use crate::raster::{FillSettings, Quality, Shading, DEFAULT_BACKGROUND, DEFAULT_POINT_SIZE};

/// No supersampling unless asked for.
pub const DEFAULT_SUPERSAMPLE: u32 = 1;

/// The options of a render request that do not move with the camera.
///
/// Stored by the daemon (serde): fields added later carry `#[serde(default)]`, so jobs
/// written before them still read.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct RenderOptions {
    /// Side of the square each point covers, in pixels.
    pub point_size: u32,
    pub quality: Quality,
    pub shading: Shading,
    pub color_mode: ColorMode,
    /// Elevation and intensity: the values the ramp spans (world Z in the file's units, raw
    /// intensity); `None`: the robust range of the dataset drawn.
    #[serde(default)]
    pub color_range: Option<ColorRange>,
    /// Elevation and intensity: the ramp; `None`: viridis for elevation, grey for intensity.
    #[serde(default)]
    pub color_ramp: Option<ColorRamp>,
    /// RGBA written where no point landed.
    pub background: [u8; 4],
    /// Visibility and hole filling; `None` turns both off.
    #[serde(default)]
    pub fill: Option<FillSettings>,
    /// Render at this many times the size in each direction and average (1 = off).
    #[serde(default = "default_supersample")]
    pub supersample: u32,
    /// Also produce the linear depth image of each frame.
    #[serde(default)]
    pub depth: bool,
    /// Render from levels of detail, refining a node while its point spacing covers more
    /// than this many pixels (0: every point); `None`: the dataset's points decide
    /// ([`crate::cut::RESIDENT_MAX_POINTS`]), at [`crate::cut::DEFAULT_LOD_ERROR_PX`].
    #[serde(default)]
    pub lod_error: Option<f64>,
    /// Which points are drawn ([`crate::filter`]); every point by default.
    #[serde(default)]
    pub filter: PointFilter,
}

fn default_supersample() -> u32 {
    DEFAULT_SUPERSAMPLE
}

impl Default for RenderOptions {
    fn default() -> Self {
        Self {
            point_size: DEFAULT_POINT_SIZE,
            quality: Quality::Basic,
            shading: Shading::None,
            color_mode: ColorMode::Rgb,
            color_range: None,
            color_ramp: None,
            background: DEFAULT_BACKGROUND,
            fill: None,
            supersample: DEFAULT_SUPERSAMPLE,
            depth: false,
            lod_error: None,
            filter: PointFilter::default(),
        }
    }
}

impl RenderOptions {
    /// How the points are coloured.
    pub fn coloring(&self) -> Coloring {
        Coloring {
            mode: self.color_mode,
            range: self.color_range,
            ramp: self.color_ramp,
        }
    }
}
