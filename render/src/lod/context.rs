//! `BuildContext`: what every stage of one build shares, the unfinished subtree roots
//! waiting in spill files for the levels above them, and how a unit of the build finishes.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::atomic::AtomicUsize;
use std::sync::Mutex;

use super::attributes::AttributeRows;
use super::error::LodError;
use super::journal::{sync_dir, BuildJournal, UnitKind, WaitingRoot};
use super::key::{NodeKey, RootCube};
use super::local::{KeptRoot, LocalBuilder, SubtreeRoot};
use super::memory::MemoryMeter;
use super::options::LodBuildOptions;
use super::regions::Region;
use super::sink::{EncodedNode, NodeSink, UnitDone};
use super::spill::SpillDir;

/// A subtree root whose own points wait in a spill file until its parent samples from them.
#[derive(Debug)]
pub struct Pending {
    pub root: WaitingRoot,
    pub path: PathBuf,
}

pub struct BuildContext<'a> {
    pub cube: RootCube,
    pub options: &'a LodBuildOptions,
    pub meter: &'a MemoryMeter,
    pub spill: &'a SpillDir,
    pub sink: &'a NodeSink<'a>,
    pub journal: &'a BuildJournal,
    /// The plan's partition size: a partition far above it is split before it is built.
    pub max_partition_points: u64,
    pub pending: Mutex<BTreeMap<NodeKey, Pending>>,
    /// Partitions that were too large for the budget and split on disk.
    pub partitions_split: AtomicUsize,
    /// The partitions built so far, each with its subtree root as stored for a store update
    /// (`regions.rs`).
    pub regions: Mutex<Vec<Region>>,
}

impl BuildContext<'_> {
    /// A builder of points whose attribute rows are `rows`.
    pub fn local_builder<'r>(&'r self, rows: &'r AttributeRows) -> LocalBuilder<'r> {
        LocalBuilder {
            cube: self.cube,
            max_leaf_points: self.options.max_leaf_points,
            sample_grid: self.options.sample_grid,
            sink: self.sink,
            rows,
        }
    }

    /// The spill file where the subtree root `key` waits for the level above.
    pub fn root_path(&self, key: NodeKey) -> PathBuf {
        self.spill.file(&format!("root-{key}.bin"))
    }

    /// Finishes a unit of `kind`: its `region` stored and recorded with its subtree root
    /// (`key`, `root`), which is stored too where it is the octree's root, else parked in a
    /// spill file (synced before the unit is recorded) for the level above; `rows` are the
    /// points' attribute rows. A partition's `kept` roots (its children's) are stored with it
    /// and listed as the store's regions; a partition without them (a leaf) is a region
    /// itself, its root kept.
    pub fn finish_unit(
        &self,
        kind: UnitKind,
        mut region: Vec<EncodedNode>,
        key: NodeKey,
        root: SubtreeRoot,
        rows: &AttributeRows,
        mut kept: Vec<KeptRoot>,
    ) -> Result<(), LodError> {
        let mut parked = None;
        // A region's subtree root is kept as it is now, before the levels above sample from
        // it, so that an update samples them again without the region's points.
        if kind == UnitKind::Partition && kept.is_empty() && key.level > 0 {
            kept.push(KeptRoot {
                key,
                points: root.points.len() as u64,
                root: self
                    .sink
                    .encode(key, &root.points, root.sample_grid, rows)?,
            });
        }
        let whole_octree = kind == UnitKind::Partition && kept.is_empty();
        let root_points = root.points.len() as u64;
        if key.level == 0 {
            region.push(
                self.sink
                    .encode(key, &root.points, root.sample_grid, rows)?,
            );
        } else {
            let path = self.root_path(key);
            let synced = self.journal.is_enabled();
            let (bytes, checksum) = self.spill.write_file(&path, &root.points, rows, synced)?;
            if synced {
                sync_dir(self.spill.path())?;
            }
            let waiting = WaitingRoot {
                count: root.points.len() as u64,
                sample_grid: root.sample_grid,
                bytes,
                checksum,
            };
            parked = Some(Pending {
                root: waiting,
                path,
            });
        }
        let done = UnitDone {
            kind,
            key,
            waiting: parked.as_ref().map(|p| p.root),
        };
        let counts: Vec<(NodeKey, u64)> = kept.iter().map(|k| (k.key, k.points)).collect();
        let kept_roots =
            self.sink
                .store(region, done, kept.into_iter().map(|k| k.root).collect())?;
        if kind == UnitKind::Partition {
            let mut regions = self
                .regions
                .lock()
                .unwrap_or_else(|poisoned| poisoned.into_inner());
            regions.extend(
                counts
                    .iter()
                    .zip(kept_roots)
                    .map(|(&(key, points), root)| Region {
                        key,
                        points,
                        root: Some(root),
                    }),
            );
            if whole_octree {
                // The octree's root as a leaf: nothing above samples from it.
                regions.push(Region {
                    key,
                    points: root_points,
                    root: None,
                });
            }
        }
        if let Some(pending) = parked {
            self.pending
                .lock()
                .unwrap_or_else(|poisoned| poisoned.into_inner())
                .insert(key, pending);
        }
        Ok(())
    }
}
