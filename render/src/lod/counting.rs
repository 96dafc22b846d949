//! The counting pass, the only pass over the source: every point checked, counted into a
//! coarse grid of the root cube (the buckets) and written as a spill record to its bucket's
//! files, with the dataset's statistics. Partitions are then unions of whole buckets
//! (`plan.rs`), so the points are not read, or decoded, a second time.
//!
//! A block of points has its buckets and records made on all cores; a thread of its own
//! appends each block's records to the buckets' buffers (and hands full buffers to the spill
//! writer's thread) while the next block is made: reading, scattering and writing overlap.
//! A bucket's records go to files of at most [`BUCKET_SEGMENT_POINTS`], so that a partition split
//! on disk holds one segment beside its children at a time.

use std::ops::Range;
use std::path::PathBuf;
use std::sync::mpsc;
use std::time::Duration;

use rayon::prelude::*;

use super::error::LodError;
use super::file_facts::{FactsGathering, FileFacts};
use super::key::RootCube;
use super::memory::MemoryMeter;
use super::pause;
use super::point::{RecordLayout, MAX_RECORD_BYTES};
use super::source::PointBatch;
use super::spill::{SpillDir, SpillWriter};
use super::stats::DatasetStats;
use super::thread_cpu::{thread_cpu, thread_cpu_since, with_readers_counted, CountingThreadsCpu};
use crate::cloud::WorldBounds;

/// The finest bucket grid: 16 cells per axis, at most 4,096 buckets (each a file at least,
/// and a buffer while the pass writes them).
pub const MAX_COUNT_LEVEL: u32 = 4;
/// Points a bucket's file holds at most (about 0.9 GB of grid records); more go to another.
pub const BUCKET_SEGMENT_POINTS: u64 = 1 << 25;
/// Points a thread of the pool makes buckets and records of in a block, and the fewest a
/// block holds.
const RECORD_BLOCK_POINTS: usize = 1 << 13;
/// Points of one task making a block's buckets and records: one pass over them.
const PER_TASK: usize = 1 << 11;

/// Points of a block, whose buckets and records are made at once on every thread of the pool:
/// [`RECORD_BLOCK_POINTS`] a thread, so that each block keeps every thread busy several
/// tasks long, within a sixteenth of `budget` for the three blocks the pass holds.
fn block_points(record_bytes: usize, budget: u64) -> usize {
    let allowed = budget / 16 / (3 * block_bytes_per_point(record_bytes) as u64);
    (rayon::current_num_threads() * RECORD_BLOCK_POINTS)
        .min(allowed as usize)
        .max(RECORD_BLOCK_POINTS)
}

/// Bytes of a block a point: its bucket and its record of `record_bytes`, whose space is
/// reserved as if it held a world position.
fn block_bytes_per_point(record_bytes: usize) -> usize {
    4 + record_bytes.max(MAX_RECORD_BYTES)
}

/// What the pass's blocks hold within `budget`, three at most (one made, one queued, one
/// scattered): each point's bucket and its record of `record_bytes`.
pub fn counting_blocks_bytes(record_bytes: usize, budget: u64) -> u64 {
    3 * (block_points(record_bytes, budget) * block_bytes_per_point(record_bytes)) as u64
}

/// Points per cell of the bucket grid at `level`, cells in x-fastest order.
pub struct CountGrid {
    pub level: u32,
    pub counts: Vec<u64>,
    /// Points a bucket's file holds at most ([`BUCKET_SEGMENT_POINTS`] in a build).
    pub segment_points: u64,
}

impl CountGrid {
    pub fn index(level: u32, cell: glam::UVec3) -> usize {
        (cell.x as usize) | ((cell.y as usize) << level) | ((cell.z as usize) << (2 * level))
    }

    /// Bytes of a grid of `level` with its planning pyramid and partition lookup (8 + 8/7 + 4 a
    /// cell).
    pub fn planning_bytes(level: u32) -> u64 {
        (1u64 << (3 * level)) * 14
    }

    /// The files bucket `bucket` was written to, in the order its points were.
    pub fn bucket_files(&self, spill: &SpillDir, bucket: usize) -> Vec<PathBuf> {
        let segments = self.counts[bucket].div_ceil(self.segment_points);
        (0..segments)
            .map(|segment| bucket_path(spill, bucket, segment))
            .collect()
    }
}

pub(super) fn bucket_path(spill: &SpillDir, bucket: usize, segment: u64) -> PathBuf {
    spill.file(&bucket_name(bucket, segment))
}

fn bucket_name(bucket: usize, segment: u64) -> String {
    format!("bucket-{bucket}-{segment}.bin")
}

/// How far outside the declared bounds a point may lie and still count as inside: bounds from
/// file headers are rounded to the files' scale.
fn tolerance(cube: &RootCube) -> f64 {
    cube.side * 1e-9
}

/// The box a point must lie in: the declared bounds, widened by the tolerance.
#[derive(Clone, Copy)]
struct Allowed {
    lo: glam::DVec3,
    hi: glam::DVec3,
}

impl Allowed {
    fn new(bounds: &WorldBounds, cube: &RootCube) -> Self {
        let tol = tolerance(cube);
        Self {
            lo: bounds.min - tol,
            hi: bounds.max + tol,
        }
    }

    /// The error of the source's point `index` at `p`, if it is not finite or lies outside.
    #[inline]
    fn check(&self, p: glam::DVec3, index: u64) -> Result<(), LodError> {
        if p.is_finite() && !p.cmplt(self.lo).any() && !p.cmpgt(self.hi).any() {
            return Ok(());
        }
        Err(self.refusal(p, index))
    }

    #[cold]
    fn refusal(&self, p: glam::DVec3, index: u64) -> LodError {
        if !p.is_finite() {
            return LodError::NonFinitePoint {
                index,
                position: p.to_array(),
            };
        }
        LodError::PointOutsideBounds {
            index,
            position: p.to_array(),
            min: self.lo.to_array(),
            max: self.hi.to_array(),
        }
    }
}

/// What a task of a block found: the facts of its points, or the first point it refused
/// (its index in the source) with the error.
type TaskFacts = Result<FileFacts, (u64, LodError)>;

/// Two tasks' findings as one: both facts, or the refusal of the earlier point.
fn merge_tasks(a: TaskFacts, b: TaskFacts) -> TaskFacts {
    match (a, b) {
        (Ok(mut a), Ok(b)) => {
            a.merge(&b);
            Ok(a)
        }
        (Err(a), Err(b)) => Err(if b.0 < a.0 { b } else { a }),
        (Err(e), Ok(_)) | (Ok(_), Err(e)) => Err(e),
    }
}

/// Points of a batch with their buckets and their spill records, made on all cores; or,
/// with `checkpoint`, the points read so far and their statistics, at the start of a part of
/// the source.
#[derive(Default)]
struct RecordBlock {
    buckets: Vec<u32>,
    records: Vec<u8>,
    checkpoint: Option<(u64, DatasetStats)>,
}

/// Where a counting pass starts: at the first point, or where an earlier run of the build
/// recorded a checkpoint, with the counts and statistics of the points before it.
pub struct CountingStart {
    pub read: u64,
    pub counts: Vec<u64>,
    pub stats: Option<DatasetStats>,
}

impl CountingStart {
    pub fn fresh(level: u32) -> Self {
        Self {
            read: 0,
            counts: vec![0; 1 << (3 * level)],
            stats: None,
        }
    }
}

/// Told at the start of each part of the source after the first, once every record before it
/// is in its bucket's files: the points read, the counts per bucket and the statistics.
pub type Checkpoint<'c> = dyn Fn(u64, &[u64], &DatasetStats) -> Result<(), LodError> + Sync + 'c;

/// What making a block's records needs beside the block: the bucket grid's level in the cube,
/// the records' layout, the box every point must lie in, and the index in the source of the
/// batch's first point.
#[derive(Clone, Copy)]
struct Making<'m> {
    level: u32,
    cube: &'m RootCube,
    layout: RecordLayout,
    allowed: Allowed,
    first: u64,
}

impl RecordBlock {
    /// Checks each point of `range` and makes its bucket and record, in one pass over the
    /// points, which also gathers their facts: the first point refused (the lowest index)
    /// is the block's error.
    fn fill(
        &mut self,
        batch: &PointBatch<'_>,
        range: Range<usize>,
        making: Making<'_>,
    ) -> Result<FileFacts, LodError> {
        let (level, cube, layout) = (making.level, making.cube, making.layout);
        let record_bytes = layout.record_bytes();
        // Blocks come back to be filled again: the records written over, never zeroed again.
        self.buckets.resize(range.len(), 0);
        self.records.resize(range.len() * record_bytes, 0);
        let has_rgb = batch.rgb.is_some();
        self.records
            .par_chunks_mut(PER_TASK * record_bytes)
            .zip(self.buckets.par_chunks_mut(PER_TASK))
            .enumerate()
            .map(|(task, (out, buckets))| {
                let start = range.start + task * PER_TASK;
                let mut facts = FileFacts::default();
                let records = out.chunks_exact_mut(record_bytes);
                for (j, (record, bucket)) in records.zip(buckets).enumerate() {
                    let i = start + j;
                    let index = making.first + i as u64;
                    let p = batch.raw_point(i);
                    making
                        .allowed
                        .check(p.position, index)
                        .map_err(|e| (index, e))?;
                    facts.add_point(p.position, has_rgb.then_some(p.rgb));
                    *bucket = CountGrid::index(level, cube.cell_at(p.position, level)) as u32;
                    let row = batch.row(i, layout.row_bytes);
                    layout.write(&p, row, record).map_err(|e| (index, e))?;
                }
                Ok(facts)
            })
            .reduce(|| Ok(FileFacts::default()), merge_tasks)
            .map_err(|(_, error)| error)
    }
}

/// Reads `source` once from `start`: checks every point, counts it into the bucket grid of
/// `level`, writes its record to its bucket's files (of at most `segment_points` each)
/// through buffers of at most `buffer_bytes`, and gathers the statistics; `checkpoint` is told
/// at each part of the source. Returns the CPU time of each of the pass's own threads beside.
#[allow(clippy::too_many_arguments)]
pub fn count_points(
    gathering: &FactsGathering<'_>,
    cube: &RootCube,
    level: u32,
    meter: &MemoryMeter,
    spill: &SpillDir,
    buffer_bytes: u64,
    segment_points: u64,
    start: CountingStart,
    checkpoint: Option<&Checkpoint<'_>>,
) -> Result<(CountGrid, DatasetStats, CountingThreadsCpu), LodError> {
    // The parts' facts are gathered by the tasks that make the records, not by the source.
    let source = gathering.source();
    let walker_start = thread_cpu();
    // A third `buffer_bytes` lets the written buffers be filled again (`SpillWriter`), where
    // the budget has it.
    let reservation = meter
        .try_reserve(3 * buffer_bytes, "the buckets' write buffers")
        .or_else(|_| meter.try_reserve(2 * buffer_bytes, "the buckets' write buffers"))?;
    let block_points = block_points(spill.layout().record_bytes(), meter.budget());
    let blocks_bytes = counting_blocks_bytes(spill.layout().record_bytes(), meter.budget());
    let _blocks = meter.try_reserve(blocks_bytes, "blocks of spill records")?;
    let buckets = 1usize << (3 * level);
    // Every bucket can take every point: as many segments each as the whole source fills.
    let segments = source.point_count().div_ceil(segment_points).max(1) as usize;
    let targets = Targets {
        segments,
        segment_points,
    };
    let folder = spill.path().to_path_buf();
    let writer = SpillWriter::named(
        spill,
        buckets * segments,
        move |target| folder.join(bucket_name(target / segments, (target % segments) as u64)),
        buffer_bytes as usize,
        reservation,
    );
    let allowed = Allowed::new(&source.bounds(), cube);
    let layout = spill.layout();
    let mut stats = start.stats;
    let mut read = start.read;
    let mut batches = 0u64;
    let parts = source.part_starts();
    let first = start.read;
    let counts = start.counts;
    let (walked, scattered) = std::thread::scope(|scope| {
        let (blocks, received) = mpsc::sync_channel::<RecordBlock>(1);
        let (spare_sender, spare) = mpsc::channel::<RecordBlock>();
        let record_bytes = layout.record_bytes();
        let scattering = scope.spawn(move || {
            let channels = (received, spare_sender);
            scatter(writer, counts, targets, record_bytes, channels, checkpoint)
        });
        let walked = with_readers_counted(|| {
            source.for_each_batch_from(first, &mut |batch| {
                pause::at("counting", batches);
                batches += 1;
                if read > first && parts.binary_search(&read).is_ok() {
                    if let Some(stats) = stats.as_ref().filter(|_| checkpoint.is_some()) {
                        let marker = RecordBlock {
                            checkpoint: Some((read, stats.clone())),
                            ..RecordBlock::default()
                        };
                        if blocks.send(marker).is_err() {
                            return Err(LodError::Source("the spill writing stopped".into()));
                        }
                    }
                }
                batch.check_lengths(layout.row_bytes)?;
                let stats = stats.get_or_insert_with(|| DatasetStats::new(batch.rgb.is_some()));
                if stats.has_rgb != batch.rgb.is_some() {
                    return Err(LodError::Source(format!(
                        "batch at point {read} {} RGB unlike the batches before it",
                        if batch.rgb.is_some() { "has" } else { "lacks" }
                    )));
                }
                let making = Making {
                    level,
                    cube,
                    layout,
                    allowed,
                    first: read,
                };
                let mut start = 0;
                while start < batch.len() {
                    // A block ends where a part of the source does, so that its facts are
                    // that part's.
                    let part_end = gathering
                        .next_start(read + start as u64)
                        .map_or(usize::MAX, |next| (next - read) as usize);
                    let end = (start + block_points).min(batch.len()).min(part_end);
                    let range = start..end;
                    start = end;
                    let mut block = spare.try_recv().unwrap_or_default();
                    // The block's counts are gathered in the pool beside its records, not on
                    // this thread, whose work a point bounds the pass on any number of cores.
                    let (filled, ()) = rayon::join(
                        || block.fill(&batch, range.clone(), making),
                        || stats.add_counts(&batch, range.clone()),
                    );
                    let facts = filled?;
                    stats.add_facts(&facts);
                    gathering.add(read + range.start as u64, &facts);
                    if blocks.send(block).is_err() {
                        // The scattering thread stopped on an error, which is returned below.
                        return Err(LodError::Source("the spill writing stopped".into()));
                    }
                }
                read += batch.len() as u64;
                Ok(())
            })
        });
        drop(blocks);
        let scattered = scattering.join().unwrap_or_else(|_| {
            Err(LodError::spill(
                spill.path(),
                std::io::Error::other("the counting pass's scattering thread panicked"),
            ))
        });
        (walked, scattered)
    });
    // The scattering thread's error is the cause of any the walk returned after it.
    let scattered = scattered?;
    let (walked, source_reader) = walked;
    walked?;
    let cpu = CountingThreadsCpu {
        walker: thread_cpu_since(walker_start),
        scatterer: scattered.scatterer,
        spill_writer: scattered.spill_writer,
        checkpoint_recorder: scattered.checkpoint_recorder,
        source_reader,
    };
    if read != source.point_count() {
        return Err(LodError::CountMismatch {
            declared: source.point_count(),
            read,
            pass: "counting",
        });
    }
    Ok((
        CountGrid {
            level,
            counts: scattered.counts,
            segment_points,
        },
        stats.unwrap_or_else(|| DatasetStats::new(false)),
        cpu,
    ))
}

/// The counts per bucket once every record is in its files, with the CPU time of the threads
/// that put them there.
struct Scattered {
    counts: Vec<u64>,
    scatterer: Duration,
    spill_writer: Duration,
    checkpoint_recorder: Duration,
}

/// How the writer's files are numbered: `segments` a bucket, bucket by bucket.
#[derive(Clone, Copy)]
struct Targets {
    segments: usize,
    segment_points: u64,
}

/// Appends every block's records to their buckets' files (a bucket's next segment once one
/// is full) and adds them to `counts`; each block goes back through `spare` to be filled
/// again. At a checkpoint's marker, every record so far is handed to the files, and the
/// checkpoint (syncing them, then recording it) runs on a thread of its own while the next
/// records are scattered: a sync waits on the disk, which would stall the decoding.
fn scatter(
    mut writer: SpillWriter<'_>,
    mut counts: Vec<u64>,
    targets: Targets,
    record_bytes: usize,
    (blocks, spare): (mpsc::Receiver<RecordBlock>, mpsc::Sender<RecordBlock>),
    checkpoint: Option<&Checkpoint<'_>>,
) -> Result<Scattered, LodError> {
    let (spill_writer, checkpoint_recorder) = std::thread::scope(|scope| {
        let (marks, marked) = mpsc::channel::<CountedSoFar>();
        let recording =
            checkpoint.map(|checkpoint| scope.spawn(move || record(marked, checkpoint)));
        let scattered = (|| {
            for mut block in blocks {
                let marker = block.checkpoint.take().filter(|_| recording.is_some());
                if let Some((read, stats)) = marker {
                    writer.settle()?;
                    if marks.send((read, counts.clone(), stats)).is_err() {
                        // The recording stopped on an error, which is returned below.
                        break;
                    }
                    continue;
                }
                let records = block.records.chunks_exact(record_bytes);
                for (&bucket, record) in block.buckets.iter().zip(records) {
                    let count = &mut counts[bucket as usize];
                    // Points beyond the declared count stay in the last segment; the pass
                    // refuses the source once it has read them.
                    let segment =
                        ((*count / targets.segment_points) as usize).min(targets.segments - 1);
                    *count += 1;
                    writer.push_record(bucket as usize * targets.segments + segment, record)?;
                }
                let _ = spare.send(block);
            }
            writer.finish()
        })();
        drop(marks);
        let recorded = recording.map_or(Ok(Duration::ZERO), |thread| {
            thread.join().unwrap_or_else(|_| {
                Err(LodError::Source(
                    "the thread recording the counting checkpoints panicked".into(),
                ))
            })
        });
        // A checkpoint's error is the cause of a scattering stopped after it.
        let recorder = recorded?;
        Ok::<_, LodError>((scattered?, recorder))
    })?;
    Ok(Scattered {
        counts,
        scatterer: thread_cpu().unwrap_or_default(),
        spill_writer,
        checkpoint_recorder,
    })
}

/// A checkpoint's points read, counts per bucket and statistics, its records in their files.
type CountedSoFar = (u64, Vec<u64>, DatasetStats);

/// Records each checkpoint `marked` hands over; where several wait, only the latest, which
/// covers the points of those before it.
fn record(
    marked: mpsc::Receiver<CountedSoFar>,
    checkpoint: &Checkpoint<'_>,
) -> Result<Duration, LodError> {
    let mut checkpoints = 0;
    while let Ok(mut counted) = marked.recv() {
        while let Ok(later) = marked.try_recv() {
            counted = later;
        }
        let (read, counts, stats) = counted;
        checkpoint(read, &counts, &stats)?;
        pause::at("checkpoint", checkpoints);
        checkpoints += 1;
    }
    Ok(thread_cpu().unwrap_or_default())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lod::{GeneratedSource, PointSource};

    /// Every point is written once, to its bucket's files in segments of the size asked,
    /// and the counts are the records the files hold.
    #[test]
    fn every_point_goes_to_its_buckets_segments() {
        let dir = tempfile::tempdir().expect("tempdir");
        let source = GeneratedSource::terrain(10_000, 1);
        // Parts that start inside the source's first batch.
        let parts = vec![0, 3_000, 7_777];
        let cube = RootCube::around(&source.bounds()).expect("cube");
        let meter = MemoryMeter::new(64 << 20);
        let spill = SpillDir::create(dir.path(), RecordLayout::for_grid(None, 0)).expect("spill");
        let gathering = FactsGathering::with_starts(&source, parts.clone());
        let (grid, stats, cpu) = count_points(
            &gathering,
            &cube,
            1,
            &meter,
            &spill,
            1 << 16,
            1_000,
            CountingStart::fresh(1),
            None,
        )
        .expect("counted");
        assert!(!cpu.walker.is_zero() && !cpu.scatterer.is_zero(), "{cpu:?}");
        assert!(!cpu.spill_writer.is_zero(), "{cpu:?}");
        assert!(cpu.ceiling_points_per_s(10_000).is_some_and(|c| c > 0.0));
        assert_eq!(grid.counts.len(), 8);
        assert_eq!(grid.counts.iter().sum::<u64>(), 10_000);
        assert_eq!(
            stats.class_counts.iter().sum::<u64>(),
            10_000,
            "every point seen"
        );
        // The facts and statistics the records' tasks gathered are those of a pass of their own.
        let facts = gathering.into_facts();
        let alone = FactsGathering::with_starts(&source, parts);
        let mut all = DatasetStats::new(true);
        alone
            .for_each_batch(&mut |batch| {
                all.add(&batch);
                Ok(())
            })
            .expect("read");
        assert_eq!(facts.len(), 3);
        assert_eq!(facts, alone.into_facts());
        assert_eq!(stats, all);
        let record = spill.layout().record_bytes() as u64;
        let mut segmented = 0;
        for (bucket, &count) in grid.counts.iter().enumerate() {
            let files = grid.bucket_files(&spill, bucket);
            assert_eq!(files.len() as u64, count.div_ceil(1_000));
            segmented += usize::from(files.len() > 1);
            let mut left = count;
            for file in &files {
                let bytes = std::fs::metadata(file).expect("a segment").len();
                assert_eq!(bytes, left.min(1_000) * record, "{}", file.display());
                left -= left.min(1_000);
            }
            // Each point in its bucket's cell.
            let mut rows = crate::lod::attributes::AttributeRows::new(0);
            let points = crate::lod::spill::read_all(&files, spill.layout(), count, &mut rows)
                .expect("read");
            for p in points {
                assert_eq!(CountGrid::index(1, cube.cell_at(p.position, 1)), bucket);
            }
        }
        assert!(segmented > 0, "a bucket over a segment");
    }
}
