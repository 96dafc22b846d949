//! Colour modes: what colour each point is drawn in.
//!
//! The renderer draws `PointCloud::colors`; a colour mode fills that vector from the cloud's
//! attributes before upload. Ranges are robust (2nd to 98th percentile), so a few outliers
//! (birds, multipath returns, saturated intensities) do not flatten the scale.

use crate::cloud::{pack_rgba8, PointCloud};

/// What the points are coloured by.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
pub enum ColorMode {
    /// The file's RGB (or, without RGB, intensity grey: the colour chosen at ingest).
    #[default]
    Rgb,
    /// Intensity as grey, stretched between robust percentiles.
    Intensity,
    /// Height (world Z) through the viridis colour map, over a robust range.
    Elevation,
    /// The ASPRS classification palette.
    Classification,
    /// Return number: first, second, third, fourth and later.
    ReturnNumber,
    /// One colour for every point.
    Fixed([u8; 3]),
}

/// Lower and upper percentile of every robust range.
const LOW_PERCENTILE: f64 = 0.02;
const HIGH_PERCENTILE: f64 = 0.98;
/// Darkest grey for intensity colouring: weak returns stay visible against a dark background.
pub const INTENSITY_GREY_MIN: u8 = 40;
/// Colour of every point when there is nothing to colour it by.
pub const CONSTANT_GREY_RGBA: u32 = u32::from_le_bytes([200, 200, 200, 255]);

/// The colour of every point of `cloud` in `mode`.
pub fn point_colors(cloud: &PointCloud, mode: ColorMode) -> Vec<u32> {
    let points = PaletteAttributes {
        classification: &cloud.classification,
        return_number: &cloud.return_number,
    };
    match mode {
        ColorMode::Rgb => cloud.colors.clone(),
        ColorMode::Intensity => intensity_grey(&cloud.intensity)
            .unwrap_or_else(|| vec![CONSTANT_GREY_RGBA; cloud.len()]),
        ColorMode::Elevation => elevation_colors(cloud),
        ColorMode::Classification => Palette::Classification.colors(points),
        ColorMode::ReturnNumber => Palette::ReturnNumber.colors(points),
        ColorMode::Fixed(rgb) => Palette::Fixed(rgb).colors(points),
    }
}

/// The attributes the palette modes colour by, one per point.
#[derive(Debug, Clone, Copy)]
pub struct PaletteAttributes<'a> {
    pub classification: &'a [u8],
    pub return_number: &'a [u8],
}

/// The modes that colour a point by its own attributes through a fixed table, needing no
/// range of the dataset.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Palette {
    Classification,
    ReturnNumber,
    Fixed([u8; 3]),
}

impl Palette {
    pub fn colors(self, points: PaletteAttributes<'_>) -> Vec<u32> {
        match self {
            Palette::Classification => points
                .classification
                .iter()
                .map(|&c| classification_color(c))
                .collect(),
            Palette::ReturnNumber => points
                .return_number
                .iter()
                .map(|&r| return_color(r))
                .collect(),
            Palette::Fixed([r, g, b]) => vec![pack_rgba8(r, g, b); points.classification.len()],
        }
    }
}

/// Grey from intensity, stretched between robust percentiles onto `INTENSITY_GREY_MIN..=255`;
/// None when every intensity is zero (the file has none).
pub fn intensity_grey(intensity: &[u16]) -> Option<Vec<u32>> {
    if intensity.iter().all(|&i| i == 0) {
        return None;
    }
    let mut histogram = vec![0u64; usize::from(u16::MAX) + 1];
    for &i in intensity {
        histogram[usize::from(i)] += 1;
    }
    let range = IntensityRange::from_histogram(&histogram)?;
    Some(intensity.iter().map(|&i| range.grey(i)).collect())
}

/// The robust range intensity is stretched over, and the grey of a value in it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct IntensityRange {
    pub low: u16,
    pub high: u16,
}

impl IntensityRange {
    /// The low and high stretch percentiles of a full 16-bit histogram (linear time, exact);
    /// `None` when every intensity is zero (the files have none).
    pub fn from_histogram(histogram: &[u64]) -> Option<Self> {
        let count: u64 = histogram.iter().sum();
        if count == histogram.first().copied().unwrap_or(0) {
            return None;
        }
        let rank = |fraction: f64| ((count - 1) as f64 * fraction).round() as u64;
        let value_at_rank = |rank: u64| {
            let mut seen = 0;
            for (value, &n) in histogram.iter().enumerate() {
                seen += n;
                if seen > rank {
                    return value as u16;
                }
            }
            u16::MAX
        };
        Some(Self {
            low: value_at_rank(rank(LOW_PERCENTILE)),
            high: value_at_rank(rank(HIGH_PERCENTILE)),
        })
    }

    /// Grey stretched onto `INTENSITY_GREY_MIN..=255`.
    pub fn grey(&self, intensity: u16) -> u32 {
        let span = f32::from(self.high.saturating_sub(self.low).max(1));
        let grey_span = f32::from(u8::MAX - INTENSITY_GREY_MIN);
        let t = ((f32::from(intensity) - f32::from(self.low)) / span).clamp(0.0, 1.0);
        let grey = INTENSITY_GREY_MIN + (t * grey_span).round() as u8;
        pack_rgba8(grey, grey, grey)
    }
}

/// Viridis at eleven evenly spaced stops (perceptually uniform, readable by colour-blind
/// viewers, prints well in grey).
const VIRIDIS: [[u8; 3]; 11] = [
    [68, 1, 84],
    [72, 36, 117],
    [65, 68, 135],
    [53, 95, 141],
    [42, 120, 142],
    [33, 145, 140],
    [34, 168, 132],
    [68, 191, 112],
    [122, 209, 81],
    [189, 223, 38],
    [253, 231, 37],
];

/// The viridis colour at `t` in [0, 1], interpolated linearly between the stops.
pub fn viridis(t: f32) -> [u8; 3] {
    let x = t.clamp(0.0, 1.0) * (VIRIDIS.len() - 1) as f32;
    let i = (x.floor() as usize).min(VIRIDIS.len() - 2);
    let f = x - i as f32;
    let (a, b) = (VIRIDIS[i], VIRIDIS[i + 1]);
    std::array::from_fn(|c| (a[c] as f32 + (b[c] as f32 - a[c] as f32) * f).round() as u8)
}

fn elevation_colors(cloud: &PointCloud) -> Vec<u32> {
    // Heights relative to the origin: the f32 offsets keep full precision.
    let mut heights: Vec<f32> = cloud.positions.iter().map(|p| p.z).collect();
    let Some(range) = ElevationRange::of(&mut heights) else {
        return Vec::new();
    };
    cloud.positions.iter().map(|p| range.color(p.z)).collect()
}

/// The robust range of heights the viridis map spans (relative to the origin).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ElevationRange {
    pub low: f32,
    pub high: f32,
}

impl ElevationRange {
    /// The 2nd and 98th percentiles of `heights` (reordered); `None` when empty.
    pub fn of(heights: &mut [f32]) -> Option<Self> {
        if heights.is_empty() {
            return None;
        }
        let rank = |fraction: f64| ((heights.len() - 1) as f64 * fraction).round() as usize;
        let (low_rank, high_rank) = (rank(LOW_PERCENTILE), rank(HIGH_PERCENTILE));
        let low = *heights.select_nth_unstable_by(low_rank, f32::total_cmp).1;
        let high = *heights.select_nth_unstable_by(high_rank, f32::total_cmp).1;
        Some(Self { low, high })
    }

    pub fn color(&self, height: f32) -> u32 {
        let span = (self.high - self.low).max(f32::MIN_POSITIVE);
        let [r, g, b] = viridis((height - self.low) / span);
        pack_rgba8(r, g, b)
    }
}

/// The ASPRS standard classes (LAS 1.4 R15, table 17) in the colours viewers commonly use.
pub fn classification_color(class: u8) -> u32 {
    let [r, g, b] = match class {
        0 | 1 => [170, 170, 170], // never classified, unclassified
        2 => [166, 118, 61],      // ground
        3 => [144, 214, 110],     // low vegetation
        4 => [60, 170, 60],       // medium vegetation
        5 => [20, 110, 30],       // high vegetation
        6 => [220, 70, 60],       // building
        7 | 18 => [255, 0, 255],  // low / high noise
        8 => [250, 230, 100],     // model key point (reserved in 1.4)
        9 => [60, 120, 230],      // water
        10 => [140, 100, 170],    // rail
        11 => [90, 90, 90],       // road surface
        13 => [250, 200, 50],     // wire guard
        14 => [255, 170, 0],      // wire conductor
        15 => [200, 140, 255],    // transmission tower
        16 => [230, 230, 60],     // wire-structure connector
        17 => [180, 180, 220],    // bridge deck
        // User-defined and reserved classes: distinct, stable colours.
        other => {
            let h = (other as u32).wrapping_mul(2_654_435_761);
            [
                (h >> 24) as u8 | 64,
                (h >> 16) as u8 | 64,
                (h >> 8) as u8 | 64,
            ]
        }
    };
    pack_rgba8(r, g, b)
}

pub fn return_color(return_number: u8) -> u32 {
    let [r, g, b] = match return_number {
        0 | 1 => [230, 230, 230], // single or first return (0: not recorded)
        2 => [250, 170, 40],
        3 => [60, 180, 240],
        _ => [220, 60, 160],
    };
    pack_rgba8(r, g, b)
}

#[cfg(test)]
mod tests {
    use glam::DVec3;

    use super::*;

    fn ramp_cloud() -> PointCloud {
        let points: Vec<DVec3> = (0..1000)
            .map(|i| DVec3::new(500_000.0, 4_000_000.0, 100.0 + i as f64 * 0.1))
            .collect();
        let mut cloud = PointCloud::from_world_points(&points, vec![0; 1000]);
        cloud.intensity = (0..1000).map(|i| i as u16 * 60).collect();
        cloud.classification = (0..1000).map(|i| (i % 20) as u8).collect();
        cloud.return_number = (0..1000).map(|i| (i % 5) as u8).collect();
        cloud
    }

    #[test]
    fn elevation_runs_from_the_bottom_to_the_top_of_viridis_over_the_robust_range() {
        let cloud = ramp_cloud();
        let colors = point_colors(&cloud, ColorMode::Elevation);
        let [r0, g0, b0] = VIRIDIS[0];
        let [r1, g1, b1] = VIRIDIS[10];
        assert_eq!(colors[0], pack_rgba8(r0, g0, b0));
        assert_eq!(
            colors[10],
            pack_rgba8(r0, g0, b0),
            "below the 2nd percentile: clamped"
        );
        assert_eq!(colors[999], pack_rgba8(r1, g1, b1));
        assert_ne!(colors[400], colors[600]);
    }

    #[test]
    fn viridis_interpolates_between_stops() {
        assert_eq!(viridis(0.0), VIRIDIS[0]);
        assert_eq!(viridis(1.0), VIRIDIS[10]);
        assert_eq!(viridis(0.5), VIRIDIS[5]);
        assert_eq!(viridis(2.0), VIRIDIS[10], "clamped");
        let between = viridis(0.05);
        for c in 0..3 {
            let (a, b) = (
                VIRIDIS[0][c].min(VIRIDIS[1][c]),
                VIRIDIS[0][c].max(VIRIDIS[1][c]),
            );
            assert!((a..=b).contains(&between[c]));
        }
    }

    #[test]
    fn intensity_ignores_outliers_and_is_never_black() {
        let mut cloud = ramp_cloud();
        cloud.intensity[999] = u16::MAX; // one saturated return
        let colors = point_colors(&cloud, ColorMode::Intensity);
        let grey = |c: u32| c.to_le_bytes()[0];
        assert_eq!(grey(colors[0]), INTENSITY_GREY_MIN);
        assert_eq!(grey(colors[990]), 255);
        assert!(
            grey(colors[500]) > 130 && grey(colors[500]) < 170,
            "{}",
            grey(colors[500])
        );
        cloud.intensity.fill(0);
        assert!(point_colors(&cloud, ColorMode::Intensity)
            .iter()
            .all(|&c| c == CONSTANT_GREY_RGBA));
    }

    #[test]
    fn classes_returns_and_fixed_colors() {
        let cloud = ramp_cloud();
        let by_class = point_colors(&cloud, ColorMode::Classification);
        assert_eq!(by_class[2], classification_color(2));
        assert_ne!(classification_color(2), classification_color(6));
        assert_ne!(classification_color(40), classification_color(41));
        let by_return = point_colors(&cloud, ColorMode::ReturnNumber);
        assert_eq!(by_return[1], by_return[6]);
        assert_ne!(by_return[1], by_return[2]);
        let fixed = point_colors(&cloud, ColorMode::Fixed([1, 2, 3]));
        assert!(fixed.iter().all(|&c| c == pack_rgba8(1, 2, 3)));
        assert_eq!(point_colors(&cloud, ColorMode::Rgb), cloud.colors);
    }
}
