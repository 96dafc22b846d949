//! What a preview draws while a dataset's store builds: a few of its points (the files'
//! chunk starts, and the nodes the build has stored so far), framed by the files' header
//! bounds as the store's frames will be.

use std::path::PathBuf;
use std::time::Instant;

use super::SourceError;
use crate::cloud::{PointCloud, WorldBounds};
use crate::ingest::{sample_chunk_starts, PreviewSample};
use crate::lod::NodePoints;

/// A preview's points, of a dataset of `points_in_files` points.
pub struct PreviewPoints {
    pub cloud: PointCloud,
    pub points_in_files: u64,
    /// The dataset files' header bounds: what the frames of its store will frame.
    pub files_bounds: WorldBounds,
    /// Of the cloud, the nodes and points a build had stored.
    pub stored_nodes: usize,
    pub stored_points: usize,
}

/// The first point of every LAZ chunk (every 50,000th record of a LAS file) of a dataset's
/// files, read once without decompressing, and their header bounds.
pub struct ChunkStarts {
    sample: PreviewSample,
    files_bounds: WorldBounds,
    /// How many files, and how long reading them took.
    pub files: usize,
    pub read_ms: f64,
}

impl ChunkStarts {
    pub fn read(files: &[PathBuf]) -> Result<Self, SourceError> {
        let started = Instant::now();
        let sample = sample_chunk_starts(files)?;
        Ok(Self::of_sample(sample, files.len(), started))
    }

    /// The sample of `files` files, read since `started`.
    pub(super) fn of_sample(sample: PreviewSample, files: usize, started: Instant) -> Self {
        Self {
            files_bounds: sample.files_bounds,
            sample,
            files,
            read_ms: started.elapsed().as_secs_f64() * 1e3,
        }
    }

    /// The chunk starts and `stored`, the nodes a build has stored so far, as a preview's
    /// points (one color decision over both).
    pub fn with_nodes(&self, stored: &[NodePoints]) -> PreviewPoints {
        PreviewPoints {
            cloud: self.sample.cloud_with_nodes(stored),
            points_in_files: self.sample.points_in_files,
            files_bounds: self.files_bounds,
            stored_nodes: stored.len(),
            stored_points: stored.iter().map(NodePoints::len).sum(),
        }
    }
}
