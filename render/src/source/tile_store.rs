//! Stores of LAS/LAZ tiles by URL, built here by streaming the tiles: each object opened
//! with a HEAD and held to the version its listing saw, checked by range as a file is, then
//! read from start to end in large blocks by the build (`ingest::DatasetSource::
//! open_objects`), never copied whole. A store is kept in the folder local datasets' stores
//! are kept in, named by the tiles' URLs, sizes and versions, so a second render opens it
//! after a listing (or a HEAD) and a replaced object gets a new one.

use std::path::PathBuf;

use rayon::prelude::*;

use super::url_tiles::tiles_pool;
use crate::cut::{CutError, StoreBuild, StoredLod};
use crate::ingest::{DatasetSource, IngestError};
use crate::remote::{ListedObject, ObjectUrl, RemoteClient, RemoteError};

/// The tiles `url` names, with the versions a build holds them to: the `.las`/`.laz` objects
/// under a prefix (one listing), or the one object (one HEAD).
pub fn listed_tiles(
    client: &RemoteClient,
    url: &ObjectUrl,
) -> Result<Vec<ListedObject>, RemoteError> {
    if url.is_prefix() {
        return client.list_point_files(url);
    }
    let object = client.open(url)?;
    Ok(vec![ListedObject {
        url: url.clone(),
        size: object.size(),
        version: object.version().map(str::to_owned),
    }])
}

/// The tiles opened, each held to its listed version, and checked as files are, many at once:
/// the source a build streams.
pub fn open_tile_source(
    client: &RemoteClient,
    tiles: &[ListedObject],
) -> Result<DatasetSource, IngestError> {
    tiles_pool(client, tiles.first().map(|tile| &tile.url))?.install(|| {
        let objects = (tiles.par_iter())
            .map(|tile| client.open_listed(&tile.url, tile.version.as_deref()))
            .collect::<Result<Vec<_>, _>>()?;
        DatasetSource::open_objects(objects)
    })
}

/// What a store is built from: files here, or tiles by URL streamed (each held to the
/// version listed).
pub enum StoreInput {
    Files(Vec<PathBuf>),
    Tiles(RemoteClient, Vec<ListedObject>),
}

/// Opens the store of `tiles` in `build`'s folder, or builds it first from the tiles streamed
/// by URL, telling its `on_build` the points before a build starts and listing in its
/// `progress` the nodes it stores.
pub fn open_or_build_tiles(
    client: &RemoteClient,
    tiles: &[ListedObject],
    build: StoreBuild<'_>,
) -> Result<StoredLod, CutError> {
    if StoredLod::is_built(build.folder) {
        return StoredLod::open_or_build_watched(&[], build);
    }
    let source = open_tile_source(client, tiles)?;
    StoredLod::open_or_build_source(&source, build)
}
