//! The counting pass's copy of a source that is costly to read again (LAZ): every point as a
//! spill record in one file, written while counting and read back, in the same order, as the
//! source of the distribution pass. It costs a spill record per point on disk until the
//! distribution ends, and saves decoding the dataset a second time.

use std::path::PathBuf;

use super::error::LodError;
use super::memory::{MemoryMeter, Reservation};
use super::point::RawPoint;
use super::source::{BatchColumns, BatchVisitor, PointBatch, PointSource};
use super::spill::{self, SpillDir, SpillWriter, READ_BLOCK_BYTES};
use crate::cloud::WorldBounds;

/// Bytes of write buffer the copy holds at most while the counting pass writes it.
const COPY_BUFFER_BYTES: u64 = 8 << 20;
/// Points per batch read back: one block of the spill file, so small budgets hold it.
const COPY_BATCH_POINTS: usize = 1 << 12;
/// Bytes a batch of columns read back holds per point (position, RGB and attributes).
const COLUMN_BYTES_PER_POINT: u64 = 40;

/// Where the counting pass writes its copy of the source.
pub struct SourceCopyWriter<'a> {
    writer: SpillWriter<'a>,
    path: PathBuf,
}

impl<'a> SourceCopyWriter<'a> {
    pub fn create(spill: &'a SpillDir, meter: &'a MemoryMeter) -> Result<Self, LodError> {
        let buffer = COPY_BUFFER_BYTES
            .min(meter.largest_possible() / 16)
            .max(1 << 12);
        let reservation = meter.try_reserve(2 * buffer, "the copy of the source")?;
        let path = spill.file("source.bin");
        let writer = SpillWriter::new(spill, vec![path.clone()], buffer as usize, reservation);
        Ok(Self { writer, path })
    }

    pub fn push_batch(&mut self, batch: &PointBatch<'_>) -> Result<(), LodError> {
        for i in 0..batch.len() {
            self.writer.push(0, &RawPoint::from_batch(batch, i))?;
        }
        Ok(())
    }

    /// The copy, complete: `count` points with or without RGB, inside `bounds`.
    pub fn finish<'m>(
        self,
        bounds: WorldBounds,
        count: u64,
        has_rgb: bool,
        meter: &'m MemoryMeter,
    ) -> Result<SourceCopy<'m>, LodError> {
        self.writer.finish()?;
        let bytes = READ_BLOCK_BYTES + COPY_BATCH_POINTS as u64 * COLUMN_BYTES_PER_POINT;
        let reservation = meter.try_reserve(bytes, "reading the copy of the source")?;
        Ok(SourceCopy {
            path: self.path,
            bounds,
            count,
            has_rgb,
            _reservation: reservation,
        })
    }
}

/// The copy as a source; its file is removed when it is dropped.
pub struct SourceCopy<'a> {
    path: PathBuf,
    bounds: WorldBounds,
    count: u64,
    has_rgb: bool,
    _reservation: Reservation<'a>,
}

impl PointSource for SourceCopy<'_> {
    fn bounds(&self) -> WorldBounds {
        self.bounds
    }

    fn point_count(&self) -> u64 {
        self.count
    }

    fn for_each_batch(&self, visit: &mut BatchVisitor<'_>) -> Result<(), LodError> {
        let mut columns = BatchColumns::default();
        let mut flush = |columns: &mut BatchColumns| {
            let result = visit(columns.batch(self.has_rgb));
            columns.clear();
            result
        };
        spill::for_each_block(&self.path, |block| {
            for p in block {
                columns.positions.push(p.position);
                columns.rgb.push(p.rgb);
                columns.intensity.push(p.intensity);
                columns.classification.push(p.classification);
                columns.return_number.push(p.return_number);
            }
            if columns.positions.len() + block.len() > COPY_BATCH_POINTS {
                flush(&mut columns)?;
            }
            Ok(())
        })?;
        if !columns.positions.is_empty() {
            flush(&mut columns)?;
        }
        Ok(())
    }
}

impl Drop for SourceCopy<'_> {
    fn drop(&mut self) {
        // The spill folder is removed at the end of the build in any case.
        let _ = std::fs::remove_file(&self.path);
    }
}
