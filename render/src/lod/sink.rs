//! `NodeSink`: where finished nodes go: encoded, appended to the store's payload file and
//! listed, with their byte ranges, for the hierarchy.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Mutex;

use super::codec::encode_node;
use super::error::LodError;
use super::hierarchy::NodeInfo;
use super::key::{NodeKey, RootCube};
use super::point::RawPoint;
use super::progress::BuildProgress;
use super::store::LodStore;

pub struct NodeSink<'a> {
    store: &'a LodStore,
    cube: RootCube,
    has_rgb: bool,
    progress: &'a BuildProgress,
    nodes: Mutex<Vec<NodeInfo>>,
    points: AtomicU64,
    bytes: AtomicU64,
}

impl<'a> NodeSink<'a> {
    pub fn new(
        store: &'a LodStore,
        cube: RootCube,
        has_rgb: bool,
        progress: &'a BuildProgress,
    ) -> Self {
        Self {
            store,
            cube,
            has_rgb,
            progress,
            nodes: Mutex::new(Vec::new()),
            points: AtomicU64::new(0),
            bytes: AtomicU64::new(0),
        }
    }

    /// Stores a finished node; `sample_grid` is 0 for a leaf. An empty node is only listed:
    /// the hierarchy keeps it if it has children.
    pub fn emit(
        &self,
        key: NodeKey,
        points: &[RawPoint],
        sample_grid: u32,
    ) -> Result<(), LodError> {
        let (mut offset, mut byte_len) = (0, 0);
        if !points.is_empty() {
            let bytes = encode_node(&self.cube, key, points, self.has_rgb);
            offset = self.store.write_node(key, &bytes)?;
            byte_len = bytes.len() as u32;
            self.bytes.fetch_add(bytes.len() as u64, Ordering::Relaxed);
            self.points
                .fetch_add(points.len() as u64, Ordering::Relaxed);
        }
        let info = NodeInfo {
            key,
            point_count: points.len() as u32,
            sample_grid,
            child_mask: 0,
            offset,
            byte_len,
        };
        self.nodes
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner())
            .push(info);
        self.progress.stored(info);
        Ok(())
    }

    /// Points stored so far.
    pub fn points(&self) -> u64 {
        self.points.load(Ordering::Relaxed)
    }

    /// Bytes of node records stored so far.
    pub fn bytes(&self) -> u64 {
        self.bytes.load(Ordering::Relaxed)
    }

    pub fn into_nodes(self) -> Vec<NodeInfo> {
        self.nodes
            .into_inner()
            .unwrap_or_else(|poisoned| poisoned.into_inner())
    }
}
