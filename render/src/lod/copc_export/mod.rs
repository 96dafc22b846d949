//! COPC 1.0 export: a built level-of-detail store written as one Cloud Optimized Point Cloud
//! file that PDAL, QGIS, Potree and laspy open.
//!
//! The store's octree is already COPC's: its node keys are COPC voxel keys, its cube is the
//! root's, and every point lies in exactly one node. So each store node becomes one COPC
//! node and one variable-size LAZ chunk, with no resampling: the file holds exactly the
//! store's points, each with every attribute its file gave it where the store keeps them.
//! Points are LAS 1.4 PDRF 6, 7 when the dataset has RGB, 8 with near-infrared too (COPC
//! allows no other), the files' wave packets and extra bytes as extra bytes ([`records`]);
//! the scale and offset come from the dataset's files when known ([`transform`]); the header's
//! bounds are those of the written coordinates. Nodes are read, converted and compressed a
//! wave at a time on all cores and written in the store's key order, so memory stays within
//! a wave's points whatever the dataset's size; the header and info VLR, which need the
//! totals and the hierarchy's offset, are written last over their reserved bytes ([`layout`]).
//! A file is written under a temporary name beside its destination and renamed into place
//! when complete, so an interrupted export leaves no half file under the real name.

mod crs;
mod error;
mod layout;
pub mod node_grids;
mod records;
mod transform;

#[cfg(test)]
mod tests;

use std::fs::File;
use std::io::{BufWriter, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

use glam::DVec3;
use laz::record::RecordCompressor;
use rayon::prelude::*;

pub use error::CopcExportError;
pub use layout::HierarchyEntry;
pub use records::{point_format, RecordFormat, PDRF6_BYTES, PDRF7_BYTES, PDRF8_BYTES};
pub use transform::{ExportTransform, DEFAULT_SCALE};

use super::hierarchy::{LodHierarchy, NodeInfo};
use super::key::RootCube;
use super::records::{read_nodes, NodeRecords};
use layout::{FileFacts, ENTRY_BYTES};
use records::node_records;

/// Points read and compressed together: the export's memory is about this many points'
/// decoded, record and compressed bytes (about 80 B a point), plus its largest node.
const WAVE_POINTS: u64 = 1 << 21;
/// Most nodes read in one request (the daemon's limit on a node request).
const WAVE_NODES: usize = 256;
/// The sampling grid assumed for the root spacing of a store whose root is a leaf.
const DEFAULT_GRID: f64 = 128.0;
/// Bytes of the write buffer.
const WRITE_BUFFER_BYTES: usize = 1 << 20;

/// How an export writes its points beyond the store: the coordinates' scale and offset, and
/// the CRS it declares.
#[derive(Debug, Clone, PartialEq)]
pub struct ExportSettings {
    pub transform: ExportTransform,
    /// The OGC WKT record to carry, as its bytes.
    pub wkt: Option<Vec<u8>>,
}

impl ExportSettings {
    /// The settings a store of the files `paths` is exported with: their finest scale and
    /// first offset (millimetres from the cube's corner without files) and the WKT record
    /// they all declare. Only files that declare points decide, as in a load: an empty tile
    /// of another scale or without a CRS changes nothing.
    pub fn of_files(paths: &[PathBuf], cube: &RootCube) -> Result<Self, CopcExportError> {
        let deciding = transform::deciding_paths(paths);
        Ok(Self {
            transform: ExportTransform::of_files(&deciding)?
                .unwrap_or_else(|| ExportTransform::fixed(cube)),
            wkt: crs::common_wkt(&deciding)?,
        })
    }

    /// Millimetres from the cube's corner, no CRS: a store whose files are not at hand.
    pub fn fixed(cube: &RootCube) -> Self {
        Self {
            transform: ExportTransform::fixed(cube),
            wkt: None,
        }
    }
}

/// What an export wrote.
#[derive(Debug, Clone, PartialEq)]
pub struct CopcExportReport {
    pub points: u64,
    pub nodes: usize,
    pub bytes: u64,
    pub transform: ExportTransform,
    /// Bounds of the written coordinates.
    pub min: DVec3,
    pub max: DVec3,
    pub point_format: u8,
}

/// Exports the store (`hierarchy` and its node `records`) as a COPC file at `path`, through a
/// temporary file beside it that is renamed into place when complete (an existing file is
/// replaced). `progress` is told the points written so far after each wave.
pub fn export_copc(
    hierarchy: &LodHierarchy,
    records: &dyn NodeRecords,
    settings: &ExportSettings,
    path: &Path,
    progress: &mut dyn FnMut(u64),
) -> Result<CopcExportReport, CopcExportError> {
    let partial = partial_path(path);
    let file = File::create(&partial).map_err(|e| CopcExportError::write(path, e))?;
    let mut out = BufWriter::with_capacity(WRITE_BUFFER_BYTES, file);
    let written =
        write_copc(hierarchy, records, settings, &mut out, &partial, progress).and_then(|report| {
            let file = out
                .into_inner()
                .map_err(|e| CopcExportError::write(&partial, e.into_error()))?;
            file.sync_all()
                .map_err(|e| CopcExportError::write(&partial, e))?;
            std::fs::rename(&partial, path).map_err(|e| CopcExportError::write(path, e))?;
            Ok(report)
        });
    if written.is_err() {
        let _ = std::fs::remove_file(&partial);
    }
    written
}

/// `path` with `.part` appended to its file name.
fn partial_path(path: &Path) -> PathBuf {
    let mut name = path.file_name().unwrap_or_default().to_os_string();
    name.push(".part");
    path.with_file_name(name)
}

/// Writes the store as a COPC file to `out` from its start; `name` names `out` in errors.
pub fn write_copc<W: Write + Seek>(
    hierarchy: &LodHierarchy,
    records: &dyn NodeRecords,
    settings: &ExportSettings,
    out: &mut W,
    name: &Path,
    progress: &mut dyn FnMut(u64),
) -> Result<CopcExportReport, CopcExportError> {
    if hierarchy.point_count == 0 {
        return Err(CopcExportError::Empty);
    }
    let io = |e: std::io::Error| CopcExportError::write(name, e);
    let cube = hierarchy.cube;
    let transform = settings.transform.fitted(&cube)?;
    let has_rgb = hierarchy.stats.has_rgb;
    // The attributes sections are read only where both the store keeps them and its records
    // source serves them: probed once, on the first node with points.
    let probe: Vec<NodeInfo> = hierarchy.stored_nodes().take(1).copied().collect();
    let keeps_rows = match records.read_attribute_rows(hierarchy, &probe) {
        Some(read) => {
            read?;
            true
        }
        None => false,
    };
    let attributes = hierarchy.attributes().filter(|_| keeps_rows);
    match attributes {
        Some(schema) if schema.extra_bytes_dropped => tracing::warn!(
            "the dataset's files declare different extra bytes; the export leaves them out"
        ),
        Some(schema) => {
            let some =
                |formats: &[u8]| formats.iter().any(|&f| schema.source_formats & 1 << f != 0);
            if !has_rgb && some(&[2, 3, 5, 7, 8, 10]) {
                tracing::warn!(
                    "only some of the dataset's files have RGB; the export leaves it out"
                );
            }
            if has_rgb && !schema.has_nir && some(&[8, 10]) {
                tracing::warn!(
                    "only some of the dataset's files have near-infrared; the export leaves it out"
                );
            }
        }
        None => tracing::warn!(
            "the store keeps no attributes beyond intensity, classification and return \
             number; the export writes the others as unknown"
        ),
    }
    let format = RecordFormat::new(has_rgb, attributes);
    let vlr_bytes = format.extra_bytes_vlr().len();
    if vlr_bytes > usize::from(u16::MAX) || format.record_len() > usize::from(u16::MAX) {
        return Err(CopcExportError::TooManyAttributes {
            record_bytes: format.record_len(),
            descriptor_bytes: vlr_bytes,
        });
    }
    let laz = layout::laz_vlr(&format);
    let data_start = layout::point_data_offset(&laz, &format, settings.wkt.as_deref());
    // The head is written last, when its totals are known; the chunk table's offset too.
    out.seek(SeekFrom::Start(0)).map_err(io)?;
    out.write_all(&vec![
        0;
        data_start as usize
            + laz::laszip::ChunkTable::OFFSET_SIZE
    ])
    .map_err(io)?;
    let mut at = data_start + laz::laszip::ChunkTable::OFFSET_SIZE as u64;

    let mut totals = Totals::default();
    let mut entries = Vec::with_capacity(hierarchy.nodes().len());
    let mut chunks = laz::laszip::ChunkTable::with_capacity(hierarchy.nodes().len());
    for wave in waves(hierarchy.nodes()) {
        let keys: Vec<_> = wave.iter().map(|n| n.key).collect();
        let nodes = read_nodes(records, hierarchy, &keys)?;
        let rows = match format.attributes {
            Some(_) => records
                .read_attribute_rows(hierarchy, wave)
                .unwrap_or_else(|| Ok(vec![Vec::new(); wave.len()]))?,
            None => vec![Vec::new(); wave.len()],
        };
        let compressed: Vec<_> = nodes
            .par_iter()
            .zip(&rows)
            .map(|(node, rows)| {
                let rows = format.attributes.as_ref().map(|_| rows.as_slice());
                let bytes = node_records(node, rows, &transform, &format);
                let chunk = if bytes.count == 0 {
                    Vec::new()
                } else {
                    compress(&bytes.bytes, &laz).map_err(|reason| CopcExportError::Compress {
                        key: node.key,
                        reason,
                    })?
                };
                Ok((bytes, chunk))
            })
            .collect::<Result<_, CopcExportError>>()?;
        for (info, (bytes, chunk)) in wave.iter().zip(compressed) {
            let key = info.key;
            let too_large = |what: String| CopcExportError::NodeTooLarge { key, what };
            let byte_size = i32::try_from(chunk.len())
                .map_err(|_| too_large(format!("{} compressed bytes", chunk.len())))?;
            let point_count = i32::try_from(bytes.count)
                .map_err(|_| too_large(format!("{} points", bytes.count)))?;
            let cell = |v: u32| i32::try_from(v).map_err(|_| too_large(format!("cell {v}")));
            entries.push(HierarchyEntry {
                level: i32::from(key.level),
                x: cell(key.x)?,
                y: cell(key.y)?,
                z: cell(key.z)?,
                offset: if bytes.count == 0 { 0 } else { at },
                byte_size,
                point_count,
            });
            if bytes.count == 0 {
                continue;
            }
            out.write_all(&chunk).map_err(io)?;
            chunks.push(laz::laszip::ChunkTableEntry {
                point_count: bytes.count,
                byte_count: chunk.len() as u64,
            });
            at += chunk.len() as u64;
            totals.add(&bytes);
        }
        progress(totals.points);
    }
    if totals.points == 0 {
        return Err(CopcExportError::Empty);
    }

    let table_start = at;
    chunks.write_to(&mut *out, &laz).map_err(io)?;
    let evlr_start = out.stream_position().map_err(io)?;
    out.write_all(&layout::hierarchy_evlr(&entries))
        .map_err(io)?;
    out.write_all(&layout::node_grids_evlr(node_grids::encode(
        hierarchy.nodes(),
    )))
    .map_err(io)?;
    let end = out.stream_position().map_err(io)?;

    let halfsize = cube.side / 2.0;
    // COPC has one spacing, halved at each level, where a store samples each node on a grid
    // of its own (halved where a node would be too full): the coarsest grid's spacing bounds
    // every node's, so a reader that refines by it never stops at a node too sparse. Each
    // node's own grid is in the node grids EVLR, for pointfarm's reader.
    let grid = hierarchy
        .nodes()
        .iter()
        .map(|n| n.sample_grid)
        .filter(|&g| g > 0)
        .min()
        .map_or(DEFAULT_GRID, f64::from);
    let point_format = format.point_format();
    let facts = FileFacts {
        format,
        gps_range: totals.gps_range,
        transform,
        points: totals.points,
        by_return: totals.by_return,
        min: totals.min,
        max: totals.max,
        centre: cube.min + DVec3::splat(halfsize),
        halfsize,
        spacing: cube.side / grid,
        evlr_start,
        hierarchy_bytes: entries.len() as u64 * ENTRY_BYTES,
        wkt: settings.wkt.clone(),
    };
    out.seek(SeekFrom::Start(0)).map_err(io)?;
    out.write_all(&layout::head(&facts, &laz)).map_err(io)?;
    out.write_all(&(table_start as i64).to_le_bytes())
        .map_err(io)?;
    out.seek(SeekFrom::Start(end)).map_err(io)?;
    out.flush().map_err(io)?;
    Ok(CopcExportReport {
        points: totals.points,
        nodes: entries.len(),
        bytes: end,
        transform,
        min: totals.min,
        max: totals.max,
        point_format,
    })
}

/// The nodes in consecutive waves of at most [`WAVE_POINTS`] points (or one node) and
/// [`WAVE_NODES`] nodes.
fn waves(nodes: &[NodeInfo]) -> impl Iterator<Item = &[NodeInfo]> {
    let mut rest = nodes;
    std::iter::from_fn(move || {
        if rest.is_empty() {
            return None;
        }
        let mut points = 0u64;
        let mut n = 0;
        while n < rest.len() && n < WAVE_NODES && (n == 0 || points < WAVE_POINTS) {
            points += u64::from(rest[n].point_count);
            n += 1;
        }
        let (wave, tail) = rest.split_at(n);
        rest = tail;
        Some(wave)
    })
}

/// One LAZ chunk of `records`: the layered (LAZ 1.4) compressor started afresh, as every
/// chunk's is.
fn compress(records: &[u8], laz: &laz::LazVlr) -> Result<Vec<u8>, String> {
    let mut compressor = laz::record::LayeredPointRecordCompressor::new(Vec::new());
    compressor
        .set_fields_from(laz.items())
        .map_err(|e| e.to_string())?;
    compressor
        .compress_many(records)
        .map_err(|e| e.to_string())?;
    compressor.done().map_err(|e| e.to_string())?;
    Ok(compressor.into_inner())
}

/// What the header sums over every written node.
struct Totals {
    points: u64,
    by_return: [u64; 15],
    min: DVec3,
    max: DVec3,
    gps_range: Option<[f64; 2]>,
}

impl Default for Totals {
    fn default() -> Self {
        Self {
            points: 0,
            gps_range: None,
            by_return: [0; 15],
            min: DVec3::splat(f64::INFINITY),
            max: DVec3::splat(f64::NEG_INFINITY),
        }
    }
}

impl Totals {
    fn add(&mut self, node: &records::NodeRecordBytes) {
        self.points += node.count;
        for (total, n) in self.by_return.iter_mut().zip(node.by_return) {
            *total += n;
        }
        self.min = self.min.min(node.min);
        self.max = self.max.max(node.max);
        if let Some([lo, hi]) = node.gps_range {
            self.gps_range = Some(match self.gps_range {
                Some([low, high]) => [low.min(lo), high.max(hi)],
                None => [lo, hi],
            });
        }
    }
}
