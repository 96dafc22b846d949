//! The partitions' local octrees, each built in memory from its buckets' files, in parallel with
//! only as many partitions in memory as the budget allows; a partition too large for the budget, or
//! much larger than the plan's partitions (a dense bucket), is split into its eight children on
//! disk first. A partition's files are removed once its build or split is recorded in the
//! journal, so a build stopped before then has them to do it again.

use std::path::PathBuf;
use std::sync::atomic::Ordering;
use std::sync::{Mutex, MutexGuard};
use std::time::Duration;

use super::attributes::AttributeRows;
use super::context::BuildContext;
use super::counting::CountGrid;
use super::error::LodError;
use super::journal::{sync_dir, UnitKind, UnitRecord};
use super::key::{NodeKey, MAX_LEVEL};
use super::memory::Reservation;
use super::options::BUILD_BYTES_PER_POINT;
use super::partition_figures::{PartitionsFigures, PartitionsTrace};
use super::pause;
use super::plan::{Partition, PartitionPlan};
use super::point::RecordLayout;
use super::scratch::{PartitionScratch, ScratchPool};
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
    // A partition's subtrees are built on every thread of the pool.
    let threads = rayon::current_num_threads();
    Ok(trace.finish(threads, threads))
}

/// How long the admitting loop waits for memory before it looks for work of the pool's to do.
const ADMIT_WAIT: Duration = Duration::from_millis(5);

/// The partitions still to build or split, largest last (taken first), how many splits are
/// under way, whose children join them, and how many units are (built or split).
struct Queue {
    partitions: Vec<(Partition, Vec<PathBuf>)>,
    splitting: usize,
    in_flight: usize,
}

impl Queue {
    fn add(&mut self, partitions: Vec<(Partition, Vec<PathBuf>)>) {
        self.partitions.extend(partitions);
        // Largest first, then by key: the same order on every run.
        self.partitions
            .sort_by(|a, b| a.0.count.cmp(&b.0.count).then(b.0.key.cmp(&a.0.key)));
    }
}

/// What the units of one partitions stage share.
struct Stage<'s, 'c> {
    ctx: &'s BuildContext<'c>,
    trace: &'s PartitionsTrace,
    queue: Mutex<Queue>,
    failed: Mutex<Option<LodError>>,
    /// Units that may hold memory at once: the pool's threads (more would wait, holding it).
    threads: usize,
    /// Buffers kept from one partition's build to the next.
    scratches: ScratchPool<'c>,
}

/// What an admitted unit does, with its memory.
enum Work<'m> {
    Split(Reservation<'m>),
    /// A build in `scratch`, kept for the next partition with its memory where `pooled`,
    /// else freed as the partition's own buffers are.
    Build {
        memory: Reservation<'m>,
        scratch: PartitionScratch,
        pooled: bool,
    },
}

/// A unit admitted: its partition and files, and its work.
type Admitted<'m> = (Partition, Vec<PathBuf>, Work<'m>);

/// Builds the partitions, largest first, each admitted once its memory is reserved and handed
/// to the pool with its reservation: no task of the pool ever waits for memory, so a thread
/// that waits for a partition's subtrees and meanwhile takes another task of the pool cannot
/// stop under a reservation of its own. Each unit that ends admits what its memory lets in;
/// this loop admits the first and, while memory or threads are short, does the pool's work.
fn build_each(
    ctx: &BuildContext<'_>,
    trace: &PartitionsTrace,
    partitions: Vec<(Partition, Vec<PathBuf>)>,
) -> Result<(), LodError> {
    let stage = Stage {
        ctx,
        trace,
        queue: Mutex::new(Queue {
            partitions: Vec::new(),
            splitting: 0,
            in_flight: 0,
        }),
        failed: Mutex::new(None),
        threads: rayon::current_num_threads(),
        scratches: ScratchPool::new(),
    };
    lock(&stage.queue).add(partitions);
    rayon::scope(|scope| loop {
        admit_all(scope, &stage);
        let queue = lock(&stage.queue);
        let done = queue.in_flight == 0 && (queue.partitions.is_empty() || stage.has_failed());
        drop(queue);
        if done {
            break;
        }
        if rayon::yield_now() != Some(rayon::Yield::Executed) {
            ctx.meter.wait_for_release(ADMIT_WAIT);
        }
    });
    let failed = stage
        .failed
        .into_inner()
        .unwrap_or_else(|poisoned| poisoned.into_inner());
    failed.map_or(Ok(()), Err)
}

impl<'c> Stage<'_, 'c> {
    fn fail(&self, error: LodError) {
        lock(&self.failed).get_or_insert(error);
    }

    fn has_failed(&self) -> bool {
        lock(&self.failed).is_some()
    }

    /// The largest partition left, with its memory, if a thread is free and its memory is
    /// free now.
    fn try_admit(&self) -> Option<Admitted<'c>> {
        if self.has_failed() {
            return None;
        }
        let mut queue = lock(&self.queue);
        if queue.in_flight >= self.threads {
            return None;
        }
        let &(partition, _) = queue.partitions.last()?;
        let admitted = needs_split(self.ctx, partition).and_then(|split| match split {
            true => self
                .reserve(split_bytes(self.ctx), "splitting a partition")
                .map(|r| r.map(Work::Split)),
            false => self.admit_build(partition),
        });
        let work = match admitted {
            Ok(work) => work?,
            Err(e) => {
                drop(queue);
                self.fail(e);
                return None;
            }
        };
        let (partition, files) = queue.partitions.pop()?;
        queue.in_flight += 1;
        queue.splitting += usize::from(matches!(work, Work::Split(_)));
        Some((partition, files, work))
    }

    /// `bytes` if they fit now, once idle scratches are dropped where they do not.
    fn reserve(&self, bytes: u64, what: &'static str) -> Result<Option<Reservation<'c>>, LodError> {
        let meter = self.ctx.meter;
        match meter.reserve_within(bytes, what, Duration::ZERO)? {
            None if self.scratches.release_idle() => {
                meter.reserve_within(bytes, what, Duration::ZERO)
            }
            reserved => Ok(reserved),
        }
    }

    /// The memory to build `partition`: a large one in a scratch kept from an earlier
    /// partition (or a new one) where its room fits beside the partition's own bytes, else the
    /// partition's bytes alone, its buffers freed as it goes.
    fn admit_build(&self, partition: Partition) -> Result<Option<Work<'c>>, LodError> {
        let layout = self.ctx.spill.layout();
        let bytes = partition_bytes(partition.count, layout);
        let what = "a partition built in memory";
        let meter = self.ctx.meter;
        if !PartitionScratch::worth_keeping(partition.count) {
            // Partitions come largest first: the ones left are small too.
            self.scratches.release_idle();
            return self.admit_unkept(bytes);
        }
        let (scratch, held) = match self.scratches.take() {
            Some((scratch, held)) => (scratch, Some(held)),
            None => (PartitionScratch::default(), None),
        };
        let extra = scratch.extra_bytes(partition.count, layout.row_bytes);
        let more = (bytes + extra).saturating_sub(held.as_ref().map_or(0, Reservation::bytes));
        if bytes + extra <= meter.largest_possible() {
            if let Some(more) = meter.reserve_within(more, what, Duration::ZERO)? {
                let memory = match held {
                    Some(mut held) => {
                        held.absorb(more);
                        held
                    }
                    None => more,
                };
                return Ok(Some(Work::Build {
                    memory,
                    scratch,
                    pooled: true,
                }));
            }
        }
        drop((scratch, held));
        self.admit_unkept(bytes)
    }

    /// `bytes` to build a partition whose buffers are freed as it goes.
    fn admit_unkept(&self, bytes: u64) -> Result<Option<Work<'c>>, LodError> {
        let reserved = self.reserve(bytes, "a partition built in memory")?;
        Ok(reserved.map(|memory| Work::Build {
            memory,
            scratch: PartitionScratch::default(),
            pooled: false,
        }))
    }
}

/// A unit counted in flight (and a split counted under way) until dropped, by a task that
/// panicked too, so that the stage ends and the panic reaches the caller.
struct Counted<'s, 'c> {
    stage: &'s Stage<'s, 'c>,
    split: bool,
}

impl Drop for Counted<'_, '_> {
    fn drop(&mut self) {
        let mut queue = lock(&self.stage.queue);
        queue.in_flight -= 1;
        queue.splitting -= usize::from(self.split);
    }
}

/// Spawns every unit that can be admitted now.
fn admit_all<'s>(scope: &rayon::Scope<'s>, stage: &'s Stage<'s, '_>) {
    while let Some((partition, files, work)) = stage.try_admit() {
        let split = matches!(work, Work::Split(_));
        let counted = Counted { stage, split };
        scope.spawn(move |scope| {
            let ctx = stage.ctx;
            let memory = match work {
                Work::Split(reservation) => {
                    let unit = stage.trace.unit(partition.key, partition.count, true);
                    // The split's writer holds its memory and releases it when done.
                    match split_partition(ctx, partition, &files, reservation) {
                        Ok(parts) => {
                            ctx.partitions_split.fetch_add(1, Ordering::Relaxed);
                            lock(&stage.queue).add(parts);
                        }
                        Err(e) => stage.fail(e),
                    }
                    unit.end();
                    None
                }
                Work::Build {
                    memory,
                    mut scratch,
                    pooled,
                } => {
                    let built =
                        build_partition(ctx, stage.trace, partition, files, &mut scratch, pooled);
                    match built {
                        Ok(()) if pooled => Some((scratch, memory)),
                        Ok(()) => Some((PartitionScratch::default(), memory)),
                        Err(e) => {
                            stage.fail(e);
                            None
                        }
                    }
                }
            };
            // Counted out (a split's children queued before), then its memory released (a
            // scratch kept with what it holds), then what that lets in admitted.
            drop(counted);
            if let Some((scratch, memory)) = memory {
                stage.scratches.put(scratch, memory);
            }
            admit_all(scope, stage);
        });
    }
}

fn lock<T>(mutex: &Mutex<T>) -> MutexGuard<'_, T> {
    mutex
        .lock()
        .unwrap_or_else(|poisoned| poisoned.into_inner())
}

/// Whether `partition` is split on disk before it is built: too large for the budget, or a
/// dense bucket far above the plan's size (split, it keeps the cores busy).
fn needs_split(ctx: &BuildContext<'_>, partition: Partition) -> Result<bool, LodError> {
    let needed = partition_bytes(partition.count, ctx.spill.layout());
    let fits = needed <= ctx.meter.largest_possible();
    let oversized =
        partition.count > 2 * ctx.max_partition_points && partition.key.level < FINEST_SPLIT_LEVEL;
    if (!fits || oversized) && partition.key.level >= MAX_LEVEL {
        return Err(LodError::TooDense {
            key: partition.key,
            count: partition.count,
        });
    }
    Ok(!fits || oversized)
}

/// Builds `partition` in the memory reserved for it, its buffers in `scratch`; those it no
/// longer needs once its points are in their runs are freed unless the scratch is `pooled`.
fn build_partition(
    ctx: &BuildContext<'_>,
    trace: &PartitionsTrace,
    partition: Partition,
    files: Vec<PathBuf>,
    scratch: &mut PartitionScratch,
    pooled: bool,
) -> Result<(), LodError> {
    let mut unit = trace.unit(partition.key, partition.count, false);
    let layout = ctx.spill.layout();
    let count = partition.count as usize;
    let mut rows =
        AttributeRows::in_buffer(layout.row_bytes, scratch.take_rows(count, layout.row_bytes));
    unit.serial(false, || {
        spill::read_all_into(
            &files,
            layout,
            partition.count,
            &mut rows,
            &mut scratch.points,
        )
    })?;
    let builder = ctx.local_builder(&rows);
    let prepared = unit.serial(false, || match pooled {
        true => {
            let PartitionScratch {
                points,
                order,
                run_of,
                ..
            } = &mut *scratch;
            builder.prepare_in(partition.key, points, order, run_of)
        }
        // Its buffers freed as soon as they are done with.
        false => builder.prepare(partition.key, std::mem::take(&mut scratch.points)),
    });
    let mut region = Vec::new();
    let mut kept = Vec::new();
    let (root, order) = builder.build_prepared(prepared, &mut region, Some(&mut kept))?;
    if let Some(order) = order.filter(|_| pooled) {
        scratch.order.entries = order.into_entries();
    }
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
    scratch.rows = rows.into_buffer();
    // Removed once the partition is recorded: a build stopped before then builds it again.
    remove_all(&files)
}

/// The write buffers and read block a split reserves.
fn split_bytes(ctx: &BuildContext<'_>) -> u64 {
    2 * split_buffer_bytes(ctx) + read_block_bytes(ctx.spill.layout())
}

fn split_buffer_bytes(ctx: &BuildContext<'_>) -> u64 {
    SPLIT_BUFFER_BYTES.min(ctx.meter.largest_possible() / 8)
}

fn remove_all(files: &[PathBuf]) -> Result<(), LodError> {
    files.iter().try_for_each(|path| spill::remove(path))
}

/// Streams a partition's files into eight files, one per child, each removed once read, in
/// the memory of `reservation` ([`split_bytes`]).
fn split_partition(
    ctx: &BuildContext<'_>,
    partition: Partition,
    files: &[PathBuf],
    reservation: Reservation<'_>,
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
    let buffer = split_buffer_bytes(ctx);
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
    if ctx.journal.is_enabled() {
        let written: Vec<PathBuf> = paths.iter().filter(|p| p.exists()).cloned().collect();
        spill::sync_files(&written)?;
        sync_dir(ctx.spill.path())?;
    }
    let commit = ctx.journal.commit();
    pause::at("split", ctx.journal.committed(UnitKind::Split));
    let queued = commit.record(&UnitRecord {
        kind: UnitKind::Split,
        key: partition.key,
        payload_end: 0,
        waiting: None,
        children: counts,
        nodes: Vec::new(),
    })?;
    ctx.sink.durable(queued)?;
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
