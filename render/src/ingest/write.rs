//! Writing clouds as LAS or LAZ (for tests, the benchmark and the generated sample scene).

use std::path::{Path, PathBuf};

use las::{point::Classification, Color, Point, PointDataBuilder};

use crate::cloud::PointCloud;

/// How [`write_las`] lays out the file.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LasWriteOptions {
    /// LAS version (major, minor).
    pub version: (u8, u8),
    /// Point format 0–10; color is written only by formats that have RGB.
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

/// Points encoded and written at a time: the writer's memory is about 150 B a point of a
/// block (the `las` crate's points, then their encoding), whatever the cloud's size.
const WRITE_BLOCK_POINTS: usize = 1 << 16;

/// Writes `cloud` in world coordinates (`origin + position`) as LAS, or LAZ when the path ends
/// in `.laz`. Colors become 16-bit by `v * 257` (so 255 maps to 65535); formats with GPS time,
/// waveforms or NIR get zeros there.
pub fn write_las(
    path: &Path,
    cloud: &PointCloud,
    options: &LasWriteOptions,
) -> Result<(), WriteLasError> {
    let mut writer = LasStreamWriter::create(path, cloud.origin, options)?;
    writer.write(cloud)?;
    writer.finish()
}

/// A LAS or LAZ file written cloud by cloud, holding one block of points at a time; the header's
/// counts and bounds are those of everything written, set by [`LasStreamWriter::finish`].
pub struct LasStreamWriter {
    path: PathBuf,
    format: las::point::Format,
    writer: las::Writer<std::io::BufWriter<std::fs::File>>,
}

impl LasStreamWriter {
    /// Creates `path` (LAZ when it ends in `.laz`), its coordinates offset by `near` rounded to
    /// whole units, so the stored integers stay small for points around it.
    pub fn create(
        path: &Path,
        near: glam::DVec3,
        options: &LasWriteOptions,
    ) -> Result<Self, WriteLasError> {
        let error = |error| WriteLasError {
            path: path.to_owned(),
            error,
        };
        let format = las::point::Format::new(options.point_format).map_err(error)?;
        let mut builder = las::Builder::from(options.version);
        builder.point_format = format;
        let axis = |origin: f64| las::Transform {
            scale: options.scale,
            offset: origin.round(),
        };
        builder.transforms = las::Vector {
            x: axis(near.x),
            y: axis(near.y),
            z: axis(near.z),
        };
        builder.generating_software = "pointfarm".to_owned();
        let header = builder.into_header().map_err(error)?;
        let writer = las::Writer::from_path(path, header).map_err(error)?;
        Ok(Self {
            path: path.to_owned(),
            format,
            writer,
        })
    }

    /// Appends the points of `cloud`, in world coordinates, a block at a time.
    pub fn write(&mut self, cloud: &PointCloud) -> Result<(), WriteLasError> {
        let format = self.format;
        for first in (0..cloud.len()).step_by(WRITE_BLOCK_POINTS) {
            let block = first..(first + WRITE_BLOCK_POINTS).min(cloud.len());
            let points = block.map(|i| {
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
            let written = points
                .collect::<las::Result<Vec<_>>>()
                .and_then(|points| {
                    PointDataBuilder::new()
                        .for_header(self.writer.header())
                        .build_from_points(points)
                })
                .and_then(|data| self.writer.write_points(&data));
            written.map_err(|error| self.error(error))?;
        }
        Ok(())
    }

    /// Writes the header's final counts and bounds and closes the file.
    pub fn finish(mut self) -> Result<(), WriteLasError> {
        self.writer.close().map_err(|error| self.error(error))
    }

    fn error(&self, error: las::Error) -> WriteLasError {
        WriteLasError {
            path: self.path.clone(),
            error,
        }
    }
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
