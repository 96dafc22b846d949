//! The disk a build takes, known before it starts, so that a dataset too large for the disk
//! is refused before a point is read.

use super::cached::COPY_SEGMENT_POINTS;
use super::codec::encoded_len;
use super::point::SPILL_RECORD_BYTES;

/// Bytes a build of `points` points needs on disk at its peak: a spill record a point (the
/// chunks' spill, or while the distribution runs that and what is left of the copy of a
/// source costly to read again, LAZ), the stored nodes, which replace the chunks' spill as
/// the chunks are built, one segment of the copy, and a margin for the hierarchy and partial
/// pages.
pub fn build_disk_bytes(points: u64, has_rgb: bool) -> u64 {
    let record = SPILL_RECORD_BYTES as u64;
    points
        .saturating_mul(record + encoded_len(1, has_rgb) as u64)
        .saturating_add(points.min(COPY_SEGMENT_POINTS) * record)
        .saturating_add(64 << 20)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_estimate_covers_spill_store_and_one_segment_of_the_copy() {
        let margin = 64 << 20;
        let record = SPILL_RECORD_BYTES as u64;
        let stored = encoded_len(1, true) as u64;
        assert_eq!(
            build_disk_bytes(1_000_000, true) - margin,
            1_000_000 * (2 * record + stored)
        );
        let large = 1_000_000_000;
        let per_point = (build_disk_bytes(large, true) - margin) as f64 / large as f64;
        assert!(
            per_point > (record + stored) as f64 && per_point < (record + stored) as f64 + 2.0,
            "{per_point}"
        );
        assert_eq!(build_disk_bytes(u64::MAX, true), u64::MAX);
    }
}
