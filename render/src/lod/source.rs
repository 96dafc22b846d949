//! What the builder reads: `PointSource`, points in batches that can be read again in the same
//! order, and its implementation for an in-memory [`PointCloud`].

use std::path::Path;

use glam::DVec3;

use super::attributes::AttributeSchema;
use super::error::LodError;
use super::grid::PositionGrid;
use super::point::RawPoint;
use crate::cloud::{PointCloud, WorldBounds};

/// One batch of original points in world coordinates (f64) with their raw attributes.
#[derive(Debug, Clone, Copy)]
pub struct PointBatch<'a> {
    pub positions: &'a [DVec3],
    /// Raw 16-bit LAS RGB fields, `None` when the files have none.
    pub rgb: Option<&'a [[u16; 3]]>,
    pub intensity: &'a [u16],
    pub classification: &'a [u8],
    pub return_number: &'a [u8],
    /// Each point's attribute row, one after another (`attributes.rs`); empty where the
    /// source has no [`PointSource::attributes`].
    pub rows: &'a [u8],
}

impl PointBatch<'_> {
    pub fn len(&self) -> usize {
        self.positions.len()
    }

    pub fn is_empty(&self) -> bool {
        self.positions.is_empty()
    }

    /// Point `i` as the builder holds it, standing for itself, its row not yet numbered.
    pub fn raw_point(&self, i: usize) -> RawPoint {
        RawPoint {
            position: self.positions[i],
            rgb: self.rgb.map_or([0; 3], |rgb| rgb[i]),
            intensity: self.intensity[i],
            classification: self.classification[i],
            return_number: self.return_number[i],
            weight: 1,
            row: 0,
        }
    }

    /// The attribute row of point `i`, rows being `row_bytes` long.
    pub fn row(&self, i: usize, row_bytes: usize) -> &[u8] {
        &self.rows[i * row_bytes..(i + 1) * row_bytes]
    }

    /// Every column as long as `positions`, and rows of `row_bytes` for each point.
    pub(crate) fn check_lengths(&self, row_bytes: usize) -> Result<(), LodError> {
        let positions = self.positions.len();
        let columns = [
            ("rgb", self.rgb.map_or(positions, <[_]>::len)),
            ("intensity", self.intensity.len()),
            ("classification", self.classification.len()),
            ("return_number", self.return_number.len()),
            (
                "rows",
                self.rows.len().checked_div(row_bytes).unwrap_or(positions),
            ),
        ];
        for (field, len) in columns {
            if len != positions {
                return Err(LodError::BatchLengths {
                    positions,
                    field,
                    len,
                });
            }
        }
        Ok(())
    }
}

/// The owned columns of one batch, reused from batch to batch by sources that make or decode
/// their points.
#[derive(Debug, Default)]
pub struct BatchColumns {
    pub positions: Vec<DVec3>,
    pub rgb: Vec<[u16; 3]>,
    pub intensity: Vec<u16>,
    pub classification: Vec<u8>,
    pub return_number: Vec<u8>,
    pub rows: Vec<u8>,
}

impl BatchColumns {
    pub fn clear(&mut self) {
        self.positions.clear();
        self.rgb.clear();
        self.intensity.clear();
        self.classification.clear();
        self.return_number.clear();
        self.rows.clear();
    }

    /// Sets every column to `n` points (RGB only `with_rgb`, else none; rows of `row_bytes`),
    /// writing only the points a column gains: a fill overwrites every value, and zeroing a
    /// batch's columns first would cost the reading thread, alone, a pass over them.
    pub fn set_len(&mut self, n: usize, with_rgb: bool, row_bytes: usize) {
        self.positions.resize(n, DVec3::ZERO);
        self.rgb.resize(if with_rgb { n } else { 0 }, [0; 3]);
        self.intensity.resize(n, 0);
        self.classification.resize(n, 0);
        self.return_number.resize(n, 0);
        self.rows.resize(n * row_bytes, 0);
    }

    /// The batch of these columns; its RGB only `with_rgb`.
    pub fn batch(&self, with_rgb: bool) -> PointBatch<'_> {
        PointBatch {
            positions: &self.positions,
            rgb: with_rgb.then_some(self.rgb.as_slice()),
            intensity: &self.intensity,
            classification: &self.classification,
            return_number: &self.return_number,
            rows: &self.rows,
        }
    }
}

/// What a [`PointSource`] hands each batch to; an error it returns stops the walk.
pub type BatchVisitor<'v> = dyn FnMut(PointBatch<'_>) -> Result<(), LodError> + 'v;

/// Points read batch by batch, in the same order each time (the builder reads them once).
pub trait PointSource: Sync {
    /// A box holding every point.
    fn bounds(&self) -> WorldBounds;
    fn point_count(&self) -> u64;
    /// Visits every point once, batch by batch; an error from `visit` stops the walk and is
    /// returned.
    fn for_each_batch(&self, visit: &mut BatchVisitor<'_>) -> Result<(), LodError>;

    /// The one LAS grid every point lies on, if there is one: the builder's spill records then
    /// hold the grid's integers instead of f64 positions.
    fn position_grid(&self) -> Option<PositionGrid> {
        None
    }

    /// A text that changes whenever the points this source reads may have (its files' paths,
    /// lengths and modification times; a generator's parameters), so that a build stopped
    /// part way resumes only over the same points. `None` where the source cannot say: its
    /// builds start over.
    fn fingerprint(&self) -> Option<String> {
        None
    }

    /// The points where a read can start without reading those before them (each file's
    /// first), ascending from 0: a build stopped in its counting pass resumes at one.
    fn part_starts(&self) -> Vec<u64> {
        vec![0]
    }

    /// [`PointSource::for_each_batch`] from the point `first`, one of
    /// [`PointSource::part_starts`], on.
    fn for_each_batch_from(
        &self,
        first: u64,
        visit: &mut BatchVisitor<'_>,
    ) -> Result<(), LodError> {
        if first != 0 {
            return Err(LodError::Source(format!(
                "the source cannot start reading at point {first}"
            )));
        }
        self.for_each_batch(visit)
    }

    /// What each point's attribute row holds, where the source has every attribute of its
    /// points to keep (its files'): the builder then stores the rows for an export.
    fn attributes(&self) -> Option<AttributeSchema> {
        None
    }
}

/// A [`PointSource::fingerprint`] of points read from `paths`: each file's absolute path,
/// length and modification time (to the nanosecond); `None` when a file cannot be looked up.
pub fn files_fingerprint<'p>(paths: impl IntoIterator<Item = &'p Path>) -> Option<String> {
    let mut text = String::new();
    for path in paths {
        let absolute = std::fs::canonicalize(path).ok()?;
        let metadata = std::fs::metadata(&absolute).ok()?;
        let modified = metadata
            .modified()
            .ok()?
            .duration_since(std::time::UNIX_EPOCH)
            .ok()?;
        text.push_str(&format!(
            "{} {} bytes modified {}.{:09}; ",
            absolute.display(),
            metadata.len(),
            modified.as_secs(),
            modified.subsec_nanos()
        ));
    }
    Some(text)
}

/// Points per batch of the in-memory and generated sources.
pub const SOURCE_BATCH_POINTS: usize = 1 << 16;

/// A [`PointCloud`] as a source: world = origin + offset, in f64. Its colors are already
/// packed for display, so its batches carry no raw RGB.
pub struct CloudSource<'a> {
    cloud: &'a PointCloud,
    bounds: WorldBounds,
}

impl<'a> CloudSource<'a> {
    /// The bounds are those of the reconstructed world positions: the cloud's own bounds came
    /// from the f64 positions before they were rounded to f32 offsets.
    pub fn new(cloud: &'a PointCloud) -> Self {
        let bounds =
            crate::cloud::bounds_of(cloud.positions.iter().map(|p| cloud.origin + p.as_dvec3()));
        Self { cloud, bounds }
    }
}

impl PointSource for CloudSource<'_> {
    fn bounds(&self) -> WorldBounds {
        self.bounds
    }

    fn point_count(&self) -> u64 {
        self.cloud.len() as u64
    }

    fn for_each_batch(&self, visit: &mut BatchVisitor<'_>) -> Result<(), LodError> {
        let cloud = self.cloud;
        let mut world = Vec::with_capacity(SOURCE_BATCH_POINTS.min(cloud.len()));
        for start in (0..cloud.len()).step_by(SOURCE_BATCH_POINTS) {
            let end = (start + SOURCE_BATCH_POINTS).min(cloud.len());
            world.clear();
            world.extend(
                cloud.positions[start..end]
                    .iter()
                    .map(|p| cloud.origin + p.as_dvec3()),
            );
            visit(PointBatch {
                positions: &world,
                rgb: None,
                intensity: &cloud.intensity[start..end],
                classification: &cloud.classification[start..end],
                return_number: &cloud.return_number[start..end],
                rows: &[],
            })?;
        }
        Ok(())
    }
}
