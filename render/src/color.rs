//! Color modes: what color each point is drawn in.
//!
//! The renderer draws `PointCloud::colors`; a color mode fills that vector from the cloud's
//! attributes before upload. Elevation and intensity go through a [`ColorRamp`] over a range:
//! a fixed [`ColorRange`] when the request gives one (the same color for the same value in
//! every tile and frame), otherwise a robust range (2nd to 98th percentile) of the data drawn,
//! so a few outliers (birds, multipath returns, saturated intensities) do not flatten the
//! scale.

use serde::{Deserialize, Serialize};

use crate::cloud::{pack_rgba8, PointCloud};

/// What the points are colored by.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub enum ColorMode {
    /// The file's RGB (or, without RGB, intensity grey: the color chosen at ingest).
    #[default]
    Rgb,
    /// Intensity through a ramp (grey by default), over a fixed or a robust range.
    Intensity,
    /// Height (world Z) through a ramp (viridis by default), over a fixed or a robust range.
    Elevation,
    /// The ASPRS classification palette.
    Classification,
    /// Return number: first, second, third, fourth and later.
    ReturnNumber,
    /// One color for every point.
    Fixed([u8; 3]),
}

impl ColorMode {
    /// The mode as the command line names it.
    pub fn name(self) -> &'static str {
        match self {
            ColorMode::Rgb => "rgb",
            ColorMode::Intensity => "intensity",
            ColorMode::Elevation => "elevation",
            ColorMode::Classification => "classification",
            ColorMode::ReturnNumber => "return",
            ColorMode::Fixed(_) => "fixed",
        }
    }

    /// Whether the mode colors a value through a ramp over a range (elevation, intensity).
    pub fn is_ramped(self) -> bool {
        matches!(self, ColorMode::Elevation | ColorMode::Intensity)
    }

    /// The ramp the mode uses when the request names none.
    pub fn default_ramp(self) -> ColorRamp {
        match self {
            ColorMode::Intensity => ColorRamp::Grey,
            _ => ColorRamp::Viridis,
        }
    }
}

/// The values a ramp spans, in the mode's units: world Z in the file's units for elevation,
/// raw values for intensity. Values outside take the ramp's end colors.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ColorRange {
    pub min: f64,
    pub max: f64,
}

/// How points are colored: the mode and, for elevation and intensity, the range and ramp
/// the request chose (`None`: the robust range of the data, the mode's default ramp).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Coloring {
    pub mode: ColorMode,
    pub range: Option<ColorRange>,
    pub ramp: Option<ColorRamp>,
}

impl Coloring {
    /// Coloring by `mode` with the robust range and the mode's default ramp.
    pub fn of_mode(mode: ColorMode) -> Self {
        Self {
            mode,
            ..Self::default()
        }
    }

    /// The ramp elevation or intensity is drawn through.
    pub fn ramp(&self) -> ColorRamp {
        self.ramp.unwrap_or(self.mode.default_ramp())
    }

    /// The stretch of elevation: the fixed range made relative to `origin_z`, else `robust`.
    pub fn elevation_stretch(
        &self,
        origin_z: f64,
        robust: impl FnOnce() -> Option<Stretch>,
    ) -> Option<Stretch> {
        match self.range {
            Some(ColorRange { min, max }) => Some(Stretch {
                low: (min - origin_z) as f32,
                high: (max - origin_z) as f32,
            }),
            None => robust(),
        }
    }

    /// The stretch of intensity when the data has any (`robust` is `None` when every
    /// intensity is zero: then there is nothing to color by, whatever the range).
    pub fn intensity_stretch(&self, robust: Option<Stretch>) -> Option<Stretch> {
        let robust = robust?;
        Some(
            self.range
                .map_or(robust, |ColorRange { min, max }| Stretch {
                    low: min as f32,
                    high: max as f32,
                }),
        )
    }
}

impl From<ColorMode> for Coloring {
    fn from(mode: ColorMode) -> Self {
        Self::of_mode(mode)
    }
}

/// Lower and upper percentile of every robust range.
const LOW_PERCENTILE: f64 = 0.02;
const HIGH_PERCENTILE: f64 = 0.98;
/// Darkest grey of the grey ramp (intensity's default): weak returns stay visible against a
/// dark background.
pub const INTENSITY_GREY_MIN: u8 = 40;
/// Color of every point when there is nothing to color it by.
pub const CONSTANT_GREY_RGBA: u32 = u32::from_le_bytes([200, 200, 200, 255]);

/// The color of every point of `cloud` as `coloring` says.
pub fn point_colors(cloud: &PointCloud, coloring: Coloring) -> Vec<u32> {
    let points = PaletteAttributes {
        classification: &cloud.classification,
        return_number: &cloud.return_number,
    };
    let ramp = coloring.ramp();
    match coloring.mode {
        ColorMode::Rgb => cloud.colors.clone(),
        ColorMode::Intensity => match resident_stretch(cloud, coloring) {
            Some(stretch) => ramp.packed_all(stretch, cloud.intensity.iter().map(|&i| i.into())),
            None => vec![CONSTANT_GREY_RGBA; cloud.len()],
        },
        ColorMode::Elevation => match resident_stretch(cloud, coloring) {
            Some(stretch) => ramp.packed_all(stretch, cloud.positions.iter().map(|p| p.z)),
            None => Vec::new(),
        },
        ColorMode::Classification => Palette::Classification.colors(points),
        ColorMode::ReturnNumber => Palette::ReturnNumber.colors(points),
        ColorMode::Fixed(rgb) => Palette::Fixed(rgb).colors(points),
    }
}

/// The range elevation or intensity of `cloud` is drawn over, in the mode's units (world Z,
/// raw intensity); `None` for the other modes or with nothing to color by.
pub fn ramp_range(cloud: &PointCloud, coloring: Coloring) -> Option<ColorRange> {
    let stretch = resident_stretch(cloud, coloring)?;
    let origin_z = match coloring.mode {
        ColorMode::Elevation => cloud.origin.z,
        _ => 0.0,
    };
    Some(coloring.range.unwrap_or(stretch.in_units(origin_z)))
}

/// The stretch of a ramped mode over `cloud` (heights relative to its origin).
fn resident_stretch(cloud: &PointCloud, coloring: Coloring) -> Option<Stretch> {
    match coloring.mode {
        ColorMode::Intensity => {
            coloring.intensity_stretch(intensity_histogram_stretch(&cloud.intensity))
        }
        ColorMode::Elevation => coloring.elevation_stretch(cloud.origin.z, || {
            let mut heights: Vec<f32> = cloud.positions.iter().map(|p| p.z).collect();
            Stretch::percentiles(&mut heights)
        }),
        _ => None,
    }
}

/// The robust stretch of `intensity`; `None` when every intensity is zero (the file has none).
fn intensity_histogram_stretch(intensity: &[u16]) -> Option<Stretch> {
    if intensity.iter().all(|&i| i == 0) {
        return None;
    }
    let mut histogram = vec![0u64; usize::from(u16::MAX) + 1];
    for &i in intensity {
        histogram[usize::from(i)] += 1;
    }
    Stretch::intensity_percentiles(&histogram)
}

/// The attributes the palette modes color by, one per point.
#[derive(Debug, Clone, Copy)]
pub struct PaletteAttributes<'a> {
    pub classification: &'a [u8],
    pub return_number: &'a [u8],
}

/// The modes that color a point by its own attributes through a fixed table, needing no
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

/// Grey from intensity over its robust range (the grey ramp, from `INTENSITY_GREY_MIN` to
/// 255); None when every intensity is zero (the file has none).
pub fn intensity_grey(intensity: &[u16]) -> Option<Vec<u32>> {
    let stretch = intensity_histogram_stretch(intensity)?;
    Some(
        intensity
            .iter()
            .map(|&i| ColorRamp::Grey.packed(stretch.t(f32::from(i))))
            .collect(),
    )
}

/// The values mapped onto a ramp: `low` to its first color, `high` to its last (heights
/// relative to the rendering origin, raw intensities).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Stretch {
    pub low: f32,
    pub high: f32,
}

impl Stretch {
    /// The low and high stretch percentiles of a full 16-bit intensity histogram (linear time,
    /// exact); `None` when every intensity is zero (the files have none).
    pub fn intensity_percentiles(histogram: &[u64]) -> Option<Self> {
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
                    return value as f32;
                }
            }
            f32::from(u16::MAX)
        };
        Some(Self {
            low: value_at_rank(rank(LOW_PERCENTILE)),
            high: value_at_rank(rank(HIGH_PERCENTILE)),
        })
    }

    /// The 2nd and 98th percentiles of `values` (reordered); `None` when empty.
    pub fn percentiles(values: &mut [f32]) -> Option<Self> {
        if values.is_empty() {
            return None;
        }
        let rank = |fraction: f64| ((values.len() - 1) as f64 * fraction).round() as usize;
        let (low_rank, high_rank) = (rank(LOW_PERCENTILE), rank(HIGH_PERCENTILE));
        let low = *values.select_nth_unstable_by(low_rank, f32::total_cmp).1;
        let high = *values.select_nth_unstable_by(high_rank, f32::total_cmp).1;
        Some(Self { low, high })
    }

    /// Where `value` lies on the ramp, in [0, 1].
    pub fn t(&self, value: f32) -> f32 {
        let span = (self.high - self.low).max(f32::MIN_POSITIVE);
        ((value - self.low) / span).clamp(0.0, 1.0)
    }

    /// The range in the mode's units, the stretch's values being relative to `origin`.
    pub fn in_units(&self, origin: f64) -> ColorRange {
        ColorRange {
            min: origin + f64::from(self.low),
            max: origin + f64::from(self.high),
        }
    }
}

/// A color map of elevation or intensity.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum ColorRamp {
    /// Perceptually uniform, readable by color-blind viewers, prints well in grey.
    Viridis,
    /// Perceptually uniform, black through red to pale yellow.
    Inferno,
    /// Google's improved rainbow map: the most distinct hues.
    Turbo,
    /// Grey from `INTENSITY_GREY_MIN` to white.
    Grey,
}

impl ColorRamp {
    pub const ALL: [ColorRamp; 4] = [Self::Viridis, Self::Inferno, Self::Turbo, Self::Grey];

    pub fn name(self) -> &'static str {
        match self {
            Self::Viridis => "viridis",
            Self::Inferno => "inferno",
            Self::Turbo => "turbo",
            Self::Grey => "grey",
        }
    }

    /// The ramp named `name` (`gray` too), ignoring case.
    pub fn from_name(name: &str) -> Option<Self> {
        match name.to_ascii_lowercase().as_str() {
            "gray" => Some(Self::Grey),
            lower => Self::ALL.into_iter().find(|r| r.name() == lower),
        }
    }

    /// The color at `t` in [0, 1] (clamped).
    pub fn color(self, t: f32) -> [u8; 3] {
        let t = t.clamp(0.0, 1.0);
        match self {
            Self::Viridis => table(&VIRIDIS, t),
            Self::Inferno => table(&INFERNO, t),
            Self::Turbo => turbo(t),
            Self::Grey => {
                let span = f32::from(u8::MAX - INTENSITY_GREY_MIN);
                [INTENSITY_GREY_MIN + (t * span).round() as u8; 3]
            }
        }
    }

    /// [`ColorRamp::color`] packed as RGBA8.
    pub fn packed(self, t: f32) -> u32 {
        let [r, g, b] = self.color(t);
        pack_rgba8(r, g, b)
    }

    /// The packed color of each of `values` (heights, intensities) placed by `stretch`.
    pub fn packed_all(self, stretch: Stretch, values: impl Iterator<Item = f32>) -> Vec<u32> {
        values.map(|v| self.packed(stretch.t(v))).collect()
    }
}

/// Viridis at eleven evenly spaced stops.
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

/// Inferno at ten evenly spaced stops.
const INFERNO: [[u8; 3]; 10] = [
    [0, 0, 4],
    [27, 12, 66],
    [75, 12, 107],
    [120, 28, 109],
    [165, 44, 96],
    [207, 68, 70],
    [237, 105, 37],
    [251, 154, 6],
    [247, 209, 61],
    [252, 255, 164],
];

/// The color at `t` in [0, 1] of evenly spaced `stops`, interpolated linearly.
fn table(stops: &[[u8; 3]], t: f32) -> [u8; 3] {
    let x = t * (stops.len() - 1) as f32;
    let i = (x.floor() as usize).min(stops.len() - 2);
    let f = x - i as f32;
    let (a, b) = (stops[i], stops[i + 1]);
    std::array::from_fn(|c| (a[c] as f32 + (b[c] as f32 - a[c] as f32) * f).round() as u8)
}

/// Turbo (Mikhailov, Google, 2019) by its published polynomial approximation (Ruofei Du).
fn turbo(t: f32) -> [u8; 3] {
    const RED: [f64; 6] = [
        0.135_721_38,
        4.615_392_6,
        -42.660_322_58,
        132.131_082_34,
        -152.942_393_96,
        59.286_379_43,
    ];
    const GREEN: [f64; 6] = [
        0.091_402_61,
        2.194_188_39,
        4.842_966_58,
        -14.185_033_33,
        4.277_298_57,
        2.829_566_04,
    ];
    const BLUE: [f64; 6] = [
        0.106_673_3,
        12.641_946_08,
        -60.582_048_36,
        110.362_767_71,
        -89.903_109_12,
        27.348_249_73,
    ];
    let t = f64::from(t);
    let channel = |k: &[f64; 6]| {
        let v = k.iter().rev().fold(0.0, |acc, &c| acc * t + c);
        (v.clamp(0.0, 1.0) * 255.0).round() as u8
    };
    [channel(&RED), channel(&GREEN), channel(&BLUE)]
}

/// The ASPRS standard classes (LAS 1.4 R15, table 17) in the colors viewers commonly use.
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
        // User-defined and reserved classes: distinct, stable colors.
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

/// The ASPRS standard classes (LAS 1.4 R15, table 17) a legend names, with their names.
pub const NAMED_CLASSES: [(u8, &str); 16] = [
    (1, "unclassified"),
    (2, "ground"),
    (3, "low vegetation"),
    (4, "medium vegetation"),
    (5, "high vegetation"),
    (6, "building"),
    (7, "low noise"),
    (9, "water"),
    (10, "rail"),
    (11, "road surface"),
    (13, "wire guard"),
    (14, "wire conductor"),
    (15, "transmission tower"),
    (16, "wire-structure connector"),
    (17, "bridge deck"),
    (18, "high noise"),
];

/// The return numbers [`return_color`] tells apart, with their names.
pub const NAMED_RETURNS: [(u8, &str); 4] = [
    (1, "first or single"),
    (2, "second"),
    (3, "third"),
    (4, "fourth and later"),
];

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

    fn colors(cloud: &PointCloud, mode: ColorMode) -> Vec<u32> {
        point_colors(cloud, Coloring::of_mode(mode))
    }

    /// `mode` over the request's range `min..max` through `ramp`.
    fn fixed_range(mode: ColorMode, min: f64, max: f64, ramp: ColorRamp) -> Coloring {
        Coloring {
            mode,
            range: Some(ColorRange { min, max }),
            ramp: Some(ramp),
        }
    }

    fn packed([r, g, b]: [u8; 3]) -> u32 {
        pack_rgba8(r, g, b)
    }

    #[test]
    fn elevation_runs_from_the_bottom_to_the_top_of_viridis_over_the_robust_range() {
        let cloud = ramp_cloud();
        let colors = colors(&cloud, ColorMode::Elevation);
        assert_eq!(colors[0], packed(VIRIDIS[0]));
        assert_eq!(
            colors[10],
            packed(VIRIDIS[0]),
            "below the 2nd percentile: clamped"
        );
        assert_eq!(colors[999], packed(VIRIDIS[10]));
        assert_ne!(colors[400], colors[600]);
    }

    #[test]
    fn a_fixed_elevation_range_is_in_world_z_whatever_the_origin() {
        let cloud = ramp_cloud();
        let coloring = fixed_range(ColorMode::Elevation, 100.0, 200.0, ColorRamp::Turbo);
        let colors = point_colors(&cloud, coloring);
        // Heights 100 to 199.9: from the bottom of the ramp to just below its middle.
        assert_eq!(colors[0], ColorRamp::Turbo.packed(0.0));
        assert_eq!(colors[500], ColorRamp::Turbo.packed(0.5));
        // The same heights in a cloud with another origin get the same colors.
        let mut shifted = ramp_cloud();
        shifted.origin.z -= 1000.0;
        for p in &mut shifted.positions {
            p.z += 1000.0;
        }
        let shifted_colors = point_colors(&shifted, coloring);
        for i in [0, 250, 500, 999] {
            assert_eq!(shifted_colors[i], colors[i], "point {i}");
        }
        assert_eq!(ramp_range(&cloud, coloring), coloring.range);
        let robust = ramp_range(&cloud, Coloring::of_mode(ColorMode::Elevation)).expect("a range");
        assert!((robust.min - 102.0).abs() < 0.01 && (robust.max - 197.9).abs() < 0.01);
    }

    #[test]
    fn ramps_run_between_their_documented_endpoints() {
        assert_eq!(ColorRamp::Viridis.color(0.0), [68, 1, 84]);
        assert_eq!(ColorRamp::Viridis.color(1.0), [253, 231, 37]);
        assert_eq!(ColorRamp::Inferno.color(0.0), [0, 0, 4]);
        assert_eq!(ColorRamp::Inferno.color(1.0), [252, 255, 164]);
        // Turbo's polynomial: near black, light green in the middle, dark red.
        assert_eq!(ColorRamp::Turbo.color(0.0), [35, 23, 27]);
        assert_eq!(ColorRamp::Turbo.color(0.5), [150, 250, 80]);
        assert_eq!(ColorRamp::Turbo.color(1.0), [144, 13, 0]);
        assert_eq!(ColorRamp::Grey.color(0.0), [INTENSITY_GREY_MIN; 3]);
        assert_eq!(ColorRamp::Grey.color(1.0), [255; 3]);
        for ramp in ColorRamp::ALL {
            assert_eq!(ramp.color(-1.0), ramp.color(0.0), "{ramp:?} clamped");
            assert_eq!(ramp.color(2.0), ramp.color(1.0), "{ramp:?} clamped");
            assert_eq!(ColorRamp::from_name(ramp.name()), Some(ramp));
        }
        assert_eq!(ColorRamp::from_name("GRAY"), Some(ColorRamp::Grey));
        assert_eq!(ColorRamp::from_name("jet"), None);
    }

    #[test]
    fn tables_interpolate_between_stops() {
        assert_eq!(table(&VIRIDIS, 0.5), VIRIDIS[5]);
        let between = table(&VIRIDIS, 0.05);
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
        let colors = colors(&cloud, ColorMode::Intensity);
        let grey = |c: u32| c.to_le_bytes()[0];
        assert_eq!(grey(colors[0]), INTENSITY_GREY_MIN);
        assert_eq!(grey(colors[990]), 255);
        assert!(
            grey(colors[500]) > 130 && grey(colors[500]) < 170,
            "{}",
            grey(colors[500])
        );
        cloud.intensity.fill(0);
        assert!(
            point_colors(&cloud, Coloring::of_mode(ColorMode::Intensity))
                .iter()
                .all(|&c| c == CONSTANT_GREY_RGBA)
        );
    }

    #[test]
    fn a_fixed_intensity_range_and_ramp() {
        let cloud = ramp_cloud();
        let coloring = fixed_range(ColorMode::Intensity, 0.0, 6000.0, ColorRamp::Inferno);
        let colors = point_colors(&cloud, coloring);
        assert_eq!(colors[0], packed(INFERNO[0]));
        assert_eq!(colors[50], ColorRamp::Inferno.packed(0.5));
        assert_eq!(colors[100], packed(INFERNO[9]));
        assert_eq!(colors[999], packed(INFERNO[9]), "above the range: clamped");
        assert_eq!(ramp_range(&cloud, coloring), coloring.range);
    }

    #[test]
    fn classes_returns_and_fixed_colors() {
        let cloud = ramp_cloud();
        let by_class = colors(&cloud, ColorMode::Classification);
        assert_eq!(by_class[2], classification_color(2));
        assert_ne!(classification_color(2), classification_color(6));
        assert_ne!(classification_color(40), classification_color(41));
        let by_return = colors(&cloud, ColorMode::ReturnNumber);
        assert_eq!(by_return[1], by_return[6]);
        assert_ne!(by_return[1], by_return[2]);
        let fixed = colors(&cloud, ColorMode::Fixed([1, 2, 3]));
        assert!(fixed.iter().all(|&c| c == pack_rgba8(1, 2, 3)));
        assert_eq!(colors(&cloud, ColorMode::Rgb), cloud.colors);
    }
}
