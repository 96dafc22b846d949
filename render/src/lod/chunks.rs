//! The chunks' local octrees, each built in memory from its buckets' files, in parallel with
//! only as many chunks in memory as the budget allows; a chunk too large for the budget, or
//! much larger than the plan's chunks (a dense bucket), is split into its eight children on
//! disk first.

use std::path::PathBuf;

use rayon::prelude::*;

use super::context::BuildContext;
use super::counting::CountGrid;
use super::error::LodError;
use super::key::MAX_LEVEL;
use super::options::BUILD_BYTES_PER_POINT;
use super::plan::{Chunk, ChunkPlan};
use super::spill::{self, SpillDir, SpillWriter, READ_BLOCK_BYTES};

/// The most bytes of write buffers when a chunk is split further.
const SPLIT_BUFFER_BYTES: u64 = 8 << 20;

/// The finest level a chunk that fits the budget is still split at for its size alone: that
/// of PotreeConverter's finest counting grid (128 cells an axis). Points too close together
/// for it are built as one chunk when they fit, however many.
const FINEST_SPLIT_LEVEL: u8 = 7;

/// Bytes a chunk of `count` points reserves while it is built.
pub fn chunk_bytes(count: u64) -> u64 {
    count * BUILD_BYTES_PER_POINT + READ_BLOCK_BYTES
}

fn chunk_path(ctx: &BuildContext<'_>, chunk: &Chunk) -> PathBuf {
    ctx.spill.file(&format!("chunk-{}.bin", chunk.key))
}

/// Each chunk of `plan` with the files of its buckets, in bucket order: the counting pass
/// wrote every point to its bucket, and a chunk is a union of whole buckets.
pub fn chunk_files(
    plan: &ChunkPlan,
    grid: &CountGrid,
    spill: &SpillDir,
) -> Vec<(Chunk, Vec<PathBuf>)> {
    let mut files = vec![Vec::new(); plan.chunks.len()];
    for (bucket, &count) in grid.counts.iter().enumerate() {
        if count > 0 {
            files[plan.lookup[bucket] as usize].extend(grid.bucket_files(spill, bucket));
        }
    }
    plan.chunks.iter().copied().zip(files).collect()
}

/// Builds every chunk, largest first, on the current rayon pool.
pub fn build_chunks(
    ctx: &BuildContext<'_>,
    mut chunks: Vec<(Chunk, Vec<PathBuf>)>,
) -> Result<(), LodError> {
    chunks.sort_by(|a, b| b.0.count.cmp(&a.0.count).then(a.0.key.cmp(&b.0.key)));
    chunks
        .into_par_iter()
        .with_max_len(1)
        .try_for_each(|(chunk, files)| build_chunk(ctx, chunk, files))
}

fn build_chunk(ctx: &BuildContext<'_>, chunk: Chunk, files: Vec<PathBuf>) -> Result<(), LodError> {
    let needed = chunk_bytes(chunk.count);
    let fits = needed <= ctx.meter.largest_possible();
    // A dense bucket is a chunk far above the plan's size: split, it keeps the cores busy.
    let oversized = chunk.count > 2 * ctx.max_chunk_points && chunk.key.level < FINEST_SPLIT_LEVEL;
    if !fits || oversized {
        if chunk.key.level >= MAX_LEVEL {
            return Err(LodError::TooDense {
                key: chunk.key,
                count: chunk.count,
            });
        }
        let parts = split_chunk(ctx, chunk, &files)?;
        ctx.chunks_split
            .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        // No reservation is held here: a task that waits for memory must hold none.
        return build_chunks(ctx, parts);
    }
    let _reservation = ctx.meter.reserve(needed, "a chunk built in memory")?;
    let points = spill::read_all(&files, ctx.spill.layout(), chunk.count)?;
    for path in &files {
        spill::remove(path)?;
    }
    let mut group = Vec::new();
    let root = ctx.local_builder().build(chunk.key, points, &mut group)?;
    ctx.sink.store(group)?;
    ctx.finish_subtree(chunk.key, &root.points, root.sample_grid)
}

/// Streams a chunk's files into eight files, one per child, each removed once read.
fn split_chunk(
    ctx: &BuildContext<'_>,
    chunk: Chunk,
    files: &[PathBuf],
) -> Result<Vec<(Chunk, Vec<PathBuf>)>, LodError> {
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
    for path in files {
        spill::for_each_block(path, ctx.spill.layout(), |block| {
            for p in block {
                let c = ctx.cube.cell_at(p.position, level) - base;
                let i = (c.x | (c.y << 1) | (c.z << 2)) as usize;
                counts[i] += 1;
                writer.push(i, p)?;
            }
            Ok(())
        })?;
        spill::remove(path)?;
    }
    writer.finish()?;
    if counts.iter().sum::<u64>() != chunk.count {
        return Err(LodError::SourceChanged(format!(
            "chunk {} holds {} points, the counting pass counted {}",
            chunk.key,
            counts.iter().sum::<u64>(),
            chunk.count
        )));
    }
    Ok(children
        .into_iter()
        .zip(paths)
        .zip(counts)
        .filter(|(_, count)| *count > 0)
        .map(|((child, path), count)| (Chunk { count, ..child }, vec![path]))
        .collect())
}
