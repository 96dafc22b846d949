//! `FileFacts`: what a store records of each file its points came from (its points, the box
//! they fill, their RGB range), so that a removed or changed file can be taken out of the store
//! (`update.rs`): a region a removed file's box meets is built again without the points inside
//! that box, and the dataset's ranges come back from the remaining files' facts.
//!
//! A region's files are those whose box meets its cube: every file that put a point in the
//! region is among them. The boxes are the points' own, gathered as a build or update reads
//! them (`FactsGathering`), not the headers' (which a file may state loosely).

use std::sync::Mutex;

use glam::DVec3;

use super::error::LodError;
use super::fields::FieldReader;
use super::source::{BatchVisitor, PointBatch, PointSource};
use crate::cloud::WorldBounds;

/// Bytes of one file's facts in the regions record.
pub(super) const ENCODED_BYTES: usize = 8 + 6 * 8 + 6 * 2;

/// One file's points: how many, the box they fill and their raw RGB range.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FileFacts {
    pub points: u64,
    pub min: DVec3,
    pub max: DVec3,
    pub min_rgb: [u16; 3],
    pub max_rgb: [u16; 3],
}

impl Default for FileFacts {
    fn default() -> Self {
        Self {
            points: 0,
            min: DVec3::INFINITY,
            max: DVec3::NEG_INFINITY,
            min_rgb: [u16::MAX; 3],
            max_rgb: [0; 3],
        }
    }
}

impl FileFacts {
    /// Adds one point at `position`, its raw RGB counted where the source has it.
    #[inline]
    pub(super) fn add_point(&mut self, position: DVec3, rgb: Option<[u16; 3]>) {
        self.points += 1;
        self.min = self.min.min(position);
        self.max = self.max.max(position);
        if let Some(c) = rgb {
            for ((min, max), v) in self.min_rgb.iter_mut().zip(&mut self.max_rgb).zip(c) {
                *min = (*min).min(v);
                *max = (*max).max(v);
            }
        }
    }

    /// Adds the points `other` has facts of.
    pub(super) fn merge(&mut self, other: &Self) {
        self.points += other.points;
        self.min = self.min.min(other.min);
        self.max = self.max.max(other.max);
        for c in 0..3 {
            self.min_rgb[c] = self.min_rgb[c].min(other.min_rgb[c]);
            self.max_rgb[c] = self.max_rgb[c].max(other.max_rgb[c]);
        }
    }

    /// Adds the points `range` of `batch`.
    fn add(&mut self, batch: &PointBatch<'_>, range: std::ops::Range<usize>) {
        self.points += range.len() as u64;
        for p in &batch.positions[range.clone()] {
            self.min = self.min.min(*p);
            self.max = self.max.max(*p);
        }
        if let Some(rgb) = batch.rgb {
            for c in &rgb[range] {
                for ((min, max), &v) in self.min_rgb.iter_mut().zip(&mut self.max_rgb).zip(c) {
                    *min = (*min).min(v);
                    *max = (*max).max(v);
                }
            }
        }
    }

    /// The file's box widened by `margin` on every side.
    pub fn widened(&self, margin: DVec3) -> WorldBounds {
        WorldBounds {
            min: self.min - margin,
            max: self.max + margin,
        }
    }

    pub(super) fn encode(&self, out: &mut Vec<u8>) {
        out.extend_from_slice(&self.points.to_le_bytes());
        for v in self.min.to_array().into_iter().chain(self.max.to_array()) {
            out.extend_from_slice(&v.to_le_bytes());
        }
        for v in self.min_rgb.into_iter().chain(self.max_rgb) {
            out.extend_from_slice(&v.to_le_bytes());
        }
    }

    pub(super) fn decode(r: &mut FieldReader<'_>) -> Result<Self, LodError> {
        Ok(Self {
            points: r.u64()?,
            min: DVec3::new(r.f64()?, r.f64()?, r.f64()?),
            max: DVec3::new(r.f64()?, r.f64()?, r.f64()?),
            min_rgb: [r.u16()?, r.u16()?, r.u16()?],
            max_rgb: [r.u16()?, r.u16()?, r.u16()?],
        })
    }
}

/// Whether `bounds` holds `p`, its faces included.
pub(super) fn holds(bounds: &WorldBounds, p: DVec3) -> bool {
    p.cmpge(bounds.min).all() && p.cmple(bounds.max).all()
}

/// Whether `bounds` meets the cube of corner `min` and side `side`.
pub(super) fn meets_cube(bounds: &WorldBounds, min: DVec3, side: f64) -> bool {
    bounds.max.cmpge(min).all() && bounds.min.cmple(min + DVec3::splat(side)).all()
}

/// A source read through, the facts of each of its parts (its files, `part_starts`)
/// gathered from the batches as they pass; or, read by the counting pass, added by it from
/// the facts its tasks gather as they make each point's record ([`Self::add`]).
pub(super) struct FactsGathering<'s> {
    source: &'s dyn PointSource,
    starts: Vec<u64>,
    facts: Mutex<Vec<FileFacts>>,
}

impl<'s> FactsGathering<'s> {
    pub(super) fn new(source: &'s dyn PointSource) -> Self {
        Self::with_starts(source, source.part_starts())
    }

    /// The facts of the parts of `source` starting at `starts` (ascending from 0).
    pub(super) fn with_starts(source: &'s dyn PointSource, starts: Vec<u64>) -> Self {
        let facts = Mutex::new(vec![FileFacts::default(); starts.len()]);
        Self {
            source,
            starts,
            facts,
        }
    }

    /// Each part's facts, as far as the source has been read.
    pub(super) fn into_facts(self) -> Vec<FileFacts> {
        self.facts
            .into_inner()
            .unwrap_or_else(|poisoned| poisoned.into_inner())
    }

    /// The source whose parts' facts this gathers.
    pub(super) fn source(&self) -> &'s dyn PointSource {
        self.source
    }

    /// The first point of the part after the one holding point `index`, if there is one.
    pub(super) fn next_start(&self, index: u64) -> Option<u64> {
        let next = self.starts.partition_point(|&s| s <= index);
        self.starts.get(next).copied()
    }

    /// Adds `facts` of points of one part from the source's point `first` on.
    pub(super) fn add(&self, first: u64, facts: &FileFacts) {
        let part = self
            .starts
            .partition_point(|&s| s <= first)
            .saturating_sub(1);
        let mut all = self
            .facts
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner());
        if let Some(f) = all.get_mut(part) {
            f.merge(facts);
        }
    }

    /// Adds `batch`, whose first point is the source's point `first`, part by part.
    fn gather(&self, first: u64, batch: &PointBatch<'_>) {
        let mut facts = self
            .facts
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner());
        let mut at = 0usize;
        while at < batch.len() {
            let index = first + at as u64;
            // The last part starting at or before the point: an empty part shares its start
            // with the next.
            let part = self
                .starts
                .partition_point(|&s| s <= index)
                .saturating_sub(1);
            let end = self.starts.get(part + 1).map_or(u64::MAX, |&s| s);
            let n = ((end - index).min((batch.len() - at) as u64)) as usize;
            if let Some(f) = facts.get_mut(part) {
                f.add(batch, at..at + n);
            }
            at += n;
        }
    }
}

impl PointSource for FactsGathering<'_> {
    fn bounds(&self) -> WorldBounds {
        self.source.bounds()
    }

    fn point_count(&self) -> u64 {
        self.source.point_count()
    }

    fn for_each_batch(&self, visit: &mut BatchVisitor<'_>) -> Result<(), LodError> {
        self.for_each_batch_from(0, visit)
    }

    fn position_grid(&self) -> Option<super::grid::PositionGrid> {
        self.source.position_grid()
    }

    fn fingerprint(&self) -> Option<String> {
        self.source.fingerprint()
    }

    fn part_starts(&self) -> Vec<u64> {
        self.starts.clone()
    }

    fn for_each_batch_from(
        &self,
        first: u64,
        visit: &mut BatchVisitor<'_>,
    ) -> Result<(), LodError> {
        let mut index = first;
        self.source.for_each_batch_from(first, &mut |batch| {
            self.gather(index, &batch);
            index += batch.len() as u64;
            visit(batch)
        })
    }

    fn attributes(&self) -> Option<super::attributes::AttributeSchema> {
        self.source.attributes()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lod::GeneratedSource;

    #[test]
    fn facts_gather_each_part_of_a_source() {
        let source = GeneratedSource::terrain(70_000, 3);
        let gathering = FactsGathering::new(&source);
        let mut count = 0u64;
        gathering
            .for_each_batch(&mut |b| {
                count += b.len() as u64;
                Ok(())
            })
            .expect("read");
        let facts = gathering.into_facts();
        assert_eq!(facts.len(), source.part_starts().len());
        assert_eq!(facts.iter().map(|f| f.points).sum::<u64>(), count);
        let bounds = source.bounds();
        for f in &facts {
            assert!(f.min.cmpge(bounds.min).all() && f.max.cmple(bounds.max).all());
        }
        let mut bytes = Vec::new();
        facts[0].encode(&mut bytes);
        assert_eq!(bytes.len(), ENCODED_BYTES);
        let mut r = FieldReader::new(&bytes, "facts: truncated");
        assert_eq!(FileFacts::decode(&mut r).expect("decoded"), facts[0]);
    }
}
