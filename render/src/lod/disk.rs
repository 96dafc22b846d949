//! The disk a build takes, known before it starts, so that a dataset too large for the disk
//! is refused before a point is read.

use super::codec::encoded_len;
use super::counting::BUCKET_SEGMENT_POINTS;
use super::point::{RecordLayout, MAX_RECORD_BYTES};
use super::source::PointSource;

/// The largest spill record, for an estimate made before the files are open.
pub const MAX_SPILL_RECORD_BYTES: u64 = MAX_RECORD_BYTES as u64;

/// Bytes of a spill record of `source`'s build: smaller where its files share one grid,
/// larger by the attribute row where the source keeps every attribute.
pub fn spill_record_bytes(source: &dyn PointSource) -> u64 {
    let row_bytes = source.attributes().map_or(0, |a| a.row_bytes());
    RecordLayout::for_grid(source.position_grid(), row_bytes).record_bytes() as u64
}

/// Bytes a build of `points` points needs on disk at its peak, in spill records of
/// `record_bytes` ([`spill_record_bytes`]): a spill record a point (the buckets the counting
/// pass writes), which the stored nodes replace partition by partition (a stored point takes less
/// than its record), with a tenth of slack; a bucket segment's records and stored points in
/// flight (a partition split on disk removes each segment once it has read it); and a margin for
/// the hierarchy and partial pages. The store itself stays after the build, at less than its
/// spill (docs/perf/campaign-1b.md).
pub fn build_disk_bytes(points: u64, has_rgb: bool, record_bytes: u64) -> u64 {
    let record = record_bytes;
    let stored = stored_bytes_per_point(has_rgb);
    let per_point = record.max(stored) + record.max(stored).div_ceil(10);
    points
        .saturating_mul(per_point)
        .saturating_add(points.min(BUCKET_SEGMENT_POINTS) * (record + stored))
        .saturating_add(64 << 20)
}

/// A stored point's bytes, its node's header and checksum left out.
fn stored_bytes_per_point(has_rgb: bool) -> u64 {
    (encoded_len(1, has_rgb) - encoded_len(0, has_rgb)) as u64
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_estimate_covers_the_spill_with_slack_and_one_segment_in_flight() {
        let margin = 64 << 20;
        let record = MAX_SPILL_RECORD_BYTES;
        let stored = stored_bytes_per_point(true);
        assert!(
            stored < record,
            "a stored point replaces its record in less"
        );
        let slack = record.div_ceil(10);
        assert_eq!(
            build_disk_bytes(1_000_000, true, record) - margin,
            1_000_000 * (record + slack + record + stored)
        );
        let large = 1_000_000_000;
        let per_point = (build_disk_bytes(large, true, record) - margin) as f64 / large as f64;
        assert!(
            per_point > (record + slack) as f64 && per_point < (record + slack) as f64 + 3.0,
            "{per_point}"
        );
        assert_eq!(build_disk_bytes(u64::MAX, true, record), u64::MAX);
        // Grid records: less disk by their difference a point, and the store still fits.
        let grid = super::super::point::GRID_RECORD_BYTES as u64;
        assert!(stored < grid);
        assert_eq!(
            build_disk_bytes(1_000_000, true, record) - build_disk_bytes(1_000_000, true, grid),
            1_000_000 * (2 * (record - grid) + slack - grid.div_ceil(10))
        );
    }
}
