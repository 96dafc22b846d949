//! Z-order (Morton) codes: the curve along which an upload sorts a cloud's points, so that
//! consecutive points lie close together, and along which `draw_order.rs` orders batches.

use glam::Vec3;

/// Indices of `positions` in Z-order over their bounding box.
pub(crate) fn morton_order(positions: &[Vec3]) -> Vec<u32> {
    let (min, max) = positions.iter().fold(
        (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY)),
        |(lo, hi), p| (lo.min(*p), hi.max(*p)),
    );
    let scale = (max - min).max_element().max(f32::MIN_POSITIVE);
    let keys = SortKeys::for_count(positions.len(), 21);
    let cells = ((1u32 << keys.axis_bits) - 1) as f32;
    keys.order(positions.iter().map(|p| {
        let q = ((*p - min) / scale * cells).clamp(Vec3::ZERO, Vec3::splat(cells));
        morton3(q.x as u32, q.y as u32, q.z as u32)
    }))
    .map(|j| j as u32)
    .collect()
}

/// `indices` (every point where `None`) in Z-order over the grid of their `bits`-bit integer
/// `cells` (a level-of-detail node's quantised coordinates): no bounding box or float
/// arithmetic.
pub(crate) fn morton_order_of_cells(
    cells: &[[u32; 3]],
    bits: u32,
    indices: Option<&[u32]>,
) -> Vec<u32> {
    let count = indices.map_or(cells.len(), <[u32]>::len);
    let keys = SortKeys::for_count(count, bits);
    let shift = bits - keys.axis_bits;
    let code = |i: u32| {
        let [x, y, z] = cells[i as usize].map(|c| c >> shift);
        morton3(x, y, z)
    };
    match indices {
        Some(indices) => keys
            .order(indices.iter().map(|&i| code(i)))
            .map(|j| indices[j])
            .collect(),
        None => keys
            .order((0..count as u32).map(code))
            .map(|j| j as u32)
            .collect(),
    }
}

/// One u64 a point, sorted as plain integers (faster than pairs): the point's position in the
/// list in the low bits, its Morton code above with as many bits an axis as are left (at most
/// 21, at most the coordinates' own; at least 10, for 2^32 points), far finer than the points'
/// spacing.
struct SortKeys {
    index_bits: u32,
    axis_bits: u32,
}

impl SortKeys {
    fn for_count(count: usize, coordinate_bits: u32) -> Self {
        let index_bits = (u64::BITS - (count.max(2) as u64 - 1).leading_zeros()).max(1);
        let axis_bits = ((u64::BITS - index_bits) / 3).min(21).min(coordinate_bits);
        Self {
            index_bits,
            axis_bits,
        }
    }

    /// The positions in the list of `codes` (each of `axis_bits` an axis), in code order.
    fn order(&self, codes: impl Iterator<Item = u64>) -> impl Iterator<Item = usize> {
        let index_bits = self.index_bits;
        let mut keys: Vec<u64> = codes
            .enumerate()
            .map(|(j, code)| code << index_bits | j as u64)
            .collect();
        keys.sort_unstable();
        let index_mask = (1u64 << index_bits) - 1;
        keys.into_iter().map(move |key| (key & index_mask) as usize)
    }
}

/// Interleaves the low 21 bits of x, y and z.
pub(crate) fn morton3(x: u32, y: u32, z: u32) -> u64 {
    fn spread(v: u32) -> u64 {
        let mut v = v as u64 & 0x1f_ffff;
        v = (v | (v << 32)) & 0x001f_0000_0000_ffff;
        v = (v | (v << 16)) & 0x001f_0000_ff00_00ff;
        v = (v | (v << 8)) & 0x100f_00f0_0f00_f00f;
        v = (v | (v << 4)) & 0x10c3_0c30_c30c_30c3;
        v = (v | (v << 2)) & 0x1249_2492_4924_9249;
        v
    }
    spread(x) | (spread(y) << 1) | (spread(z) << 2)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn morton_code_interleaves_bits() {
        assert_eq!(morton3(1, 0, 0), 0b001);
        assert_eq!(morton3(0, 1, 0), 0b010);
        assert_eq!(morton3(0, 0, 1), 0b100);
        assert_eq!(morton3(3, 0, 0), 0b001_001);
        assert_eq!(morton3(0x1f_ffff, 0x1f_ffff, 0x1f_ffff), (1u64 << 63) - 1);
    }

    #[test]
    fn cells_are_ordered_by_their_morton_codes_keeping_only_the_indices() {
        let cells: Vec<[u32; 3]> = (0..500u32)
            .map(|i| [i * 7919 % 1024, i * 104_729 % 1024, i * 1_299_709 % 1024])
            .collect();
        let by_code = |indices: Vec<u32>| {
            let mut sorted = indices;
            sorted.sort_by_key(|&i| {
                let [x, y, z] = cells[i as usize];
                (morton3(x, y, z), i)
            });
            sorted
        };
        // 10-bit cells: every bit counts (500 points leave 18 bits an axis).
        assert_eq!(
            morton_order_of_cells(&cells, 10, None),
            by_code((0..500).collect())
        );
        let kept: Vec<u32> = (0..500).filter(|i| i % 3 != 0).collect();
        assert_eq!(
            morton_order_of_cells(&cells, 10, Some(&kept)),
            by_code(kept.clone())
        );
        // 30-bit cells as a node stores them: the top 18 bits order them, the same order.
        let wide: Vec<[u32; 3]> = cells
            .iter()
            .map(|c| c.map(|v| v << 20 | 0x5_5555))
            .collect();
        assert_eq!(morton_order_of_cells(&wide, 30, Some(&kept)), by_code(kept));
    }

    /// Clouds of every size keep a permutation, and points in one cell keep their order.
    #[test]
    fn morton_order_is_a_permutation_at_every_size() {
        for n in [0usize, 1, 2, 3, 1000, 70_000] {
            let positions: Vec<Vec3> = (0..n)
                .map(|i| Vec3::new((i % 37) as f32, (i % 11) as f32, 0.0))
                .collect();
            let order = morton_order(&positions);
            let mut sorted = order.clone();
            sorted.sort_unstable();
            assert_eq!(sorted, (0..n as u32).collect::<Vec<u32>>(), "{n} points");
            for pair in order.windows(2) {
                let (a, b) = (pair[0] as usize, pair[1] as usize);
                if positions[a] == positions[b] {
                    assert!(a < b, "{n} points: equal positions in index order");
                }
            }
        }
    }

    #[test]
    fn morton_order_is_a_permutation_that_keeps_neighbours_together() {
        let positions: Vec<Vec3> = (0..64)
            .map(|i| Vec3::new((i % 4) as f32, ((i / 4) % 4) as f32, (i / 16) as f32))
            .collect();
        let order = morton_order(&positions);
        let mut sorted = order.clone();
        sorted.sort_unstable();
        assert_eq!(sorted, (0..64).collect::<Vec<u32>>());
        // The first eight points in Z-order form the 2x2x2 cube at the corner.
        for &i in &order[..8] {
            let p = positions[i as usize];
            assert!(p.max_element() <= 1.0, "{p}");
        }
    }
}
