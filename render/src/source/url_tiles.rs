//! LAS/LAZ tiles by URL: each object's header, records and chunk table read by range and
//! checked as a file's are, for `info` and for a preview from the tiles' chunk starts; no
//! tile is copied whole.
//!
//! A tile's bytes are read through `copc::CopcBytes`, the crate's one ranged face over a file
//! or an object, by the same pre-parse and sampling code as files here
//! (`ingest::RangedBytes`). Tiles are opened, checked and sampled many at once: each of their
//! reads waits a round trip, which the connections overlap.

use std::time::Instant;

use rayon::prelude::*;

use super::preview::ChunkStarts;
use super::SourceError;
use crate::copc::CopcBytes;
use crate::ingest::{sample_ranged, ChunkChecks, FileInfo, IngestError, LAS_PREVIEW_STRIDE};
use crate::remote::{ListedObject, ObjectUrl, RemoteClient, RemoteError, RemoteObject};

/// What the LAS/LAZ file at `url` holds, as [`FileInfo::read`] says of a file here: its header
/// and records read by range (up to the chunk table), never its points.
pub fn describe_tile_url(client: &RemoteClient, url: &ObjectUrl) -> Result<FileInfo, SourceError> {
    describe_tile(client.open(url).map_err(crate::copc::CopcError::from)?)
}

/// What the LAS/LAZ object opened as `object` holds, as [`describe_tile_url`] says: read at
/// the version it was opened at (a tile held to the version its listing recorded, through
/// `RemoteClient::open_listed`). Its `read_points` streams the object at that version.
pub fn describe_tile(object: RemoteObject) -> Result<FileInfo, SourceError> {
    let info = FileInfo::read_ranged(&CopcBytes::remote(object.clone()))?;
    Ok(info.streaming_from(object))
}

impl ChunkStarts {
    /// The chunk starts of the LAS/LAZ tiles at `urls`, read as [`ChunkStarts::read`] reads
    /// files here: the same sample, origin and bounds, the tiles' sampled records fetched by
    /// sparse range reads, many tiles at once.
    pub fn read_urls(client: &RemoteClient, urls: &[ObjectUrl]) -> Result<Self, SourceError> {
        Self::read_opened(client, urls, urls.first(), |url| client.open(url))
    }

    /// The chunk starts of `tiles`, as [`Self::read_urls`] reads them, each tile held to the
    /// version listed: one replaced since is `ObjectChanged`, naming it, and nothing of it is
    /// sampled.
    pub fn read_tiles(client: &RemoteClient, tiles: &[ListedObject]) -> Result<Self, SourceError> {
        let first = tiles.first().map(|tile| &tile.url);
        Self::read_opened(client, tiles, first, |tile| {
            client.open_listed(&tile.url, tile.version.as_deref())
        })
    }

    /// The chunk starts of the objects `open` opens from `items`, many at once.
    fn read_opened<T: Sync>(
        client: &RemoteClient,
        items: &[T],
        first: Option<&ObjectUrl>,
        open: impl Fn(&T) -> Result<RemoteObject, RemoteError> + Sync,
    ) -> Result<Self, SourceError> {
        let started = Instant::now();
        let pool = tiles_pool(client, first)?;
        let sample = pool.install(|| {
            let tiles = items
                .par_iter()
                .map(|item| open(item).map(CopcBytes::remote))
                .collect::<Result<Vec<_>, _>>()
                .map_err(crate::copc::CopcError::from)?;
            sample_ranged(&tiles, ChunkChecks::Table, LAS_PREVIEW_STRIDE)
        })?;
        Ok(Self::of_sample(sample, items.len(), started))
    }
}

/// The threads tiles are opened and checked on, as many as the client's parallel requests:
/// each of their reads waits a round trip, which the connections overlap.
pub(super) fn tiles_pool(
    client: &RemoteClient,
    first: Option<&ObjectUrl>,
) -> Result<rayon::ThreadPool, IngestError> {
    rayon::ThreadPoolBuilder::new()
        .num_threads(client.settings().parallel_requests.max(1))
        .thread_name(|i| format!("pointfarm-tiles-{i}"))
        .build()
        .map_err(|error| IngestError::Io {
            path: first.map(|url| url.to_string()).unwrap_or_default().into(),
            error: std::io::Error::other(error),
        })
}
