//! The counting pass: every point checked and counted into a coarse grid of the root cube,
//! with the dataset's statistics.

use rayon::prelude::*;

use super::cached::SourceCopyWriter;
use super::error::LodError;
use super::key::RootCube;
use super::memory::MemoryMeter;
use super::source::{PointBatch, PointSource};
use super::stats::DatasetStats;
use crate::cloud::WorldBounds;

/// The finest counting grid: 128 cells per axis, as PotreeConverter's.
pub const MAX_COUNT_LEVEL: u32 = 7;
/// Points whose cells are computed at once (in parallel) when a pass walks a batch.
pub const CELL_BLOCK_POINTS: usize = 1 << 14;

/// Points per cell of the counting grid at `level`, cells in x-fastest order.
pub struct CountGrid {
    pub level: u32,
    pub counts: Vec<u64>,
}

impl CountGrid {
    pub fn index(level: u32, cell: glam::UVec3) -> usize {
        (cell.x as usize) | ((cell.y as usize) << level) | ((cell.z as usize) << (2 * level))
    }

    /// Bytes of a grid of `level` with its planning pyramid and chunk lookup (8 + 8/7 + 4 a cell).
    pub fn planning_bytes(level: u32) -> u64 {
        (1u64 << (3 * level)) * 14
    }
}

/// How far outside the declared bounds a point may lie and still count as inside: bounds from
/// file headers are rounded to the files' scale.
fn tolerance(cube: &RootCube) -> f64 {
    cube.side * 1e-9
}

/// Checks a batch's columns and that its points are finite and inside the declared bounds
/// (the cube holds those); `first` is the index of its first point overall. Whether a point
/// lies on the grid its records hold it on is the record's write to check.
pub fn check_batch(
    batch: &PointBatch<'_>,
    bounds: &WorldBounds,
    cube: &RootCube,
    first: u64,
) -> Result<(), LodError> {
    batch.check_lengths()?;
    let tol = tolerance(cube);
    let lo = bounds.min - tol;
    let hi = bounds.max + tol;
    let bad = batch
        .positions
        .par_iter()
        .position_first(|p| !p.is_finite() || p.cmplt(lo).any() || p.cmpgt(hi).any());
    let Some(i) = bad else {
        return Ok(());
    };
    let p = batch.positions[i];
    let index = first + i as u64;
    if !p.is_finite() {
        return Err(LodError::NonFinitePoint {
            index,
            position: p.to_array(),
        });
    }
    Err(LodError::PointOutsideBounds {
        index,
        position: p.to_array(),
        min: lo.to_array(),
        max: hi.to_array(),
    })
}

/// Counts every point of `source` into a grid of `level` and gathers the statistics; with
/// `copy`, every point is also written to the copy of the source.
pub fn count_points(
    source: &dyn PointSource,
    cube: &RootCube,
    level: u32,
    meter: &MemoryMeter,
    mut copy: Option<&mut SourceCopyWriter<'_>>,
) -> Result<(CountGrid, DatasetStats), LodError> {
    let mut counts = vec![0u64; 1 << (3 * level)];
    let mut stats: Option<DatasetStats> = None;
    let mut read = 0u64;
    let _cells_buffer = meter.try_reserve(CELL_BLOCK_POINTS as u64 * 8, "cell indices")?;
    let mut cells: Vec<usize> = Vec::with_capacity(CELL_BLOCK_POINTS);
    let bounds = source.bounds();
    source.for_each_batch(&mut |batch| {
        check_batch(&batch, &bounds, cube, read)?;
        let stats = stats.get_or_insert_with(|| DatasetStats::new(batch.rgb.is_some()));
        if stats.has_rgb != batch.rgb.is_some() {
            return Err(LodError::Source(format!(
                "batch at point {read} {} RGB unlike the batches before it",
                if batch.rgb.is_some() { "has" } else { "lacks" }
            )));
        }
        for block in batch.positions.chunks(CELL_BLOCK_POINTS) {
            block
                .par_iter()
                .map(|p| CountGrid::index(level, cube.cell_at(*p, level)))
                .collect_into_vec(&mut cells);
            for &c in &cells {
                counts[c] += 1;
            }
        }
        stats.add(&batch);
        if let Some(copy) = copy.as_deref_mut() {
            copy.push_batch(&batch)?;
        }
        read += batch.len() as u64;
        Ok(())
    })?;
    if read != source.point_count() {
        return Err(LodError::CountMismatch {
            declared: source.point_count(),
            read,
            pass: "counting",
        });
    }
    Ok((
        CountGrid { level, counts },
        stats.unwrap_or_else(|| DatasetStats::new(false)),
    ))
}
