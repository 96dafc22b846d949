//! `BuildProgress`: what a running build has stored so far, so that a preview can draw the
//! nodes built while the rest is still building.
//!
//! A node is listed only once its record is in the payload file, which is written with
//! positioned writes and no buffer, so every listed node reads back whole while the build
//! goes on. The nodes come partition by partition, each partition's subtree but its root (the
//! levels above still sample from it), then the levels above the partitions at the end.
//!
//! A preview is drawn again each time the build has stored another share of the points
//! ([`PREVIEW_REDRAW_SHARE`]); the number of whole shares stored is the preview's version, which
//! the local render and the daemon count alike.

use std::sync::Mutex;

use super::codec::{decode_node, NodePoints};
use super::error::LodError;
use super::hierarchy::NodeInfo;
use super::key::RootCube;
use super::store::LodStore;

/// The most points of stored nodes a preview draws: a resident cloud of about 100 MB that
/// renders in tens of milliseconds at 1080p on lavapipe.
pub const PREVIEW_STORED_POINTS: u64 = 4_000_000;

/// The share of the dataset a build stores between two redraws of the preview.
pub const PREVIEW_REDRAW_SHARE: f64 = 0.1;

/// The preview version of a build that has stored `stored` of `total` points: the whole
/// shares ([`PREVIEW_REDRAW_SHARE`]) stored, 0 before the build counted its points.
pub fn preview_version(stored: u64, total: u64) -> u32 {
    if total == 0 {
        return 0;
    }
    // Counted in integers: a float quotient such as 0.3 / 0.1 falls just short of 3.
    let shares = (1.0 / PREVIEW_REDRAW_SHARE).round().max(1.0) as u128;
    let version = u128::from(stored.min(total)) * shares / u128::from(total);
    u32::try_from(version).unwrap_or(u32::MAX)
}

/// Shared between a build and whoever watches it; empty until the build has counted its
/// points.
#[derive(Default)]
pub struct BuildProgress {
    state: Mutex<Option<Stored>>,
    /// Told the new preview version each time it moves.
    on_version: Option<Box<dyn Fn(u32) + Send + Sync>>,
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

    /// A progress that tells `on_version` the new preview version each time the build has
    /// stored another share of the points, on the build's thread, so that a watcher need not
    /// poll.
    pub fn notifying(on_version: impl Fn(u32) + Send + Sync + 'static) -> Self {
        Self {
            state: Mutex::default(),
            on_version: Some(Box::new(on_version)),
        }
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
        let moved = self.state().as_mut().and_then(|state| {
            let before = preview_version(state.points, state.point_count);
            state.points += u64::from(info.point_count);
            state.nodes.push(info);
            let after = preview_version(state.points, state.point_count);
            (after != before).then_some(after)
        });
        // Told outside the lock: the watcher may read the progress.
        if let (Some(version), Some(on_version)) = (moved, &self.on_version) {
            on_version(version);
        }
    }

    /// Points stored so far, and the points of the whole build (0 and 0 before it counted).
    pub fn points(&self) -> (u64, u64) {
        self.state()
            .as_ref()
            .map_or((0, 0), |state| (state.points, state.point_count))
    }

    /// The preview version of what is stored so far ([`preview_version`]).
    pub fn preview_version(&self) -> u32 {
        let (stored, total) = self.points();
        preview_version(stored, total)
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
        // On the calling thread: the build keeps the shared thread pool busy with partitions that
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_preview_version_counts_whole_shares_stored() {
        assert_eq!(preview_version(0, 0), 0);
        assert_eq!(preview_version(5, 0), 0);
        assert_eq!(preview_version(0, 1_000), 0);
        assert_eq!(preview_version(99, 1_000), 0);
        assert_eq!(preview_version(100, 1_000), 1);
        assert_eq!(preview_version(300, 1_000), 3);
        assert_eq!(preview_version(999, 1_000), 9);
        assert_eq!(preview_version(1_000, 1_000), 10);
        assert_eq!(preview_version(u64::MAX, u64::MAX), 10);
        assert_eq!(BuildProgress::new().preview_version(), 0);
    }
}
