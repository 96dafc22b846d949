//! The distribution pass (every point appended to its chunk's spill file) and the chunks'
//! local octrees, built in parallel with only as many chunks in memory as the budget allows;
//! a chunk too large for the budget is split into its eight children on disk first.

use std::path::{Path, PathBuf};

use rayon::prelude::*;

use super::context::BuildContext;
use super::counting::{check_batch, CountGrid, CELL_BLOCK_POINTS};
use super::error::LodError;
use super::key::MAX_LEVEL;
use super::options::BUILD_BYTES_PER_POINT;
use super::plan::{Chunk, ChunkPlan};
use super::point::RawPoint;
use super::source::PointSource;
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

/// Reads the source a second time and writes every point into its chunk's file; the
/// points of each chunk must be those the counting pass saw.
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
    let mut writer = SpillWriter::new(ctx.spill, paths.clone(), buffer_bytes as usize, reservation);
    let mut counts = vec![0u64; plan.chunks.len()];
    let mut read = 0u64;
    let bounds = source.bounds();
    let _targets_buffer = ctx
        .meter
        .try_reserve(CELL_BLOCK_POINTS as u64 * 4, "chunk indices")?;
    let mut targets: Vec<u32> = Vec::with_capacity(CELL_BLOCK_POINTS);
    source.for_each_batch(&mut |batch| {
        check_batch(&batch, &bounds, &ctx.cube, read)?;
        for (b, block) in batch.positions.chunks(CELL_BLOCK_POINTS).enumerate() {
            block
                .par_iter()
                .map(|p| {
                    plan.lookup[CountGrid::index(plan.level, ctx.cube.cell_at(*p, plan.level))]
                })
                .collect_into_vec(&mut targets);
            for (j, &target) in targets.iter().enumerate() {
                let i = b * CELL_BLOCK_POINTS + j;
                let Some(count) = counts.get_mut(target as usize) else {
                    return Err(LodError::SourceChanged(format!(
                        "point {} lies where the first pass counted none",
                        read + i as u64
                    )));
                };
                *count += 1;
                writer.push(target as usize, &RawPoint::from_batch(&batch, i))?;
            }
        }
        read += batch.len() as u64;
        Ok(())
    })?;
    writer.finish()?;
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
    let points = spill::read_all(&path, chunk.count)?;
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
    spill::for_each_block(path, |block| {
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
