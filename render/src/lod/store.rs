//! `LodStore`: a built dataset in two places. The node payloads are appended to one file (as
//! Potree 2's `octree.bin`), each addressed by the byte range its [`NodeInfo`] records; the
//! hierarchy is one record in a `sled::Tree` the caller owns (so it can live in the dataset
//! cache). Payloads are kept out of sled because sled holds process memory in proportion to
//! the bytes it stores (docs/perf/lod-build.md).
//!
//! The hierarchy is written last, after the payload file is synced, so a build that did not
//! finish leaves no hierarchy and is never read as complete. Nodes are appended from many
//! threads at offsets reserved from an atomic counter, and read with positioned reads on one
//! shared handle: reads need no lock and may run on many threads at once.

use std::fs::{File, OpenOptions};
use std::io;
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

use super::codec::{coarse_len, NodePoints};
use super::error::LodError;
use super::hierarchy::{LodHierarchy, NodeInfo};
use super::key::NodeKey;
use super::records::{read_concurrently, read_nodes, NodeRecords};

const HIERARCHY_KEY: &[u8] = b"hierarchy";

#[derive(Debug, Clone)]
pub struct LodStore {
    tree: sled::Tree,
    payload: Arc<Payload>,
}

/// The payload file: one handle for positioned reads and writes, and the offset of the next
/// append.
#[derive(Debug)]
struct Payload {
    path: PathBuf,
    file: File,
    end: AtomicU64,
}

impl Payload {
    fn error(&self, error: io::Error) -> LodError {
        LodError::payload(&self.path, error)
    }

    fn len(&self) -> Result<u64, LodError> {
        Ok(self.file.metadata().map_err(|e| self.error(e))?.len())
    }
}

impl LodStore {
    /// A store whose hierarchy lives in `tree` and whose node payloads live in the file at
    /// `payload_path` (created if missing; its folder must exist). Both hold this dataset only.
    pub fn open(tree: sled::Tree, payload_path: impl Into<PathBuf>) -> Result<Self, LodError> {
        let path = payload_path.into();
        let file = OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .open(&path)
            .map_err(|e| LodError::payload(&path, e))?;
        let end = file
            .metadata()
            .map_err(|e| LodError::payload(&path, e))?
            .len();
        let payload = Payload {
            path,
            file,
            end: AtomicU64::new(end),
        };
        Ok(Self {
            tree,
            payload: Arc::new(payload),
        })
    }

    pub fn tree(&self) -> &sled::Tree {
        &self.tree
    }

    pub fn payload_path(&self) -> &Path {
        &self.payload.path
    }

    /// Bytes in the payload file now.
    pub fn payload_bytes(&self) -> Result<u64, LodError> {
        self.payload.len()
    }

    /// Removes everything, hierarchy first (and synced), so a half-cleared store is never read
    /// as built; then empties the payload file.
    pub(crate) fn clear(&self) -> Result<(), LodError> {
        self.tree.remove(HIERARCHY_KEY)?;
        self.tree.flush()?;
        self.payload
            .file
            .set_len(0)
            .map_err(|e| self.payload.error(e))?;
        self.payload.end.store(0, Ordering::SeqCst);
        self.tree.clear()?;
        Ok(())
    }

    /// Appends a node's record to the payload file and returns its offset; callable from many
    /// threads at once (each write goes to a range reserved for it alone).
    pub(crate) fn write_node(&self, key: NodeKey, bytes: &[u8]) -> Result<u64, LodError> {
        u32::try_from(bytes.len()).map_err(|_| LodError::CorruptNode {
            key,
            reason: format!("{} bytes is more than a node may hold", bytes.len()),
        })?;
        let offset = self
            .payload
            .end
            .fetch_add(bytes.len() as u64, Ordering::Relaxed);
        self.payload
            .file
            .write_all_at(bytes, offset)
            .map_err(|e| self.payload.error(e))?;
        Ok(offset)
    }

    /// Syncs the payload file, then writes the hierarchy and flushes sled: a hierarchy on disk
    /// always describes payloads on disk. Returns the record's length.
    pub(crate) fn write_hierarchy(&self, hierarchy: &LodHierarchy) -> Result<u64, LodError> {
        self.payload
            .file
            .sync_data()
            .map_err(|e| self.payload.error(e))?;
        let record = hierarchy.encode();
        let len = record.len() as u64;
        self.tree.insert(HIERARCHY_KEY, record)?;
        self.tree.flush()?;
        Ok(len)
    }

    pub fn read_hierarchy(&self) -> Result<LodHierarchy, LodError> {
        let bytes = self
            .tree
            .get(HIERARCHY_KEY)?
            .ok_or(LodError::MissingHierarchy)?;
        LodHierarchy::decode(&bytes)
    }

    /// Reads a node's byte range from the payload file, after checking that the file holds it
    /// (a damaged hierarchy or a truncated file must not cause a huge allocation).
    pub(super) fn read_range(&self, info: &NodeInfo) -> Result<Vec<u8>, LodError> {
        self.read_prefix(info, info.byte_len)
    }

    /// The first `len` bytes of `info`'s record (at most its length).
    fn read_prefix(&self, info: &NodeInfo, len: u32) -> Result<Vec<u8>, LodError> {
        let key = info.key;
        let corrupt = |reason: String| LodError::CorruptNode { key, reason };
        let file_len = self.payload.len()?;
        let end = info.offset.checked_add(u64::from(info.byte_len));
        if end.is_none_or(|end| end > file_len) {
            return Err(corrupt(format!(
                "its {} bytes at offset {} run past the end of the payload file ({file_len} bytes)",
                info.byte_len, info.offset
            )));
        }
        let mut bytes = vec![0; len.min(info.byte_len) as usize];
        match self.payload.file.read_exact_at(&mut bytes, info.offset) {
            Ok(()) => Ok(bytes),
            Err(e) if e.kind() == io::ErrorKind::UnexpectedEof => Err(corrupt(format!(
                "the payload file ended within its {} bytes at offset {}",
                info.byte_len, info.offset
            ))),
            Err(e) => Err(self.payload.error(e)),
        }
    }

    /// The raw stored bytes of a node of `hierarchy` (tests and tools that check the store);
    /// `None` when the hierarchy does not list it or it stores no points.
    pub fn node_bytes(
        &self,
        hierarchy: &LodHierarchy,
        key: NodeKey,
    ) -> Result<Option<Vec<u8>>, LodError> {
        match hierarchy.node(key) {
            Some(info) if info.point_count > 0 => self.read_range(info).map(Some),
            _ => Ok(None),
        }
    }

    /// Reads and checks one node of `hierarchy`; callable from many threads at once.
    pub fn read_node(
        &self,
        hierarchy: &LodHierarchy,
        key: NodeKey,
    ) -> Result<NodePoints, LodError> {
        let mut nodes = read_nodes(self, hierarchy, &[key])?;
        Ok(nodes.pop().expect("one node read"))
    }

    /// Replaces a node's stored bytes, to test that damage is detected: in place when the
    /// length is unchanged, else appended as a new copy, with the node's range updated in
    /// `hierarchy` and in the stored record.
    #[cfg(test)]
    pub(crate) fn overwrite_node_bytes(
        &self,
        hierarchy: &mut LodHierarchy,
        key: NodeKey,
        bytes: &[u8],
    ) -> Result<(), LodError> {
        let info = *hierarchy.node(key).ok_or(LodError::UnknownNode { key })?;
        if bytes.len() == info.byte_len as usize {
            return self
                .payload
                .file
                .write_all_at(bytes, info.offset)
                .map_err(|e| self.payload.error(e));
        }
        let offset = self.write_node(key, bytes)?;
        hierarchy.set_byte_range(key, offset, bytes.len() as u32);
        self.write_hierarchy(hierarchy).map(drop)
    }
}

impl NodeRecords for LodStore {
    /// Positioned reads of the payload file, several in flight.
    fn read_records(&self, nodes: &[NodeInfo]) -> Result<Vec<Vec<u8>>, LodError> {
        read_concurrently(nodes, |info| self.read_range(info))
    }

    /// The records' coarse sections: their first bytes, as long as the record's point count
    /// and colours make that section.
    fn read_coarse_records(
        &self,
        nodes: &[NodeInfo],
        has_rgb: bool,
    ) -> Option<Result<Vec<Vec<u8>>, LodError>> {
        Some(read_concurrently(nodes, |info| {
            let len = coarse_len(info.point_count as usize, has_rgb);
            self.read_prefix(info, u32::try_from(len).unwrap_or(u32::MAX))
        }))
    }
}
