//! What a LAS/LAZ file is, for `pointfarm info`: the facts of its header and records
//! ([`FileInfo`], without reading a point) and a summary of its points read in one stream,
//! batch by batch, never held whole ([`PointSummary`]). The file passes the same pre-parse as
//! a load, so a corrupt one is an [`IngestError`] naming it, never a panic.

use std::path::{Path, PathBuf};

use glam::DVec3;

use super::columns::world_bounds;
use super::contain::contain_panics;
use super::crs::{crs_of, Crs};
use super::preparse::ChunkChecks;
use super::ranged::{check_ranged, RangedBytes};
use super::read::DatasetFile;
use super::IngestError;
use crate::cloud::{ColorSource, WorldBounds};
use crate::extra_bytes;

/// What a file's header and records say.
pub struct FileInfo {
    pub path: PathBuf,
    pub file_bytes: u64,
    /// (major, minor).
    pub version: (u8, u8),
    pub point_format: u8,
    pub compressed: bool,
    /// Bytes of a point record (the format's fields and any extra bytes).
    pub record_len: u16,
    /// The points the header declares.
    pub points: u64,
    /// The header's points by return number (return 1 first), up to the last one it counts;
    /// empty when it counts none.
    pub points_by_return: Vec<u64>,
    pub vlrs: usize,
    pub evlrs: usize,
    /// The header's bounds.
    pub bounds: WorldBounds,
    pub scale: DVec3,
    pub offset: DVec3,
    pub crs: Crs,
    pub attributes: Attributes,
    file: DatasetFile,
}

/// The attributes a point carries besides position, intensity, returns and classification.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Attributes {
    pub gps_time: bool,
    pub rgb: bool,
    pub nir: bool,
    pub waveform: bool,
    /// Bytes a point carries beyond its format's fields.
    pub extra_bytes: u16,
    /// The names the extra bytes VLR gives them, in order.
    pub extra_names: Vec<String>,
}

impl Attributes {
    /// The attributes of point format `format`, its extra bytes named `extra_names`.
    pub fn of_format(format: &las::point::Format, extra_names: Vec<String>) -> Self {
        Self {
            gps_time: format.has_gps_time,
            rgb: format.has_color,
            nir: format.has_nir,
            waveform: format.has_waveform,
            extra_bytes: format.extra_bytes,
            extra_names,
        }
    }
}

impl FileInfo {
    /// Reads the header and records of `path` (checked as a load checks them).
    pub fn read(path: &Path) -> Result<Self, IngestError> {
        let file = DatasetFile::check(path)?;
        let header = file.header()?;
        Ok(Self::of_header(file, &header))
    }

    /// Reads the header and records of a file read by range, an object by URL (checked up to
    /// its chunk table, as a preview of it is): what [`Self::read`] says of a file here. Its
    /// points are not read through it: [`Self::read_points`] reads files here, and objects
    /// given with [`Self::streaming_from`].
    pub(crate) fn read_ranged<B: RangedBytes>(bytes: &B) -> Result<Self, B::Error> {
        let (file, header) = check_ranged(bytes, ChunkChecks::Table)?;
        Ok(Self::of_header(file, &header))
    }

    /// The same facts, whose [`Self::read_points`] streams `object` (the one they were read
    /// from, at its version) in large ranged blocks, never whole.
    pub(crate) fn streaming_from(mut self, object: crate::remote::RemoteObject) -> Self {
        self.file.object = Some(std::sync::Arc::new(object));
        self
    }

    fn of_header(file: DatasetFile, header: &las::Header) -> Self {
        let format = header.point_format();
        let transforms = header.transforms();
        let mut points_by_return: Vec<u64> = (1..=15)
            .map(|n| header.number_of_points_by_return(n).unwrap_or(0))
            .collect();
        while points_by_return.last() == Some(&0) {
            points_by_return.pop();
        }
        Self {
            path: file.path.clone(),
            file_bytes: file.file_len(),
            version: file.facts.version,
            point_format: file.facts.point_format,
            compressed: file.facts.compressed,
            record_len: file.facts.record_len,
            points: file.facts.declared_points,
            points_by_return,
            vlrs: header.vlrs().len(),
            evlrs: header.evlrs().len(),
            bounds: world_bounds(header.bounds()),
            scale: DVec3::new(transforms.x.scale, transforms.y.scale, transforms.z.scale),
            offset: DVec3::new(
                transforms.x.offset,
                transforms.y.offset,
                transforms.z.offset,
            ),
            crs: crs_of(header),
            attributes: Attributes::of_format(format, extra_byte_names(header)),
            file,
        }
    }

    /// Reads every point once, batch by batch, telling `progress` the points read so far.
    pub fn read_points(&self, mut progress: impl FnMut(u64)) -> Result<PointSummary, IngestError> {
        let mut summary = PointSummary::new(self.attributes.rgb);
        contain_panics(&self.path, || {
            self.file.for_each_batch(|batch| {
                summary.add(batch);
                progress(summary.points);
                Ok(())
            })
        })?;
        Ok(summary)
    }
}

/// The attribute names of the extra bytes VLR; a descriptor cut short is left out.
fn extra_byte_names(header: &las::Header) -> Vec<String> {
    header
        .all_vlrs()
        .find(|vlr| vlr.user_id == extra_bytes::USER_ID && vlr.record_id == extra_bytes::RECORD_ID)
        .map(|vlr| {
            extra_bytes::parse(&vlr.data)
                .into_iter()
                .map(|d| d.name)
                .collect()
        })
        .unwrap_or_default()
}

/// What the points of a file hold, gathered in one pass.
#[derive(Debug, Clone, PartialEq)]
pub struct PointSummary {
    /// Points read.
    pub points: u64,
    /// Points per classification code (all 256).
    pub classes: Vec<u64>,
    /// Points per return number (0 to 15; 0 where the writer gave none).
    pub returns: [u64; 16],
    /// The lowest and highest intensity; `None` without points.
    pub intensity: Option<[u16; 2]>,
    /// The bounds of the points themselves; `None` without points.
    pub bounds: Option<WorldBounds>,
    /// The RGB fields' range; `None` when the format has none.
    pub rgb: Option<RgbRange>,
}

/// The lowest and highest value of each RGB channel over every point.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RgbRange {
    pub min: [u16; 3],
    pub max: [u16; 3],
}

impl RgbRange {
    /// Whether the colors say anything: some channel varies (not all zero, not one color).
    pub fn varies(&self) -> bool {
        self.min != self.max
    }

    /// How the renderer reads these fields: [`ColorSource::of_rgb`], the one RGB decision.
    pub fn source(&self) -> Option<ColorSource> {
        ColorSource::of_rgb(self.max.into_iter().max().unwrap_or(0))
    }
}

impl PointSummary {
    fn new(has_rgb: bool) -> Self {
        Self {
            points: 0,
            classes: vec![0; 256],
            returns: [0; 16],
            intensity: None,
            bounds: None,
            rgb: has_rgb.then_some(RgbRange {
                min: [u16::MAX; 3],
                max: [0; 3],
            }),
        }
    }

    fn add(&mut self, batch: &las::PointData) {
        for class in batch.classification() {
            self.classes[usize::from(class)] += 1;
        }
        for number in batch.return_number() {
            self.returns[usize::from(number & 15)] += 1;
        }
        for value in batch.intensity() {
            let [low, high] = self.intensity.get_or_insert([value, value]);
            *low = (*low).min(value);
            *high = (*high).max(value);
        }
        for ((x, y), z) in batch.x().zip(batch.y()).zip(batch.z()) {
            let point = DVec3::new(x, y, z);
            let bounds = self.bounds.get_or_insert(WorldBounds {
                min: point,
                max: point,
            });
            bounds.min = bounds.min.min(point);
            bounds.max = bounds.max.max(point);
        }
        if let (Some(range), Some(rgb)) = (self.rgb.as_mut(), batch.rgb()) {
            for (r, g, b) in rgb {
                for (channel, value) in [r, g, b].into_iter().enumerate() {
                    range.min[channel] = range.min[channel].min(value);
                    range.max[channel] = range.max[channel].max(value);
                }
            }
        }
        self.points += batch.len() as u64;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ingest::test_files::*;
    use crate::ingest::LasWriteOptions;

    #[test]
    fn a_written_file_reports_its_header_and_points() {
        let dir = tempfile::tempdir().expect("temp dir");
        let mut cloud = test_cloud(1_000);
        cloud.classification = (0..1_000).map(|i| (i % 3) as u8 + 1).collect();
        cloud.return_number = (0..1_000).map(|i| (i % 2) as u8 + 1).collect();
        cloud.intensity = (0..1_000).map(|i| 10 + i as u16).collect();
        let path = write_default(dir.path(), "info.las", &cloud);

        let info = FileInfo::read(&path).expect("info");
        assert_eq!(info.points, 1_000);
        assert!(info.attributes.rgb);
        assert_eq!(info.crs, Crs::None);
        let summary = info.read_points(|_| {}).expect("points");
        assert_eq!(summary.points, 1_000);
        assert_eq!(&summary.classes[1..4], &[334, 333, 333]);
        assert_eq!(&summary.returns[1..3], &[500, 500]);
        assert_eq!(summary.intensity, Some([10, 1_009]));
        let bounds = summary.bounds.expect("bounds");
        assert!((bounds.min - cloud.bounds.min).abs().max_element() < 1e-2);
        assert!((bounds.max - cloud.bounds.max).abs().max_element() < 1e-2);

        let options = LasWriteOptions {
            point_format: 1,
            ..LasWriteOptions::default()
        };
        let path = write(dir.path(), "no_rgb.laz", &cloud, &options);
        let info = FileInfo::read(&path).expect("info");
        assert!(info.compressed && !info.attributes.rgb && info.attributes.gps_time);
        assert_eq!(info.read_points(|_| {}).expect("points").rgb, None);
    }

    #[test]
    fn a_truncated_file_is_an_error_naming_it() {
        let dir = tempfile::tempdir().expect("temp dir");
        let (path, bytes) = file_to_cut(dir.path(), "cut.las", 100);
        std::fs::write(&path, &bytes[..bytes.len() - 100]).expect("cut");
        let error = FileInfo::read(&path)
            .and_then(|info| info.read_points(|_| {}))
            .expect_err("truncated");
        assert!(error.to_string().contains("cut.las"), "{error}");
    }
}
