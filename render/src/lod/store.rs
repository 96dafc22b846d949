//! `LodStore`: a built dataset in two places. The node payloads are appended to one file (as
//! Potree 2's `octree.bin`), each record in two pieces its [`NodeInfo`] locates (`sink.rs`
//! lays them out); the hierarchy is one record in a `sled::Tree` the caller owns (so it can
//! live in the dataset cache). Payloads are kept out of sled because sled holds process memory
//! in proportion to the bytes it stores (docs/perf/lod-build.md).
//!
//! A grown store's payload is a chain of layers (`layers.rs`): the earlier stores' payload
//! files, read only, then its own file, to which it appends; offsets address their
//! concatenation, so everything that reads records reads layers alike.
//!
//! The hierarchy is written last, after the payload file is synced, so a build that did not
//! finish leaves no hierarchy and is never read as complete. Regions are appended from many
//! threads at offsets reserved from an atomic counter. Reads join nearby pieces into runs,
//! positioned reads on one shared handle: they need no lock and run several at once.

use std::fs::{File, OpenOptions};
use std::io;
use std::ops::Range;
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, RwLock};

use super::attributes::decode_section;
use super::codec::NodePoints;
use super::error::LodError;
use super::hierarchy::{LodHierarchy, NodeInfo};
use super::key::NodeKey;
use super::layers::{advise_random, read_across, remove_layers, Layers};
use super::records::{read_concurrently, read_nodes, NodeRecords};
use super::regions::StoreRegions;

const HIERARCHY_KEY: &[u8] = b"hierarchy";
/// The store's regions (`regions.rs`), written with the hierarchy in one batch.
const REGIONS_KEY: &[u8] = b"regions";

#[derive(Debug, Clone)]
pub struct LodStore {
    tree: sled::Tree,
    payload: Arc<Payload>,
}

/// The payload: its layers and its own file, one handle each for positioned reads (and writes
/// to its own file), and the offset of the next append.
#[derive(Debug)]
struct Payload {
    path: PathBuf,
    parts: RwLock<Parts>,
    end: AtomicU64,
}

/// What the payload reads from, replaced whole when the store is cleared.
#[derive(Debug)]
struct Parts {
    layers: Layers,
    /// The payload's own file, at [`Layers::base`] in the concatenation.
    file: File,
    /// Why the layers were refused, for every read to say: the store is built again.
    refused: Option<String>,
}

impl Payload {
    fn error(&self, error: io::Error) -> LodError {
        LodError::payload(&self.path, error)
    }

    fn parts(&self) -> std::sync::RwLockReadGuard<'_, Parts> {
        self.parts
            .read()
            .unwrap_or_else(|poisoned| poisoned.into_inner())
    }

    /// The parts, failing where the layers were refused.
    fn checked(&self) -> Result<std::sync::RwLockReadGuard<'_, Parts>, LodError> {
        let parts = self.parts();
        match &parts.refused {
            Some(reason) => Err(LodError::CorruptLayers(reason.clone())),
            None => Ok(parts),
        }
    }

    /// Bytes of the concatenation.
    fn len(&self) -> Result<u64, LodError> {
        let parts = self.checked()?;
        let own = parts.file.metadata().map_err(|e| self.error(e))?.len();
        Ok(parts.layers.base() + own)
    }

    /// Reads `buf.len()` bytes at `offset` of the concatenation.
    fn read_exact_at(&self, buf: &mut [u8], offset: u64) -> Result<(), (PathBuf, io::Error)> {
        let parts = self.checked().map_err(|e| {
            (
                self.path.clone(),
                io::Error::new(io::ErrorKind::InvalidData, e.to_string()),
            )
        })?;
        read_across(&parts.layers, &parts.file, &self.path, buf, offset)
    }

    /// Writes `bytes` at `offset` of the concatenation, which lies in the payload's own file:
    /// a layer is never written.
    fn write_all_at(&self, bytes: &[u8], offset: u64) -> Result<(), LodError> {
        let parts = self.checked()?;
        let at = offset.checked_sub(parts.layers.base()).ok_or_else(|| {
            self.error(io::Error::new(
                io::ErrorKind::InvalidInput,
                format!("a write at {offset} falls in a read-only layer"),
            ))
        })?;
        parts
            .file
            .write_all_at(bytes, at)
            .map_err(|e| self.error(e))
    }

    fn sync_data(&self) -> Result<(), LodError> {
        self.checked()?.file.sync_data().map_err(|e| self.error(e))
    }
}

/// Opens the payload's own file at `path`, created if missing.
fn open_own(path: &Path) -> Result<File, LodError> {
    let file = OpenOptions::new()
        .read(true)
        .write(true)
        .create(true)
        .truncate(false)
        .open(path)
        .map_err(|e| LodError::payload(path, e))?;
    advise_random(&file, path);
    Ok(file)
}

/// Turns a positioned read's failure into the store's error: an end reached early is a
/// damaged node, `key`'s.
fn read_failure(key: NodeKey, range: Range<u64>, (path, error): (PathBuf, io::Error)) -> LodError {
    if error.kind() == io::ErrorKind::UnexpectedEof {
        return LodError::CorruptNode {
            key,
            reason: format!(
                "the payload file ended within bytes {}..{}",
                range.start, range.end
            ),
        };
    }
    LodError::payload(path, error)
}

impl LodStore {
    /// A store whose hierarchy lives in `tree` and whose node payloads live in the file at
    /// `payload_path` (created if missing; its folder must exist) and the layers listed beside
    /// it. Both hold this dataset only. Layers that fail their checks leave the store opened
    /// but unreadable ([`LodError::CorruptLayers`]), so it is built again.
    pub fn open(tree: sled::Tree, payload_path: impl Into<PathBuf>) -> Result<Self, LodError> {
        let path = payload_path.into();
        let file = open_own(&path)?;
        let (layers, refused) = match Layers::open(&path) {
            Ok(layers) => (layers, None),
            Err(error) => {
                tracing::warn!(%error, "a store's payload layers are refused");
                let reason = match error {
                    LodError::CorruptLayers(reason) => reason,
                    other => other.to_string(),
                };
                (Layers::default(), Some(reason))
            }
        };
        let own = file
            .metadata()
            .map_err(|e| LodError::payload(&path, e))?
            .len();
        let end = layers.base() + own;
        let payload = Payload {
            path,
            parts: RwLock::new(Parts {
                layers,
                file,
                refused,
            }),
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

    /// Bytes in the payload now: its layers' and its own file's.
    pub fn payload_bytes(&self) -> Result<u64, LodError> {
        self.payload.len()
    }

    /// Files the payload is kept in: its layers and its own.
    pub fn payload_files(&self) -> usize {
        self.payload.parts().layers.count() + 1
    }

    /// Reads `buf.len()` bytes of the payload at `offset` (of its layers' concatenation), as
    /// a published store's one payload object holds them.
    pub fn read_payload(&self, buf: &mut [u8], offset: u64) -> Result<(), LodError> {
        self.payload
            .read_exact_at(buf, offset)
            .map_err(|(path, error)| LodError::payload(path, error))
    }

    /// Removes everything, hierarchy first (and synced), so a half-cleared store is never read
    /// as built; then drops the payload's layers and replaces its own file with an empty one
    /// (a new file, not the old one cut: another store may hold the old one as a layer).
    pub(crate) fn clear(&self) -> Result<(), LodError> {
        self.tree.remove(HIERARCHY_KEY)?;
        self.tree.flush()?;
        self.reset_payload(None)?;
        self.tree.clear()?;
        Ok(())
    }

    /// Makes the file at `path` the payload's one file, its layers dropped (a compaction's
    /// last step before the hierarchy that addresses it is written).
    pub(crate) fn replace_payload(&self, path: &Path) -> Result<(), LodError> {
        self.reset_payload(Some(path))
    }

    /// Drops the payload's layers and makes `replacement` its own file, or a new empty one.
    fn reset_payload(&self, replacement: Option<&Path>) -> Result<(), LodError> {
        let payload = &self.payload;
        let mut parts = payload.parts.write().unwrap_or_else(|p| p.into_inner());
        remove_layers(&payload.path)?;
        let replaced = match replacement {
            Some(path) => std::fs::rename(path, &payload.path),
            None => std::fs::remove_file(&payload.path).or_else(|e| match e.kind() {
                io::ErrorKind::NotFound => Ok(()),
                _ => Err(e),
            }),
        };
        replaced.map_err(|e| payload.error(e))?;
        let file = open_own(&payload.path)?;
        let len = file.metadata().map_err(|e| payload.error(e))?.len();
        *parts = Parts {
            layers: Layers::default(),
            file,
            refused: None,
        };
        payload.end.store(len, Ordering::SeqCst);
        Ok(())
    }

    /// Appends `pieces` one after another to the payload file and returns where the first
    /// starts; callable from many threads at once (each region is reserved for one caller).
    pub(crate) fn write_region(&self, pieces: &[&[u8]]) -> Result<u64, LodError> {
        let len: u64 = pieces.iter().map(|p| p.len() as u64).sum();
        let start = self.payload.end.fetch_add(len, Ordering::Relaxed);
        let mut at = start;
        for piece in pieces {
            self.payload.write_all_at(piece, at)?;
            at += piece.len() as u64;
        }
        Ok(start)
    }

    /// Syncs the payload file's bytes, so that a journal may list the nodes written so far.
    pub(crate) fn sync_payload(&self) -> Result<(), LodError> {
        self.payload.sync_data()
    }

    /// Cuts the payload file to its first `len` bytes, what a resumed build's journal lists:
    /// the rest is a unit that was being written when the build stopped. Fails when the file
    /// is shorter.
    pub(crate) fn cut_payload(&self, len: u64) -> Result<(), LodError> {
        let now = self.payload.len()?;
        if now < len {
            let error = io::Error::new(
                io::ErrorKind::UnexpectedEof,
                format!("{now} bytes, the build's journal lists {len}"),
            );
            return Err(self.payload.error(error));
        }
        let parts = self.payload.checked()?;
        let own = len.checked_sub(parts.layers.base()).ok_or_else(|| {
            let error = io::Error::new(
                io::ErrorKind::InvalidInput,
                format!("the build's journal lists {len} bytes, within a read-only layer"),
            );
            self.payload.error(error)
        })?;
        parts
            .file
            .set_len(own)
            .and_then(|()| parts.file.sync_all())
            .map_err(|e| self.payload.error(e))?;
        self.payload.end.store(len, Ordering::SeqCst);
        Ok(())
    }

    /// Syncs the payload file, then writes the hierarchy and flushes sled: a hierarchy on disk
    /// always describes payloads on disk. Returns the record's length.
    #[cfg(test)]
    pub(crate) fn write_hierarchy(&self, hierarchy: &LodHierarchy) -> Result<u64, LodError> {
        self.write_hierarchy_with(hierarchy, None)
    }

    /// [`LodStore::write_hierarchy`] with the store's `regions` in the same sled batch, so
    /// that both switch to a new generation at once (a store update's last step); without
    /// them, the regions of an earlier generation are removed in that batch.
    pub(crate) fn write_hierarchy_with(
        &self,
        hierarchy: &LodHierarchy,
        regions: Option<&StoreRegions>,
    ) -> Result<u64, LodError> {
        self.payload.sync_data()?;
        let record = hierarchy.encode();
        let len = record.len() as u64;
        let mut batch = sled::Batch::default();
        batch.insert(HIERARCHY_KEY, record);
        match regions {
            Some(regions) => batch.insert(REGIONS_KEY, regions.encode()),
            None => batch.remove(REGIONS_KEY),
        }
        self.tree.apply_batch(batch)?;
        self.tree.flush()?;
        Ok(len)
    }

    /// The store's regions, written with its hierarchy; `None` for a store built without
    /// them (a resumed build), which is built again rather than updated.
    pub fn read_regions(&self) -> Result<Option<StoreRegions>, LodError> {
        match self.tree.get(REGIONS_KEY)? {
            Some(bytes) => StoreRegions::decode(&bytes).map(Some),
            None => Ok(None),
        }
    }

    /// Replaces the files the store's regions list (in one insert), where it has regions.
    pub fn set_region_files(&self, files: Vec<String>) -> Result<bool, LodError> {
        let Some(mut regions) = self.read_regions()? else {
            return Ok(false);
        };
        regions.files = files;
        self.tree.insert(REGIONS_KEY, regions.encode())?;
        self.tree.flush()?;
        Ok(true)
    }

    pub fn read_hierarchy(&self) -> Result<LodHierarchy, LodError> {
        drop(self.payload.checked()?);
        let bytes = self
            .tree
            .get(HIERARCHY_KEY)?
            .ok_or(LodError::MissingHierarchy)?;
        LodHierarchy::decode(&bytes)
    }

    /// Reads a node's record from the payload file, after checking that the file holds it
    /// (a damaged hierarchy or a truncated file must not cause a huge allocation).
    pub(super) fn read_range(&self, info: &NodeInfo) -> Result<Vec<u8>, LodError> {
        let mut records = self.read_parts(std::slice::from_ref(info), |n| n.byte_len)?;
        Ok(records.pop().expect("one record read"))
    }

    /// The first `len(node)` bytes of each of `nodes`' records, in order. Every piece is
    /// checked against the file before anything is allocated; the pieces are then read in
    /// runs ([`read_runs`]), several runs in flight.
    fn read_parts(
        &self,
        nodes: &[NodeInfo],
        len: impl Fn(&NodeInfo) -> u32,
    ) -> Result<Vec<Vec<u8>>, LodError> {
        let file_len = self.payload.len()?;
        for info in nodes {
            check_within(info, file_len)?;
        }
        let (mut pieces, lens) = pieces_of(nodes, len);
        let runs = read_runs(&mut pieces);
        let read = read_concurrently(&runs, |run| self.read_run(nodes, &pieces, run))?;
        let mut records: Vec<Vec<u8>> = (0..nodes.len()).map(|_| Vec::new()).collect();
        let mut rests = Vec::new();
        for (piece, bytes) in pieces.iter().zip(read.into_iter().flatten()) {
            match piece.part {
                0 => records[piece.node] = bytes,
                _ => rests.push((piece.node, bytes)),
            }
        }
        for (node, rest) in rests {
            let record = &mut records[node];
            record.reserve_exact(lens[node] - record.len());
            record.extend_from_slice(&rest);
        }
        Ok(records)
    }

    /// One run's pieces, each its own buffer: read straight into it where the run is one
    /// piece, else cut from the run's bytes.
    fn read_run(
        &self,
        nodes: &[NodeInfo],
        pieces: &[Piece],
        run: &Run,
    ) -> Result<Vec<Vec<u8>>, LodError> {
        let first = &pieces[run.pieces.start];
        let key = nodes[first.node].key;
        let mut bytes = vec![0; (run.range.end - run.range.start) as usize];
        self.payload
            .read_exact_at(&mut bytes, run.range.start)
            .map_err(|failure| read_failure(key, run.range.clone(), failure))?;
        if run.pieces.len() == 1 && first.range == run.range {
            return Ok(vec![bytes]);
        }
        Ok(pieces[run.pieces.clone()]
            .iter()
            .map(|p| {
                let start = (p.range.start - run.range.start) as usize;
                bytes[start..start + (p.range.end - p.range.start) as usize].to_vec()
            })
            .collect())
    }

    /// The checked rows of `nodes`' attributes sections, `row_bytes` a row; each section is
    /// checked to lie within the payload file before it is read.
    pub(super) fn read_attribute_sections(
        &self,
        row_bytes: usize,
        nodes: &[NodeInfo],
    ) -> Result<Vec<Vec<u8>>, LodError> {
        let file_len = self.payload.len()?;
        let path = self.payload.path.as_path();
        for info in nodes.iter().filter(|n| n.point_count > 0) {
            let range = info.attributes_range();
            if info.attributes_len == 0 || range.end > file_len {
                return Err(LodError::CorruptNode {
                    key: info.key,
                    reason: format!(
                        "its attributes section {}..{} is not within {} ({file_len} bytes)",
                        range.start,
                        range.end,
                        path.display()
                    ),
                });
            }
        }
        let read = |info: &NodeInfo| -> Result<Vec<u8>, LodError> {
            if info.point_count == 0 {
                return Ok(Vec::new());
            }
            let mut bytes = vec![0; info.attributes_len as usize];
            self.payload
                .read_exact_at(&mut bytes, info.attributes_offset)
                .map_err(|failure| read_failure(info.key, info.attributes_range(), failure))?;
            let rows = decode_section(info.key, info.point_count, row_bytes, &bytes, path)?;
            Ok(rows.to_vec())
        };
        read_concurrently(nodes, read)
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
            let (head, rest) = bytes.split_at(info.head_len as usize);
            for (piece, at) in [(head, info.offset), (rest, info.rest_offset)] {
                self.payload.write_all_at(piece, at)?;
            }
            return Ok(());
        }
        let offset = self.write_region(&[bytes])?;
        hierarchy.set_byte_range(key, offset, bytes.len() as u32);
        self.write_hierarchy(hierarchy).map(drop)
    }
}

impl NodeRecords for LodStore {
    /// Positioned reads of the payload file, several in flight.
    fn read_records(&self, nodes: &[NodeInfo]) -> Result<Vec<Vec<u8>>, LodError> {
        self.read_parts(nodes, |n| n.byte_len)
    }

    /// The records' coarse sections: their heads, which the build stores apart from the rest.
    fn read_coarse_records(&self, nodes: &[NodeInfo]) -> Option<Result<Vec<Vec<u8>>, LodError>> {
        Some(self.read_parts(nodes, |n| n.head_len))
    }

    /// The nodes' attributes sections, one positioned read each, several in flight.
    fn read_attribute_rows(
        &self,
        hierarchy: &LodHierarchy,
        nodes: &[NodeInfo],
    ) -> Option<Result<Vec<Vec<u8>>, LodError>> {
        let schema = hierarchy.attributes()?;
        Some(self.read_attribute_sections(schema.row_bytes(), nodes))
    }
}

/// Ranges of the payload file closer than this are read as one, the bytes between them read
/// and dropped: a disk spends longer on a second request than on this many more bytes of one
/// (docs/perf/payload-layout.md).
const MERGE_GAP: u64 = 64 << 10;

/// The longest read a run makes: long enough that a disk streams, short enough that a wave
/// of nodes stored together still spreads over the reads in flight.
const MAX_RUN: u64 = 1 << 20;

/// A piece of a record to read: `part` 0 is the first the record has, 1 the second.
struct Piece {
    node: usize,
    part: usize,
    range: Range<u64>,
}

/// One read: `range` of the payload file, covering `pieces` (indices into the sorted pieces).
struct Run {
    range: Range<u64>,
    pieces: Range<usize>,
}

/// The pieces of the first `len(node)` bytes of each of `nodes`' records, and those lengths.
fn pieces_of(nodes: &[NodeInfo], len: impl Fn(&NodeInfo) -> u32) -> (Vec<Piece>, Vec<usize>) {
    let mut pieces = Vec::new();
    let mut lens = Vec::with_capacity(nodes.len());
    for (node, info) in nodes.iter().enumerate() {
        let len = len(info).min(info.byte_len);
        lens.push(len as usize);
        for (part, range) in info.pieces(len).enumerate() {
            pieces.push(Piece { node, part, range });
        }
    }
    (pieces, lens)
}

/// Sorts `pieces` by where they lie and joins those at most [`MERGE_GAP`] apart into runs of
/// at most [`MAX_RUN`] bytes (a longer piece is a run of its own).
fn read_runs(pieces: &mut [Piece]) -> Vec<Run> {
    pieces.sort_unstable_by_key(|p| p.range.start);
    let mut runs: Vec<Run> = Vec::new();
    for (i, piece) in pieces.iter().enumerate() {
        match runs.last_mut() {
            Some(run)
                if piece.range.start <= run.range.end + MERGE_GAP
                    && piece.range.end.max(run.range.end) - run.range.start <= MAX_RUN =>
            {
                run.range.end = run.range.end.max(piece.range.end);
                run.pieces.end = i + 1;
            }
            _ => runs.push(Run {
                range: piece.range.clone(),
                pieces: i..i + 1,
            }),
        }
    }
    runs
}

/// Fails unless both pieces of `info`'s record lie within a payload file of `file_len` bytes.
pub(super) fn check_within(info: &NodeInfo, file_len: u64) -> Result<(), LodError> {
    for range in info.pieces(info.byte_len) {
        if range.end > file_len {
            return Err(LodError::CorruptNode {
                key: info.key,
                reason: format!(
                    "its bytes {}..{} run past the end of the payload file ({file_len} bytes)",
                    range.start, range.end
                ),
            });
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pieces(ranges: &[Range<u64>]) -> Vec<Piece> {
        ranges
            .iter()
            .enumerate()
            .map(|(node, range)| Piece {
                node,
                part: 0,
                range: range.clone(),
            })
            .collect()
    }

    fn runs(ranges: &[Range<u64>]) -> Vec<(Range<u64>, Vec<usize>)> {
        let mut pieces = pieces(ranges);
        read_runs(&mut pieces)
            .into_iter()
            .map(|run| {
                let nodes = pieces[run.pieces].iter().map(|p| p.node).collect();
                (run.range, nodes)
            })
            .collect()
    }

    /// Pieces join while the gap between them is at most `MERGE_GAP` and the run stays within
    /// `MAX_RUN`; they are taken in file order whatever order they are asked in, and a piece
    /// inside another's range (a damaged hierarchy) still reads.
    #[test]
    fn pieces_join_into_runs_by_gap_and_length() {
        let gap = MERGE_GAP;
        assert_eq!(
            runs(&[100..200, 0..100, 200 + gap..300 + gap]),
            vec![(0..300 + gap, vec![1, 0, 2])]
        );
        assert_eq!(
            runs(&[0..100, 101 + gap..200 + gap]),
            vec![(0..100, vec![0]), (101 + gap..200 + gap, vec![1])]
        );
        let half = MAX_RUN / 2;
        assert_eq!(
            runs(&[0..half, half..2 * half, 2 * half..2 * half + 1]),
            vec![(0..MAX_RUN, vec![0, 1]), (MAX_RUN..MAX_RUN + 1, vec![2])]
        );
        assert_eq!(
            runs(&[0..3 * MAX_RUN, 10..20]),
            vec![(0..3 * MAX_RUN, vec![0]), (10..20, vec![1])]
        );
        assert_eq!(runs(&[0..1_000, 10..20]), vec![(0..1_000, vec![0, 1])]);
        assert!(runs(&[]).is_empty());
    }
}
