//! `NodeSink`: where finished nodes go: encoded, stored in the payload file a region at a time
//! and listed, with where their records lie, for the hierarchy.
//!
//! A region (a partition's octree, or the children of a node above the partitions) is one
//! contiguous range of the payload file: the coarse sections of its nodes, shallow levels first and
//! each level along a Z curve, then the rest of their records in the same order. A cut takes a
//! partition's nodes from the top down and reads most of them coarse, so it reads a few long ranges
//! where it would read one range a node (docs/perf/payload-layout.md). The nodes' attributes
//! sections, which only an export reads, follow the rests, so no frame's read runs through
//! them.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Mutex;

use super::attributes::{encode_section, AttributeRows};
use super::codec::{coarse_len, encode_node};
use super::error::LodError;
use super::hierarchy::NodeInfo;
use super::journal::{BuildJournal, Queued, UnitKind, UnitRecord, WaitingRoot};
use super::key::{NodeKey, RootCube};
use super::pause;
use super::point::RawPoint;
use super::progress::BuildProgress;
use super::store::LodStore;

pub struct NodeSink<'a> {
    store: &'a LodStore,
    journal: &'a BuildJournal,
    cube: RootCube,
    has_rgb: bool,
    progress: &'a BuildProgress,
    nodes: Mutex<Vec<NodeInfo>>,
    points: AtomicU64,
    bytes: AtomicU64,
}

/// A unit whose nodes are stored: what the journal records of it beside them.
pub struct UnitDone {
    pub kind: UnitKind,
    pub key: NodeKey,
    pub waiting: Option<WaitingRoot>,
}

/// A finished node, encoded, waiting to be stored with the rest of its region.
pub struct EncodedNode {
    info: NodeInfo,
    record: Vec<u8>,
    attributes: Vec<u8>,
}

impl<'a> NodeSink<'a> {
    pub fn new(
        store: &'a LodStore,
        journal: &'a BuildJournal,
        cube: RootCube,
        has_rgb: bool,
        progress: &'a BuildProgress,
    ) -> Self {
        Self {
            store,
            journal,
            cube,
            has_rgb,
            progress,
            nodes: Mutex::new(Vec::new()),
            points: AtomicU64::new(0),
            bytes: AtomicU64::new(0),
        }
    }

    /// The cube the nodes are cells of.
    pub fn cube(&self) -> RootCube {
        self.cube
    }

    /// The journal each stored unit is recorded in.
    pub fn journal(&self) -> &'a BuildJournal {
        self.journal
    }

    /// Encodes a finished node, with its points' attribute `rows` where the build keeps
    /// them; `sample_grid` is 0 for a leaf. An empty node is only listed: the hierarchy keeps
    /// it if it has children.
    pub fn encode(
        &self,
        key: NodeKey,
        points: &[RawPoint],
        sample_grid: u32,
        rows: &AttributeRows,
    ) -> Result<EncodedNode, LodError> {
        let record = match points.is_empty() {
            true => Vec::new(),
            false => encode_node(&self.cube, key, points, self.has_rgb),
        };
        let byte_len = u32::try_from(record.len()).map_err(|_| LodError::CorruptNode {
            key,
            reason: format!("{} bytes is more than a node may hold", record.len()),
        })?;
        let head_len = match points.is_empty() {
            true => 0,
            false => coarse_len(points.len(), self.has_rgb) as u32,
        };
        let attributes = encode_section(key, points, rows);
        let attributes_len =
            u32::try_from(attributes.len()).map_err(|_| LodError::CorruptNode {
                key,
                reason: format!(
                    "{} bytes of attributes is more than a node may hold",
                    attributes.len()
                ),
            })?;
        let info = NodeInfo {
            point_count: points.len() as u32,
            sample_grid,
            byte_len,
            head_len,
            attributes_len,
            ..NodeInfo::empty(key)
        };
        Ok(EncodedNode {
            info,
            record,
            attributes,
        })
    }

    /// Stores `region`, the nodes of the unit `done`, as one contiguous range of the payload
    /// file (the module's layout), records the unit in the journal and lists its nodes. Units
    /// write their regions one at a time and queue their frames in the same order, then wait
    /// for a flush of the journal shared with the units queued beside them, so the payload
    /// file holds the units in the journal's order and, past the last one recorded, only
    /// units still waiting; a resumed build cuts those off.
    ///
    /// `kept_roots`, the store's regions' subtree roots as they were before the levels above
    /// sampled from them, are stored after the region, each in one piece, and not listed: a
    /// store update samples the levels above again from them (`update.rs`). Returns where
    /// they lie.
    pub fn store(
        &self,
        mut region: Vec<EncodedNode>,
        done: UnitDone,
        kept_roots: Vec<EncodedNode>,
    ) -> Result<Vec<NodeInfo>, LodError> {
        region.sort_unstable_by_key(|n| (n.info.key.level, n.info.key.morton()));
        let (heads, rests): (Vec<&[u8]>, Vec<&[u8]>) = region
            .iter()
            .map(|n| n.record.split_at(n.info.head_len as usize))
            .unzip();
        let attributes = region.iter().map(|n| n.attributes.as_slice());
        let root_pieces = kept_roots
            .iter()
            .flat_map(|n| [n.record.as_slice(), n.attributes.as_slice()]);
        let pieces: Vec<&[u8]> = heads
            .into_iter()
            .chain(rests)
            .chain(attributes)
            .chain(root_pieces)
            .collect();
        let commit = self.journal.commit();
        let mut at = self.store.write_region(&pieces)?;
        let mut infos: Vec<NodeInfo> = region.iter().map(|n| n.info).collect();
        for info in infos.iter_mut().filter(|n| n.byte_len > 0) {
            info.offset = at;
            at += u64::from(info.head_len);
        }
        for info in infos.iter_mut().filter(|n| n.byte_len > 0) {
            info.rest_offset = at;
            at += u64::from(info.byte_len - info.head_len);
        }
        for info in infos.iter_mut().filter(|n| n.attributes_len > 0) {
            info.attributes_offset = at;
            at += u64::from(info.attributes_len);
        }
        let kept_roots: Vec<NodeInfo> = kept_roots
            .iter()
            .map(|n| {
                let mut info = n.info.in_one_piece(at, n.info.byte_len);
                at += u64::from(info.byte_len);
                if info.attributes_len > 0 {
                    info.attributes_offset = at;
                    at += u64::from(info.attributes_len);
                }
                info
            })
            .collect();
        pause::at(done.kind.stage(), self.journal.committed(done.kind));
        let queued = commit.record(&UnitRecord {
            kind: done.kind,
            key: done.key,
            payload_end: at,
            waiting: done.waiting,
            children: [0; 8],
            nodes: infos.clone(),
        })?;
        self.durable(queued)?;
        self.list(infos);
        for root in &kept_roots {
            self.bytes.fetch_add(root.stored_bytes(), Ordering::Relaxed);
        }
        Ok(kept_roots)
    }

    /// Returns once `queued` is durable in the journal, syncing the payload file first where
    /// this unit leads the journal's flush.
    pub fn durable(&self, queued: Queued<'_>) -> Result<(), LodError> {
        queued.wait(|| self.store.sync_payload())
    }

    /// Lists nodes whose records are in the payload file: stored now, or by the run of the
    /// build that this one resumes.
    pub fn list(&self, infos: Vec<NodeInfo>) {
        for info in &infos {
            self.bytes.fetch_add(info.stored_bytes(), Ordering::Relaxed);
            self.points
                .fetch_add(u64::from(info.point_count), Ordering::Relaxed);
            self.progress.stored(*info);
        }
        self.nodes
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner())
            .extend(infos);
    }

    /// Points stored so far.
    pub fn points(&self) -> u64 {
        self.points.load(Ordering::Relaxed)
    }

    /// Bytes of node records stored so far, and of the partitions' kept subtree roots.
    pub fn bytes(&self) -> u64 {
        self.bytes.load(Ordering::Relaxed)
    }

    pub fn into_nodes(self) -> Vec<NodeInfo> {
        self.nodes
            .into_inner()
            .unwrap_or_else(|poisoned| poisoned.into_inner())
    }
}
