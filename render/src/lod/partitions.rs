//! The partitions' local octrees, each built in memory from its buckets' files, in parallel with
//! only as many partitions in memory as the budget allows; a partition too large for the budget, or
//! much larger than the plan's partitions (a dense bucket), is split into its eight children on
//! disk first. A partition's files are removed once its build or split is recorded in the
//! journal, so a build stopped before then has them to do it again.

use std::path::PathBuf;

use rayon::prelude::*;

use super::attributes::AttributeRows;
use super::context::BuildContext;
use super::counting::CountGrid;
use super::error::LodError;
use super::journal::{sync_dir, UnitKind, UnitRecord};
use super::key::{NodeKey, MAX_LEVEL};
use super::options::BUILD_BYTES_PER_POINT;
use super::partition_figures::{PartitionsFigures, PartitionsTrace};
use super::pause;
use super::plan::{Partition, PartitionPlan};
use super::point::RecordLayout;
use super::spill::{self, read_block_bytes, SpillDir, SpillWriter};

/// The most bytes of write buffers when a partition is split further.
const SPLIT_BUFFER_BYTES: u64 = 8 << 20;

/// The finest level a partition that fits the budget is still split at for its size alone: that
/// of PotreeConverter's finest counting grid (128 cells an axis). Points too close together
/// for it are built as one partition when they fit, however many.
const FINEST_SPLIT_LEVEL: u8 = 7;

/// Bytes a point takes while it is built, with its attribute row (held once, beside it).
pub fn build_bytes_per_point(layout: RecordLayout) -> u64 {
    BUILD_BYTES_PER_POINT + layout.row_bytes as u64
}

/// Bytes a partition of `count` points, records in `layout`, reserves while it is built.
pub fn partition_bytes(count: u64, layout: RecordLayout) -> u64 {
    count * build_bytes_per_point(layout) + read_block_bytes(layout)
}

/// The spill file of a partition a split made.
pub fn partition_path(spill: &SpillDir, key: NodeKey) -> PathBuf {
    spill.file(&format!("partition-{key}.bin"))
}

/// Each partition of `plan` with the files of its buckets, in bucket order: the counting pass
/// wrote every point to its bucket, and a partition is a union of whole buckets.
pub fn partition_files(
    plan: &PartitionPlan,
    grid: &CountGrid,
    spill: &SpillDir,
) -> Vec<(Partition, Vec<PathBuf>)> {
    let mut files = vec![Vec::new(); plan.partitions.len()];
    for (bucket, &count) in grid.counts.iter().enumerate() {
        if count > 0 {
            files[plan.lookup[bucket] as usize].extend(grid.bucket_files(spill, bucket));
        }
    }
    plan.partitions.iter().copied().zip(files).collect()
}

/// Builds every partition, largest first, on the current rayon pool.
pub fn build_partitions(
    ctx: &BuildContext<'_>,
    partitions: Vec<(Partition, Vec<PathBuf>)>,
) -> Result<(), LodError> {
    build_partitions_traced(ctx, partitions).map(|_| ())
}

/// [`build_partitions`], with what the stage did unit by unit.
pub fn build_partitions_traced(
    ctx: &BuildContext<'_>,
    partitions: Vec<(Partition, Vec<PathBuf>)>,
) -> Result<PartitionsFigures, LodError> {
    let trace = PartitionsTrace::new();
    build_each(ctx, &trace, partitions)?;
    // A partition is built on one thread.
    Ok(trace.finish(rayon::current_num_threads(), 1))
}

fn build_each(
    ctx: &BuildContext<'_>,
    trace: &PartitionsTrace,
    mut partitions: Vec<(Partition, Vec<PathBuf>)>,
) -> Result<(), LodError> {
    partitions.sort_by(|a, b| b.0.count.cmp(&a.0.count).then(a.0.key.cmp(&b.0.key)));
    partitions
        .into_par_iter()
        .with_max_len(1)
        .try_for_each(|(partition, files)| build_partition(ctx, trace, partition, files))
}

fn build_partition(
    ctx: &BuildContext<'_>,
    trace: &PartitionsTrace,
    partition: Partition,
    files: Vec<PathBuf>,
) -> Result<(), LodError> {
    let needed = partition_bytes(partition.count, ctx.spill.layout());
    let fits = needed <= ctx.meter.largest_possible();
    // A dense bucket is a partition far above the plan's size: split, it keeps the cores busy.
    let oversized =
        partition.count > 2 * ctx.max_partition_points && partition.key.level < FINEST_SPLIT_LEVEL;
    if !fits || oversized {
        if partition.key.level >= MAX_LEVEL {
            return Err(LodError::TooDense {
                key: partition.key,
                count: partition.count,
            });
        }
        let unit = trace.unit(partition.key, partition.count, true);
        let parts = split_partition(ctx, partition, &files)?;
        unit.end();
        ctx.partitions_split
            .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        // No reservation is held here: a task that waits for memory must hold none.
        return build_each(ctx, trace, parts);
    }
    let _reservation = ctx.meter.reserve(needed, "a partition built in memory")?;
    let mut unit = trace.unit(partition.key, partition.count, false);
    let layout = ctx.spill.layout();
    let mut rows = AttributeRows::new(layout.row_bytes);
    let points = unit.serial(false, || {
        spill::read_all(&files, layout, partition.count, &mut rows)
    })?;
    let mut region = Vec::new();
    let mut kept = Vec::new();
    let root =
        ctx.local_builder(&rows)
            .build(partition.key, points, &mut region, Some(&mut kept))?;
    unit.serial(true, || {
        ctx.finish_unit(
            UnitKind::Partition,
            region,
            partition.key,
            root,
            &rows,
            kept,
        )
    })?;
    unit.end();
    // Removed once the partition is recorded: a build stopped before then builds it again.
    remove_all(&files)
}

fn remove_all(files: &[PathBuf]) -> Result<(), LodError> {
    files.iter().try_for_each(|path| spill::remove(path))
}

/// Streams a partition's files into eight files, one per child, each removed once read.
fn split_partition(
    ctx: &BuildContext<'_>,
    partition: Partition,
    files: &[PathBuf],
) -> Result<Vec<(Partition, Vec<PathBuf>)>, LodError> {
    let paths: Vec<PathBuf> = (0..8)
        .map(|i| partition_path(ctx.spill, partition.key.child(i)))
        .collect();
    // The writer appends: files a stopped split left are started again.
    for path in &paths {
        match std::fs::remove_file(path) {
            Err(e) if e.kind() != std::io::ErrorKind::NotFound => {
                return Err(LodError::spill(path, e))
            }
            _ => {}
        }
    }
    let buffer = SPLIT_BUFFER_BYTES.min(ctx.meter.largest_possible() / 8);
    let reservation = ctx.meter.reserve(
        2 * buffer + read_block_bytes(ctx.spill.layout()),
        "splitting a partition",
    )?;
    let mut writer = SpillWriter::new(ctx.spill, paths.clone(), buffer as usize, reservation);
    let mut counts = [0u64; 8];
    let level = u32::from(partition.key.level) + 1;
    let base = partition.key.cell() * 2;
    for path in files {
        let record_bytes = ctx.spill.layout().record_bytes();
        spill::for_each_block(path, ctx.spill.layout(), |block, records| {
            for (p, record) in block.iter().zip(records.chunks_exact(record_bytes)) {
                let c = ctx.cube.cell_at(p.position, level) - base;
                let i = (c.x | (c.y << 1) | (c.z << 2)) as usize;
                counts[i] += 1;
                writer.push_record(i, record)?;
            }
            Ok(())
        })?;
    }
    writer.finish()?;
    if counts.iter().sum::<u64>() != partition.count {
        return Err(LodError::SourceChanged(format!(
            "partition {} holds {} points, the counting pass counted {}",
            partition.key,
            counts.iter().sum::<u64>(),
            partition.count
        )));
    }
    let mut commit = ctx.journal.commit();
    if commit.is_enabled() {
        let written: Vec<PathBuf> = paths.iter().filter(|p| p.exists()).cloned().collect();
        spill::sync_files(&written)?;
        sync_dir(ctx.spill.path())?;
    }
    pause::at("split", ctx.journal.committed(UnitKind::Split));
    commit.record(&UnitRecord {
        kind: UnitKind::Split,
        key: partition.key,
        payload_end: 0,
        waiting: None,
        children: counts,
        nodes: Vec::new(),
    })?;
    drop(commit);
    // Removed once the split is recorded: a build stopped before then splits it again.
    remove_all(files)?;
    Ok(split_children(partition.key, counts, |key| {
        partition_path(ctx.spill, key)
    }))
}

/// The children a split of `key` left with points, each with its file at `path`.
pub fn split_children(
    key: NodeKey,
    counts: [u64; 8],
    path: impl Fn(NodeKey) -> PathBuf,
) -> Vec<(Partition, Vec<PathBuf>)> {
    (0..8)
        .filter(|&i| counts[i] > 0)
        .map(|i| {
            let child = Partition {
                key: key.child(i),
                count: counts[i],
            };
            (child, vec![path(child.key)])
        })
        .collect()
}
