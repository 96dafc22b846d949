//! `BuildContext`: what every stage of one build shares, and the unfinished subtree roots
//! waiting in spill files for the levels above them.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::atomic::AtomicUsize;
use std::sync::Mutex;

use super::attributes::AttributeRows;
use super::error::LodError;
use super::key::{NodeKey, RootCube};
use super::local::LocalBuilder;
use super::memory::MemoryMeter;
use super::options::LodBuildOptions;
use super::point::RawPoint;
use super::sink::NodeSink;
use super::spill::SpillDir;

/// A subtree root whose own points wait in a spill file until its parent samples from them.
#[derive(Debug)]
pub struct Pending {
    pub count: u64,
    pub sample_grid: u32,
    pub path: PathBuf,
}

pub struct BuildContext<'a> {
    pub cube: RootCube,
    pub options: &'a LodBuildOptions,
    pub meter: &'a MemoryMeter,
    pub spill: &'a SpillDir,
    pub sink: &'a NodeSink<'a>,
    /// The plan's partition size: a partition far above it is split before it is built.
    pub max_partition_points: u64,
    pub pending: Mutex<BTreeMap<NodeKey, Pending>>,
    /// Partitions that were too large for the budget and split on disk.
    pub partitions_split: AtomicUsize,
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

    /// Finishes the root, or parks a subtree root for the level above; `rows` are the
    /// points' attribute rows.
    pub fn finish_subtree(
        &self,
        key: NodeKey,
        points: &[RawPoint],
        sample_grid: u32,
        rows: &AttributeRows,
    ) -> Result<(), LodError> {
        if key.level == 0 {
            return self.sink.emit(key, points, sample_grid, rows);
        }
        let path = self.spill.file(&format!("root-{key}.bin"));
        self.spill.write_file(&path, points, rows)?;
        let pending = Pending {
            count: points.len() as u64,
            sample_grid,
            path,
        };
        self.pending
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner())
            .insert(key, pending);
        Ok(())
    }
}
