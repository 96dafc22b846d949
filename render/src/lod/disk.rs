//! The disk a build takes, known before it starts, so that a dataset too large for the disk
//! is refused before a point is read.

use super::codec::encoded_len;
use super::point::SPILL_RECORD_BYTES;

/// Bytes a build of `points` points needs on disk at its peak: the spilled chunks (every
/// point once) and the stored nodes, with a margin for the hierarchy and partial pages.
pub fn build_disk_bytes(points: u64, has_rgb: bool) -> u64 {
    let stored = encoded_len(1, has_rgb) as u64;
    points
        .saturating_mul(SPILL_RECORD_BYTES as u64 + stored)
        .saturating_add(64 << 20)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_estimate_covers_spill_and_store() {
        let per_point = (build_disk_bytes(1_000_000, true) - (64 << 20)) / 1_000_000;
        assert!(per_point >= SPILL_RECORD_BYTES as u64 + 22, "{per_point}");
        assert_eq!(build_disk_bytes(u64::MAX, true), u64::MAX);
    }
}
