//! A dataset's files as a level-of-detail [`PointSource`]: read batch by batch, file after
//! file, in world coordinates with their raw attributes, never held whole.

use std::path::PathBuf;
use std::sync::mpsc;

use glam::DVec3;
use rayon::prelude::*;

use super::contain::contain_panics;
use super::read::{dataset_bounds, deciding_files, DatasetFile};
use super::IngestError;
use crate::cloud::WorldBounds;
use crate::lod::attributes::{extra_descriptors, RowFiller};
use crate::lod::{
    AttributeSchema, BatchColumns, BatchVisitor, LodError, PointSource, PositionGrid,
};

/// The files of a dataset, checked, as a source the level-of-detail builder reads once.
pub struct DatasetSource {
    files: Vec<DatasetFile>,
    bounds: WorldBounds,
    points: u64,
    has_rgb: bool,
    grid: Option<SharedGrid>,
    /// Every attribute of the files' points, kept in the store for an export.
    attributes: AttributeSchema,
    /// How each file's records become attribute rows.
    fillers: Vec<RowFiller>,
}

impl DatasetSource {
    /// Checks every file (the same pre-parse as a load); the bounds are the union of the
    /// headers' of the files that declare points (`read.rs`), widened by their rounding. A
    /// file whose header bounds are unusable is an error naming it: the builder needs bounds
    /// before it reads a point.
    pub fn open(paths: &[PathBuf]) -> Result<Self, IngestError> {
        Self::of_files(DatasetFile::check_all(paths)?)
    }

    /// The source of files checked already, here or by URL (`objects.rs`).
    pub(super) fn of_files(files: Vec<DatasetFile>) -> Result<Self, IngestError> {
        let bounds = dataset_bounds(&files)?;
        let attributes = attribute_schema(&files);
        let fillers = files
            .iter()
            .map(|file| {
                let keep_extra = attributes.extra_bytes > 0;
                RowFiller::new(
                    file.facts.point_format,
                    file.format_len,
                    keep_extra,
                    &attributes,
                )
            })
            .collect();
        Ok(Self {
            attributes,
            fillers,
            grid: shared_grid(&files, &bounds),
            points: files.iter().map(|file| file.facts.declared_points).sum(),
            has_rgb: deciding_files(&files).iter().all(|file| file.has_color),
            bounds,
            files,
        })
    }

    /// A build's refusal of a point outside the bounds said as the file it came from and its
    /// header's bounds: what a user can correct. Other errors are as they are.
    pub fn naming_the_file(&self, error: LodError) -> Result<IngestError, LodError> {
        let LodError::PointOutsideBounds {
            index, position, ..
        } = error
        else {
            return Err(error);
        };
        let starts = self.part_starts();
        let place = starts.partition_point(|&start| start <= index);
        // The last file starting at or before the point that holds points: an empty file
        // shares its start with the next.
        let file = (0..place)
            .rev()
            .map(|i| &self.files[i])
            .find(|file| file.has_points());
        match file {
            Some(file) => Ok(IngestError::PointOutsideHeaderBounds {
                path: file.path.clone(),
                position,
                min: file.header_bounds.min.to_array(),
                max: file.header_bounds.max.to_array(),
            }),
            None => Err(error),
        }
    }
}

/// The attributes the files' points hold: near-infrared where every file has it, wave
/// packets where one has them, and the extra bytes where every file declares the same ones
/// (else they are dropped, and the schema says so, for the export to tell).
fn attribute_schema(files: &[DatasetFile]) -> AttributeSchema {
    let files = deciding_files(files);
    let descriptors: Vec<Vec<u8>> = files
        .iter()
        .map(|file| {
            let extra = usize::from(file.facts.record_len).saturating_sub(file.format_len);
            extra_descriptors(file.extra_bytes_vlr.as_deref(), extra)
        })
        .collect();
    let shared = descriptors.windows(2).all(|pair| pair[0] == pair[1]);
    let extra_descriptors = match shared {
        true => descriptors.first().cloned().unwrap_or_default(),
        false => Vec::new(),
    };
    let extra_bytes = crate::lod::attributes::declared_bytes(&extra_descriptors)
        .and_then(|n| u16::try_from(n).ok())
        .unwrap_or(0);
    let format = |file: &DatasetFile| file.facts.point_format;
    AttributeSchema {
        has_nir: files.iter().all(|file| matches!(format(file), 8 | 10)),
        has_waveform: files
            .iter()
            .any(|file| matches!(format(file), 4 | 5 | 9 | 10)),
        extra_descriptors: if extra_bytes > 0 {
            extra_descriptors
        } else {
            Vec::new()
        },
        extra_bytes,
        source_formats: files
            .iter()
            .fold(0, |bits, file| bits | 1u16 << format(file).min(15)),
        extra_bytes_dropped: !shared,
    }
}

/// One grid for all of a dataset's files: the first deciding file's (`read.rs`), and for each
/// file the integers that move its coordinates onto it.
#[derive(Debug, Clone)]
struct SharedGrid {
    grid: PositionGrid,
    shifts: Vec<[i64; 3]>,
}

/// The shared grid of files with one scale whose offsets lie on each other's grids (tiles of
/// one survey: one offset, or offsets a whole number of steps apart), and whose bounds fit
/// i32 integers on it. A file's points then read as `scale * (i + shift) + offset` of the
/// first deciding file: the same coordinates, at most an f64 step apart, on one grid.
fn shared_grid(files: &[DatasetFile], bounds: &WorldBounds) -> Option<SharedGrid> {
    let first = *deciding_files(files).first()?;
    let grid = PositionGrid::new(first.scale, first.offset)?;
    let same_scale = |file: &DatasetFile| {
        file.scale.to_array().map(f64::to_bits) == first.scale.to_array().map(f64::to_bits)
    };
    let shift = |file: &DatasetFile| -> Option<[i64; 3]> {
        let steps = (file.offset - first.offset) / first.scale;
        let whole = steps.round();
        let on_grid = (steps - whole).abs().max_element() <= 1e-6;
        (same_scale(file) && on_grid && whole.abs().max_element() < 2f64.powi(40))
            .then(|| whole.to_array().map(|v| v as i64))
    };
    // A file without points reads nothing onto the grid, whatever its scale and offset.
    let shifts = files
        .iter()
        .map(|file| match file.has_points() || !first.has_points() {
            true => shift(file),
            false => Some([0; 3]),
        })
        .collect::<Option<Vec<_>>>()?;
    // Every point inside the bounds (the batches' check) must have an i32 on the grid.
    let limit = f64::from(i32::MAX) - 1.0;
    let lo = (bounds.min - first.offset) / first.scale;
    let hi = (bounds.max - first.offset) / first.scale;
    let fits = lo.cmpge(DVec3::splat(-limit)).all() && hi.cmple(DVec3::splat(limit)).all();
    fits.then_some(SharedGrid { grid, shifts })
}

/// Records decoded per task when a batch is turned into columns on all cores.
const FILL_BLOCK_POINTS: usize = 1 << 14;

/// Where a record's fields lie, from its point format (as the `las` crate lays them out).
#[derive(Clone, Copy)]
struct RecordFields {
    len: usize,
    extended: bool,
    rgb: Option<usize>,
}

impl RecordFields {
    fn of(batch: &las::PointData) -> Self {
        let format = batch.format();
        // Legacy: XYZ, intensity, 2 flag bytes, scan angle, user data, source id (20 bytes),
        // then GPS time; extended (6-10): 3 flag bytes and a 2-byte scan angle (22), GPS time.
        let rgb = if format.is_extended {
            30
        } else {
            20 + if format.has_gps_time { 8 } else { 0 }
        };
        Self {
            len: batch.record_len(),
            extended: format.is_extended,
            rgb: format.has_color.then_some(rgb),
        }
    }
}

fn u16_at(record: &[u8], at: usize) -> u16 {
    u16::from_le_bytes([record[at], record[at + 1]])
}

fn i32_at(record: &[u8], at: usize) -> i32 {
    i32::from_le_bytes([record[at], record[at + 1], record[at + 2], record[at + 3]])
}

/// One task's share of a batch: its records and the columns they fill.
struct FillBlock<'c> {
    records: &'c [u8],
    positions: &'c mut [DVec3],
    intensity: &'c mut [u16],
    classification: &'c mut [u8],
    return_number: &'c mut [u8],
    /// Empty where the batch keeps no RGB, as `rows` where its rows are empty.
    rgb: &'c mut [[u16; 3]],
    rows: &'c mut [u8],
}

/// `column` cut into `blocks` pieces of `per` values, empty pieces where it runs out (a
/// column the batch does not keep).
fn pieces<T>(column: &mut [T], per: usize, blocks: usize) -> impl Iterator<Item = &mut [T]> {
    column
        .chunks_mut(per.max(1))
        .chain(std::iter::repeat_with(|| &mut [][..]))
        .take(blocks)
}

/// Fills `columns` with a decoded batch of a file of `transforms` (its RGB only `with_rgb`),
/// each block of records decoded once, by one task, into every column: the same values as
/// the `las` crate's column iterators, positions on `grid` (with the file's shift) where the
/// dataset has one.
fn fill(
    columns: &mut BatchColumns,
    batch: &las::PointData,
    transforms: &las::Vector<las::Transform>,
    with_rgb: bool,
    grid: Option<(&PositionGrid, [i64; 3])>,
    rows: &RowFiller,
) {
    let fields = RecordFields::of(batch);
    let n = batch.len();
    let bytes = &batch.raw_bytes()[..n * fields.len];
    let (tx, ty, tz) = (transforms.x, transforms.y, transforms.z);
    let row_bytes = rows.row_bytes();
    let rgb_at = fields.rgb.filter(|_| with_rgb);
    columns.set_len(n, rgb_at.is_some(), row_bytes);
    let blocks = n.div_ceil(FILL_BLOCK_POINTS);
    let per = FILL_BLOCK_POINTS;
    let tasks: Vec<FillBlock<'_>> = bytes
        .chunks(per * fields.len)
        .zip(pieces(&mut columns.positions, per, blocks))
        .zip(pieces(&mut columns.intensity, per, blocks))
        .zip(pieces(&mut columns.classification, per, blocks))
        .zip(pieces(&mut columns.return_number, per, blocks))
        .zip(pieces(&mut columns.rgb, per, blocks))
        .zip(pieces(&mut columns.rows, per * row_bytes, blocks))
        .map(
            |((((((records, positions), intensity), classification), return_number), rgb), r)| {
                FillBlock {
                    records,
                    positions,
                    intensity,
                    classification,
                    return_number,
                    rgb,
                    rows: r,
                }
            },
        )
        .collect();
    tasks.into_par_iter().for_each(|block| {
        let records = block.records.chunks_exact(fields.len);
        for (i, r) in records.enumerate() {
            block.positions[i] = match grid {
                Some((grid, shift)) => grid.position([
                    i64::from(i32_at(r, 0)) + shift[0],
                    i64::from(i32_at(r, 4)) + shift[1],
                    i64::from(i32_at(r, 8)) + shift[2],
                ]),
                None => DVec3::new(
                    tx.direct(i32_at(r, 0)),
                    ty.direct(i32_at(r, 4)),
                    tz.direct(i32_at(r, 8)),
                ),
            };
            block.intensity[i] = u16_at(r, 12);
            if fields.extended {
                block.return_number[i] = r[14] & 15;
                block.classification[i] = r[16];
            } else {
                block.return_number[i] = r[14] & 7;
                block.classification[i] = r[15] & 0b0001_1111;
            }
            if let Some(at) = rgb_at {
                block.rgb[i] = [u16_at(r, at), u16_at(r, at + 2), u16_at(r, at + 4)];
            }
            if row_bytes > 0 {
                rows.fill(r, &mut block.rows[i * row_bytes..(i + 1) * row_bytes]);
            }
        }
    });
}

impl PointSource for DatasetSource {
    fn bounds(&self) -> WorldBounds {
        self.bounds
    }

    fn point_count(&self) -> u64 {
        self.points
    }

    /// Positions are decoded on the shared grid (`fill`), exactly as it computes them.
    fn position_grid(&self) -> Option<PositionGrid> {
        self.grid.as_ref().map(|shared| shared.grid)
    }

    /// Every attribute of the files' points, which the export writes back.
    fn attributes(&self) -> Option<AttributeSchema> {
        Some(self.attributes.clone())
    }

    /// The files' paths, lengths and modification times; objects' URLs, sizes and versions.
    fn fingerprint(&self) -> Option<String> {
        if self.files.iter().any(|file| file.object.is_some()) {
            return super::objects::objects_fingerprint(&self.files);
        }
        crate::lod::source::files_fingerprint(self.files.iter().map(|file| file.path.as_path()))
    }

    /// The files are decoded on a thread of their own, a batch ahead of `visit`: what the
    /// visitor does on one core (a build's spill copy, its statistics) overlaps the decoding
    /// of the next batch instead of leaving the other cores idle (docs/perf/lod-build.md). At
    /// most two batches of columns exist at once: one visited, one handed over.
    fn for_each_batch(&self, visit: &mut BatchVisitor<'_>) -> Result<(), LodError> {
        self.for_each_batch_from(0, visit)
    }

    /// Each file's first point.
    fn part_starts(&self) -> Vec<u64> {
        let mut start = 0;
        self.files
            .iter()
            .map(|file| {
                let first = start;
                start += file.facts.declared_points;
                first
            })
            .collect()
    }

    /// The files from the one whose first point is `first` on.
    fn for_each_batch_from(
        &self,
        first: u64,
        visit: &mut BatchVisitor<'_>,
    ) -> Result<(), LodError> {
        let skipped = self
            .part_starts()
            .iter()
            .position(|&start| start == first)
            .ok_or_else(|| LodError::Source(format!("no file starts at point {first}")))?;
        let (filled, batches) = mpsc::sync_channel::<BatchColumns>(0);
        let (spare, spares) = mpsc::channel::<BatchColumns>();
        // The reading thread's CPU time counts in a build's account of its threads.
        let account = crate::lod::thread_cpu::ThreadAccount::reader();
        std::thread::scope(|scope| {
            let reader = scope.spawn(move || {
                let _account = account;
                self.decode_into(skipped, &filled, &spares)
            });
            let mut visited = Ok(());
            for columns in &batches {
                visited = visit(columns.batch(self.has_rgb));
                if visited.is_err() {
                    break;
                }
                let _ = spare.send(columns);
            }
            // A reader still decoding finds no one to hand its batch to, and stops.
            drop(batches);
            let read = reader.join().unwrap_or_else(|_| {
                Err(LodError::Source(
                    "the thread reading the files panicked".into(),
                ))
            });
            // The visitor's error is the cause of the reader's stop after it.
            visited.and(read)
        })
    }
}

impl DatasetSource {
    /// Decodes every file after the first `skipped` into columns (taken from `spares` where
    /// one is back), handing each batch to `filled`; stops without an error when no one takes
    /// it.
    fn decode_into(
        &self,
        skipped: usize,
        filled: &mpsc::SyncSender<BatchColumns>,
        spares: &mpsc::Receiver<BatchColumns>,
    ) -> Result<(), LodError> {
        // One batch of records for every file: the reader's share of each point is its fill.
        let mut records = None;
        for (k, file) in self.files.iter().enumerate().skip(skipped) {
            let grid = self
                .grid
                .as_ref()
                .map(|shared| (&shared.grid, shared.shifts[k]));
            let mut stopped = false;
            let read = contain_panics(&file.path, || {
                file.for_each_batch_into(&mut records, |batch, transforms| {
                    let mut columns = spares.try_recv().unwrap_or_default();
                    let filler = &self.fillers[k];
                    fill(&mut columns, batch, transforms, self.has_rgb, grid, filler);
                    filled.send(columns).map_err(|_| {
                        stopped = true;
                        IngestError::Corrupt {
                            path: file.path.clone(),
                            what: "reading stopped".into(),
                        }
                    })
                })
            });
            if stopped {
                return Ok(());
            }
            read.map_err(|error| LodError::Source(error.to_string()))?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests;
