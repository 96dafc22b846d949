//! What a dataset's store is built from: its files on the server, or its LAS/LAZ tiles by
//! URL, streamed through the render crate's one tiles path (`source::StoreInput`), each tile
//! held to the version its registration recorded, so that a tile replaced since fails the
//! build naming it.

use std::path::Path;

use pointfarm_render::cut::{CutError, StoreBuild, StoredLod};
use pointfarm_render::ingest::dataset_point_count;
use pointfarm_render::lod::{BuildProgress, PointSource};
use pointfarm_render::remote::{ListedObject, ObjectUrl, RemoteClient};
use pointfarm_render::source::{open_or_build_tiles, open_tile_source, StoreInput};

use super::{DatasetStores, Kept, ReadyStore};
use crate::error::DaemonError;
use crate::model::Dataset;

impl DatasetStores {
    /// Datasets of tiles by URL are read through `client` (none: their stores are refused).
    pub fn reading_urls(mut self, client: Option<RemoteClient>) -> Self {
        self.urls = client;
        self
    }

    /// What the store of `dataset` is built from.
    pub(super) fn input_of(&self, dataset: &Dataset) -> Result<StoreInput, DaemonError> {
        if dataset.tiles.is_empty() {
            return Ok(StoreInput::Files(
                dataset.files().into_iter().map(|file| file.path).collect(),
            ));
        }
        let (client, tiles) = self.tiles_of(dataset)?;
        Ok(StoreInput::Tiles(client, tiles))
    }

    /// The client and the tiles of a dataset of tiles by URL, each with the version its
    /// registration recorded, which every read of it is held to.
    pub(crate) fn tiles_of(
        &self,
        dataset: &Dataset,
    ) -> Result<(RemoteClient, Vec<ListedObject>), DaemonError> {
        let client = self.urls.clone().ok_or_else(|| {
            DaemonError::FailedPrecondition(format!(
                "dataset {} is read by URL, which this daemon reads no more (no \
                 --allow-url-prefix)",
                dataset.id
            ))
        })?;
        let tiles = (dataset.tiles.iter())
            .map(|tile| {
                Ok(ListedObject {
                    url: ObjectUrl::parse(&tile.url)?,
                    size: tile.size_bytes,
                    version: Some(tile.version.clone()),
                })
            })
            .collect::<Result<Vec<_>, DaemonError>>()?;
        Ok((client, tiles))
    }

    /// The points of `dataset`, from its files' headers, or its tiles' read by range (each
    /// at its recorded version).
    pub(super) fn point_count(&self, dataset: &Dataset) -> Result<u64, DaemonError> {
        let counted = match self.input_of(dataset)? {
            StoreInput::Files(paths) => dataset_point_count(&paths),
            StoreInput::Tiles(client, tiles) => {
                open_tile_source(&client, &tiles).map(|source| source.point_count())
            }
        };
        counted.map_err(|e| DaemonError::FailedPrecondition(format!("dataset {}: {e}", dataset.id)))
    }
}

/// Opens the store in `folder`, building it from `input` first when it has none.
pub(super) fn open_or_build_input(
    input: &StoreInput,
    folder: &Path,
    budget: u64,
    progress: &BuildProgress,
) -> Result<StoredLod, CutError> {
    with_build(folder, budget, progress, |build| match input {
        StoreInput::Files(files) => StoredLod::open_or_build_watched(files, build),
        StoreInput::Tiles(client, tiles) => open_or_build_tiles(client, tiles, build),
    })
}

/// `open` given the build of a store in `folder` within `budget` bytes, which lists the nodes
/// it stores in `progress`.
pub(super) fn with_build<T>(
    folder: &Path,
    budget: u64,
    progress: &BuildProgress,
    open: impl FnOnce(StoreBuild<'_>) -> T,
) -> T {
    open(StoreBuild {
        folder,
        memory_budget: budget,
        disk_budget: None,
        on_build: &mut |_| {},
        progress,
    })
}

/// Opens the store in `folder`, building it from `input` first when it has none, listing in
/// `progress` the nodes the build stores.
pub(super) fn open_or_build(
    input: &StoreInput,
    folder: &Path,
    budget: u64,
    progress: &BuildProgress,
) -> Result<ReadyStore, CutError> {
    let lod = open_or_build_input(input, folder, budget, progress)?;
    Ok(ready_of(lod, folder))
}

/// The opened store `lod` in `folder`, as workers are sent it.
pub(super) fn ready_of(lod: StoredLod, folder: &Path) -> ReadyStore {
    let build_ms = lod.built.as_ref().map_or(0.0, |(_, seconds)| seconds * 1e3);
    let resumed = lod
        .built
        .as_ref()
        .and_then(|(report, _)| super::resume::taken_over(report));
    let hierarchy_record = lod.dataset.hierarchy().encode();
    tracing::info!(
        folder = %folder.display(),
        points = lod.dataset.point_count(),
        built = lod.built.is_some(),
        "store ready for workers"
    );
    ReadyStore {
        kept: Kept::Store(Box::new(lod)),
        hierarchy_record,
        build_ms,
        resumed,
        copc: None,
        grown: None,
    }
}
