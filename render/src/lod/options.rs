//! `LodBuildOptions`: the builder's knobs and their defaults, stated once.

use std::path::PathBuf;

use super::error::LodError;

/// The most points a leaf holds before it splits, and the most an inner node's sample may
/// hold before its grid is coarsened: Potree and Scheiblauer keep nodes at tens of thousands.
pub const DEFAULT_MAX_LEAF_POINTS: usize = 50_000;
/// Cells per axis of an inner node's sampling grid (its spacing is the node's side / this).
pub const DEFAULT_SAMPLE_GRID: u32 = 128;
/// The default host-memory budget of a build.
pub const DEFAULT_MEMORY_BUDGET_BYTES: u64 = 1 << 30;
/// The most points the counting pass puts in one partition (PotreeConverter uses about 10M).
pub const DEFAULT_MAX_PARTITION_POINTS: u64 = 4_000_000;

/// What the builder reserves from the budget per point it holds in memory: the point (40 B),
/// its copy while a node is split into children, the sampling map and the encoded node.
pub const BUILD_BYTES_PER_POINT: u64 = 128;

#[derive(Debug, Clone, PartialEq)]
pub struct LodBuildOptions {
    /// Host memory the builder's own buffers may hold at once (the source's batches aside).
    pub memory_budget_bytes: u64,
    /// A folder for spill files; the build makes a fresh folder inside and removes it.
    pub spill_dir: PathBuf,
    /// The most points of a leaf (and of an inner node's sample).
    pub max_leaf_points: usize,
    /// Cells per axis of an inner node's sampling grid; a power of two, 1 to 128.
    pub sample_grid: u32,
    /// The most points of a partition the counting pass makes; the budget may lower it.
    pub max_partition_points: u64,
    /// Rayon threads for the build; `None` uses the global pool (every core).
    pub threads: Option<usize>,
}

impl LodBuildOptions {
    pub fn new(spill_dir: impl Into<PathBuf>) -> Self {
        Self {
            memory_budget_bytes: DEFAULT_MEMORY_BUDGET_BYTES,
            spill_dir: spill_dir.into(),
            max_leaf_points: DEFAULT_MAX_LEAF_POINTS,
            sample_grid: DEFAULT_SAMPLE_GRID,
            max_partition_points: DEFAULT_MAX_PARTITION_POINTS,
            threads: None,
        }
    }

    /// The smallest budget these options can run in: an upper node's eight children and
    /// itself at full size, twice over, so the merge step always fits, and 2 MiB for the
    /// statistics, the counting grid, read blocks and write buffers.
    pub fn min_memory_budget_bytes(&self) -> u64 {
        16 * self.max_leaf_points as u64 * BUILD_BYTES_PER_POINT + (2 << 20)
    }

    pub(crate) fn validate(&self) -> Result<(), LodError> {
        let fail = |message: String| Err(LodError::InvalidOptions(message));
        if self.max_leaf_points < 16 || self.max_leaf_points > 1 << 24 {
            return fail(format!(
                "max_leaf_points is {}, expected 16 to 16777216",
                self.max_leaf_points
            ));
        }
        if !self.sample_grid.is_power_of_two() || self.sample_grid > 128 {
            return fail(format!(
                "sample_grid is {}, expected a power of two from 1 to 128",
                self.sample_grid
            ));
        }
        if self.max_partition_points < self.max_leaf_points as u64 {
            return fail(format!(
                "max_partition_points ({}) is below max_leaf_points ({})",
                self.max_partition_points, self.max_leaf_points
            ));
        }
        if self.threads == Some(0) {
            return fail("threads is 0".into());
        }
        let min = self.min_memory_budget_bytes();
        if self.memory_budget_bytes < min {
            return fail(format!(
                "memory_budget_bytes is {}, at least {min} are needed for max_leaf_points {}",
                self.memory_budget_bytes, self.max_leaf_points
            ));
        }
        Ok(())
    }
}
