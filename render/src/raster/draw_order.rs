//! The order in which a frame's listed batches are drawn: near to far, and still along a
//! Z-order curve.
//!
//! The point passes' early depth test skips the atomic and the color fetch of a point
//! behind one already drawn, so drawing near batches first saves work. Sorting the batches by
//! depth loses what the cloud's Morton order gives: consecutive workgroups write nearby pixels
//! (on lavapipe that sort made frames slower: docs/perf/draw-order.md). Instead, the
//! batches follow the Z-order curve of the space mirrored on each axis along which depth
//! falls. At every level of that curve's octree the near half of a cell comes first, and
//! consecutive batches stay neighbours. For a view from outside the cell the "near half" is
//! taken from the depth gradient, exact for orthographic views and nearly so for perspective
//! ones.
//!
//! The order lets far fewer points pass the early depth test, nearly as few as an exact depth
//! order would (docs/perf/draw-order.md).

use std::sync::OnceLock;

use glam::{DVec3, Vec3};

use super::gpu_data::GpuBatch;
use super::morton::morton3;

/// Cells per axis of the curve the batches are ordered along.
const CELLS: u32 = 1 << 10;
// The curve's key (3 bits per level) fills the upper half of a u64, the entry's index the lower.
const _: () = assert!(CELLS <= 1 << 10);

/// Sorts `entries` near to far along the mirrored Z-order curve; `depth_gradient` is the
/// direction in which the view's linear depth grows. Entries with the same box (runs of one
/// batch) keep their order.
pub(crate) fn sort_near_to_far(entries: &mut [GpuBatch], depth_gradient: DVec3) {
    let order = near_to_far_order(entries, mirrored_axes(depth_gradient));
    let sorted: Vec<GpuBatch> = order.iter().map(|&i| entries[i as usize]).collect();
    entries.copy_from_slice(&sorted);
}

/// The indices of `entries` near to far along the Z-order curve of the space mirrored on the
/// axes `mirrored` (see [`mirrored_axes`]); equal keys keep their order.
fn near_to_far_order(entries: &[GpuBatch], mirrored: [bool; 3]) -> Vec<u32> {
    if entries.len() < 2 {
        return (0..entries.len() as u32).collect();
    }
    let (mut low, mut high) = (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY));
    for entry in entries {
        low = low.min(Vec3::from_array(entry.min));
        high = high.max(Vec3::from_array(entry.max));
    }
    let largest = (CELLS - 1) as f32;
    let scale = largest / (high - low).max_element().max(f32::MIN_POSITIVE);
    // Key and index in one word: an unstable sort of plain integers is several times faster
    // than a stable sort by cached keys, and the index keeps runs of one batch in order.
    let mut keyed: Vec<u64> = entries
        .iter()
        .enumerate()
        .map(|(i, entry)| {
            let centre = (Vec3::from_array(entry.min) + Vec3::from_array(entry.max)) * 0.5;
            let cell = ((centre - low) * scale).clamp(Vec3::ZERO, Vec3::splat(largest));
            let [x, y, z] = std::array::from_fn(|axis| {
                let c = cell[axis] as u32;
                if mirrored[axis] {
                    CELLS - 1 - c
                } else {
                    c
                }
            });
            (morton3(x, y, z) << 32) | i as u64
        })
        .collect();
    keyed.sort_unstable();
    keyed.iter().map(|&k| (k & 0xffff_ffff) as u32).collect()
}

/// The axes along which depth falls as the coordinate grows: on those the upper half of a
/// cell is the near one.
fn mirrored_axes(depth_gradient: DVec3) -> [bool; 3] {
    depth_gradient.to_array().map(|g| g < 0.0)
}

/// A batch table's near-to-far orders, one per octant of view directions, each built the
/// first time a view needs it. The order depends only on which axes depth falls along, so a
/// frame lists its batches by walking the order instead of sorting them (on the 10M-point
/// cube that sort was half of the host's culling).
#[derive(Debug, Default)]
pub(crate) struct DrawOrders {
    octants: [OnceLock<Vec<u32>>; 8],
}

impl DrawOrders {
    /// The indices of `batches` (always the same table) near to far for a view whose depth
    /// grows along `depth_gradient`.
    pub fn get(&self, batches: &[GpuBatch], depth_gradient: DVec3) -> &[u32] {
        let mirrored = mirrored_axes(depth_gradient);
        let octant = mirrored
            .iter()
            .enumerate()
            .map(|(axis, &m)| usize::from(m) << axis)
            .sum::<usize>();
        let order = self.octants[octant].get_or_init(|| near_to_far_order(batches, mirrored));
        debug_assert_eq!(order.len(), batches.len(), "orders of another table");
        order
    }
}

#[cfg(test)]
mod tests {
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    use super::*;

    fn grid_batches(side: u32) -> Vec<GpuBatch> {
        let mut batches = Vec::new();
        for z in 0..side {
            for y in 0..side {
                for x in 0..side {
                    let min = Vec3::new(x as f32, y as f32, z as f32) * 2.0;
                    batches.push(GpuBatch {
                        min: min.to_array(),
                        first: batches.len() as u32 * 64,
                        max: (min + Vec3::splat(1.5)).to_array(),
                        count: 64,
                    });
                }
            }
        }
        batches
    }

    /// Of two boxes where the second lies behind the first on every axis (farther or level
    /// along the depth gradient), the first is drawn first, for any direction of view.
    #[test]
    fn a_box_is_drawn_before_every_box_behind_it() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        for _ in 0..50 {
            let gradient = DVec3::new(
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
            );
            let mut batches = grid_batches(6);
            // Start from a shuffled table: the order must come from the sort alone.
            for i in (1..batches.len()).rev() {
                batches.swap(i, rng.random_range(0..=i));
            }
            sort_near_to_far(&mut batches, gradient);
            for (i, a) in batches.iter().enumerate() {
                for b in &batches[..i] {
                    // b is drawn before a: a must not lie in front of b on every axis.
                    let step = Vec3::from_array(b.min) - Vec3::from_array(a.min);
                    let a_in_front = (0..3).all(|axis| {
                        f64::from(step[axis]) * gradient[axis] >= 0.0 || step[axis] == 0.0
                    }) && step != Vec3::ZERO;
                    assert!(
                        !a_in_front,
                        "gradient {gradient}: {a:?} is drawn after {b:?}, which is behind it"
                    );
                }
            }
        }
    }

    /// A table's orders are built once per octant of view directions, and each is the
    /// order the sort gives the whole table.
    #[test]
    fn each_octant_keeps_the_order_the_sort_gives() {
        let batches = grid_batches(5);
        let orders = DrawOrders::default();
        for octant in 0..8 {
            let gradient = DVec3::new(
                if octant & 1 != 0 { -0.3 } else { 0.5 },
                if octant & 2 != 0 { -1.0 } else { 0.2 },
                if octant & 4 != 0 { -0.7 } else { 0.9 },
            );
            let order = orders.get(&batches, gradient);
            let mut sorted = batches.clone();
            sort_near_to_far(&mut sorted, gradient);
            let walked: Vec<GpuBatch> = order.iter().map(|&i| batches[i as usize]).collect();
            assert_eq!(walked, sorted, "octant {octant}");
            // Another view of the same octant finds the order already built.
            let again = orders.get(
                &batches,
                gradient * 2.0 + DVec3::splat(1e-3) * gradient.signum(),
            );
            assert!(std::ptr::eq(order, again), "octant {octant} built twice");
        }
        let first = orders.get(&batches, DVec3::ONE);
        let opposite = orders.get(&batches, -DVec3::ONE);
        assert_ne!(first, opposite);
    }

    #[test]
    fn runs_of_one_batch_stay_together_in_order() {
        let mut batches = grid_batches(4);
        // The first batch as two runs: same box, consecutive points.
        let mut second_run = batches[0];
        batches[0].count = 32;
        second_run.first += 32;
        second_run.count = 32;
        let first_run = batches.remove(0);
        // The other boxes in reverse, the runs last.
        batches.reverse();
        batches.extend([first_run, second_run]);
        sort_near_to_far(&mut batches, DVec3::ONE);
        // Depth grows with every coordinate: the box at the origin comes first, in its two
        // runs, and the far corner last.
        let firsts: Vec<u32> = batches.iter().map(|b| b.first).collect();
        assert_eq!(&firsts[..2], &[0, 32]);
        assert_eq!(batches.last().map(|b| b.min), Some([6.0; 3]));
    }
}
