//! The frame's batch table: the batches that can be in view.
//!
//! Every frame, on the host, before any GPU work, each segment's batches are culled against the
//! view frustum (Günther et al.'s frustum culling, per batch): a batch is left out when all
//! eight corners of its box lie beyond the same plane of the frustum, widened by the point
//! size and a pixel of margin for the shaders' f32 arithmetic. The point passes read this
//! table instead of the cloud's own and dispatch one workgroup per entry, so a culled batch
//! costs the GPU nothing (docs/perf/batch-culling.md). Points of listed entries are still
//! culled one by one.
//!
//! - Runs of 32 batches (groups) are tested first: a group wholly in view is listed without
//!   testing its batches, a group wholly outside is dropped with them.
//! - On a CPU adapter, a batch that straddles the edge of the view is culled again in runs of
//!   256 points (sub-batches, whose boxes only the host keeps), and only its runs that can be
//!   in view are listed, which shortens the point pass on lavapipe
//!   (docs/perf/batch-culling.md). A GPU draws the whole batch faster than the host tests
//!   them.
//! - A cloud of many segments is culled on all cores, a segment per task.
//!
//! The same pass over the boxes bounds the frame's footprint: the pixels any listed point can
//! touch. The resolve skips the rest of the image when it is known to be empty (`targets.rs`).
//!
//! The table holds a word per listed batch (`ListedEntry`: the batch's index in its segment's
//! resident table and the run of its sub-batches to draw), not a copy of its 32-byte entry.
//! Each segment's entries are listed near to far along a mirrored Z-order curve
//! (`draw_order.rs`: the order is kept per segment and octant of view directions, so a frame
//! walks it instead of sorting), and the segments themselves are ordered near to far. This is
//! the stage "cull" of a frame's timings, part of its frame time.
//!
//! - `frustum.rs`: the frustum and the test of one box against it;
//! - `listing.rs`: a segment's entries that can be in view, near to far;
//! - `batch_table.rs`: the frame's tables of every segment in one GPU buffer.

mod batch_table;
mod frustum;
mod listing;

pub(crate) use batch_table::FrameBatches;
pub(crate) use frustum::Frustum;

#[cfg(test)]
use crate::raster::gpu_data::GpuBatch;
#[cfg(test)]
use glam::Vec3;

/// Entries of a frame table as the shaders see them, from their segment's `batches`.
#[cfg(test)]
pub(crate) fn decoded(entries: &[u32], batches: &[GpuBatch]) -> Vec<GpuBatch> {
    entries
        .iter()
        .map(|&entry| listing::ListedEntry(entry).batch(batches))
        .collect()
}

/// A box from `min` to `max` holding one point.
#[cfg(test)]
pub(crate) fn batch(min: Vec3, max: Vec3) -> GpuBatch {
    GpuBatch {
        min: min.to_array(),
        first: 0,
        max: max.to_array(),
        count: 1,
    }
}
