//! `build_lod`: the whole build, PotreeConverter-2-like and streaming:
//!
//! 1. counting: the source read once, every point checked, counted into a coarse grid of the
//!    root cube (its buckets) and written to its bucket's spill files through bounded
//!    buffers, with the dataset's statistics;
//! 2. planning: buckets merged into partitions of at most a budget-derived number of points, so
//!    that a partition's points are its buckets' files and the source is never read again (LAZ is
//!    decoded once);
//! 3. partitions: each partition's local octree built in memory, in parallel, as many at once
//!    as the budget holds (a partition too large, or a dense bucket far above the plan's size, is
//!    split on disk first);
//! 4. upper levels: the nodes above the partitions sampled from their children up to the root;
//! 5. the hierarchy written last.
//!
//! Every buffer the builder holds is reserved from one [`MemoryMeter`] first; the source's
//! own batches are outside it. Node payloads go to the store's payload file, not to sled,
//! whose memory grows with the bytes it stores (docs/perf/lod-build.md).

use std::path::PathBuf;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Mutex;
use std::time::{Duration, Instant};

use super::checksum::checksum64;
use super::context::BuildContext;
use super::counting::{
    count_points, counting_blocks_bytes, Checkpoint, CountGrid, CountingStart,
    BUCKET_SEGMENT_POINTS, MAX_COUNT_LEVEL,
};
use super::error::LodError;
use super::file_facts::FactsGathering;
use super::hierarchy::LodHierarchy;
use super::journal::{sync_dir, BuildJournal, Counted, Replay};
use super::key::RootCube;
use super::memory::MemoryMeter;
use super::options::LodBuildOptions;
use super::partition_figures::PartitionsFigures;
use super::partitions::{build_bytes_per_point, build_partitions_traced, partition_bytes};
use super::pause;
use super::point::RecordLayout;
use super::progress::BuildProgress;
use super::regions::StoreRegions;
use super::resume::{counting_start, Expected, Resumed};
use super::sink::NodeSink;
use super::source::PointSource;
use super::spill::{sync_files, SpillDir};
use super::stats::DatasetStats;
use super::store::LodStore;
use super::thread_cpu::CountingThreadsCpu;
use super::upper::build_upper_levels;

/// The most bytes of records the counting pass buffers before it appends them to files.
const BUCKET_BUFFER_BYTES: u64 = 16 << 20;

/// Seconds each stage took.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct BuildTimings {
    /// Reading the source, with every point written to its bucket.
    pub counting: Duration,
    pub partitions: Duration,
    pub upper_levels: Duration,
    pub total: Duration,
    /// CPU time of each of the counting pass's own threads (zero where the pass was taken
    /// whole from an earlier run).
    pub counting_threads: CountingThreadsCpu,
}

#[derive(Debug, Clone)]
pub struct LodBuildReport {
    pub hierarchy: LodHierarchy,
    pub partitions: usize,
    /// Partitions split on disk before they were built: too large for the budget, or a dense
    /// bucket far above the partition size.
    pub partitions_split: usize,
    /// The partitions stage unit by unit: its parallelism and CPU time.
    pub partitions_figures: PartitionsFigures,
    /// The bucket grid's level (cells per axis = 2^level).
    pub count_level: u32,
    /// Bytes written to spill files.
    pub spilled_bytes: u64,
    /// Bytes of a point's spill record: smaller where every point lies on one LAS grid.
    pub spill_record_bytes: usize,
    /// Bytes of node records written to the store's payload file.
    pub stored_bytes: u64,
    /// Bytes of the hierarchy's record in sled.
    pub hierarchy_bytes: u64,
    /// The most bytes the builder's buffers held at once.
    pub peak_memory_bytes: u64,
    pub memory_budget_bytes: u64,
    /// The build's spill folder (removed when the build returned).
    pub spill_path: PathBuf,
    pub timings: BuildTimings,
    /// Whether the counting pass was taken up, whole or from a checkpoint, from an earlier
    /// run of this build that stopped.
    pub counting_resumed: bool,
    /// Units (partitions built or split, nodes above them) taken from that run.
    pub resumed_units: usize,
}

impl LodBuildReport {
    /// The store's bytes on disk per point: the payload file and the hierarchy's record (sled's
    /// own overhead, in a database the caller owns, is not counted).
    pub fn disk_bytes_per_point(&self) -> f64 {
        let points = self.hierarchy.point_count.max(1);
        (self.stored_bytes + self.hierarchy_bytes) as f64 / points as f64
    }
}

/// The context of a build or update storing through `sink` (of its cube and journal) whose
/// partitions hold about `max_partition_points`, no subtree root waiting yet.
pub(super) fn build_context<'a>(
    options: &'a LodBuildOptions,
    meter: &'a MemoryMeter,
    spill: &'a SpillDir,
    sink: &'a NodeSink<'a>,
    max_partition_points: u64,
) -> BuildContext<'a> {
    BuildContext {
        cube: sink.cube(),
        options,
        meter,
        spill,
        sink,
        journal: sink.journal(),
        max_partition_points,
        pending: Mutex::new(Default::default()),
        partitions_split: AtomicUsize::new(0),
        regions: Mutex::new(Vec::new()),
    }
}

/// Builds the level-of-detail store of `source` into `store`, replacing what it held.
pub fn build_lod(
    source: &dyn PointSource,
    store: &LodStore,
    options: &LodBuildOptions,
) -> Result<LodBuildReport, LodError> {
    build_lod_watched(source, store, options, &BuildProgress::new())
}

/// [`build_lod`], listing each node in `progress` as it is stored.
pub fn build_lod_watched(
    source: &dyn PointSource,
    store: &LodStore,
    options: &LodBuildOptions,
    progress: &BuildProgress,
) -> Result<LodBuildReport, LodError> {
    on_threads(options, || build_on_pool(source, store, options, progress))
}

/// Runs `work` once `options` are valid, on a pool of `options.threads` threads when set,
/// else on the global pool.
pub(super) fn on_threads<T: Send>(
    options: &LodBuildOptions,
    work: impl FnOnce() -> Result<T, LodError> + Send,
) -> Result<T, LodError> {
    options.validate()?;
    match options.threads {
        Some(threads) => rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .map_err(|e| LodError::InvalidOptions(format!("threads: {e}")))?
            .install(work),
        None => work(),
    }
}

/// Runs the partitions stage's `work` on one thread more than a pool of several threads when
/// units are journaled: each unit waits for its outputs to reach the disk before it is
/// recorded, and meanwhile the extra thread keeps that core busy. The memory budget still
/// bounds the partitions held at once; a pool of one thread stays one, as asked.
fn on_partition_threads<T: Send>(
    ctx: &BuildContext<'_>,
    work: impl FnOnce() -> Result<T, LodError> + Send,
) -> Result<T, LodError> {
    let threads = rayon::current_num_threads();
    if !ctx.journal.is_enabled() || threads < 2 {
        return work();
    }
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads + 1)
        .build()
        .map_err(|e| LodError::InvalidOptions(format!("threads: {e}")))?
        .install(work)
}

/// The bucket grid's level: fine enough that merged buckets make partitions well below the
/// partition size on surfaces (which fill about 4^level cells), at most [`MAX_COUNT_LEVEL`], within
/// a quarter of the budget.
fn count_level(points: u64, max_partition_points: u64, budget: u64) -> u32 {
    let wanted = 64.0 * points as f64 / max_partition_points as f64;
    let mut level = 0;
    while level < MAX_COUNT_LEVEL && 4f64.powi(level as i32) < wanted {
        level += 1;
    }
    while level > 0 && CountGrid::planning_bytes(level) > budget / 4 {
        level -= 1;
    }
    level
}

fn build_on_pool(
    source: &dyn PointSource,
    store: &LodStore,
    options: &LodBuildOptions,
    progress: &BuildProgress,
) -> Result<LodBuildReport, LodError> {
    let start = Instant::now();
    let mut timings = BuildTimings::default();
    let bounds = source.bounds();
    let cube = RootCube::around(&bounds).ok_or(LodError::InvalidBounds {
        min: bounds.min.to_array(),
        max: bounds.max.to_array(),
    })?;
    let meter = MemoryMeter::new(options.memory_budget_bytes);
    meter.pin(DatasetStats::HEAP_BYTES, "the dataset's statistics")?;
    let budget = meter.largest_possible();
    let threads = rayon::current_num_threads() as u64;
    let leaf = options.max_leaf_points as u64;
    let attributes = source.attributes();
    let row_bytes = attributes.as_ref().map_or(0, |a| a.row_bytes());
    let layout = RecordLayout::for_grid(source.position_grid(), row_bytes);
    let point_bytes = build_bytes_per_point(layout);
    // Small enough that every thread can hold a partition and has several to build, never below
    // a few leaves, and always within the budget.
    let max_partition = (budget / (point_bytes * threads))
        .min(options.max_partition_points)
        .min(source.point_count() / (4 * threads))
        .max(4 * leaf)
        .min(budget.saturating_sub(partition_bytes(0, layout)) / point_bytes)
        .max(1);
    let level = count_level(source.point_count(), max_partition, budget);
    let expected = Expected {
        level,
        segment_points: BUCKET_SEGMENT_POINTS,
        point_count: source.point_count(),
        max_partition_points: max_partition,
    };
    let inputs = build_inputs(source, options, layout, &expected, threads);
    // Each file's facts, for a store update to take a removed file out (`file_facts.rs`).
    let gathering = FactsGathering::new(source);
    let (journal, spill, replay) = open_build_folder(store, options, layout, inputs.as_deref())?;
    let mut rejected = false;
    let mut counting_from = None;
    let resumed = replay.and_then(|replay| {
        let resumed = match replay.counted.points_read < expected.point_count {
            true => counting_start(replay.counted, &expected, &spill).map(|start| {
                counting_from = Some(start);
                None
            }),
            false => Resumed::from_replay(replay, &expected, store, &spill).map(Some),
        };
        resumed.unwrap_or_else(|reason| {
            tracing::warn!(%reason, folder = %spill.path().display(), "starting the build over");
            rejected = true;
            None
        })
    });
    let counting_resumed = resumed.is_some() || counting_from.is_some();
    let resumed = match resumed {
        Some(resumed) => {
            store.cut_payload(resumed.payload_end)?;
            tracing::info!(
                units = resumed.units,
                nodes = resumed.nodes.len(),
                partitions_left = resumed.partitions.len(),
                waiting = resumed.waiting.len(),
                "resuming a build"
            );
            resumed
        }
        None => {
            if let Some(inputs) = inputs.as_deref().filter(|_| rejected) {
                journal.start_over(inputs)?;
            }
            if let Some(start) = &counting_from {
                tracing::info!(points = start.read, "resuming a build's counting pass");
            } else {
                store.clear()?;
            }
            let grid_bytes = CountGrid::planning_bytes(level);
            let _grid = meter.try_reserve(grid_bytes, "the counting grid")?;
            let blocks_bytes = counting_blocks_bytes(layout.record_bytes(), meter.budget());
            let buffer_bytes = (budget.saturating_sub(grid_bytes + blocks_bytes) / 4)
                .clamp(1 << 16, BUCKET_BUFFER_BYTES);
            // The pass's progress, recorded at each part of the source and at its end.
            let record = |points_read: u64, counts: &[u64], stats: &DatasetStats| {
                let grid = CountGrid {
                    level,
                    counts: counts.to_vec(),
                    segment_points: BUCKET_SEGMENT_POINTS,
                };
                let files: Vec<PathBuf> = (0..grid.counts.len())
                    .flat_map(|bucket| grid.bucket_files(&spill, bucket))
                    .collect();
                sync_files(&files)?;
                sync_dir(spill.path())?;
                journal.record_counted(&Counted {
                    points_read,
                    level,
                    segment_points: grid.segment_points,
                    counts: grid.counts,
                    stats: stats.clone(),
                })
            };
            let checkpoint: Option<&Checkpoint<'_>> = journal.is_enabled().then_some(&record);
            let (grid, stats, threads_cpu) = count_points(
                &gathering,
                &cube,
                level,
                &meter,
                &spill,
                buffer_bytes,
                BUCKET_SEGMENT_POINTS,
                counting_from.unwrap_or_else(|| CountingStart::fresh(level)),
                checkpoint,
            )?;
            timings.counting_threads = threads_cpu;
            if let Some(record) = checkpoint {
                record(source.point_count(), &grid.counts, &stats)?;
            }
            Resumed::counted(&grid, stats, &expected, &spill)
        }
    };
    let partitions = resumed.partitions;
    let partition_count = partitions.len();
    timings.counting = start.elapsed();
    tracing::info!(
        points = source.point_count(),
        partitions = partition_count,
        level,
        "counted"
    );

    progress.begin(store, cube, source.point_count());
    let stats = resumed.stats;
    let sink = NodeSink::new(store, &journal, cube, stats.has_rgb, progress);
    sink.list(resumed.nodes);
    let ctx = BuildContext {
        pending: Mutex::new(resumed.waiting),
        ..build_context(options, &meter, &spill, &sink, max_partition)
    };
    let building = Instant::now();
    let partitions_figures =
        on_partition_threads(&ctx, || build_partitions_traced(&ctx, partitions))?;
    timings.partitions = building.elapsed();
    let upper = Instant::now();
    build_upper_levels(&ctx)?;
    timings.upper_levels = upper.elapsed();
    let partitions_split = ctx.partitions_split.load(Ordering::Relaxed);
    let regions = ctx
        .regions
        .into_inner()
        .unwrap_or_else(|poisoned| poisoned.into_inner());

    let stored_points = sink.points();
    let stored_bytes = sink.bytes();
    if stored_points != source.point_count() {
        return Err(LodError::SourceChanged(format!(
            "{stored_points} points were stored of {}",
            source.point_count()
        )));
    }
    let hierarchy = LodHierarchy::assemble(
        cube,
        source.point_count(),
        options.max_leaf_points as u32,
        stats,
        sink.into_nodes(),
    )
    .with_attributes(attributes);
    // A resumed build lists only the partitions this run built: its store is built again,
    // not updated, when its files change.
    let regions = (!counting_resumed).then(|| StoreRegions {
        grid: source.position_grid(),
        regions,
        files: Vec::new(),
        file_facts: Some(gathering.into_facts()),
    });
    pause::at("hierarchy", 0);
    let hierarchy_bytes = store.write_hierarchy_with(&hierarchy, regions.as_ref())?;
    timings.total = start.elapsed();
    let spilled_bytes = spill.written_bytes();
    let spill_path = spill.path().to_path_buf();
    // Finished: the folder and its journal go.
    spill.release();
    drop(spill);
    Ok(LodBuildReport {
        hierarchy,
        partitions: partition_count,
        partitions_split,
        partitions_figures,
        count_level: level,
        spilled_bytes,
        spill_record_bytes: layout.record_bytes(),
        stored_bytes,
        hierarchy_bytes,
        peak_memory_bytes: meter.peak(),
        memory_budget_bytes: meter.budget(),
        spill_path,
        timings,
        counting_resumed,
        resumed_units: resumed.units,
    })
}

/// What the build reads and how, as the journal records it: the source's fingerprint, the
/// options and what the build derived from them. `None` where the source has no fingerprint:
/// such a build does not resume.
fn build_inputs(
    source: &dyn PointSource,
    options: &LodBuildOptions,
    layout: RecordLayout,
    expected: &Expected,
    threads: u64,
) -> Option<String> {
    let fingerprint = source.fingerprint()?;
    let bounds = source.bounds();
    Some(format!(
        "pointfarm level-of-detail build 1\nsource: {fingerprint}\npoints: {}\n\
         bounds: {:?} {:?}\nrecords: {layout:?}\nattributes: {:?}\nleaf points: {}\n\
         sample grid: {}\nmemory budget: {}\nthreads: {threads}\npartition points: {}\n\
         count level: {}\nsegment points: {}\n",
        expected.point_count,
        bounds.min.to_array(),
        bounds.max.to_array(),
        source.attributes(),
        options.max_leaf_points,
        options.sample_grid,
        options.memory_budget_bytes,
        expected.max_partition_points,
        expected.level,
        expected.segment_points,
    ))
}

/// The build's spill folder and journal, with what an earlier run of the same build
/// recorded. A build of `inputs` uses a folder named after its store's payload file inside
/// the options' spill folder, kept until the build finishes; one without uses a fresh folder
/// it removes, and does not resume.
fn open_build_folder(
    store: &LodStore,
    options: &LodBuildOptions,
    layout: RecordLayout,
    inputs: Option<&str>,
) -> Result<(BuildJournal, SpillDir, Option<Replay>), LodError> {
    let Some(inputs) = inputs else {
        let spill = SpillDir::create(&options.spill_dir, layout)?;
        return Ok((BuildJournal::disabled(spill.path()), spill, None));
    };
    let payload = store.payload_path();
    let payload = std::fs::canonicalize(payload).unwrap_or_else(|_| payload.to_path_buf());
    let name = checksum64(b"store", payload.as_os_str().as_encoded_bytes());
    let dir = options
        .spill_dir
        .join(format!("pointfarm-lod-build-{name:016x}"));
    let (journal, replay) = BuildJournal::open(&dir, inputs)?;
    Ok((journal, SpillDir::at(dir, layout, true), replay))
}
