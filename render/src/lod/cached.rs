//! The counting pass's copy of a source that is costly to read again (LAZ): every point as a
//! spill record, written while counting and read back once, in the same order, as the source
//! of the distribution pass. It saves decoding the dataset a second time. The copy is cut into
//! segments, each removed as soon as the distribution has read it, so the copy's disk shrinks
//! as the chunks' spill grows: together they take a spill record a point and one segment.

use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};

use super::error::LodError;
use super::memory::{MemoryMeter, Reservation};
use super::point::{RawPoint, RecordLayout};
use super::source::{BatchColumns, BatchVisitor, PointBatch, PointSource};
use super::spill::{self, SpillDir, SpillWriter, READ_BLOCK_BYTES};
use crate::cloud::WorldBounds;

/// Bytes of write buffer the copy holds at most while the counting pass writes it.
const COPY_BUFFER_BYTES: u64 = 8 << 20;
/// Points per batch read back: one block of the spill file, so small budgets hold it.
const COPY_BATCH_POINTS: usize = 1 << 12;
/// Bytes a batch of columns read back holds per point (position, RGB and attributes).
const COLUMN_BYTES_PER_POINT: u64 = 40;
/// Points per segment of the copy (about 1.1 GB of records).
pub const COPY_SEGMENT_POINTS: u64 = 1 << 25;

/// Where the counting pass writes its copy of the source.
pub struct SourceCopyWriter<'a> {
    writer: SpillWriter<'a>,
    layout: RecordLayout,
    segments: Vec<PathBuf>,
    segment_points: u64,
    written: u64,
}

impl<'a> SourceCopyWriter<'a> {
    /// A copy of a source that declares `points` points.
    pub fn create(
        spill: &'a SpillDir,
        meter: &'a MemoryMeter,
        points: u64,
    ) -> Result<Self, LodError> {
        Self::in_segments(spill, meter, points, COPY_SEGMENT_POINTS)
    }

    fn in_segments(
        spill: &'a SpillDir,
        meter: &'a MemoryMeter,
        points: u64,
        segment_points: u64,
    ) -> Result<Self, LodError> {
        let buffer = COPY_BUFFER_BYTES
            .min(meter.largest_possible() / 16)
            .max(1 << 12);
        let reservation = meter.try_reserve(2 * buffer, "the copy of the source")?;
        let segments: Vec<PathBuf> = (0..points.div_ceil(segment_points).max(1))
            .map(|k| spill.file(&format!("source-{k}.bin")))
            .collect();
        let writer = SpillWriter::new(spill, segments.clone(), buffer as usize, reservation);
        Ok(Self {
            writer,
            layout: spill.layout(),
            segments,
            segment_points,
            written: 0,
        })
    }

    pub fn push_batch(&mut self, batch: &PointBatch<'_>) -> Result<(), LodError> {
        for i in 0..batch.len() {
            // Points beyond the declared count go to the last segment; the counting pass
            // refuses the source once it has read them.
            let segment = (self.written / self.segment_points) as usize;
            let segment = segment.min(self.segments.len() - 1);
            self.writer.push(segment, &RawPoint::from_batch(batch, i))?;
            self.written += 1;
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
        let mut segments = self.segments;
        segments.truncate(self.written.div_ceil(self.segment_points) as usize);
        Ok(SourceCopy {
            segments,
            layout: self.layout,
            bounds,
            count,
            has_rgb,
            read: AtomicBool::new(false),
            _reservation: reservation,
        })
    }
}

/// The copy as a source, read once: each segment is removed once read, and any left when
/// the copy is dropped.
pub struct SourceCopy<'a> {
    segments: Vec<PathBuf>,
    layout: RecordLayout,
    bounds: WorldBounds,
    count: u64,
    has_rgb: bool,
    read: AtomicBool,
    _reservation: Reservation<'a>,
}

impl PointSource for SourceCopy<'_> {
    fn bounds(&self) -> WorldBounds {
        self.bounds
    }

    fn point_count(&self) -> u64 {
        self.count
    }

    /// Costly in disk to read twice: the segments are gone once read.
    fn rereads_cheaply(&self) -> bool {
        false
    }

    fn for_each_batch(&self, visit: &mut BatchVisitor<'_>) -> Result<(), LodError> {
        if self.read.swap(true, Ordering::Relaxed) {
            return Err(LodError::Source(
                "the copy of the source is read only once".into(),
            ));
        }
        let mut columns = BatchColumns::default();
        let mut flush = |columns: &mut BatchColumns| {
            let result = visit(columns.batch(self.has_rgb));
            columns.clear();
            result
        };
        for segment in &self.segments {
            spill::for_each_block(segment, self.layout, |block| {
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
            spill::remove(segment)?;
        }
        if !columns.positions.is_empty() {
            flush(&mut columns)?;
        }
        Ok(())
    }
}

impl Drop for SourceCopy<'_> {
    fn drop(&mut self) {
        // The spill folder is removed at the end of the build in any case.
        for segment in &self.segments {
            let _ = std::fs::remove_file(segment);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lod::GeneratedSource;

    #[test]
    fn the_copy_reads_back_every_point_in_order_and_removes_each_segment_once_read() {
        let dir = tempfile::tempdir().expect("tempdir");
        let spill = SpillDir::create(dir.path(), RecordLayout::World).expect("spill");
        let meter = MemoryMeter::new(64 << 20);
        let source = GeneratedSource::cube(12_000, 3);
        let mut expected = Vec::new();
        let mut writer = SourceCopyWriter::in_segments(&spill, &meter, source.point_count(), 3_000)
            .expect("copy");
        source
            .for_each_batch(&mut |batch| {
                expected.extend((0..batch.len()).map(|i| RawPoint::from_batch(&batch, i)));
                writer.push_batch(&batch)
            })
            .expect("written");
        let copy = writer
            .finish(source.bounds(), source.point_count(), true, &meter)
            .expect("finished");
        assert_eq!(copy.segments.len(), 4);
        assert!(copy.segments.iter().all(|s| s.is_file()));

        let mut read = Vec::new();
        let mut left_when_read = Vec::new();
        copy.for_each_batch(&mut |batch| {
            left_when_read.push(copy.segments.iter().filter(|s| s.is_file()).count());
            read.extend((0..batch.len()).map(|i| RawPoint::from_batch(&batch, i)));
            Ok(())
        })
        .expect("read");
        assert_eq!(read, expected);
        // A batch is handed on after each segment's block, before that segment is removed.
        assert_eq!(left_when_read, [4, 3, 2, 1], "earlier segments are gone");
        assert!(copy.segments.iter().all(|s| !s.exists()));
        let again = copy.for_each_batch(&mut |_| Ok(()));
        assert!(matches!(again, Err(LodError::Source(_))), "{again:?}");
    }
}
