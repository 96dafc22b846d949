//! The decoded points, batch by batch, and the cloud made of them: the recentring origin,
//! the positions in f32 relative to it, and display colors (16-bit RGB, 8-bit values in
//! 16-bit fields, intensity grey, or one grey).

use glam::{DVec3, Vec3};
use las::PointData;

use crate::cloud::{bounds_of, pack_rgba8, ColorSource, PointCloud, WorldBounds, MAX_COORDINATE};
use crate::color::{intensity_grey, CONSTANT_GREY_RGBA};
use crate::lod::NodePoints;

pub(super) fn world_bounds(bounds: las::Bounds) -> WorldBounds {
    let vector = |v: las::Vector<f64>| DVec3::new(v.x, v.y, v.z);
    WorldBounds {
        min: vector(bounds.min),
        max: vector(bounds.max),
    }
}

/// The recentring origin: the centre of the header bounds when they are finite and contain the
/// first point (writers do leave stale or zeroed bounds), else the first point itself.
pub(super) fn choose_origin(header_bounds: &WorldBounds, first_batch: &PointData) -> DVec3 {
    let first_point = match (
        first_batch.x().next(),
        first_batch.y().next(),
        first_batch.z().next(),
    ) {
        (Some(x), Some(y), Some(z)) => DVec3::new(x, y, z),
        _ => return header_bounds.center(),
    };
    let usable = header_bounds.min.is_finite()
        && header_bounds.max.is_finite()
        && header_bounds.min.cmple(header_bounds.max).all();
    // Header bounds are rounded to the file's scale; allow for that and a little more.
    let slack = DVec3::splat(1e-3) + header_bounds.size().abs() * 1e-9;
    let contains_first = usable
        && (header_bounds.min - slack).cmple(first_point).all()
        && first_point.cmple(header_bounds.max + slack).all();
    if contains_first {
        header_bounds.center()
    } else {
        first_point
    }
}

/// Per-point columns accumulated batch by batch, before colors can be decided (that needs
/// the whole file: 8-bit detection and intensity percentiles are global).
#[derive(Clone)]
pub(super) struct DecodedPoints {
    positions: Vec<Vec3>,
    bounds_min: DVec3,
    bounds_max: DVec3,
    rgb: Option<Vec<[u16; 3]>>,
    intensity: Vec<u16>,
    classification: Vec<u8>,
    return_number: Vec<u8>,
}

impl DecodedPoints {
    pub fn with_capacity(points: usize, has_color: bool) -> Self {
        Self {
            positions: Vec::with_capacity(points),
            bounds_min: DVec3::splat(f64::INFINITY),
            bounds_max: DVec3::splat(f64::NEG_INFINITY),
            rgb: has_color.then(|| Vec::with_capacity(points)),
            intensity: Vec::with_capacity(points),
            classification: Vec::with_capacity(points),
            return_number: Vec::with_capacity(points),
        }
    }

    /// The decoded coordinate farthest from zero, when it lies beyond [`MAX_COORDINATE`] or
    /// is not finite (a huge scale factor or offset).
    pub fn implausible_extreme(&self) -> Option<f64> {
        if self.positions.is_empty() {
            return None;
        }
        let extreme = self
            .bounds_min
            .abs()
            .max(self.bounds_max.abs())
            .max_element();
        let plausible = extreme.is_finite() && extreme <= MAX_COORDINATE;
        (!plausible).then_some(extreme)
    }

    pub fn append(&mut self, batch: &PointData, origin: DVec3) {
        for ((x, y), z) in batch.x().zip(batch.y()).zip(batch.z()) {
            let world = DVec3::new(x, y, z);
            self.bounds_min = self.bounds_min.min(world);
            self.bounds_max = self.bounds_max.max(world);
            // Subtract in f64, round once: the f32 keeps the offset's full precision.
            self.positions.push((world - origin).as_vec3());
        }
        if let (Some(rgb), Some(batch_rgb)) = (self.rgb.as_mut(), batch.rgb()) {
            rgb.extend(batch_rgb.map(|(r, g, b)| [r, g, b]));
        }
        self.intensity.extend(batch.intensity());
        self.classification.extend(batch.classification());
        self.return_number.extend(batch.return_number());
    }

    /// Appends a stored node's points: the centres of their quantisation steps, and their raw
    /// attributes (black where the node has no RGB and the points have).
    pub fn append_node(&mut self, node: &NodePoints, origin: DVec3) {
        for world in node.world_positions() {
            self.bounds_min = self.bounds_min.min(world);
            self.bounds_max = self.bounds_max.max(world);
            self.positions.push((world - origin).as_vec3());
        }
        if let Some(rgb) = self.rgb.as_mut() {
            match &node.rgb {
                Some(node_rgb) => rgb.extend_from_slice(node_rgb),
                None => rgb.resize(rgb.len() + node.len(), [0; 3]),
            }
        }
        self.intensity.extend_from_slice(&node.intensity);
        self.classification.extend_from_slice(&node.classification);
        self.return_number.extend_from_slice(&node.return_number);
    }

    pub fn into_cloud(self, origin: DVec3) -> PointCloud {
        let has_intensity = self.intensity.iter().any(|&i| i != 0);
        let rgb = self.rgb.as_ref().and_then(|rgb| {
            let (mut min, mut max) = ([u16::MAX; 3], [0; 3]);
            for color in rgb {
                for c in 0..3 {
                    min[c] = min[c].min(color[c]);
                    max[c] = max[c].max(color[c]);
                }
            }
            ColorSource::of_rgb_range(min, max, has_intensity).map(|source| (rgb, source))
        });
        let (colors, color_source) = match rgb {
            Some((rgb, source)) => (colors_from_rgb(rgb, source), source),
            None => match intensity_grey(&self.intensity) {
                Some(colors) => (colors, ColorSource::IntensityGrey),
                None => (
                    vec![CONSTANT_GREY_RGBA; self.intensity.len()],
                    ColorSource::Constant,
                ),
            },
        };
        let bounds = if self.positions.is_empty() {
            bounds_of([])
        } else {
            WorldBounds {
                min: self.bounds_min,
                max: self.bounds_max,
            }
        };
        PointCloud {
            origin,
            positions: self.positions,
            colors,
            intensity: self.intensity,
            classification: self.classification,
            return_number: self.return_number,
            bounds,
            color_source,
        }
    }
}

/// Display colors from the RGB fields, as [`ColorSource::of_rgb`] decided to read them.
fn colors_from_rgb(rgb: &[[u16; 3]], source: ColorSource) -> Vec<u32> {
    let shift = if source == ColorSource::Rgb16 { 8 } else { 0 };
    rgb.iter()
        .map(|c| {
            let [r, g, b] = c.map(|v| (v >> shift) as u8);
            pack_rgba8(r, g, b)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use std::fs;
    use std::path::Path;

    use las::{Color, Point};

    use super::*;
    use crate::color::INTENSITY_GREY_MIN;
    use crate::ingest::test_files::*;
    use crate::ingest::{load_point_cloud, LasWriteOptions};

    /// Writes points with the given raw 16-bit colors (write_las always widens 8-bit colors)
    /// and intensities 100, 200, ...
    fn write_raw_rgb(path: &Path, rgb: &[[u16; 3]]) {
        let mut builder = las::Builder::from((1, 2));
        builder.point_format = las::point::Format::new(2).expect("format 2");
        let mut writer =
            las::Writer::from_path(path, builder.into_header().expect("header")).expect("writer");
        for (i, &[r, g, b]) in rgb.iter().enumerate() {
            let point = Point {
                x: i as f64,
                y: 2.0 * i as f64,
                z: 1.0,
                color: Some(Color::new(r, g, b)),
                intensity: 100 * (i as u16 + 1),
                ..Point::default()
            };
            writer.write_point(point).expect("write point");
        }
        writer.close().expect("close");
    }

    /// The points of [`write_raw_rgb`], written as `name` and loaded back.
    fn load_raw_rgb(name: &str, rgb: &[[u16; 3]]) -> PointCloud {
        let dir = tempfile::tempdir().expect("temp dir");
        let path = dir.path().join(name);
        write_raw_rgb(&path, rgb);
        load_point_cloud(&path).expect("load")
    }

    /// The greys of the points of [`write_raw_rgb`] loaded back, whose colors must have
    /// given way to their intensity.
    fn greys_instead_of_rgb(name: &str, rgb: &[[u16; 3]]) -> Vec<u8> {
        let cloud = load_raw_rgb(name, rgb);
        assert_eq!(cloud.color_source, ColorSource::IntensityGrey);
        let greys: Vec<u8> = cloud.colors.iter().map(|c| c.to_le_bytes()[0]).collect();
        assert!(greys[0] < greys[49], "intensity 100 to 5000 spans greys");
        greys
    }

    /// `cloud` written as `name` in a point format without color fields (0 or 1), loaded back.
    fn written_without_color(cloud: &PointCloud, point_format: u8, name: &str) -> PointCloud {
        let dir = tempfile::tempdir().expect("temp dir");
        let options = LasWriteOptions {
            point_format,
            ..LasWriteOptions::default()
        };
        let path = write(dir.path(), name, cloud, &options);
        load_point_cloud(&path).expect("load")
    }

    #[test]
    fn eight_bit_values_in_sixteen_bit_fields_are_used_as_they_are() {
        let cloud = load_raw_rgb("rgb8.las", &[[0, 128, 255], [10, 20, 30], [255, 255, 255]]);
        assert_eq!(cloud.color_source, ColorSource::Rgb8In16Bit);
        assert_eq!(
            cloud.colors,
            [
                pack_rgba8(0, 128, 255),
                pack_rgba8(10, 20, 30),
                pack_rgba8(255, 255, 255)
            ]
        );
    }

    #[test]
    fn rgb_fields_that_are_all_zero_give_way_to_intensity() {
        let greys = greys_instead_of_rgb("unfilled.las", &[[0, 0, 0]; 50]);
        assert!(greys.windows(2).all(|w| w[0] <= w[1]), "{greys:?}");
    }

    #[test]
    fn one_color_for_every_point_gives_way_to_intensity() {
        greys_instead_of_rgb("placeholder.las", &[[65_535, 65_535, 65_535]; 50]);
        // Without intensity the one color is all there is, and it is drawn.
        assert_eq!(
            ColorSource::of_rgb_range([200; 3], [200; 3], false),
            Some(ColorSource::Rgb8In16Bit)
        );
        assert_eq!(ColorSource::of_rgb_range([0; 3], [0; 3], false), None);
        assert_eq!(
            ColorSource::of_rgb_range([0, 0, 0], [0, 0, 300], true),
            Some(ColorSource::Rgb16)
        );
    }

    #[test]
    fn sixteen_bit_colors_keep_their_high_byte() {
        // One channel above 255 makes the whole file 16-bit, dark points included.
        let cloud = load_raw_rgb("rgb16.las", &[[65_535, 32_768, 256], [255, 100, 0]]);
        assert_eq!(cloud.color_source, ColorSource::Rgb16);
        assert_eq!(cloud.colors, [pack_rgba8(255, 128, 1), pack_rgba8(0, 0, 0)]);
    }

    #[test]
    fn intensity_without_color_becomes_a_stretched_grey_that_is_never_black() {
        let mut cloud = test_cloud(1_000);
        // Mostly 100..1100, plus outliers the percentile stretch must ignore.
        cloud.intensity = (0..1_000).map(|i| 100 + i as u16).collect();
        cloud.intensity[0] = 0;
        cloud.intensity[1] = 65_535;
        let loaded = written_without_color(&cloud, 1, "intensity.las");

        assert_eq!(loaded.color_source, ColorSource::IntensityGrey);
        assert_eq!(loaded.intensity, cloud.intensity, "raw intensity is kept");
        let greys: Vec<u8> = loaded
            .colors
            .iter()
            .map(|color| {
                let [r, g, b, a] = color.to_le_bytes();
                assert!(
                    r == g && g == b && a == 255,
                    "not an opaque grey: {color:#x}"
                );
                r
            })
            .collect();
        assert_eq!(
            greys[0], INTENSITY_GREY_MIN,
            "darkest return is dim, not black"
        );
        assert_eq!(greys[1], 255);
        assert!(greys.iter().all(|&grey| grey >= INTENSITY_GREY_MIN));
        // The stretch spans the bulk of the data: the middle return is mid-grey.
        assert!(
            (130..=165).contains(&greys[500]),
            "middle grey {}",
            greys[500]
        );
        assert!(
            greys[2..].windows(2).all(|pair| pair[0] <= pair[1]),
            "monotonic in intensity"
        );
    }

    #[test]
    fn no_color_and_no_intensity_gives_one_light_grey() {
        let mut cloud = test_cloud(100);
        cloud.intensity = vec![0; 100];
        let loaded = written_without_color(&cloud, 0, "plain.laz");
        assert_eq!(loaded.color_source, ColorSource::Constant);
        let grey = CONSTANT_GREY_RGBA;
        assert!(loaded.colors.iter().all(|&color| color == grey));
    }

    #[test]
    fn origin_falls_back_to_the_first_point_when_header_bounds_are_wrong() {
        let dir = tempfile::tempdir().expect("temp dir");
        let cloud = test_cloud(50);
        let path = write_default(dir.path(), "stale_bounds.las", &cloud);
        let mut bytes = fs::read(&path).expect("read back");
        // Header bounds (max x, min x, max y, min y, max z, min z) at 179: zero them all.
        bytes[179..227].fill(0);
        fs::write(&path, &bytes).expect("patch");
        let loaded = load_point_cloud(&path).expect("load");
        let first_point = world_positions(&cloud).next().expect("a point");
        assert!(
            (loaded.origin - first_point).abs().max_element() < 1e-4,
            "{}",
            loaded.origin
        );
        assert!(max_position_error(&loaded, &cloud) < 1e-4);
    }
}
