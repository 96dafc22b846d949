//! `BuildProgress`: what a running build has stored so far, so that a preview can draw the
//! nodes built while the rest is still building.
//!
//! A node is listed only once its record is in the payload file, which is written with
//! positioned writes and no buffer, so every listed node reads back whole while the build
//! goes on. The nodes come chunk by chunk, each chunk's subtree but its root (the levels above
//! still sample from it), then the levels above the chunks at the end.

use std::sync::Mutex;

use super::codec::{decode_node, NodePoints};
use super::error::LodError;
use super::hierarchy::NodeInfo;
use super::key::RootCube;
use super::store::LodStore;

/// Shared between a build and whoever watches it; empty until the build has counted its
/// points.
#[derive(Default)]
pub struct BuildProgress {
    state: Mutex<Option<Stored>>,
}

struct Stored {
    store: LodStore,
    cube: RootCube,
    nodes: Vec<NodeInfo>,
    points: u64,
    point_count: u64,
}

impl BuildProgress {
    pub fn new() -> Self {
        Self::default()
    }

    fn state(&self) -> std::sync::MutexGuard<'_, Option<Stored>> {
        self.state
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner())
    }

    /// A build of `point_count` points into `store`, in `cube`, has begun storing nodes.
    pub(crate) fn begin(&self, store: &LodStore, cube: RootCube, point_count: u64) {
        *self.state() = Some(Stored {
            store: store.clone(),
            cube,
            nodes: Vec::new(),
            points: 0,
            point_count,
        });
    }

    /// A node's record is in the payload file.
    pub(crate) fn stored(&self, info: NodeInfo) {
        if let Some(state) = self.state().as_mut() {
            state.points += u64::from(info.point_count);
            state.nodes.push(info);
        }
    }

    /// Points stored so far, and the points of the whole build (0 and 0 before it counted).
    pub fn points(&self) -> (u64, u64) {
        self.state()
            .as_ref()
            .map_or((0, 0), |state| (state.points, state.point_count))
    }

    /// Up to `max_points` of the points stored so far, coarse levels first: every node of a
    /// level while the whole level fits, then that level's nodes in key order while they fit.
    /// Each node is read and checked as a render reads it.
    pub fn read_points(&self, max_points: u64) -> Result<Vec<NodePoints>, LodError> {
        let Some((store, cube, mut nodes)) = self.state().as_ref().map(|state| {
            (
                state.store.clone(),
                state.cube,
                state
                    .nodes
                    .iter()
                    .filter(|n| n.point_count > 0)
                    .copied()
                    .collect::<Vec<_>>(),
            )
        }) else {
            return Ok(Vec::new());
        };
        nodes.sort_unstable_by_key(|n| (n.key.level, n.key.to_bytes()));
        let mut chosen = Vec::new();
        let mut total = 0u64;
        for level in nodes.chunk_by(|a, b| a.key.level == b.key.level) {
            let level_points: u64 = level.iter().map(|n| u64::from(n.point_count)).sum();
            if total + level_points <= max_points {
                chosen.extend_from_slice(level);
                total += level_points;
                continue;
            }
            for node in level {
                if total + u64::from(node.point_count) > max_points {
                    break;
                }
                chosen.push(*node);
                total += u64::from(node.point_count);
            }
            break;
        }
        // On the calling thread: the build keeps the shared thread pool busy with chunks that
        // take seconds each, so work queued there would wait for them.
        chosen
            .iter()
            .map(|info| {
                let bytes = store.read_range(info)?;
                decode_node(&cube, info.key, info.point_count, &bytes)
            })
            .collect()
    }
}
