//! `NodeColoring`: the color of each point of a node, decided once for the whole dataset.
//!
//! A color mode's ranges are the dataset's, never a node's, or neighbouring nodes would not
//! match: the RGB decision (8-bit values in 16-bit fields, or 16-bit) and the intensity
//! percentiles come from the statistics of every point gathered while the store was built;
//! the elevation percentiles from the coarsest nodes, a spatially even sample of the dataset.
//! A request's fixed range replaces the percentiles, as it does for a resident cloud.

use super::{DatasetStats, NodePoints};
use crate::cloud::{pack_rgba8, ColorSource};
use crate::color::{
    ColorMode, ColorRange, Coloring, Palette, PaletteAttributes, Stretch, CONSTANT_GREY_RGBA,
};

/// What coloring needs of a dataset.
#[derive(Debug, Clone, PartialEq)]
pub struct DatasetColoring {
    /// Whether the RGB fields hold 8-bit values (no channel above 255); `None` without RGB,
    /// or with RGB that says nothing ([`ColorSource::of_rgb_range`]).
    rgb_is_8_bit: Option<bool>,
    intensity: Option<Stretch>,
    /// Heights relative to the rendering origin.
    elevation: Option<Stretch>,
    /// The rendering origin's height, which the heights are relative to.
    origin_z: f64,
}

impl DatasetColoring {
    /// From the store's statistics and the heights (relative to `origin_z`) of a sample.
    pub fn new(stats: &DatasetStats, mut sample_heights: Vec<f32>, origin_z: f64) -> Self {
        let intensity = Stretch::intensity_percentiles(&stats.intensity_histogram);
        Self {
            rgb_is_8_bit: stats
                .has_rgb
                .then(|| {
                    ColorSource::of_rgb_range(stats.min_rgb, stats.max_rgb, intensity.is_some())
                })
                .flatten()
                .map(|source| source == ColorSource::Rgb8In16Bit),
            intensity,
            elevation: Stretch::percentiles(&mut sample_heights),
            origin_z,
        }
    }

    /// From the store's statistics and an elevation stretch already taken from a sample (a
    /// daemon's, sent with the hierarchy so a worker need not read the sample again).
    pub fn with_elevation(stats: &DatasetStats, elevation: Option<Stretch>, origin_z: f64) -> Self {
        Self {
            elevation,
            ..Self::new(stats, Vec::new(), origin_z)
        }
    }

    /// The elevation stretch, relative to the origin.
    pub fn elevation(&self) -> Option<Stretch> {
        self.elevation
    }

    /// The colors of `node`'s points (RGBA8), their heights relative to the origin given.
    /// Whether `mode` colors a node from its RGB or its heights alone: what a node read
    /// coarse keeps (`codec::Detail`).
    pub fn needs_only_coarse(&self, mode: ColorMode) -> bool {
        match mode {
            ColorMode::Rgb => self.rgb_is_8_bit.is_some(),
            ColorMode::Elevation => true,
            _ => false,
        }
    }

    pub fn colors(&self, node: &NodePoints, heights: &[f32], coloring: Coloring) -> Vec<u32> {
        let n = node.len();
        let points = PaletteAttributes {
            classification: &node.classification,
            return_number: &node.return_number,
        };
        let ramp = coloring.ramp();
        match coloring.mode {
            ColorMode::Rgb => match (&node.rgb, self.rgb_is_8_bit) {
                (Some(rgb), Some(eight_bit)) => {
                    let shift = if eight_bit { 0 } else { 8 };
                    rgb.iter()
                        .map(|c| {
                            let [r, g, b] = c.map(|v| (v >> shift) as u8);
                            pack_rgba8(r, g, b)
                        })
                        .collect()
                }
                _ => self.intensity_colors(node, Coloring::of_mode(ColorMode::Intensity)),
            },
            ColorMode::Intensity => self.intensity_colors(node, coloring),
            ColorMode::Elevation => match self.elevation_stretch(coloring) {
                Some(stretch) => heights.iter().map(|&z| ramp.packed(stretch.t(z))).collect(),
                None => vec![CONSTANT_GREY_RGBA; n],
            },
            ColorMode::Classification => Palette::Classification.colors(points),
            ColorMode::ReturnNumber => Palette::ReturnNumber.colors(points),
            ColorMode::Fixed(rgb) => Palette::Fixed(rgb).colors(points),
        }
    }

    /// The range elevation or intensity is drawn over, in the mode's units (world Z, raw
    /// intensity); `None` for the other modes or with nothing to color by.
    pub fn ramp_range(&self, coloring: Coloring) -> Option<ColorRange> {
        let drawn = match coloring.mode {
            ColorMode::Elevation => self.elevation_stretch(coloring)?.in_units(self.origin_z),
            ColorMode::Intensity => coloring.intensity_stretch(self.intensity)?.in_units(0.0),
            _ => return None,
        };
        // The request's own numbers where it gave a range, not their round trip through f32.
        Some(coloring.range.unwrap_or(drawn))
    }

    fn elevation_stretch(&self, coloring: Coloring) -> Option<Stretch> {
        coloring.elevation_stretch(self.origin_z, || self.elevation)
    }

    fn intensity_colors(&self, node: &NodePoints, coloring: Coloring) -> Vec<u32> {
        let ramp = coloring.ramp();
        match coloring.intensity_stretch(self.intensity) {
            Some(stretch) => node
                .intensity
                .iter()
                .map(|&i| ramp.packed(stretch.t(f32::from(i))))
                .collect(),
            None => vec![CONSTANT_GREY_RGBA; node.len()],
        }
    }
}
