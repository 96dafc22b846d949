//! A preview sample of a dataset read without decompressing anything: the first point of
//! every LAZ chunk, and every k-th record of a LAS file.
//!
//! LASzip writes the first point of each chunk as raw record bytes before the arithmetic
//! coder starts (point-wise chunks: the items' raw bytes, then the coder's init bytes;
//! layered chunks: the raw record, then the chunk's point count and its layer sizes), so the
//! checked chunk table gives an evenly spread subsample of a file of any size in one small
//! read per chunk (as LidarScout does). An old unchunked LAZ file gives its first point only.
//! The sample becomes a cloud as a dataset's load makes one: the same origin (the first
//! sampled point is the file's first point) and the same color rule, decided on the sample.

use std::ops::Range;
use std::path::PathBuf;
use std::time::Instant;

use glam::DVec3;
use las::PointDataBuilder;
use rayon::prelude::*;

use super::columns::{choose_origin, DecodedPoints};
use super::contain::contain_panics;
use super::laz_layout::LazLayout;
use super::preparse::ChunkChecks;
use super::ranged::{check_ranged, LocalFile, RangedBytes};
use super::read::{
    dataset_bounds, dataset_header_bounds, deciding_files, require_points, DatasetFile,
};
use super::IngestError;
use crate::cloud::{PointCloud, WorldBounds};
use crate::lod::NodePoints;

/// Records between two sampled records of a LAS file: LASzip's default chunk size, so LAS and
/// LAZ files give previews of one density.
pub const LAS_PREVIEW_STRIDE: u64 = 50_000;

/// A dataset's preview sample as one cloud, and the points its files declare.
pub struct PreviewSample {
    pub cloud: PointCloud,
    pub points_in_files: u64,
    /// What the frames of the dataset's store frame: its files' header bounds.
    pub files_bounds: WorldBounds,
    /// The sampled records before their colors were decided, for [`Self::cloud_with_nodes`].
    decoded: DecodedPoints,
}

impl PreviewSample {
    /// The sample and `nodes` of the dataset's store (those a build has stored so far) as one
    /// cloud: the sample's origin, bounds over both and one color decision over both.
    pub fn cloud_with_nodes(&self, nodes: &[NodePoints]) -> PointCloud {
        let mut decoded = self.decoded.clone();
        for node in nodes {
            decoded.append_node(node, self.cloud.origin);
        }
        decoded.into_cloud(self.cloud.origin)
    }
}

/// The chunk starts of a dataset's LAZ files and every [`LAS_PREVIEW_STRIDE`]-th record of
/// its LAS files, as one cloud (one origin, bounds and color decision, as
/// [`load_dataset`](super::load_dataset) decides them). Every file is pre-parsed as a load
/// pre-parses it; every offset read lies inside the checked chunk table's extent.
pub fn sample_chunk_starts(paths: &[PathBuf]) -> Result<PreviewSample, IngestError> {
    sample_dataset(paths, LAS_PREVIEW_STRIDE)
}

fn sample_dataset(paths: &[PathBuf], las_stride: u64) -> Result<PreviewSample, IngestError> {
    let files: Vec<LocalFile> = paths.iter().map(|path| LocalFile::new(path)).collect();
    sample_ranged(&files, ChunkChecks::Layers, las_stride)
}

/// [`sample_chunk_starts`] of files read by range, each checked as far into its LAZ chunks
/// as `chunks` says: a file here is checked as a load checks it, an object by URL up to its
/// chunk table, since its layer tables guard a decoder this sample never runs and would cost
/// a request per chunk.
pub(crate) fn sample_ranged<B: RangedBytes>(
    sources: &[B],
    chunks: ChunkChecks,
    las_stride: u64,
) -> Result<PreviewSample, B::Error> {
    let started = Instant::now();
    if sources.is_empty() {
        return Err(IngestError::NoFiles.into());
    }
    // The reads are small and scattered (one a chunk), an object's each a round trip: files
    // in parallel keep the disk's queue, or the connections, full.
    let checked = sources
        .par_iter()
        .map(|source| check_ranged(source, chunks))
        .collect::<Result<Vec<_>, _>>()?;
    let (files, headers): (Vec<DatasetFile>, Vec<las::Header>) = checked.into_iter().unzip();
    require_points(&files)?;
    let files_bounds = dataset_bounds(&files)?;
    let header_bounds = dataset_header_bounds(&files);
    let has_color = deciding_files(&files).iter().all(|file| file.has_color);
    let samples = (sources.par_iter().zip(&files).zip(&headers))
        .map(|((source, file), header)| sample_file(source, file, header, las_stride))
        .collect::<Result<Vec<_>, _>>()?;
    let sampled = samples.iter().map(las::PointData::len).sum();
    let mut decoded = DecodedPoints::with_capacity(sampled, has_color);
    let mut origin = None;
    for (file, sample) in files.iter().zip(&samples) {
        // A load fixes the origin with the first file that has points; so does the sample.
        if sample.is_empty() {
            continue;
        }
        let origin = *origin.get_or_insert_with(|| choose_origin(&header_bounds, sample));
        decoded.append(sample, origin);
        if let Some(extreme) = decoded.implausible_extreme() {
            return Err(IngestError::ImplausibleCoordinates {
                path: file.path.clone(),
                extreme,
            }
            .into());
        }
    }
    let cloud = decoded.clone().into_cloud(origin.unwrap_or(DVec3::ZERO));
    let points_in_files = files.iter().map(|file| file.facts.declared_points).sum();
    tracing::info!(
        files = files.len(),
        sampled = cloud.len(),
        points = points_in_files,
        elapsed_ms = started.elapsed().as_secs_f64() * 1e3,
        "sampled chunk starts"
    );
    Ok(PreviewSample {
        cloud,
        points_in_files,
        files_bounds,
        decoded,
    })
}

/// Reads `file`'s sampled records by range, each span checked against the file's size.
fn sample_file<B: RangedBytes>(
    source: &B,
    file: &DatasetFile,
    header: &las::Header,
    las_stride: u64,
) -> Result<las::PointData, B::Error> {
    let record_len = u64::from(file.facts.record_len);
    let ranges: Vec<Range<u64>> = record_starts(file, las_stride)?
        .iter()
        .map(|start| start.offset..start.offset + record_len)
        .collect();
    // Each range was checked to lie in the file, so the records are at most its size.
    let bytes = source.read_sparse(&ranges)?.concat();
    let path = file.path.as_path();
    let points = contain_panics(path, || {
        PointDataBuilder::new()
            .for_header(header)
            .build_from_bytes(bytes)
            .map_err(|error| IngestError::Malformed {
                path: path.to_owned(),
                error,
            })
    })?;
    Ok(points)
}

/// A sampled record: its index in the file's point order and its byte offset.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct RecordStart {
    index: u64,
    offset: u64,
}

/// Where the sampled records of `file` lie: LAZ chunk starts after the chunk table's offset
/// field (or the first point of an unchunked file), or every `las_stride`-th LAS record.
fn record_starts(file: &DatasetFile, las_stride: u64) -> Result<Vec<RecordStart>, IngestError> {
    let corrupt = |what: String| IngestError::Corrupt {
        path: file.path.clone(),
        what,
    };
    let facts = &file.facts;
    let record_len = u64::from(facts.record_len);
    let declared = facts.declared_points;
    let data_start = facts.offset_to_point_data;
    let mut starts = Vec::new();
    match file.laz {
        None => {
            let stride = las_stride.max(1);
            // The pre-parse checked that the declared records fit in the file.
            starts.extend((0..declared.div_ceil(stride)).map(|k| RecordStart {
                index: k * stride,
                offset: data_start + k * stride * record_len,
            }));
        }
        Some(LazLayout::Unchunked) => {
            if declared > 0 {
                starts.push(RecordStart {
                    index: 0,
                    offset: data_start,
                });
            }
        }
        Some(LazLayout::Chunked) => {
            // The chunks follow the 8-byte offset of the chunk table.
            let mut offset = data_start + 8;
            let mut index = 0u64;
            for (chunk_index, chunk) in file.chunks.as_ref().iter().enumerate() {
                if index >= declared {
                    break;
                }
                if chunk.point_count > 0 {
                    if chunk.byte_count < record_len {
                        return Err(corrupt(format!(
                            "LAZ chunk {chunk_index} of {} bytes cannot hold its first point ({record_len}-byte records)",
                            chunk.byte_count
                        )));
                    }
                    starts.push(RecordStart { index, offset });
                }
                index = index.saturating_add(chunk.point_count);
                offset = offset.saturating_add(chunk.byte_count);
            }
        }
    }
    let file_len = file.file_len();
    for start in &starts {
        if start
            .offset
            .checked_add(record_len)
            .is_none_or(|end| end > file_len)
        {
            return Err(corrupt(format!(
                "a sampled point record ({record_len} bytes at offset {}) runs past the end of \
                 the file ({file_len} bytes)",
                start.offset
            )));
        }
    }
    Ok(starts)
}

/// The sample of one file and the sampled points' indices in the file's point order, for
/// tests that compare it with the file decoded whole.
#[cfg(test)]
fn sample_one(
    path: &std::path::Path,
    las_stride: u64,
) -> Result<(Vec<u64>, las::PointData), IngestError> {
    let source = LocalFile::new(path);
    let (file, header) = check_ranged(&source, ChunkChecks::Layers)?;
    let indices = record_starts(&file, las_stride)?
        .iter()
        .map(|start| start.index)
        .collect();
    let points = sample_file(&source, &file, &header, las_stride)?;
    Ok((indices, points))
}

#[cfg(test)]
#[path = "chunk_starts_tests.rs"]
mod tests;
