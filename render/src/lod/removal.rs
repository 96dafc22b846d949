//! `Removal`: the files taken out of a store by an update (`update.rs`), as the boxes of their
//! points (`file_facts.rs`), and which of a region's stored points they take with them.
//!
//! A store does not know which file each point came from, only each file's box. Every stored
//! point of a region a removed box meets that lies inside that box is dropped; the remaining
//! files whose boxes hold such a point are read again, and their points inside the removed
//! boxes put back. Tiles of a survey do not overlap, so a removed tile's points are dropped
//! and no other file is read; where boxes overlap, only the overlapping files are read.
//!
//! The test is exact because a store that takes removals keeps its points on one LAS grid
//! (`update.rs` puts decoded positions back on it): the boxes are widened by half a grid step,
//! so a point on a box's face lies inside it whichever of its two bit-near spellings it has.

use std::collections::BTreeSet;

use super::error::LodError;
use super::file_facts::{holds, meets_cube, FileFacts};
use super::key::{NodeKey, RootCube};
use super::point::RawPoint;
use super::regions::StoreRegions;
use super::stats::DatasetStats;
use crate::cloud::WorldBounds;

fn cannot(reason: impl Into<String>) -> LodError {
    LodError::CannotUpdate(reason.into())
}

pub(super) struct Removal {
    /// The removed files' boxes, widened.
    removed: Vec<WorldBounds>,
    /// Each remaining file's place in the store's facts, with its box, widened.
    remaining: Vec<(usize, WorldBounds)>,
    /// The remaining files (by place) holding a dropped point: read again.
    pub reread: BTreeSet<usize>,
    /// Stored points dropped.
    pub dropped: u64,
}

impl Removal {
    /// The removal of the files at places `removed` in `regions`' facts; `None` when none is.
    /// Refused for a store without facts or without one LAS grid.
    pub fn plan(regions: &StoreRegions, removed: &[usize]) -> Result<Option<Self>, LodError> {
        if removed.is_empty() {
            return Ok(None);
        }
        let facts: &[FileFacts] = regions.file_facts.as_deref().ok_or_else(|| {
            cannot("the store does not record which files its regions hold, so none can be removed")
        })?;
        let grid = regions.grid.ok_or_else(|| {
            cannot("the store's points lie on no one LAS grid, so a removed file's cannot be told")
        })?;
        if let Some(&bad) = removed.iter().find(|&&i| i >= facts.len()) {
            return Err(cannot(format!(
                "file {bad} is removed, the store records {}",
                facts.len()
            )));
        }
        let margin = grid.scale() / 2.0;
        let gone: BTreeSet<usize> = removed.iter().copied().collect();
        Ok(Some(Self {
            removed: gone.iter().map(|&i| facts[i].widened(margin)).collect(),
            remaining: (0..facts.len())
                .filter(|i| !gone.contains(i))
                .map(|i| (i, facts[i].widened(margin)))
                .collect(),
            reread: BTreeSet::new(),
            dropped: 0,
        }))
    }

    /// Whether a removed file's box meets the cube of `key`: its region may lose points.
    pub fn meets(&self, cube: &RootCube, key: NodeKey) -> bool {
        let (min, side) = (cube.node_min(key), cube.side_at(key.level));
        self.removed.iter().any(|b| meets_cube(b, min, side))
    }

    /// Whether `p` lies inside a removed file's box.
    pub fn inside(&self, p: glam::DVec3) -> bool {
        self.removed.iter().any(|b| holds(b, p))
    }

    /// Whether the stored point `p` is dropped; a dropped point leaves `stats`, and the
    /// remaining files whose boxes hold it are to be read again.
    pub fn drops(&mut self, p: &RawPoint, stats: &mut DatasetStats) -> bool {
        if !self.inside(p.position) {
            return false;
        }
        for (i, bounds) in &self.remaining {
            if holds(bounds, p.position) {
                self.reread.insert(*i);
            }
        }
        self.dropped += 1;
        count_point(stats, p, false);
        true
    }
}

/// Counts `p` into the histograms of `stats`, or out of them; the ranges come from the files'
/// facts.
pub(super) fn count_point(stats: &mut DatasetStats, p: &RawPoint, into: bool) {
    let bins = [
        &mut stats.intensity_histogram[usize::from(p.intensity)],
        &mut stats.class_counts[usize::from(p.classification)],
    ];
    for bin in bins {
        *bin = match into {
            true => *bin + 1,
            false => bin.saturating_sub(1),
        };
    }
}

/// The dataset's ranges (z, RGB) of the points of `facts`, as a build of their files finds.
pub(super) fn ranges_of(stats: &mut DatasetStats, facts: &[FileFacts]) {
    stats.z_range = [f64::INFINITY, f64::NEG_INFINITY];
    stats.min_rgb = [u16::MAX; 3];
    stats.max_rgb = [0; 3];
    for f in facts.iter().filter(|f| f.points > 0) {
        stats.z_range[0] = stats.z_range[0].min(f.min.z);
        stats.z_range[1] = stats.z_range[1].max(f.max.z);
        for (min, &v) in stats.min_rgb.iter_mut().zip(&f.min_rgb) {
            *min = (*min).min(v);
        }
        for (max, &v) in stats.max_rgb.iter_mut().zip(&f.max_rgb) {
            *max = (*max).max(v);
        }
    }
}
