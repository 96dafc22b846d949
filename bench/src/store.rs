//! The level-of-detail stores the benchmarks build: one place that makes one.

use std::path::Path;

use pointfarm_render::lod::{LodError, LodStore};

use crate::BenchError;

/// A fresh store under `dir`: the one place the benchmark makes one. Everything the store
/// writes lives under `dir`, so that the folder's size is the store's disk.
pub(crate) struct BenchStore {
    _db: sled::Db,
    pub(crate) store: LodStore,
}

pub(crate) fn create_store(dir: &Path) -> Result<BenchStore, BenchError> {
    // sled's page cache is outside the builder's budget; small, as in the builder's own
    // throughput test, so that the peak shows the builder and the store's writes.
    let db = sled::Config::new()
        .path(dir.join("sled"))
        .cache_capacity(64 << 20)
        .open()
        .map_err(LodError::from)?;
    // The payload file beside sled's folder, which sled's open has made `dir`.
    let store = LodStore::open(
        db.open_tree("lod").map_err(LodError::from)?,
        dir.join("nodes.bin"),
    )?;
    Ok(BenchStore { _db: db, store })
}
