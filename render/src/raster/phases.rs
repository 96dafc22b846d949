//! The phases of a frame's depth-writing point pass: its listed batches split by depth.
//!
//! Between phases the occlusion tiles are built from the framebuffer (`occlusion.rs`), and a
//! later phase skips the batches that lie behind them. A phase is the batches whose nearest
//! corner lies within a band of depths: phase 0 the nearest share of all listed batches
//! (across the segments), then the next share, and so on. Within a phase
//! each segment keeps its near-to-far Z-order (`draw_order.rs`), whose neighbouring batches
//! write neighbouring pixels.
//!
//! Phases by depth, not by position along that curve, because a batch late on the curve may
//! still lie near the camera somewhere on screen, and phases by depth skip more batches
//! (docs/perf/depth-phases.md).

use glam::{DVec3, DVec4, Vec3};

use super::gpu_data::GpuBatch;

/// One segment's listed entries (`ListedEntry` words) and the resident batch table they index.
pub(crate) struct SegmentEntries<'a> {
    pub entries: &'a mut [u32],
    pub batches: &'a [GpuBatch],
}

/// Splits every segment's entries into phases at the depths below which the shares `cuts`
/// (ascending, in 0..1) of all listed batches lie: reorders each segment's entries phase by
/// phase, each keeping its order, and returns per segment the end of each phase's entries
/// (`cuts.len() + 1` of them). Phase boundaries are rounded up to multiples of `alignment`
/// entries, so that each phase's entries can be bound on their own: a few batches move to
/// the phase before theirs, which only tests them against older tiles.
pub(crate) fn split_by_depth(
    segments: &mut [SegmentEntries<'_>],
    cuts: &[f64],
    depth_row: DVec4,
    alignment: u32,
) -> Vec<Vec<u32>> {
    if cuts.is_empty() {
        return segments
            .iter()
            .map(|segment| vec![segment.entries.len() as u32])
            .collect();
    }
    // Each entry's nearest depth, once, all segments back to back.
    let depths: Vec<f64> = segments
        .iter()
        .flat_map(|segment| {
            segment
                .entries
                .iter()
                .map(|&e| nearest_depth(&segment.batches[(e >> 8) as usize], depth_row))
        })
        .collect();
    let cut_depths = quantiles(&mut depths.clone(), cuts);
    let phase_of = |depth: f64| cut_depths.iter().filter(|&&cut| depth >= cut).count();
    let mut segment_depths = depths.as_slice();
    segments
        .iter_mut()
        .map(|segment| {
            let count = segment.entries.len();
            let (own, rest) = segment_depths.split_at(count);
            segment_depths = rest;
            // A stable partition by phase: a counting sort.
            let phases: Vec<usize> = own.iter().map(|&depth| phase_of(depth)).collect();
            let mut next = vec![0u32; cut_depths.len() + 1];
            for &phase in &phases {
                next[phase] += 1;
            }
            // From the phases' sizes to their starts.
            let mut start = 0;
            for slot in &mut next {
                (*slot, start) = (start, start + *slot);
            }
            let mut sorted = vec![0u32; count];
            for (&entry, &phase) in segment.entries.iter().zip(&phases) {
                sorted[next[phase] as usize] = entry;
                next[phase] += 1;
            }
            segment.entries.copy_from_slice(&sorted);
            // `next` now holds each phase's end.
            next.iter()
                .map(|&end| end.next_multiple_of(alignment.max(1)).min(count as u32))
                .collect()
        })
        .collect()
}

/// The linear depth of the nearest point of `batch`'s box.
fn nearest_depth(batch: &GpuBatch, depth_row: DVec4) -> f64 {
    let (min, max) = (
        Vec3::from_array(batch.min).as_dvec3(),
        Vec3::from_array(batch.max).as_dvec3(),
    );
    let gradient: DVec3 = depth_row.truncate();
    gradient.dot((min + max) * 0.5) + depth_row.w - gradient.abs().dot((max - min) * 0.5)
}

/// The values below which the shares `cuts` of `values` lie (reorders `values`).
fn quantiles(values: &mut [f64], cuts: &[f64]) -> Vec<f64> {
    cuts.iter()
        .map(|&share| {
            let rank = ((values.len() as f64 * share) as usize).min(values.len() - 1);
            *values.select_nth_unstable_by(rank, f64::total_cmp).1
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A unit box centred at depth `z` for a camera looking down -z from the origin.
    fn batch_at(z: f32) -> GpuBatch {
        GpuBatch {
            min: [-0.5, -0.5, -z - 0.5],
            first: 0,
            max: [0.5, 0.5, -z + 0.5],
            count: 4096,
        }
    }

    const LOOKING_DOWN_Z: DVec4 = DVec4::new(0.0, 0.0, -1.0, 0.0);

    #[test]
    fn the_nearest_share_comes_first_and_each_phase_keeps_its_order() {
        // Two segments; batch b of each lies at depth 10 + b in segment 0 and 5 + 2b in segment 1.
        let tables: [Vec<GpuBatch>; 2] = [
            (0..10).map(|b| batch_at(10.0 + b as f32)).collect(),
            (0..10).map(|b| batch_at(5.0 + 2.0 * b as f32)).collect(),
        ];
        // Entries in a shuffled order (as the Z-order curve may list them), whole batches.
        let mut lists: [Vec<u32>; 2] = [
            [3u32, 0, 7, 1, 9, 2, 8, 4, 6, 5]
                .map(|b| b << 8 | 15)
                .to_vec(),
            [9u32, 1, 0, 5, 2, 8, 3, 7, 4, 6]
                .map(|b| b << 8 | 15)
                .to_vec(),
        ];
        let [a, b] = &mut lists;
        let mut segments = [
            SegmentEntries {
                entries: a,
                batches: &tables[0],
            },
            SegmentEntries {
                entries: b,
                batches: &tables[1],
            },
        ];
        let ends = split_by_depth(&mut segments, &[0.25, 0.5], LOOKING_DOWN_Z, 1);
        // Nearest depths of the 20 batches: 9.5, 10.5, ..., 18.5 and 4.5, 6.5, ..., 22.5. The
        // 25% cut (rank 5 of the 20) is 10.5, the 50% cut (rank 10) is 14.5.
        let depth = |segment: usize, entry: u32| {
            nearest_depth(&tables[segment][(entry >> 8) as usize], LOOKING_DOWN_Z)
        };
        for (segment, list) in lists.iter().enumerate() {
            let mut start = 0;
            for (phase, &end) in ends[segment].iter().enumerate() {
                let band = [f64::MIN, 10.5, 14.5, f64::MAX];
                for &entry in &list[start as usize..end as usize] {
                    let d = depth(segment, entry);
                    assert!(
                        d >= band[phase] && d < band[phase + 1],
                        "{segment} {phase} {d}"
                    );
                }
                start = end;
            }
            assert_eq!(start, 10);
        }
        // Each phase keeps the order the batches were listed in.
        let batches = |list: &[u32]| list.iter().map(|e| e >> 8).collect::<Vec<_>>();
        assert_eq!(batches(&lists[0]), [0, 3, 1, 2, 4, 7, 9, 8, 6, 5]);
        assert_eq!(ends[0], [1, 5, 10]);
        assert_eq!(batches(&lists[1]), [1, 0, 2, 3, 4, 9, 5, 8, 7, 6]);
        assert_eq!(ends[1], [3, 5, 10]);
    }

    #[test]
    fn boundaries_round_up_to_the_alignment_and_no_cuts_is_one_phase() {
        let table: Vec<GpuBatch> = (0..10).map(|b| batch_at(1.0 + b as f32)).collect();
        let mut list: Vec<u32> = (0..10u32).rev().map(|b| b << 8 | 15).collect();
        let mut segments = [SegmentEntries {
            entries: &mut list,
            batches: &table,
        }];
        let ends = split_by_depth(&mut segments, &[0.3], LOOKING_DOWN_Z, 4);
        // Three batches in the first phase, rounded up to four entries.
        assert_eq!(ends, [vec![4, 10]]);
        let ends = split_by_depth(&mut segments, &[], LOOKING_DOWN_Z, 4);
        assert_eq!(ends, [vec![10]]);
    }
}
