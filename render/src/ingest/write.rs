//! Writing clouds as LAS or LAZ (for tests, the benchmark and the generated sample scene).

use std::path::{Path, PathBuf};

use las::{point::Classification, Color, Point, PointDataBuilder};

use crate::cloud::PointCloud;

/// How [`write_las`] lays out the file.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LasWriteOptions {
    /// LAS version (major, minor).
    pub version: (u8, u8),
    /// Point format 0–10; colour is written only by formats that have RGB.
    pub point_format: u8,
    /// Coordinate scale in file units (the precision of the written coordinates).
    pub scale: f64,
}

impl Default for LasWriteOptions {
    /// LAS 1.2 with RGB (format 3) at millimetre precision: readable by nearly everything.
    fn default() -> Self {
        Self {
            version: (1, 2),
            point_format: 3,
            scale: 0.001,
        }
    }
}

/// A cloud could not be written.
#[derive(Debug, thiserror::Error)]
#[error("{}: cannot write LAS/LAZ: {error}", path.display())]
pub struct WriteLasError {
    pub path: PathBuf,
    pub error: las::Error,
}

/// Writes `cloud` in world coordinates (`origin + position`) as LAS, or LAZ when the path ends
/// in `.laz`. Colours become 16-bit by `v * 257` (so 255 maps to 65535); formats with GPS time,
/// waveforms or NIR get zeros there.
pub fn write_las(
    path: &Path,
    cloud: &PointCloud,
    options: &LasWriteOptions,
) -> Result<(), WriteLasError> {
    write_las_inner(path, cloud, options).map_err(|error| WriteLasError {
        path: path.to_owned(),
        error,
    })
}

fn write_las_inner(path: &Path, cloud: &PointCloud, options: &LasWriteOptions) -> las::Result<()> {
    let format = las::point::Format::new(options.point_format)?;
    let mut builder = las::Builder::from(options.version);
    builder.point_format = format;
    // Offset on whole units near the cloud keeps the stored integers small.
    let axis = |origin: f64| las::Transform {
        scale: options.scale,
        offset: origin.round(),
    };
    builder.transforms = las::Vector {
        x: axis(cloud.origin.x),
        y: axis(cloud.origin.y),
        z: axis(cloud.origin.z),
    };
    builder.generating_software = "pointfarm".to_owned();
    let mut writer = las::Writer::from_path(path, builder.into_header()?)?;

    let points = (0..cloud.len()).map(|i| {
        let world = cloud.origin + cloud.positions[i].as_dvec3();
        let [r, g, b, _alpha] = cloud.colors[i].to_le_bytes();
        let widen = |channel: u8| u16::from(channel) * 257;
        Ok(Point {
            x: world.x,
            y: world.y,
            z: world.z,
            intensity: cloud.intensity[i],
            return_number: cloud.return_number[i],
            number_of_returns: cloud.return_number[i],
            classification: Classification::new(cloud.classification[i])?,
            gps_time: format.has_gps_time.then_some(0.0),
            color: format
                .has_color
                .then(|| Color::new(widen(r), widen(g), widen(b))),
            waveform: format.has_waveform.then(Default::default),
            nir: format.has_nir.then_some(0),
            ..Point::default()
        })
    });
    let points = points.collect::<las::Result<Vec<_>>>()?;
    let data = PointDataBuilder::new()
        .for_header(writer.header())
        .build_from_points(points)?;
    writer.write_points(&data)?;
    writer.close()
}

#[cfg(test)]
mod tests {
    use crate::cloud::{bounds_of, ColorSource};
    use crate::ingest::test_files::*;
    use crate::ingest::{load_point_cloud, LasWriteOptions};

    /// Point formats each LAS version can hold.
    fn formats_of_version(minor: u8) -> std::ops::RangeInclusive<u8> {
        match minor {
            0 | 1 => 0..=1,
            2 => 0..=3,
            3 => 0..=5,
            _ => 0..=10,
        }
    }

    #[test]
    fn every_version_and_point_format_round_trips_as_las_and_laz() {
        let dir = tempfile::tempdir().expect("temp dir");
        let original = test_cloud(1_500);
        for minor in 0..=4 {
            for point_format in formats_of_version(minor) {
                for extension in ["las", "laz"] {
                    let options = LasWriteOptions {
                        version: (1, minor),
                        point_format,
                        scale: 0.001,
                    };
                    let name = format!("v1{minor}_f{point_format}.{extension}");
                    let path = write(dir.path(), &name, &original, &options);
                    let loaded = load_point_cloud(&path).unwrap_or_else(|e| panic!("{e}"));

                    assert_eq!(loaded.len(), original.len(), "{name}");
                    // Coordinates are on the file's grid; what remains is f32 rounding of the
                    // offsets (< 2^-19 m for offsets under 32 m).
                    let error = max_position_error(&loaded, &original);
                    assert!(error < 1e-4, "{name}: position error {error}");
                    assert_eq!(loaded.intensity, original.intensity, "{name}");
                    assert_eq!(loaded.classification, original.classification, "{name}");
                    assert_eq!(loaded.return_number, original.return_number, "{name}");
                    let has_rgb = matches!(point_format, 2 | 3 | 5 | 7 | 8 | 10);
                    if has_rgb {
                        assert_eq!(loaded.color_source, ColorSource::Rgb16, "{name}");
                        assert_eq!(loaded.colors, original.colors, "{name}");
                    } else {
                        assert_eq!(loaded.color_source, ColorSource::IntensityGrey, "{name}");
                    }
                    let expected_bounds = bounds_of(world_positions(&original));
                    assert!(
                        (loaded.bounds.min - expected_bounds.min)
                            .abs()
                            .max_element()
                            < 1e-4
                    );
                    assert!(
                        (loaded.bounds.max - expected_bounds.max)
                            .abs()
                            .max_element()
                            < 1e-4
                    );
                }
            }
        }
    }
}
