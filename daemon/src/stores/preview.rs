//! The preview sample the daemon serves while a dataset's store builds: the chunk starts of
//! its files (or of its tiles by URL, read by range at their registered versions), read once,
//! joined with the nodes the build has stored so far each time its version moves (read on the
//! request's thread, under a lock of that content's preview alone), the latest kept until the
//! store is ready.

use std::sync::Arc;

use pointfarm_render::cache::encode_cloud;
use pointfarm_render::cloud::WorldBounds;
use pointfarm_render::lod::PREVIEW_STORED_POINTS;
use pointfarm_render::source::{ChunkStarts, StoreInput};

use super::DatasetStores;
use crate::error::DaemonError;
use crate::model::Dataset;

/// A dataset's preview sample as workers are sent it.
pub struct PreviewBytes {
    /// The sample's cloud, `pointfarm_render::cache::encode_cloud`'s bytes.
    pub cloud: Vec<u8>,
    pub points_in_files: u64,
    /// The files' header bounds, which frame the camera as the store's bounds will.
    pub framed: WorldBounds,
    /// The whole tenths of the points the build had stored when the sample was read
    /// (`lod::preview_version`): 0 for the chunk starts alone.
    pub version: u32,
}

/// What is known of a content's preview.
#[derive(Default)]
pub(super) struct PreviewState {
    /// The chunk starts of the dataset's files and their header bounds, read on first use
    /// (or the file at fault, said to every request).
    chunk_starts: Option<Result<Arc<ChunkStarts>, String>>,
    /// The latest sample served.
    latest: Option<Arc<PreviewBytes>>,
}

impl DatasetStores {
    /// The preview sample of `dataset`: its chunk starts, read from its files on first use
    /// and kept, with the nodes its build has stored so far, read again when the build's
    /// version has moved past the latest sample's. A file that cannot be sampled (a damaged
    /// chunk table) is refused, named, now and later.
    pub fn preview_sample(&self, dataset: &Dataset) -> Result<Arc<PreviewBytes>, DaemonError> {
        let state = Arc::clone(
            self.previews
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .entry(dataset.sha256.clone())
                .or_default(),
        );
        let mut state = state.lock().unwrap_or_else(|e| e.into_inner());
        let chunk_starts = match &state.chunk_starts {
            Some(known) => known.clone(),
            None => {
                self.check_files(dataset)?;
                let read = read_chunk_starts(dataset, self.input_of(dataset)?);
                state.chunk_starts = Some(read.clone());
                read
            }
        }
        .map_err(DaemonError::FailedPrecondition)?;
        let progress = self.building_progress(&dataset.sha256);
        let version = progress.as_ref().map_or(0, |p| p.preview_version());
        if let Some(latest) = state.latest.as_ref().filter(|l| l.version >= version) {
            return Ok(Arc::clone(latest));
        }
        let started = std::time::Instant::now();
        let nodes = match progress.filter(|_| version > 0) {
            Some(progress) => {
                // Read on this request's thread: the build keeps the shared thread pool busy.
                progress.read_points(PREVIEW_STORED_POINTS).map_err(|e| {
                    DaemonError::Internal(format!(
                        "dataset {}: reading the nodes stored so far: {e}",
                        dataset.id
                    ))
                })?
            }
            None => Vec::new(),
        };
        let points = chunk_starts.with_nodes(&nodes);
        if !nodes.is_empty() {
            tracing::info!(dataset = %dataset.id, version, nodes = nodes.len(),
                points = points.cloud.len(), read_ms = started.elapsed().as_secs_f64() * 1e3,
                "preview sample read again with the nodes stored so far");
        }
        let sample = Arc::new(PreviewBytes {
            cloud: encode_cloud(&points.cloud),
            points_in_files: points.points_in_files,
            framed: points.files_bounds,
            version,
        });
        state.latest = Some(Arc::clone(&sample));
        Ok(sample)
    }
}

/// The chunk starts of `dataset`'s files (`input`) and the files' header bounds, or why there
/// are none.
fn read_chunk_starts(dataset: &Dataset, input: StoreInput) -> Result<Arc<ChunkStarts>, String> {
    let read = match input {
        StoreInput::Files(paths) => ChunkStarts::read(&paths),
        // Each tile held to the version registered, as the store's build holds it: a tile
        // replaced since fails the preview naming it rather than show another version.
        StoreInput::Tiles(client, tiles) => ChunkStarts::read_tiles(&client, &tiles),
    };
    let read = read
        .map(Arc::new)
        .map_err(|e| format!("dataset {}: no preview: {e}", dataset.id));
    match &read {
        Ok(read) => tracing::info!(dataset = %dataset.id, files = read.files,
            read_ms = read.read_ms, "preview sample read"),
        Err(reason) => tracing::warn!(%reason, "the dataset's preview sample is refused"),
    }
    read
}
