//! Reading checked files: the `las` reader (LAZ decoded on all cores, old unchunked LAZ
//! sequentially) filled batch by batch into the point columns (`columns.rs`), inside the
//! panic containment of `contain.rs`; the files of a dataset into one cloud.

use std::io::{BufReader, Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

use glam::DVec3;
use las::{PointDataBuilder, Reader, Transform, Vector};
use laz::laszip::ChunkTable;

use super::columns::{choose_origin, world_bounds, DecodedPoints};
use super::contain::contain_panics;
use super::files::{open_dataset_file, Symlinks};
use super::header::HeaderFacts;
use super::laz_layout::LazLayout;
use super::preparse::{check_file, CheckedFile};
use super::IngestError;
use crate::cloud::{PointCloud, WorldBounds};
use crate::remote::RemoteObject;

/// Points decoded per batch at most. Bounds the scratch buffer, and for LAZ spans ~20 chunks
/// of the usual 50,000 points, enough for the parallel decompressor to keep every core busy.
const POINTS_PER_BATCH: u64 = 1 << 20;
/// Bytes of decoded records per batch at most, for records made long by extra bytes.
const BYTES_PER_BATCH: u64 = 64 << 20;

/// Loads a LAS or LAZ file (LAS 1.0–1.4, point formats 0–10) into a recentred cloud.
///
/// Coordinates are decoded in f64 and recentred on an origin fixed before the points are read
/// (the centre of the header bounds, or the first point if those are unusable), so the f32
/// positions keep the file's precision. See [`ColorSource`] for how display colors are chosen.
///
/// [`ColorSource`]: crate::cloud::ColorSource
pub fn load_point_cloud(path: &Path) -> Result<PointCloud, IngestError> {
    load_dataset(&[path.to_path_buf()])
}

/// Loads the files of one dataset (tiles or scan positions of a campaign) into one cloud, as
/// if they were one file: one origin (the centre of the union of their header bounds, or the
/// first point), one set of bounds and one color decision over every point. Files may differ
/// in version, point format, scale and offset. RGB is used only when every file has it. A
/// file that cannot be read fails the whole load with that file named.
pub fn load_dataset(paths: &[PathBuf]) -> Result<PointCloud, IngestError> {
    let started = Instant::now();
    let (files, header_bounds, has_color) = checked_dataset(paths)?;
    let capacity = files
        .iter()
        .map(|file| file.facts.capacity_hint(file.file_len))
        .fold(0usize, usize::saturating_add);
    let mut decoded = DecodedPoints::with_capacity(capacity, has_color);
    let mut origin = None;
    for file in &files {
        contain_panics(&file.path, || {
            file.decode_into(&header_bounds, &mut origin, &mut decoded)
        })?;
        tracing::info!(
            file = %file.path.display(),
            points = file.facts.declared_points,
            version = %format_args!("{}.{}", file.facts.version.0, file.facts.version.1),
            point_format = file.facts.point_format,
            compressed = file.facts.compressed,
            "read"
        );
    }
    let cloud = decoded.into_cloud(origin.unwrap_or(DVec3::ZERO));
    tracing::info!(
        files = files.len(),
        points = cloud.len(),
        color_source = ?cloud.color_source,
        elapsed_ms = started.elapsed().as_secs_f64() * 1e3,
        "loaded point cloud"
    );
    Ok(cloud)
}

/// Every file of a dataset checked, with what a load decides from their headers before it
/// reads a point: the bounds its origin is chosen against, and whether it keeps RGB (only
/// when every file has it). A sample of the dataset decides both alike.
pub(super) fn checked_dataset(
    paths: &[PathBuf],
) -> Result<(Vec<DatasetFile>, WorldBounds, bool), IngestError> {
    let files = DatasetFile::check_all(paths)?;
    require_points(&files)?;
    let header_bounds = dataset_header_bounds(&files);
    let has_color = deciding_files(&files).iter().all(|file| file.has_color);
    Ok((files, header_bounds, has_color))
}

/// What decides for a dataset among `items`, one of each of its files, given the points each
/// file declares: those of the files that declare points. A file without any (an empty tile
/// of a campaign) is read like the others and decides nothing (bounds, origin, color,
/// attributes, grid, an export's scale, offset and CRS); where no file declares a point, all
/// of them decide.
pub fn deciding<T>(items: &[T], points: impl Fn(&T) -> u64) -> Vec<&T> {
    let with_points: Vec<&T> = items.iter().filter(|item| points(item) > 0).collect();
    match with_points.is_empty() {
        true => items.iter().collect(),
        false => with_points,
    }
}

/// The files whose headers decide what their dataset is ([`deciding`]).
pub(super) fn deciding_files(files: &[DatasetFile]) -> Vec<&DatasetFile> {
    deciding(files, |file| file.facts.declared_points)
}

/// An error unless one of the files declares a point: a dataset of empty files has nothing
/// to frame or render.
pub(super) fn require_points(files: &[DatasetFile]) -> Result<(), IngestError> {
    match files {
        _ if files.iter().any(DatasetFile::has_points) => Ok(()),
        [only] => Err(IngestError::NoPoints {
            path: only.path.clone(),
        }),
        _ => Err(IngestError::NoPointsInFiles { files: files.len() }),
    }
}

/// The union of the deciding files' usable header bounds (the first one's when none is),
/// which the dataset's origin is chosen against.
pub(super) fn dataset_header_bounds(files: &[DatasetFile]) -> WorldBounds {
    let deciding = deciding_files(files);
    deciding
        .iter()
        .map(|file| file.header_bounds)
        .filter(usable)
        .reduce(|a, b| WorldBounds {
            min: a.min.min(b.min),
            max: a.max.max(b.max),
        })
        .unwrap_or(deciding[0].header_bounds)
}

/// What a store of a dataset's files frames: the union of the deciding files' header bounds,
/// widened by what rounding them to the files' scales may hide; a deciding file whose header
/// bounds are not finite or inverted cannot be framed. Files without points lie nowhere.
pub(super) fn dataset_bounds(files: &[DatasetFile]) -> Result<WorldBounds, IngestError> {
    let deciding = deciding_files(files);
    let Some(first) = deciding.first() else {
        return Err(IngestError::NoFiles);
    };
    if !first.has_points() {
        // An empty source lies nowhere, wherever its headers put it.
        return Ok(WorldBounds::NOWHERE);
    }
    if let Some(file) = deciding.iter().find(|file| !usable(&file.header_bounds)) {
        return Err(IngestError::Corrupt {
            path: file.path.clone(),
            what: "its header bounds are not finite or inverted".into(),
        });
    }
    let union = dataset_header_bounds(files);
    // Header bounds are rounded to the files' scales; allow for that and a little more.
    let slack = DVec3::splat(1e-3) + union.size().abs() * 1e-9;
    Ok(WorldBounds {
        min: union.min - slack,
        max: union.max + slack,
    })
}

/// Header bounds worth taking into the union: finite and not inverted.
pub(super) fn usable(bounds: &WorldBounds) -> bool {
    bounds.min.is_finite() && bounds.max.is_finite() && bounds.min.cmple(bounds.max).all()
}

/// The points a dataset's files declare, each file checked as a load checks it: what a caller
/// reads to choose how to render a dataset before it reads a point. An error where none of
/// them declares a point, as a load's.
pub fn dataset_point_count(paths: &[PathBuf]) -> Result<u64, IngestError> {
    let files = DatasetFile::check_all(paths)?;
    require_points(&files)?;
    Ok(files.iter().map(|file| file.facts.declared_points).sum())
}

/// A file of a dataset that passed the pre-parse, with what its header says.
pub(super) struct DatasetFile {
    pub path: PathBuf,
    file_len: u64,
    pub facts: HeaderFacts,
    pub laz: Option<LazLayout>,
    /// The checked chunk table of chunked LAZ (empty otherwise).
    pub chunks: ChunkTable,
    pub header_bounds: WorldBounds,
    pub has_color: bool,
    /// The header's scale factors and offsets: world = scale * integer + offset per axis.
    pub scale: DVec3,
    pub offset: DVec3,
    /// Bytes of a record's point format fields, before its extra bytes.
    pub format_len: usize,
    /// The data of the file's extra bytes VLR (or EVLR), when it has one.
    pub extra_bytes_vlr: Option<Vec<u8>>,
    /// The object the file is read from by URL (`objects.rs`); `None` for a file here.
    pub object: Option<Arc<RemoteObject>>,
}

impl DatasetFile {
    /// Whether the file declares any point.
    pub(super) fn has_points(&self) -> bool {
        self.facts.declared_points > 0
    }

    /// Every file of a dataset, checked; there must be one at least.
    pub(super) fn check_all(paths: &[PathBuf]) -> Result<Vec<Self>, IngestError> {
        if paths.is_empty() {
            return Err(IngestError::NoFiles);
        }
        paths.iter().map(|path| Self::check(path)).collect()
    }

    pub(super) fn check(path: &Path) -> Result<Self, IngestError> {
        let io_error = |error| IngestError::Io {
            path: path.to_owned(),
            error,
        };
        let mut file = open_dataset_file(path, Symlinks::Follow).map_err(io_error)?;
        let file_len = file.metadata().map_err(io_error)?.len();
        let checked = check_file(path, &mut file, file_len)?;
        file.seek(SeekFrom::Start(0)).map_err(io_error)?;
        let laz = checked.laz;
        let file = BufReader::new(file);
        let header = contain_panics(path, || Ok(open_reader(path, file, laz)?.header().clone()))?;
        Ok(Self::of_header(path, file_len, checked, &header))
    }

    /// A file that passed the pre-parse, with what its header (read by the `las` crate after
    /// the pre-parse) says.
    pub(super) fn of_header(
        path: &Path,
        file_len: u64,
        checked: CheckedFile,
        header: &las::Header,
    ) -> Self {
        let CheckedFile { facts, laz, chunks } = checked;
        let t = header.transforms();
        let format = header.point_format();
        let extra_bytes_vlr = header
            .all_vlrs()
            .find(|vlr| {
                vlr.user_id == crate::extra_bytes::USER_ID
                    && vlr.record_id == crate::extra_bytes::RECORD_ID
            })
            .map(|vlr| vlr.data.clone());
        Self {
            path: path.to_owned(),
            file_len,
            facts,
            laz,
            chunks,
            header_bounds: world_bounds(header.bounds()),
            has_color: format.has_color,
            scale: DVec3::new(t.x.scale, t.y.scale, t.z.scale),
            offset: DVec3::new(t.x.offset, t.y.offset, t.z.offset),
            format_len: usize::from(format.len() - format.extra_bytes),
            extra_bytes_vlr,
            object: None,
        }
    }

    /// The file's header as the `las` crate reads it, with every VLR and EVLR (each one's
    /// extent checked by the pre-parse before it is allocated).
    pub(super) fn header(&self) -> Result<las::Header, IngestError> {
        let path = self.path.as_path();
        let file = self.open_bytes()?;
        contain_panics(path, || {
            Ok(open_reader(path, file, self.laz)?.header().clone())
        })
    }

    /// Bytes of the file when it was checked.
    pub(super) fn file_len(&self) -> u64 {
        self.file_len
    }

    /// Decodes every declared point into `decoded`, relative to `origin` (fixed by the first
    /// batch of the dataset against the dataset's `header_bounds`).
    fn decode_into(
        &self,
        header_bounds: &WorldBounds,
        origin: &mut Option<DVec3>,
        decoded: &mut DecodedPoints,
    ) -> Result<(), IngestError> {
        self.for_each_batch(|batch| {
            let origin = *origin.get_or_insert_with(|| choose_origin(header_bounds, batch));
            decoded.append(batch, origin);
            Ok(())
        })?;
        // The files before were plausible: an extreme now is this file's.
        if let Some(extreme) = decoded.implausible_extreme() {
            return Err(IngestError::ImplausibleCoordinates {
                path: self.path.clone(),
                extreme,
            });
        }
        Ok(())
    }

    /// Decodes every declared point, handing `visit` one batch at a time; an error of
    /// `visit` stops the reading and is returned.
    pub(super) fn for_each_batch(
        &self,
        mut visit: impl FnMut(&las::PointData) -> Result<(), IngestError>,
    ) -> Result<(), IngestError> {
        self.for_each_batch_into(&mut None, |batch, _| visit(batch))
    }

    /// Decodes every declared point into `records` (made for this file where it is `None`),
    /// handing `visit` each batch with this file's transforms: a reader of many files keeps
    /// one `records` for all of them, since the `las` crate sizes and zeroes a fresh one a
    /// file, a pass over every record's bytes on the reading thread. The batch's own
    /// transforms may be those of the file it was made for; its positions are read through
    /// the transforms given.
    pub(super) fn for_each_batch_into(
        &self,
        records: &mut Option<las::PointData>,
        mut visit: impl FnMut(&las::PointData, &Vector<Transform>) -> Result<(), IngestError>,
    ) -> Result<(), IngestError> {
        let path = self.path.as_path();
        let facts = &self.facts;
        let file = self.open_bytes()?;
        let mut reader = open_reader(path, file, self.laz)?;
        let malformed = |error| IngestError::Malformed {
            path: path.to_owned(),
            error,
        };
        let transforms = *reader.header().transforms();
        let records = records
            .get_or_insert_with(|| PointDataBuilder::new().for_header(reader.header()).build());
        let batch_points =
            (BYTES_PER_BATCH / u64::from(facts.record_len)).clamp(1, POINTS_PER_BATCH);
        let mut read = 0;
        while read < facts.declared_points {
            let wanted = batch_points.min(facts.declared_points - read);
            let filled = reader.fill_points(wanted, records).map_err(malformed)?;
            if filled == 0 {
                break;
            }
            visit(records, &transforms)?;
            read += filled;
        }
        // Unreachable after the checks above unless the file changes while we read it.
        if read < facts.declared_points {
            return Err(IngestError::Truncated {
                path: path.to_owned(),
                declared: facts.declared_points,
                available: read,
            });
        }
        Ok(())
    }
}

/// Opens the `las` reader: chunked LAZ with the parallel decompressor (the crate's default
/// with `laz-parallel`), old non-chunked LAZ with the sequential one.
pub(super) fn open_reader(
    path: &Path,
    bytes: impl Read + Seek + Send + Sync + 'static,
    laz: Option<LazLayout>,
) -> Result<Reader, IngestError> {
    let parallelism = match laz {
        Some(LazLayout::Unchunked) => las::LazParallelism::No,
        Some(LazLayout::Chunked) | None => las::LazParallelism::Yes,
    };
    let options = las::ReaderOptions::default().with_laz_parallelism(parallelism);
    Reader::with_options(bytes, options).map_err(|error| IngestError::Malformed {
        path: path.to_owned(),
        error,
    })
}

#[cfg(test)]
mod tests {
    use std::io;
    use std::path::PathBuf;

    use super::*;
    use crate::cloud::ColorSource;
    use crate::ingest::test_files::*;

    /// Loads a real scan, or says why the test is skipped.
    fn load_shared(name: &str) -> Option<(PathBuf, PointCloud)> {
        let Some(path) = shared_data_dir()
            .map(|dir| dir.join(name))
            .filter(|path| path.is_file())
        else {
            eprintln!("skipped: shared/data/{name} is not in this checkout");
            return None;
        };
        let started = Instant::now();
        let cloud = load_point_cloud(&path).unwrap_or_else(|e| panic!("{e}"));
        eprintln!(
            "loaded {name}: {} points in {:.1?}",
            cloud.len(),
            started.elapsed()
        );
        Some((path, cloud))
    }

    #[test]
    fn rejects_a_missing_file() {
        let dir = tempfile::tempdir().expect("temp dir");
        let path = dir.path().join("nowhere.laz");
        let error = load_error(&path);
        assert!(
            matches!(&error, IngestError::Io { error, .. } if error.kind() == io::ErrorKind::NotFound),
            "{error}"
        );
    }

    #[test]
    fn autzen_las_and_laz_load_to_the_same_points() {
        let (Some((_, las)), Some((_, laz))) = (
            load_shared("autzen_trim.las"),
            load_shared("autzen_trim.laz"),
        ) else {
            return;
        };
        assert_eq!(las.len(), 110_000);
        // The data README says 16-bit RGB, but no channel exceeds 236: 8-bit values in 16-bit
        // fields. Scaling them down by 256 would paint the whole scan black.
        assert_eq!(las.color_source, ColorSource::Rgb8In16Bit);
        assert!(las == laz, "LAS and LAZ decode differently");
        // Oregon state plane, feet.
        let center = las.bounds.center();
        assert!((center.x - 636_000.0).abs() < 5_000.0 && (center.y - 849_000.0).abs() < 5_000.0);
    }

    #[test]
    fn lone_star_loads_as_intensity_grey_around_its_utm_position() {
        let Some((_, cloud)) = load_shared("lone-star.laz") else {
            return;
        };
        assert_eq!(cloud.len(), 518_862);
        assert_eq!(cloud.color_source, ColorSource::IntensityGrey);
        assert!(
            (cloud.origin.x - 515_370.0).abs() < 100.0,
            "origin {}",
            cloud.origin
        );
        assert!(
            (cloud.origin.y - 4_918_340.0).abs() < 100.0,
            "origin {}",
            cloud.origin
        );
        let size = cloud.bounds.size();
        assert!(
            size.min_element() > 1.0 && size.max_element() < 500.0,
            "extent {size}"
        );
        assert!(
            cloud.bounds.min.cmple(cloud.origin).all()
                && cloud.origin.cmple(cloud.bounds.max).all()
        );
    }

    #[test]
    fn lone_star_positions_keep_the_file_precision() {
        let Some((path, cloud)) = load_shared("lone-star.laz") else {
            return;
        };
        let mut reader = Reader::from_path(&path).expect("las reader");
        let points = reader.read_all().expect("read all");
        let direct = points
            .x()
            .zip(points.y())
            .zip(points.z())
            .map(|((x, y), z)| DVec3::new(x, y, z));
        assert_eq!(points.len(), cloud.len());
        let max_error = world_positions(&cloud)
            .zip(direct)
            .map(|(ours, direct)| (ours - direct).abs().max_element())
            .fold(0.0, f64::max);
        eprintln!("lone-star: max |origin + position - file coordinate| = {max_error:e} m");
        // Measured: 9.5e-7 m, the f32 rounding of offsets of a few tens of metres (the file's own
        // resolution is 0.00025 m). Without recentring, f32 would be off by up to 0.25 m here.
        assert!(max_error < 1e-3, "max error {max_error} m");
    }
}
