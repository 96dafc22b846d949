//! The CPU-side point cloud: what ingest produces and what the GPU upload and the CPU
//! reference renderer consume.
//!
//! Survey coordinates are large (UTM, state plane): an f32 has a 24-bit mantissa, so at
//! x ≈ 500,000 m it resolves only ~3 cm. Positions are therefore decoded in f64, recentred on
//! [`PointCloud::origin`] in f64, and only the small offsets are stored as f32. Every camera is
//! built relative to the same origin (see `camera`).

use glam::{DVec3, Vec3};

/// The largest coordinate magnitude of a point or camera, in the file's units: survey
/// coordinates, even geocentric ones in millimetres, stay below 1e10; beyond this the
/// camera's arithmetic overflows. Files and camera paths beyond it are refused.
pub const MAX_COORDINATE: f64 = 1e12;

/// An axis-aligned box in f64 world coordinates.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WorldBounds {
    pub min: DVec3,
    pub max: DVec3,
}

impl WorldBounds {
    /// The box of no points: inverted, so a union takes nothing from it and nothing lies in
    /// it.
    pub const NOWHERE: WorldBounds = WorldBounds {
        min: DVec3::INFINITY,
        max: DVec3::NEG_INFINITY,
    };

    /// Whether the box holds any place: not inverted on any axis.
    pub fn is_somewhere(&self) -> bool {
        self.min.cmple(self.max).all()
    }

    pub fn center(&self) -> DVec3 {
        (self.min + self.max) * 0.5
    }

    pub fn size(&self) -> DVec3 {
        self.max - self.min
    }

    /// Radius of the bounding sphere around the box centre.
    pub fn radius(&self) -> f64 {
        self.size().length() * 0.5
    }
}

/// Where the display color of the points came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ColorSource {
    /// 16-bit RGB fields holding 16-bit values (scaled down by 256).
    Rgb16,
    /// 16-bit RGB fields holding 8-bit values (some writers do this; used as they are).
    Rgb8In16Bit,
    /// No RGB in the file: intensity as grey, stretched between robust percentiles.
    IntensityGrey,
    /// Neither RGB nor intensity: one neutral grey.
    Constant,
}

impl ColorSource {
    /// What the RGB color mode shows, in words for people.
    pub fn describe(self) -> &'static str {
        match self {
            Self::Rgb16 => "color from 16-bit RGB",
            Self::Rgb8In16Bit => "color from RGB (8-bit values in 16-bit fields)",
            Self::IntensityGrey => "grey from intensity",
            Self::Constant => "one grey (no color or intensity)",
        }
    }

    /// The one RGB decision, from the largest channel of any point of the whole dataset
    /// (`max_channel`). `None` when every channel is 0: the fields exist but were never filled
    /// (some writers do this), and the points are colored from intensity instead of black.
    /// The spec says 16-bit, but some writers store 8-bit values as they are; if no channel
    /// exceeds 255 that is what the fields hold.
    pub fn of_rgb(max_channel: u16) -> Option<Self> {
        match max_channel {
            0 => None,
            1..=255 => Some(Self::Rgb8In16Bit),
            _ => Some(Self::Rgb16),
        }
    }

    /// The RGB decision from the lowest and highest value of each channel over the whole
    /// dataset: as [`of_rgb`](Self::of_rgb), and also `None` when every point has one color
    /// while the points carry intensity, which then says more than the RGB does (a writer's
    /// placeholder color).
    pub fn of_rgb_range(min: [u16; 3], max: [u16; 3], has_intensity: bool) -> Option<Self> {
        if min == max && has_intensity {
            return None;
        }
        Self::of_rgb(max.into_iter().max().unwrap_or(0))
    }
}

/// Packs an opaque RGB color into the renderer's RGBA8 word (red in the low byte, alpha 255).
pub fn pack_rgba8(r: u8, g: u8, b: u8) -> u32 {
    u32::from_le_bytes([r, g, b, 255])
}

/// A point cloud recentred on `origin`. All per-point vectors have the same length.
#[derive(Debug, Clone, PartialEq)]
pub struct PointCloud {
    /// World position that all `positions` are relative to (f64, never rounded).
    pub origin: DVec3,
    /// Position of each point minus `origin`, computed in f64 and then stored as f32.
    pub positions: Vec<Vec3>,
    /// Display color of each point, packed with [`pack_rgba8`].
    pub colors: Vec<u32>,
    /// Raw LAS intensity (0 where the file has none), kept for intensity color modes.
    pub intensity: Vec<u16>,
    /// ASPRS classification code, kept for classification color modes.
    pub classification: Vec<u8>,
    /// Return number (1-based in LAS; 0 where unknown), kept for return color modes.
    pub return_number: Vec<u8>,
    /// Bounds of the points in world coordinates, computed from the data (not the header).
    pub bounds: WorldBounds,
    pub color_source: ColorSource,
}

impl PointCloud {
    /// No points yet, room for `points` of them (a count already checked against its source).
    pub fn with_capacity(
        origin: DVec3,
        bounds: WorldBounds,
        color_source: ColorSource,
        points: usize,
    ) -> Self {
        Self {
            origin,
            positions: Vec::with_capacity(points),
            colors: Vec::with_capacity(points),
            intensity: Vec::with_capacity(points),
            classification: Vec::with_capacity(points),
            return_number: Vec::with_capacity(points),
            bounds,
            color_source,
        }
    }

    pub fn len(&self) -> usize {
        self.positions.len()
    }

    pub fn is_empty(&self) -> bool {
        self.positions.is_empty()
    }

    /// The typical distance between neighbouring points ([`crate::spacing::of_points`]).
    pub fn spacing(&self) -> Option<f64> {
        crate::spacing::of_points(&self.positions)
    }

    /// Builds a cloud from world positions and colors (for generated and test clouds):
    /// recentres on the bounds' centre in f64. Intensity, classification and returns are zero.
    pub fn from_world_points(points: &[DVec3], colors: Vec<u32>) -> Self {
        assert_eq!(points.len(), colors.len(), "one color per point");
        let bounds = bounds_of(points.iter().copied());
        let origin = bounds.center();
        Self {
            origin,
            positions: points.iter().map(|p| (*p - origin).as_vec3()).collect(),
            colors,
            intensity: vec![0; points.len()],
            classification: vec![0; points.len()],
            return_number: vec![0; points.len()],
            bounds,
            color_source: ColorSource::Rgb16,
        }
    }

    /// Keeps only the points at `indices` (in that order); bounds are recomputed.
    pub fn select(&self, indices: &[usize]) -> Self {
        let positions: Vec<Vec3> = indices.iter().map(|&i| self.positions[i]).collect();
        let origin = self.origin;
        let bounds = bounds_of(positions.iter().map(|p| origin + p.as_dvec3()));
        Self {
            origin,
            positions,
            colors: indices.iter().map(|&i| self.colors[i]).collect(),
            intensity: indices.iter().map(|&i| self.intensity[i]).collect(),
            classification: indices.iter().map(|&i| self.classification[i]).collect(),
            return_number: indices.iter().map(|&i| self.return_number[i]).collect(),
            bounds,
            color_source: self.color_source,
        }
    }
}

/// Bounds of a set of world points; an empty set gives a degenerate box at the origin.
pub fn bounds_of(points: impl IntoIterator<Item = DVec3>) -> WorldBounds {
    let mut min = DVec3::splat(f64::INFINITY);
    let mut max = DVec3::splat(f64::NEG_INFINITY);
    for p in points {
        min = min.min(p);
        max = max.max(p);
    }
    if min.x > max.x {
        return WorldBounds {
            min: DVec3::ZERO,
            max: DVec3::ZERO,
        };
    }
    WorldBounds { min, max }
}
