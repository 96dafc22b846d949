//! Where a build resumes: in its counting pass, at the last part of the source (a file) it
//! checkpointed, its bucket files cut back to the checkpoint; after it, the journal's units replayed and checked against what is on disk
//! before anything of theirs is trusted. Each stored node's record and attributes section is
//! read back and its checksums checked, each subtree root waiting in a spill file is checked
//! against the length and checksum its unit recorded, and each partition still to build has
//! the files of the length its points take. Anything amiss starts the build over: a unit's
//! inputs are removed once it is recorded, so it cannot be redone alone.

use std::collections::{BTreeMap, HashMap, HashSet};
use std::fs::OpenOptions;
use std::path::{Path, PathBuf};

use super::codec::check_node;
use super::context::Pending;
use super::counting::{bucket_path, CountGrid, CountingStart};
use super::hierarchy::NodeInfo;
use super::journal::{Counted, Replay, UnitKind, WaitingRoot};
use super::key::NodeKey;
use super::partitions::{partition_files, partition_path, split_children};
use super::plan::{plan_partitions, Partition};
use super::records::NodeRecords;
use super::spill::{file_checksum, SpillDir};
use super::stats::DatasetStats;
use super::store::LodStore;

/// Nodes whose records are read back at once while they are checked.
const CHECK_BATCH_NODES: usize = 256;

/// What the build derived before it read the journal; the counting record must agree.
pub struct Expected {
    pub level: u32,
    pub segment_points: u64,
    pub point_count: u64,
    pub max_partition_points: u64,
}

/// A build's state after its counting pass: where a fresh build starts its partitions, or
/// where a resumed one takes up again.
pub struct Resumed {
    pub stats: DatasetStats,
    /// Partitions to build, with their files.
    pub partitions: Vec<(Partition, Vec<PathBuf>)>,
    /// Nodes stored by the run resumed, and the payload bytes they take.
    pub nodes: Vec<NodeInfo>,
    pub payload_end: u64,
    /// Subtree roots waiting for the level above.
    pub waiting: BTreeMap<NodeKey, Pending>,
    /// Units taken from the run resumed.
    pub units: usize,
}

impl Resumed {
    /// A build that has just counted: every partition of `grid`'s plan to build.
    pub fn counted(
        grid: &CountGrid,
        stats: DatasetStats,
        expected: &Expected,
        spill: &SpillDir,
    ) -> Self {
        let plan = plan_partitions(grid, expected.max_partition_points);
        Self {
            stats,
            partitions: partition_files(&plan, grid, spill),
            nodes: Vec::new(),
            payload_end: 0,
            waiting: BTreeMap::new(),
            units: 0,
        }
    }

    /// Where the run `replay` recorded stopped, once everything it lists is checked; else why
    /// the build starts over.
    pub fn from_replay(
        replay: Replay,
        expected: &Expected,
        store: &LodStore,
        spill: &SpillDir,
    ) -> Result<Self, String> {
        let counted = replay.counted;
        if counted.level != expected.level
            || counted.segment_points != expected.segment_points
            || counted.points_read != expected.point_count
            || counted.counts.iter().sum::<u64>() != expected.point_count
        {
            return Err("its counting record is of another plan".into());
        }
        let grid = CountGrid {
            level: counted.level,
            counts: counted.counts,
            segment_points: counted.segment_points,
        };
        let mut resumed = Self::counted(&grid, counted.stats, expected, spill);
        let mut built = HashSet::new();
        let mut splits = HashMap::new();
        let mut consumed = Vec::new();
        resumed.units = replay.units.len();
        for unit in replay.units {
            resumed.payload_end = resumed.payload_end.max(unit.payload_end);
            match unit.kind {
                UnitKind::Partition => {
                    built.insert(unit.key);
                }
                UnitKind::Split => {
                    splits.insert(unit.key, unit.children);
                }
                UnitKind::Parent => {
                    for i in 0..8 {
                        if let Some(child) = resumed.waiting.remove(&unit.key.child(i)) {
                            consumed.push(child.path);
                        }
                    }
                }
            }
            if let Some(root) = unit.waiting {
                let path = spill.file(&format!("root-{}.bin", unit.key));
                resumed.waiting.insert(unit.key, Pending { root, path });
            }
            resumed.nodes.extend(unit.nodes);
        }
        let row_bytes = spill.layout().row_bytes;
        check_nodes(store, &resumed.nodes, resumed.payload_end, row_bytes)?;
        let record_bytes = spill.layout().record_bytes() as u64;
        for pending in resumed.waiting.values() {
            check_waiting(&pending.root, &pending.path, record_bytes)?;
        }
        let planned = std::mem::take(&mut resumed.partitions);
        resumed.partitions = remaining(planned, &built, &splits, spill, record_bytes)?;
        // Inputs of recorded units the stopped run had not removed yet.
        remove_if_present(consumed)?;
        Ok(resumed)
    }
}

/// Where the counting pass takes up from `counted`, a checkpoint of an earlier run: each
/// bucket's files cut to the records the checkpoint counted (a stopped run wrote past it), a
/// file shorter than that refusing the checkpoint.
pub fn counting_start(
    counted: Counted,
    expected: &Expected,
    spill: &SpillDir,
) -> Result<CountingStart, String> {
    let cells = 1usize << (3 * expected.level);
    if counted.level != expected.level
        || counted.segment_points != expected.segment_points
        || counted.counts.len() != cells
        || counted.counts.iter().sum::<u64>() != counted.points_read
        || counted.points_read >= expected.point_count
    {
        return Err("its counting checkpoint is of another plan".into());
    }
    let record_bytes = spill.layout().record_bytes() as u64;
    let per_file = counted.segment_points;
    let segments = expected.point_count.div_ceil(per_file).max(1);
    for (bucket, &count) in counted.counts.iter().enumerate() {
        for segment in 0..segments {
            let path = bucket_path(spill, bucket, segment);
            let held = count.saturating_sub(segment * per_file).min(per_file) * record_bytes;
            if held == 0 {
                remove_if_present(vec![path])?;
                continue;
            }
            let cut = OpenOptions::new().write(true).open(&path).and_then(|file| {
                let len = file.metadata()?.len();
                if len < held {
                    return Err(std::io::Error::other(format!(
                        "{len} bytes, {held} checkpointed"
                    )));
                }
                file.set_len(held)?;
                file.sync_all()
            });
            cut.map_err(|e| format!("{}: {e}", path.display()))?;
        }
    }
    Ok(CountingStart {
        read: counted.points_read,
        counts: counted.counts,
        stats: Some(counted.stats),
    })
}

/// The partitions of `planned` still to build: those recorded as built left out, those
/// recorded as split replaced by their children, each with files of its points' length.
fn remaining(
    mut planned: Vec<(Partition, Vec<PathBuf>)>,
    built: &HashSet<NodeKey>,
    splits: &HashMap<NodeKey, [u64; 8]>,
    spill: &SpillDir,
    record_bytes: u64,
) -> Result<Vec<(Partition, Vec<PathBuf>)>, String> {
    let mut left = Vec::new();
    while let Some((partition, files)) = planned.pop() {
        let recorded = built.contains(&partition.key);
        if let Some(&counts) = splits.get(&partition.key).filter(|_| !recorded) {
            if counts.iter().sum::<u64>() != partition.count {
                return Err(format!("split {} lists other points", partition.key));
            }
            remove_if_present(files)?;
            planned.extend(split_children(partition.key, counts, |key| {
                partition_path(spill, key)
            }));
            continue;
        }
        if recorded {
            remove_if_present(files)?;
            continue;
        }
        let mut bytes = 0;
        for file in &files {
            let metadata = std::fs::metadata(file)
                .map_err(|e| format!("partition {}: {}: {e}", partition.key, file.display()))?;
            bytes += metadata.len();
        }
        if bytes != partition.count * record_bytes {
            return Err(format!(
                "partition {}'s files hold {bytes} bytes, its {} points take {}",
                partition.key,
                partition.count,
                partition.count * record_bytes
            ));
        }
        left.push((partition, files));
    }
    left.reverse();
    Ok(left)
}

/// Reads back every node's record and attributes section and checks them.
fn check_nodes(
    store: &LodStore,
    nodes: &[NodeInfo],
    payload_end: u64,
    row_bytes: usize,
) -> Result<(), String> {
    let stored: Vec<NodeInfo> = nodes
        .iter()
        .filter(|n| n.point_count > 0)
        .copied()
        .collect();
    for info in &stored {
        let ends = [
            info.offset + u64::from(info.head_len),
            info.rest_offset + u64::from(info.byte_len - info.head_len),
            info.attributes_range().end,
        ];
        if ends.iter().any(|&end| end > payload_end) {
            return Err(format!("node {} lies past its units' bytes", info.key));
        }
    }
    for batch in stored.chunks(CHECK_BATCH_NODES) {
        let records = store.read_records(batch).map_err(|e| e.to_string())?;
        for (info, record) in batch.iter().zip(&records) {
            check_node(info.key, info.point_count, record).map_err(|e| e.to_string())?;
        }
        let with_rows: Vec<NodeInfo> = batch
            .iter()
            .filter(|n| n.attributes_len > 0)
            .copied()
            .collect();
        if !with_rows.is_empty() {
            store
                .read_attribute_sections(row_bytes, &with_rows)
                .map_err(|e| e.to_string())?;
        }
    }
    Ok(())
}

fn check_waiting(root: &WaitingRoot, path: &Path, record_bytes: u64) -> Result<(), String> {
    let (bytes, checksum) = file_checksum(path).map_err(|e| e.to_string())?;
    if bytes != root.bytes || checksum != root.checksum || bytes != root.count * record_bytes {
        return Err(format!(
            "{} is not the subtree root its unit recorded",
            path.display()
        ));
    }
    Ok(())
}

fn remove_if_present(files: Vec<PathBuf>) -> Result<(), String> {
    for file in files {
        match std::fs::remove_file(&file) {
            Err(e) if e.kind() != std::io::ErrorKind::NotFound => {
                return Err(format!("{}: {e}", file.display()))
            }
            _ => {}
        }
    }
    Ok(())
}
