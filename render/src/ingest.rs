//! LAS/LAZ ingest: reads a file into a recentred [`PointCloud`], and writes clouds back out
//! (for tests and the generated sample scene).
//!
//! Every failure is an [`IngestError`] naming the file, never a panic. The header is checked by
//! hand before the `las` crate sees it, because the crate trusts the declared point count: it
//! sizes its read buffer from it (an inflated count means a huge allocation), in LAS 1.4 files it
//! multiplies the 64-bit count by the record length unchecked, and its parallel LAZ decoder
//! panics when asked for more points than the file's chunks hold.
//!
//! LAZ is decoded on all cores (`laz-parallel`, rayon); LAS is a plain sequential read.

use std::fs::File;
use std::io::{self, BufReader, Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};
use std::time::Instant;

use glam::{DVec3, Vec3};
use las::{point::Classification, Color, Point, PointData, PointDataBuilder, Reader};

use crate::cloud::{bounds_of, pack_rgba8, ColorSource, PointCloud, WorldBounds};
use crate::color::{intensity_grey, CONSTANT_GREY_RGBA};

/// Why a file could not be loaded. Every variant names the file, and every message is complete
/// on its own (the underlying cause is part of it), so it reads well in logs and the CLI.
#[derive(Debug, thiserror::Error)]
pub enum IngestError {
    /// Opening, reading or seeking failed (missing file, permissions, device errors).
    #[error("{}: {error}", path.display())]
    Io { path: PathBuf, error: io::Error },

    /// The file does not start with the `LASF` signature.
    #[error("{}: not a LAS/LAZ file (starts with {found:?}, expected \"LASF\")", path.display())]
    NotLas { path: PathBuf, found: String },

    /// The file ends before its header (and VLRs) do.
    #[error("{}: truncated: the file ends inside the LAS header ({file_len} bytes)", path.display())]
    TruncatedHeader { path: PathBuf, file_len: u64 },

    /// The point data holds fewer points than the header declares.
    #[error(
        "{}: truncated: header says {declared} points but data ends after {available}",
        path.display()
    )]
    Truncated {
        path: PathBuf,
        declared: u64,
        available: u64,
    },

    /// The declared count times the record length overflows 64 bits: no file holds that many.
    #[error("{}: corrupt header: it declares {declared} points", path.display())]
    ImpossiblePointCount { path: PathBuf, declared: u64 },

    /// The LAZ chunk table accounts for fewer points than the header declares. With fixed-size
    /// chunks (the usual case) the last chunk's count is not recorded, so this is an upper bound.
    #[error(
        "{}: truncated: header says {declared} points but the LAZ chunks hold at most {chunk_capacity}",
        path.display()
    )]
    TruncatedLaz {
        path: PathBuf,
        declared: u64,
        chunk_capacity: u64,
    },

    /// The LAZ chunk table, written after the points, is missing or unreadable: usually a file
    /// that was cut short or whose writer never finished.
    #[error("{}: truncated or unfinished LAZ: cannot read the chunk table: {error}", path.display())]
    LazChunkTable {
        path: PathBuf,
        error: laz::LasZipError,
    },

    #[error("{}: unsupported LAS version {major}.{minor} (1.0 to 1.4 are supported)", path.display())]
    UnsupportedVersion { path: PathBuf, major: u8, minor: u8 },

    #[error("{}: unsupported point format {format} (0 to 10 are supported)", path.display())]
    UnsupportedPointFormat { path: PathBuf, format: u8 },

    #[error("{}: the file contains no points", path.display())]
    NoPoints { path: PathBuf },

    /// Anything else the `las` crate rejects: malformed VLRs, corrupt LAZ chunks, ...
    #[error("{}: malformed LAS/LAZ data: {error}", path.display())]
    Malformed { path: PathBuf, error: las::Error },
}

/// Points decoded per batch. Bounds the scratch buffer, and for LAZ spans ~20 chunks of the
/// usual 50,000 points, enough for the parallel decompressor to keep every core busy.
const POINTS_PER_BATCH: u64 = 1 << 20;

/// Loads a LAS or LAZ file (LAS 1.0–1.4, point formats 0–10) into a recentred cloud.
///
/// Coordinates are decoded in f64 and recentred on an origin fixed before the points are read
/// (the centre of the header bounds, or the first point if those are unusable), so the f32
/// positions keep the file's precision. See [`ColorSource`] for how display colours are chosen.
pub fn load_point_cloud(path: &Path) -> Result<PointCloud, IngestError> {
    let started = Instant::now();
    let io_error = |error| IngestError::Io {
        path: path.to_owned(),
        error,
    };

    let mut file = File::open(path).map_err(io_error)?;
    let file_len = file.metadata().map_err(io_error)?.len();
    let facts = HeaderFacts::read(path, &mut file, file_len)?;
    if facts.compressed {
        check_laz_chunk_capacity(path, &mut file, facts.declared_points)?;
    }
    file.seek(SeekFrom::Start(0)).map_err(io_error)?;

    let mut reader = open_reader(path, file)?;
    let malformed = |error| IngestError::Malformed {
        path: path.to_owned(),
        error,
    };
    let header_bounds = world_bounds(reader.header().bounds());

    let has_color = reader.header().point_format().has_color;
    let mut decoded = DecodedPoints::with_capacity(facts.capacity_hint(file_len), has_color);
    let mut batch = PointDataBuilder::new().for_header(reader.header()).build();
    let mut origin = None;
    while decoded.len() < facts.declared_points {
        let wanted = POINTS_PER_BATCH.min(facts.declared_points - decoded.len());
        if reader.fill_points(wanted, &mut batch).map_err(malformed)? == 0 {
            break;
        }
        let origin = *origin.get_or_insert_with(|| choose_origin(&header_bounds, &batch));
        decoded.append(&batch, origin);
    }
    // Unreachable after the checks above unless the file changes while we read it.
    if decoded.len() < facts.declared_points {
        return Err(IngestError::Truncated {
            path: path.to_owned(),
            declared: facts.declared_points,
            available: decoded.len(),
        });
    }

    let cloud = decoded.into_cloud(origin.unwrap_or(DVec3::ZERO));
    tracing::info!(
        file = %path.display(),
        points = cloud.len(),
        version = %format_args!("{}.{}", facts.version.0, facts.version.1),
        point_format = facts.point_format,
        compressed = facts.compressed,
        color_source = ?cloud.color_source,
        elapsed_ms = started.elapsed().as_secs_f64() * 1e3,
        "loaded point cloud"
    );
    Ok(cloud)
}

/// Checks the declared point count against the LAZ chunk table before decoding: the parallel
/// decompressor asserts (and in release builds underflows) when asked for more points than its
/// chunks hold. Within the last fixed-size chunk the decoder's own end-of-data error applies.
fn check_laz_chunk_capacity(
    path: &Path,
    file: &mut File,
    declared: u64,
) -> Result<(), IngestError> {
    let malformed = |error| IngestError::Malformed {
        path: path.to_owned(),
        error,
    };
    file.seek(SeekFrom::Start(0))
        .map_err(|error| IngestError::Io {
            path: path.to_owned(),
            error,
        })?;
    let mut read = BufReader::new(file);
    // Parsing the header leaves `read` at the start of the point data, where the table offset is.
    let header = las::Header::new(&mut read).map_err(malformed)?;
    let vlr = header.laz_vlr().map_err(malformed)?;
    if !is_chunked_laz(&header) {
        return Ok(()); // Pre-2011 LAZ: no chunk table, and decoded sequentially.
    }
    let chunk_table = laz::laszip::ChunkTable::read_from(&mut read, &vlr).map_err(|error| {
        IngestError::LazChunkTable {
            path: path.to_owned(),
            error,
        }
    })?;
    let chunk_capacity = chunk_table
        .as_ref()
        .iter()
        .map(|chunk| chunk.point_count)
        .sum();
    if declared > chunk_capacity {
        return Err(IngestError::TruncatedLaz {
            path: path.to_owned(),
            declared,
            chunk_capacity,
        });
    }
    Ok(())
}

/// Whether the LASzip VLR names a chunked compressor (its first field; `laz` keeps it private).
fn is_chunked_laz(header: &las::Header) -> bool {
    const POINT_WISE_UNCHUNKED: u16 = 1;
    header
        .vlrs()
        .iter()
        .find(|vlr| vlr.user_id == laz::LazVlr::USER_ID && vlr.record_id == laz::LazVlr::RECORD_ID)
        .and_then(|vlr| vlr.data.get(..2))
        .is_some_and(|compressor| {
            u16::from_le_bytes([compressor[0], compressor[1]]) != POINT_WISE_UNCHUNKED
        })
}

/// Opens the `las` reader. LAZ is decoded by the parallel decompressor (the crate's default with
/// `laz-parallel`), which only handles chunked LAZ; old non-chunked files fall back to the
/// sequential one.
fn open_reader(path: &Path, file: File) -> Result<Reader, IngestError> {
    let malformed = |error| IngestError::Malformed {
        path: path.to_owned(),
        error,
    };
    match Reader::new(BufReader::new(file)) {
        Err(las::Error::LasZipError(error)) => {
            tracing::debug!(file = %path.display(), %error, "parallel LAZ decoding unavailable");
            let file = File::open(path).map_err(|error| IngestError::Io {
                path: path.to_owned(),
                error,
            })?;
            let options =
                las::ReaderOptions::default().with_laz_parallelism(las::LazParallelism::No);
            Reader::with_options(BufReader::new(file), options).map_err(malformed)
        }
        result => result.map_err(malformed),
    }
}

/// The header fields that decide whether a file can be read at all, validated before the
/// `las` crate parses it.
struct HeaderFacts {
    version: (u8, u8),
    /// Point format number without the LAZ compression bits.
    point_format: u8,
    compressed: bool,
    declared_points: u64,
}

impl HeaderFacts {
    fn read(path: &Path, file: &mut File, file_len: u64) -> Result<Self, IngestError> {
        let mut signature = [0u8; 4];
        let signature_len = read_up_to(file, &mut signature).map_err(|error| IngestError::Io {
            path: path.to_owned(),
            error,
        })?;
        if signature[..signature_len] != *b"LASF" {
            return Err(IngestError::NotLas {
                path: path.to_owned(),
                found: String::from_utf8_lossy(&signature[..signature_len]).into_owned(),
            });
        }
        file.seek(SeekFrom::Start(0))
            .map_err(|error| IngestError::Io {
                path: path.to_owned(),
                error,
            })?;
        let raw =
            las::raw::Header::read_from(BufReader::new(&mut *file)).map_err(
                |error| match error {
                    las::Error::Io(error) if error.kind() == io::ErrorKind::UnexpectedEof => {
                        IngestError::TruncatedHeader {
                            path: path.to_owned(),
                            file_len,
                        }
                    }
                    error => IngestError::Malformed {
                        path: path.to_owned(),
                        error,
                    },
                },
            )?;

        let version = (raw.version.major, raw.version.minor);
        if version.0 != 1 || version.1 > 4 {
            return Err(IngestError::UnsupportedVersion {
                path: path.to_owned(),
                major: version.0,
                minor: version.1,
            });
        }
        // LASzip marks compressed data by setting bit 7 (and sometimes bit 6) of the format.
        let compressed = raw.point_data_record_format & 0x80 != 0;
        let point_format = raw.point_data_record_format & 0x3f;
        if point_format > 10 {
            return Err(IngestError::UnsupportedPointFormat {
                path: path.to_owned(),
                format: point_format,
            });
        }

        // LAS 1.4 keeps a 64-bit count; a non-zero legacy count wins, as the spec asks.
        let legacy_points = u64::from(raw.number_of_point_records);
        let declared_points = match raw.large_file {
            Some(large) if legacy_points == 0 => large.number_of_point_records,
            _ => legacy_points,
        };
        if declared_points == 0 {
            return Err(IngestError::NoPoints {
                path: path.to_owned(),
            });
        }

        let data_start = u64::from(raw.offset_to_point_data);
        if data_start > file_len {
            return Err(IngestError::TruncatedHeader {
                path: path.to_owned(),
                file_len,
            });
        }
        let record_len = u64::from(raw.point_data_record_length);
        let bytes_after_header = file_len - data_start;
        if compressed {
            // `las` computes `count * record_len` unchecked while parsing the header; an absurd
            // 64-bit count would overflow it.
            if declared_points.checked_mul(record_len).is_none() {
                return Err(IngestError::ImpossiblePointCount {
                    path: path.to_owned(),
                    declared: declared_points,
                });
            }
        } else if record_len > 0 && declared_points.saturating_mul(record_len) > bytes_after_header
        {
            // Uncompressed data has a fixed size: check it up front, so a short file is reported
            // with the number of points that are really there.
            return Err(IngestError::Truncated {
                path: path.to_owned(),
                declared: declared_points,
                available: bytes_after_header / record_len,
            });
        }
        Ok(Self {
            version,
            point_format,
            compressed,
            declared_points,
        })
    }

    /// Points to allocate for up front: the declared count, unless the file is too small to
    /// hold that many (then the vectors grow as points are actually decoded).
    fn capacity_hint(&self, file_len: u64) -> usize {
        let capacity = if self.compressed {
            self.declared_points.min(file_len)
        } else {
            self.declared_points
        };
        usize::try_from(capacity).unwrap_or(0)
    }
}

/// Like `read_exact`, but returns how many bytes there were instead of failing on a short file.
fn read_up_to(read: &mut impl Read, buf: &mut [u8]) -> io::Result<usize> {
    let mut filled = 0;
    while filled < buf.len() {
        match read.read(&mut buf[filled..]) {
            Ok(0) => break,
            Ok(n) => filled += n,
            Err(error) if error.kind() == io::ErrorKind::Interrupted => {}
            Err(error) => return Err(error),
        }
    }
    Ok(filled)
}

fn world_bounds(bounds: las::Bounds) -> WorldBounds {
    let vector = |v: las::Vector<f64>| DVec3::new(v.x, v.y, v.z);
    WorldBounds {
        min: vector(bounds.min),
        max: vector(bounds.max),
    }
}

/// The recentring origin: the centre of the header bounds when they are finite and contain the
/// first point (writers do leave stale or zeroed bounds), else the first point itself.
fn choose_origin(header_bounds: &WorldBounds, first_batch: &PointData) -> DVec3 {
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

/// Per-point columns accumulated batch by batch, before colours can be decided (that needs
/// the whole file: 8-bit detection and intensity percentiles are global).
struct DecodedPoints {
    positions: Vec<Vec3>,
    bounds_min: DVec3,
    bounds_max: DVec3,
    rgb: Option<Vec<[u16; 3]>>,
    intensity: Vec<u16>,
    classification: Vec<u8>,
    return_number: Vec<u8>,
}

impl DecodedPoints {
    fn with_capacity(points: usize, has_color: bool) -> Self {
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

    fn len(&self) -> u64 {
        self.positions.len() as u64
    }

    fn append(&mut self, batch: &PointData, origin: DVec3) {
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

    fn into_cloud(self, origin: DVec3) -> PointCloud {
        let (colors, color_source) = match &self.rgb {
            Some(rgb) => colors_from_rgb(rgb),
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

/// Display colours from the RGB fields. The spec says 16-bit, but some writers store 8-bit
/// values as they are; if no channel of any point exceeds 255 that is what the file holds.
fn colors_from_rgb(rgb: &[[u16; 3]]) -> (Vec<u32>, ColorSource) {
    let max_channel = rgb.iter().flatten().copied().max().unwrap_or(0);
    if max_channel <= 255 {
        let colors = rgb
            .iter()
            .map(|&[r, g, b]| pack_rgba8(r as u8, g as u8, b as u8))
            .collect();
        (colors, ColorSource::Rgb8In16Bit)
    } else {
        let high_byte = |channel: u16| (channel >> 8) as u8;
        let colors = rgb
            .iter()
            .map(|&[r, g, b]| pack_rgba8(high_byte(r), high_byte(g), high_byte(b)))
            .collect();
        (colors, ColorSource::Rgb16)
    }
}

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
    use super::*;
    use crate::color::INTENSITY_GREY_MIN;
    use std::fs;

    /// A small cloud in survey-like coordinates with varied attributes; its coordinates are on
    /// the millimetre grid, so a file written at scale 0.001 stores them exactly.
    fn test_cloud(points: usize) -> PointCloud {
        let world: Vec<DVec3> = (0..points)
            .map(|i| {
                let i = i as f64;
                DVec3::new(
                    636_000.0 + (i * 0.731).rem_euclid(40.0),
                    849_000.0 + (i * 1.913).rem_euclid(25.0),
                    120.0 + (i * 0.057).rem_euclid(9.0),
                )
            })
            .map(|p| (p * 1000.0).round() / 1000.0)
            .collect();
        let colors = (0..points)
            .map(|i| pack_rgba8((i * 7) as u8, (i * 13 + 50) as u8, (255 - i % 256) as u8))
            .collect();
        let mut cloud = PointCloud::from_world_points(&world, colors);
        cloud.intensity = (0..points).map(|i| (i * 37 % 4000) as u16).collect();
        cloud.classification = (0..points).map(|i| [1, 2, 5, 6][i % 4]).collect();
        cloud.return_number = (0..points).map(|i| (i % 3 + 1) as u8).collect();
        cloud
    }

    fn world_positions(cloud: &PointCloud) -> impl Iterator<Item = DVec3> + '_ {
        cloud.positions.iter().map(|p| cloud.origin + p.as_dvec3())
    }

    fn max_position_error(a: &PointCloud, b: &PointCloud) -> f64 {
        world_positions(a)
            .zip(world_positions(b))
            .map(|(a, b)| (a - b).abs().max_element())
            .fold(0.0, f64::max)
    }

    fn file_name(path: &Path) -> String {
        path.file_name()
            .map(|name| name.to_string_lossy().into_owned())
            .unwrap_or_default()
    }

    /// Loads a file that must fail, and checks that the message names it.
    fn load_error(path: &Path) -> IngestError {
        let error = match load_point_cloud(path) {
            Ok(cloud) => panic!(
                "{} loaded {} points, expected an error",
                path.display(),
                cloud.len()
            ),
            Err(error) => error,
        };
        let message = error.to_string();
        assert!(
            message.contains(&file_name(path)),
            "message does not name the file: {message}"
        );
        error
    }

    fn write(dir: &Path, name: &str, cloud: &PointCloud, options: &LasWriteOptions) -> PathBuf {
        let path = dir.join(name);
        write_las(&path, cloud, options).expect("write test file");
        path
    }

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

    /// Writes points with the given raw 16-bit colours (write_las always widens 8-bit colours).
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
                ..Point::default()
            };
            writer.write_point(point).expect("write point");
        }
        writer.close().expect("close");
    }

    #[test]
    fn eight_bit_values_in_sixteen_bit_fields_are_used_as_they_are() {
        let dir = tempfile::tempdir().expect("temp dir");
        let path = dir.path().join("rgb8.las");
        write_raw_rgb(&path, &[[0, 128, 255], [10, 20, 30], [255, 255, 255]]);
        let cloud = load_point_cloud(&path).expect("load");
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
    fn sixteen_bit_colors_keep_their_high_byte() {
        let dir = tempfile::tempdir().expect("temp dir");
        let path = dir.path().join("rgb16.las");
        // One channel above 255 makes the whole file 16-bit, dark points included.
        write_raw_rgb(&path, &[[65_535, 32_768, 256], [255, 100, 0]]);
        let cloud = load_point_cloud(&path).expect("load");
        assert_eq!(cloud.color_source, ColorSource::Rgb16);
        assert_eq!(cloud.colors, [pack_rgba8(255, 128, 1), pack_rgba8(0, 0, 0)]);
    }

    #[test]
    fn intensity_without_color_becomes_a_stretched_grey_that_is_never_black() {
        let dir = tempfile::tempdir().expect("temp dir");
        let mut cloud = test_cloud(1_000);
        // Mostly 100..1100, plus outliers the percentile stretch must ignore.
        cloud.intensity = (0..1_000).map(|i| 100 + i as u16).collect();
        cloud.intensity[0] = 0;
        cloud.intensity[1] = 65_535;
        let options = LasWriteOptions {
            point_format: 1,
            ..LasWriteOptions::default()
        };
        let path = write(dir.path(), "intensity.las", &cloud, &options);
        let loaded = load_point_cloud(&path).expect("load");

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
        let dir = tempfile::tempdir().expect("temp dir");
        let mut cloud = test_cloud(100);
        cloud.intensity = vec![0; 100];
        let options = LasWriteOptions {
            point_format: 0,
            ..LasWriteOptions::default()
        };
        let path = write(dir.path(), "plain.laz", &cloud, &options);
        let loaded = load_point_cloud(&path).expect("load");
        assert_eq!(loaded.color_source, ColorSource::Constant);
        let grey = CONSTANT_GREY_RGBA;
        assert!(loaded.colors.iter().all(|&color| color == grey));
    }

    #[test]
    fn origin_falls_back_to_the_first_point_when_header_bounds_are_wrong() {
        let dir = tempfile::tempdir().expect("temp dir");
        let cloud = test_cloud(50);
        let path = write(
            dir.path(),
            "stale_bounds.las",
            &cloud,
            &LasWriteOptions::default(),
        );
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

    // Byte offsets of header fields patched below (LAS 1.0–1.4 public header block).
    const VERSION_MINOR_OFFSET: usize = 25;
    const POINT_FORMAT_OFFSET: usize = 104;
    const LEGACY_POINT_COUNT_OFFSET: usize = 107;
    const POINT_COUNT_OFFSET_1_4: usize = 247;

    fn patch_point_count(path: &Path, count: u64) {
        let mut bytes = fs::read(path).expect("read back");
        let legacy = u32::try_from(count).unwrap_or(0);
        bytes[LEGACY_POINT_COUNT_OFFSET..][..4].copy_from_slice(&legacy.to_le_bytes());
        if bytes[VERSION_MINOR_OFFSET] == 4 {
            bytes[POINT_COUNT_OFFSET_1_4..][..8].copy_from_slice(&count.to_le_bytes());
        }
        fs::write(path, bytes).expect("patch");
    }

    #[test]
    fn rejects_files_that_are_not_las() {
        let dir = tempfile::tempdir().expect("temp dir");
        let path = dir.path().join("notes.las");
        fs::write(&path, "x,y,z\n1,2,3\n").expect("write");
        assert!(matches!(load_error(&path), IngestError::NotLas { found, .. } if found == "x,y,"));

        let empty = dir.path().join("empty.las");
        fs::write(&empty, "").expect("write");
        assert!(matches!(load_error(&empty), IngestError::NotLas { .. }));
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
    fn reports_how_many_points_a_truncated_las_file_holds() {
        let dir = tempfile::tempdir().expect("temp dir");
        let path = write(
            dir.path(),
            "cut.las",
            &test_cloud(1_000),
            &LasWriteOptions::default(),
        );
        let bytes = fs::read(&path).expect("read back");
        // Format 3 records are 34 bytes: keep 412 and a half.
        let data_start = bytes.len() - 1_000 * 34;
        fs::write(&path, &bytes[..data_start + 412 * 34 + 17]).expect("cut");
        let error = load_error(&path);
        assert!(
            matches!(
                error,
                IngestError::Truncated {
                    declared: 1_000,
                    available: 412,
                    ..
                }
            ),
            "{error}"
        );
        assert!(error
            .to_string()
            .ends_with("truncated: header says 1000 points but data ends after 412"));

        fs::write(&path, &bytes[..150]).expect("cut inside the header");
        assert!(matches!(
            load_error(&path),
            IngestError::TruncatedHeader { file_len: 150, .. }
        ));
    }

    #[test]
    fn rejects_a_point_count_larger_than_the_data() {
        let dir = tempfile::tempdir().expect("temp dir");
        let cloud = test_cloud(1_000);
        for (minor, point_format) in [(2, 3), (4, 1), (4, 7)] {
            let options = LasWriteOptions {
                version: (1, minor),
                point_format,
                scale: 0.001,
            };
            let las = write(
                dir.path(),
                &format!("count_1{minor}_{point_format}.las"),
                &cloud,
                &options,
            );
            patch_point_count(&las, 1_001);
            let error = load_error(&las);
            assert!(
                matches!(
                    error,
                    IngestError::Truncated {
                        declared: 1_001,
                        available: 1_000,
                        ..
                    }
                ),
                "{error}"
            );
            if minor == 4 {
                // A 64-bit count that would overflow `count * record_length` in `las`.
                patch_point_count(&las, u64::MAX / 2);
                let error = load_error(&las);
                assert!(matches!(error, IngestError::Truncated { .. }), "{error}");
            }

            let laz = write(
                dir.path(),
                &format!("count_1{minor}_{point_format}.laz"),
                &cloud,
                &options,
            );
            // Beyond the one 50,000-point chunk: caught from the chunk table, before decoding.
            let beyond_u32: &[u64] = if minor == 4 {
                &[u64::from(u32::MAX) + 1]
            } else {
                &[]
            };
            for &declared in [60_000].iter().chain(beyond_u32) {
                patch_point_count(&laz, declared);
                let error = load_error(&laz);
                assert!(
                    matches!(
                        error,
                        IngestError::TruncatedLaz {
                            chunk_capacity: 50_000,
                            ..
                        }
                    ),
                    "{error}"
                );
            }
            if minor == 4 {
                patch_point_count(&laz, u64::MAX / 2);
                let error = load_error(&laz);
                assert!(
                    matches!(error, IngestError::ImpossiblePointCount { .. }),
                    "{error}"
                );
            }
        }
    }

    #[test]
    fn rejects_a_laz_file_cut_short() {
        let dir = tempfile::tempdir().expect("temp dir");
        let path = write(
            dir.path(),
            "cut.laz",
            &test_cloud(1_000),
            &LasWriteOptions::default(),
        );
        let bytes = fs::read(&path).expect("read back");
        fs::write(&path, &bytes[..bytes.len() * 2 / 3]).expect("cut");
        let error = load_error(&path);
        assert!(
            matches!(error, IngestError::LazChunkTable { .. }),
            "{error}"
        );
    }

    #[test]
    fn rejects_a_file_without_points() {
        let dir = tempfile::tempdir().expect("temp dir");
        for name in ["empty_cloud.las", "empty_cloud.laz"] {
            let path = write(
                dir.path(),
                name,
                &test_cloud(0),
                &LasWriteOptions::default(),
            );
            assert!(matches!(load_error(&path), IngestError::NoPoints { .. }));
        }
    }

    #[test]
    fn rejects_unsupported_point_formats_and_versions() {
        let dir = tempfile::tempdir().expect("temp dir");
        let path = write(
            dir.path(),
            "odd.las",
            &test_cloud(10),
            &LasWriteOptions::default(),
        );
        let original = fs::read(&path).expect("read back");

        let mut bytes = original.clone();
        bytes[POINT_FORMAT_OFFSET] = 42;
        fs::write(&path, &bytes).expect("patch");
        let error = load_error(&path);
        assert!(
            matches!(
                error,
                IngestError::UnsupportedPointFormat { format: 42, .. }
            ),
            "{error}"
        );

        let mut bytes = original;
        bytes[VERSION_MINOR_OFFSET] = 9;
        fs::write(&path, &bytes).expect("patch");
        let error = load_error(&path);
        assert!(
            matches!(
                error,
                IngestError::UnsupportedVersion {
                    major: 1,
                    minor: 9,
                    ..
                }
            ),
            "{error}"
        );
    }

    /// The real scans in `shared/data` next to the repository, if this checkout has them.
    fn shared_data_dir() -> Option<PathBuf> {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data");
        dir.is_dir().then_some(dir)
    }

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
