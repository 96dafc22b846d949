//! The distribution pass (every point appended to its chunk's spill file) and the chunks'
//! local octrees, built in parallel with only as many chunks in memory as the budget allows;
//! a chunk too large for the budget is split into its eight children on disk first.

use std::ops::Range;
use std::path::{Path, PathBuf};
use std::sync::mpsc;

use rayon::prelude::*;

use super::context::BuildContext;
use super::counting::{check_batch, CountGrid};
use super::error::LodError;
use super::key::{RootCube, MAX_LEVEL};
use super::options::BUILD_BYTES_PER_POINT;
use super::plan::{Chunk, ChunkPlan};
use super::point::{RawPoint, RecordLayout, MAX_RECORD_BYTES};
use super::source::{PointBatch, PointSource};
use super::spill::{self, SpillWriter, READ_BLOCK_BYTES};

/// The most bytes of write buffers when a chunk is split further.
const SPLIT_BUFFER_BYTES: u64 = 8 << 20;

/// Bytes a chunk of `count` points reserves while it is built.
pub fn chunk_bytes(count: u64) -> u64 {
    count * BUILD_BYTES_PER_POINT + READ_BLOCK_BYTES
}

fn chunk_path(ctx: &BuildContext<'_>, chunk: &Chunk) -> PathBuf {
    ctx.spill.file(&format!("chunk-{}.bin", chunk.key))
}

/// Points a block of spill records holds on its way to the scattering thread.
const RECORD_BLOCK_POINTS: usize = 1 << 13;
/// What the distribution's blocks hold, three at most (one made, one queued, one
/// scattered): each point's chunk and its record.
pub const DISTRIBUTION_BLOCKS_BYTES: u64 =
    3 * (RECORD_BLOCK_POINTS * (4 + MAX_RECORD_BYTES)) as u64;

/// Points of a batch with their chunks and their spill records, made on all cores.
#[derive(Default)]
struct RecordBlock {
    targets: Vec<u32>,
    records: Vec<u8>,
}

impl RecordBlock {
    fn fill(
        &mut self,
        batch: &PointBatch<'_>,
        range: Range<usize>,
        plan: &ChunkPlan,
        cube: &RootCube,
        layout: RecordLayout,
    ) -> Result<(), LodError> {
        batch.positions[range.clone()]
            .par_iter()
            .map(|p| plan.lookup[CountGrid::index(plan.level, cube.cell_at(*p, plan.level))])
            .collect_into_vec(&mut self.targets);
        const PER_TASK: usize = 1 << 10;
        let record_bytes = layout.record_bytes();
        self.records.resize(range.len() * record_bytes, 0);
        self.records
            .par_chunks_mut(PER_TASK * record_bytes)
            .enumerate()
            .try_for_each(|(task, out)| {
                let first = range.start + task * PER_TASK;
                for (j, record) in out.chunks_exact_mut(record_bytes).enumerate() {
                    layout.write(&RawPoint::from_batch(batch, first + j), record)?;
                }
                Ok(())
            })
    }
}

/// Reads the source a second time and writes every point into its chunk's file; the
/// points of each chunk must be those the counting pass saw.
///
/// The points' chunks and records are made on all cores, a block at a time; a thread of its
/// own appends each block's records to the chunks' buffers (and hands full buffers to the
/// spill writer's thread) while the next block is read and made.
pub fn distribute(
    ctx: &BuildContext<'_>,
    source: &dyn PointSource,
    plan: &ChunkPlan,
    buffer_bytes: u64,
) -> Result<Vec<(Chunk, PathBuf)>, LodError> {
    let paths: Vec<PathBuf> = plan.chunks.iter().map(|c| chunk_path(ctx, c)).collect();
    let reservation = ctx
        .meter
        .try_reserve(2 * buffer_bytes, "distribution write buffers")?;
    let _blocks = ctx
        .meter
        .try_reserve(DISTRIBUTION_BLOCKS_BYTES, "blocks of spill records")?;
    let writer = SpillWriter::new(ctx.spill, paths.clone(), buffer_bytes as usize, reservation);
    let chunk_count = plan.chunks.len();
    let bounds = source.bounds();
    let layout = ctx.spill.layout();
    let mut read = 0u64;
    let (walked, scattered) = std::thread::scope(|scope| {
        let (blocks, received) = mpsc::sync_channel::<RecordBlock>(1);
        let (spare_sender, spare) = mpsc::channel::<RecordBlock>();
        let record_bytes = layout.record_bytes();
        let scattering =
            scope.spawn(move || scatter(writer, chunk_count, record_bytes, received, spare_sender));
        let walked = source.for_each_batch(&mut |batch| {
            check_batch(&batch, &bounds, &ctx.cube, read)?;
            for start in (0..batch.len()).step_by(RECORD_BLOCK_POINTS) {
                let range = start..(start + RECORD_BLOCK_POINTS).min(batch.len());
                let mut block = spare.try_recv().unwrap_or_default();
                block.fill(&batch, range, plan, &ctx.cube, layout)?;
                if let Some(j) = block
                    .targets
                    .iter()
                    .position(|&t| t as usize >= chunk_count)
                {
                    return Err(LodError::SourceChanged(format!(
                        "point {} lies where the first pass counted none",
                        read + (start + j) as u64
                    )));
                }
                if blocks.send(block).is_err() {
                    // The scattering thread stopped on an error, which is returned below.
                    return Err(LodError::Source("the spill writing stopped".into()));
                }
            }
            read += batch.len() as u64;
            Ok(())
        });
        drop(blocks);
        let scattered = scattering.join().unwrap_or_else(|_| {
            Err(LodError::spill(
                ctx.spill.path(),
                std::io::Error::other("the distribution's scattering thread panicked"),
            ))
        });
        (walked, scattered)
    });
    // The scattering thread's error is the cause of any the walk returned after it.
    let counts = scattered?;
    walked?;
    if read != source.point_count() {
        return Err(LodError::CountMismatch {
            declared: source.point_count(),
            read,
            pass: "distribution",
        });
    }
    for (chunk, &count) in plan.chunks.iter().zip(&counts) {
        if count != chunk.count {
            return Err(LodError::SourceChanged(format!(
                "chunk {} got {count} points, the first pass counted {}",
                chunk.key, chunk.count
            )));
        }
    }
    Ok(plan.chunks.iter().copied().zip(paths).collect())
}

/// Appends every block's records to their chunks' files and counts them per chunk; each
/// block goes back through `spare` to be filled again.
fn scatter(
    mut writer: SpillWriter<'_>,
    chunks: usize,
    record_bytes: usize,
    blocks: mpsc::Receiver<RecordBlock>,
    spare: mpsc::Sender<RecordBlock>,
) -> Result<Vec<u64>, LodError> {
    let mut counts = vec![0u64; chunks];
    for block in blocks {
        let records = block.records.chunks_exact(record_bytes);
        for (&target, record) in block.targets.iter().zip(records) {
            counts[target as usize] += 1;
            writer.push_record(target as usize, record)?;
        }
        let _ = spare.send(block);
    }
    writer.finish()?;
    Ok(counts)
}

/// Builds every chunk, largest first, on the current rayon pool.
pub fn build_chunks(
    ctx: &BuildContext<'_>,
    mut chunks: Vec<(Chunk, PathBuf)>,
) -> Result<(), LodError> {
    chunks.sort_by(|a, b| b.0.count.cmp(&a.0.count).then(a.0.key.cmp(&b.0.key)));
    chunks
        .into_par_iter()
        .with_max_len(1)
        .try_for_each(|(chunk, path)| build_chunk(ctx, chunk, path))
}

fn build_chunk(ctx: &BuildContext<'_>, chunk: Chunk, path: PathBuf) -> Result<(), LodError> {
    let needed = chunk_bytes(chunk.count);
    if needed > ctx.meter.largest_possible() {
        if chunk.key.level >= MAX_LEVEL {
            return Err(LodError::TooDense {
                key: chunk.key,
                count: chunk.count,
            });
        }
        let parts = split_chunk(ctx, chunk, &path)?;
        ctx.chunks_split
            .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        // No reservation is held here: a task that waits for memory must hold none.
        return build_chunks(ctx, parts);
    }
    let _reservation = ctx.meter.reserve(needed, "a chunk built in memory")?;
    let points = spill::read_all(&path, ctx.spill.layout(), chunk.count)?;
    spill::remove(&path)?;
    let root = ctx.local_builder().build(chunk.key, points)?;
    ctx.finish_subtree(chunk.key, &root.points, root.sample_grid)
}

/// Streams a chunk's file into eight files, one per child.
fn split_chunk(
    ctx: &BuildContext<'_>,
    chunk: Chunk,
    path: &Path,
) -> Result<Vec<(Chunk, PathBuf)>, LodError> {
    let children: Vec<Chunk> = (0..8)
        .map(|i| Chunk {
            key: chunk.key.child(i),
            count: 0,
        })
        .collect();
    let paths: Vec<PathBuf> = children.iter().map(|c| chunk_path(ctx, c)).collect();
    let buffer = SPLIT_BUFFER_BYTES.min(ctx.meter.largest_possible() / 8);
    let reservation = ctx
        .meter
        .reserve(2 * buffer + READ_BLOCK_BYTES, "splitting a chunk")?;
    let mut writer = SpillWriter::new(ctx.spill, paths.clone(), buffer as usize, reservation);
    let mut counts = [0u64; 8];
    let level = u32::from(chunk.key.level) + 1;
    let base = chunk.key.cell() * 2;
    spill::for_each_block(path, ctx.spill.layout(), |block| {
        for p in block {
            let c = ctx.cube.cell_at(p.position, level) - base;
            let i = (c.x | (c.y << 1) | (c.z << 2)) as usize;
            counts[i] += 1;
            writer.push(i, p)?;
        }
        Ok(())
    })?;
    writer.finish()?;
    spill::remove(path)?;
    Ok(children
        .into_iter()
        .zip(paths)
        .zip(counts)
        .filter(|(_, count)| *count > 0)
        .map(|((child, path), count)| (Chunk { count, ..child }, path))
        .collect())
}
