//! How a request's points become pixels: size, colors, quality, filling, shading,
//! supersampling and the depth output, with their defaults (the ranges are in
//! [`crate::raster`]'s settings, shared with the renderer's own checks).

use serde::{Deserialize, Serialize};

use crate::color::{ColorMode, ColorRamp, ColorRange, Coloring};
use crate::filter::PointFilter;
use crate::raster::{FillSettings, Quality, Shading, DEFAULT_BACKGROUND};

/// No supersampling unless asked for.
pub const DEFAULT_SUPERSAMPLE: u32 = 1;

/// How large each point is drawn.
///
/// Stored and sent as one number, 0 meaning adaptive, so that jobs stored with a plain size
/// read as that fixed size.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(from = "u32", into = "u32")]
pub enum PointSize {
    /// Potree's adaptive size: the cloud's point spacing as it projects at each point's depth,
    /// rounded, from 1 to [`crate::raster::MAX_ADAPTIVE_POINT_SIZE`] pixels, so that a
    /// surface reads closed without hiding detail ([`super::point_size`]).
    #[default]
    Adaptive,
    /// A square of this many pixels a side.
    Fixed(u32),
}

impl From<u32> for PointSize {
    fn from(size: u32) -> Self {
        match size {
            0 => PointSize::Adaptive,
            side => PointSize::Fixed(side),
        }
    }
}

impl From<PointSize> for u32 {
    fn from(size: PointSize) -> u32 {
        match size {
            PointSize::Adaptive => 0,
            PointSize::Fixed(side) => side,
        }
    }
}

/// The options of a render request that do not move with the camera.
///
/// Stored by the daemon (serde): fields added later carry `#[serde(default)]`, so jobs
/// written before them still read.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct RenderOptions {
    pub point_size: PointSize,
    /// Draw each point as the disc its square bounds (sizes of 4 pixels and more).
    #[serde(default)]
    pub round_points: bool,
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
            point_size: PointSize::Adaptive,
            round_points: false,
            quality: Quality::Basic,
            // Eye-Dome Lighting, as Potree: raw scans read as surfaces, and scans without
            // color show their shape, for about the cost of encoding the frame
            // (docs/gallery.md, docs/perf/edl-constants.md).
            shading: Shading::EDL,
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
    /// How the points are colored.
    pub fn coloring(&self) -> Coloring {
        Coloring {
            mode: self.color_mode,
            range: self.color_range,
            ramp: self.color_ramp,
        }
    }
}
