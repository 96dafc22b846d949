//! What decides the pixels of a frame: its size, camera, quality, filling, shading and
//! supersampling, with the limits the renderer accepts.

use std::ops::RangeInclusive;

use serde::{Deserialize, Serialize};

use super::RenderError;
use crate::camera::Camera;

/// Largest image side accepted, in pixels.
pub const MAX_IMAGE_SIDE: u32 = 16384;
/// Largest supersampling factor.
pub const MAX_SUPERSAMPLE: u32 = 4;
/// Largest point size accepted, in pixels.
pub const MAX_POINT_SIZE: u32 = 64;
/// One-pixel points unless asked otherwise.
pub const DEFAULT_POINT_SIZE: u32 = 1;
/// The largest side an adaptive point takes, in pixels: a point nearer than its spacing
/// allows keeps a hole rather than cost the point passes more than 64 pixels.
pub const MAX_ADAPTIVE_POINT_SIZE: u32 = 8;
/// Dark grey (#18181c), opaque: written where no point landed unless asked otherwise.
pub const DEFAULT_BACKGROUND: [u8; 4] = [24, 24, 28, 255];
/// High quality averages the points up to this fraction behind the nearest depth (the
/// papers' 1%).
pub const DEFAULT_DEPTH_BAND: f32 = 0.01;
/// Depth bands accepted: a fraction of the nearest depth.
pub const DEPTH_BAND_RANGE: RangeInclusive<f32> = 0.0..=1.0;
/// Eye-Dome Lighting strengths accepted.
pub const EDL_STRENGTH_RANGE: RangeInclusive<f32> = 0.0..=100.0;
/// Eye-Dome Lighting sample distances accepted, in pixels.
pub const EDL_RADIUS_RANGE: RangeInclusive<f32> = 0.5..=16.0;
/// Pintus weight exponents accepted.
pub const PINTUS_EXPONENT_RANGE: RangeInclusive<f32> = 0.0..=4.0;
/// Smallest and largest visibility kernel side, in pixels (odd).
pub const MIN_FILL_KERNEL: u32 = 3;
pub const MAX_FILL_KERNEL: u32 = 9;
/// Most smoothing levels of the Pintus shading.
pub const MAX_PINTUS_LEVELS: u32 = 32;
/// Visibility: a pixel is visible when the solid angle left open around its ray to the camera
/// is at least 0.8 pi steradians, 40% of a hemisphere. A point on any plane, at any tilt, has
/// about a hemisphere (2 pi); a point beside the edge of a nearer surface about half that
/// (pi); a point seen through a hole that closes 6 of the 8 sectors at most pi / 2. Background
/// pixels count 4 pi / 8 per sector without points: one beside a silhouette (3 or more open
/// sectors, 1.5 pi) stays background, one enclosed by points (at most 1 open, pi / 2) is filled.
pub const VISIBILITY_MIN_SOLID_ANGLE: f32 = 0.8 * std::f32::consts::PI;
/// Filling: the paper's delta, as a fraction of the pixel's depth. A neighbour whose depth
/// differs by 5% or more gets no weight, so the filling does not blur across depth edges;
/// the depth step between neighbouring pixels of a plane seen at 10 degrees is about 2%
/// (50 degree view, 240 pixels high).
pub const FILL_DEPTH_TOLERANCE: f32 = 0.05;

#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub enum AtomicsMode {
    /// 64-bit where the device has them, else 32-bit.
    #[default]
    Auto,
    /// Always the 32-bit path (for adapters without 64-bit atomics, and to test it).
    Force32,
}

/// How the color of a pixel is chosen.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub enum Quality {
    /// The nearest point's color (one atomic minimum per pixel).
    Basic,
    /// The average color of all points whose depth is at most `(1 + depth_band)` times the
    /// nearest depth of the pixel (Schütz & Wimmer's high-quality mode).
    High { depth_band: f32 },
}

impl Quality {
    /// High quality with the papers' default band of 1%.
    pub const HIGH: Quality = Quality::High {
        depth_band: DEFAULT_DEPTH_BAND,
    };
}

/// Screen-space shading applied after the resolve.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub enum Shading {
    None,
    /// Eye-Dome Lighting as in Potree: `strength` scales the darkening, `radius` is the
    /// distance in pixels of the eight depth samples.
    Edl {
        strength: f32,
        radius: f32,
    },
    /// Pintus et al.'s shape-depicting shading: a directional-light, ambient-occlusion and
    /// line-drawing term from the depth alone, summed over `levels` smoothing levels with
    /// weights 1 / (k + 1)^`exponent` (the paper's xi).
    Pintus {
        levels: u32,
        exponent: f32,
    },
}

impl Shading {
    /// Potree's default EDL strength.
    pub const DEFAULT_EDL_STRENGTH: f32 = 1.0;
    /// Potree's default EDL radius, in pixels.
    pub const DEFAULT_EDL_RADIUS: f32 = 1.4;
    /// Smoothing levels of the Pintus term.
    pub const DEFAULT_PINTUS_LEVELS: u32 = 8;
    /// The paper's weight exponent, 3/2.
    pub const DEFAULT_PINTUS_EXPONENT: f32 = 1.5;

    pub const EDL: Shading = Shading::Edl {
        strength: Self::DEFAULT_EDL_STRENGTH,
        radius: Self::DEFAULT_EDL_RADIUS,
    };
    pub const PINTUS: Shading = Shading::Pintus {
        levels: Self::DEFAULT_PINTUS_LEVELS,
        exponent: Self::DEFAULT_PINTUS_EXPONENT,
    };
}

/// How the gain after Eye-Dome Lighting is chosen (`raster::exposure`).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub enum Exposure {
    /// Measured on this frame: the gain that brings its shaded median luma back to the
    /// unshaded one.
    #[default]
    Measured,
    /// Held at this gain (finite, within [`GAIN_RANGE`](super::exposure::GAIN_RANGE)), measured on another frame: the
    /// frames of a turntable or a job share their first frame's, so their brightness does
    /// not drift from frame to frame.
    Held(f32),
}

/// Pintus et al.'s visibility and anisotropic filling, run after the resolve: points seen
/// through holes of a nearer surface are removed, then the holes (and background pixels
/// enclosed by points) get the depth and color of the surface around them. Pixels outside
/// silhouettes stay background.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct FillSettings {
    /// Side of the visibility kernel in pixels: odd, 3 to 9. Holes up to about a third of it
    /// are closed; the filling runs twice this many 3x3 steps.
    pub kernel: u32,
}

impl Default for FillSettings {
    fn default() -> Self {
        Self {
            kernel: Self::DEFAULT_KERNEL,
        }
    }
}

impl FillSettings {
    pub const DEFAULT_KERNEL: u32 = 7;

    /// The paper's iteration count: twice the kernel size.
    pub fn iterations(&self) -> u32 {
        2 * self.kernel
    }
}

/// Everything that decides the pixels of one frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FrameSettings {
    pub width: u32,
    pub height: u32,
    pub camera: Camera,
    /// Side of the square each point covers, in pixels; with `adaptive_size`, the largest.
    pub point_size: u32,
    /// Potree's adaptive point size: a point's side is this over its linear depth (the
    /// cloud's point spacing times the focal length in pixels), rounded, from 1 to
    /// `point_size`. `None`: every point covers `point_size`.
    pub adaptive_size: Option<f32>,
    /// Round points: a point covers the pixels of its square whose centres lie in the disc
    /// the square bounds.
    pub round_points: bool,
    /// RGBA written where no point landed.
    pub background: [u8; 4],
    pub atomics: AtomicsMode,
    pub quality: Quality,
    /// Visibility and filling; `None` turns both off.
    pub fill: Option<FillSettings>,
    pub shading: Shading,
    /// The gain after Eye-Dome Lighting; ignored by the other shadings.
    pub exposure: Exposure,
    /// Supersampling anti-aliasing: render at this many times the size in each direction
    /// (points and shading radius scaled with it) and average k x k blocks. 1 turns it off.
    pub supersample: u32,
    /// Also read back the linear depth image.
    pub read_depth: bool,
}

impl FrameSettings {
    /// Defaults: one-pixel points on a dark grey background, automatic atomics.
    pub fn new(width: u32, height: u32, camera: Camera) -> Self {
        Self {
            width,
            height,
            camera,
            point_size: DEFAULT_POINT_SIZE,
            adaptive_size: None,
            round_points: false,
            background: DEFAULT_BACKGROUND,
            atomics: AtomicsMode::Auto,
            quality: Quality::Basic,
            fill: None,
            shading: Shading::None,
            exposure: Exposure::Measured,
            supersample: 1,
            read_depth: false,
        }
    }
}

impl FrameSettings {
    /// The checks every renderer makes: each side 1 to `max_side` pixels (at most
    /// [`MAX_IMAGE_SIDE`]) and a camera that can render.
    pub(crate) fn validate_view(&self, max_side: u32) -> Result<(), RenderError> {
        let (width, height) = (self.width, self.height);
        if width == 0
            || height == 0
            || width > max_side.min(MAX_IMAGE_SIDE)
            || height > max_side.min(MAX_IMAGE_SIDE)
        {
            return Err(RenderError::ImageSize { width, height });
        }
        Ok(self.camera.validate()?)
    }

    /// The side of the square a point at linear depth `depth` covers, in pixels: the shaders'
    /// `project_quantised` in f32, as the CPU reference needs it.
    pub fn point_side_at(&self, depth: f32) -> u32 {
        match self.adaptive_size {
            None => self.point_size,
            Some(scale) => (scale / depth + 0.5)
                .floor()
                .clamp(1.0, self.point_size as f32) as u32,
        }
    }

    /// Whether the frame needs the resolved depth image: to read it back, or for filling or
    /// shading, which work on it. Otherwise the resolve does not write it.
    pub fn needs_depth_image(&self) -> bool {
        self.read_depth || self.rewrites_resolved_images()
    }

    /// Whether passes after the resolve rewrite its images (filling, shading).
    pub fn rewrites_resolved_images(&self) -> bool {
        self.fill.is_some() || self.shading != Shading::None
    }

    /// The settings at which a supersampled frame is rendered before it is downsampled.
    pub fn scaled_for_supersampling(&self) -> FrameSettings {
        let k = self.supersample.max(1);
        FrameSettings {
            width: self.width.saturating_mul(k),
            height: self.height.saturating_mul(k),
            point_size: self.point_size.saturating_mul(k),
            adaptive_size: self.adaptive_size.map(|size| size * k as f32),
            shading: match self.shading {
                Shading::Edl { strength, radius } => Shading::Edl {
                    strength,
                    radius: radius * k as f32,
                },
                other => other,
            },
            // The same holes are k times wider: the kernel radius grows with them (the kernel
            // may then exceed MAX_FILL_KERNEL, which bounds what a user asks for).
            fill: self.fill.map(|fill| FillSettings {
                kernel: (fill.kernel / 2) * k * 2 + 1,
            }),
            supersample: 1,
            ..*self
        }
    }
}
