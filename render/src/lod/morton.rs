//! A Z-curve order of a node's points: each point's cell some levels below the node, its three
//! indices interleaved into one code (x in bit 0 of each group of three, y in bit 1, z in bit
//! 2, as a [`NodeKey::child`] index), the points sorted by it once. Every node below is then
//! one run of the order, and a node's children are the runs of the code's next three bits.

use super::key::{NodeKey, RootCube};
use super::point::RawPoint;

/// The most levels a code spans: three bits a level in a `u64`.
pub const MAX_CODE_LEVELS: u32 = 21;

/// Bits of one digit of the radix sort: few enough buckets that each pass writes to a few
/// hundred places, which the caches hold.
const DIGIT_BITS: u32 = 8;

/// Below this many entries a comparison sort is quicker than the radix sort's passes.
const RADIX_MIN_ENTRIES: usize = 1024;

/// The buffers an order is built in, kept between orders so that their room is reused.
#[derive(Default)]
pub struct OrderBuffers {
    pub entries: Vec<(u64, u32)>,
    pub sorted: Vec<(u64, u32)>,
}

/// Points in Z-curve order: each entry a point's code and its index among the points.
pub struct MortonOrder {
    entries: Vec<(u64, u32)>,
    bits: u32,
}

impl MortonOrder {
    /// The order of `points`, all in `key`'s cube of `cube`, by their cells `levels` levels
    /// below `key` (at most [`MAX_CODE_LEVELS`]); points of one cell keep the order they came
    /// in.
    #[cfg(test)]
    pub fn below(cube: &RootCube, key: NodeKey, points: &[RawPoint], levels: u8) -> Self {
        Self::below_in(cube, key, points, levels, OrderBuffers::default()).0
    }

    /// [`Self::below`] in `buffers`, whose room is reused: the entries are written where an
    /// earlier order's were, and the sort's second buffer is kept in `buffers.sorted`.
    pub fn below_in(
        cube: &RootCube,
        key: NodeKey,
        points: &[RawPoint],
        levels: u8,
        buffers: OrderBuffers,
    ) -> (Self, Vec<(u64, u32)>) {
        let OrderBuffers {
            mut entries,
            mut sorted,
        } = buffers;
        let bits = u32::from(levels).min(MAX_CODE_LEVELS);
        let level = u32::from(key.level) + bits;
        let base = key.cell() << bits;
        entries.clear();
        entries.reserve_exact(points.len());
        entries.extend(points.iter().enumerate().map(|(i, p)| {
            let c = cube.cell_at(p.position, level) - base;
            (
                spread(c.x) | (spread(c.y) << 1) | (spread(c.z) << 2),
                i as u32,
            )
        }));
        sort(&mut entries, &mut sorted, 3 * bits);
        (Self { entries, bits }, sorted)
    }

    /// The entries' buffer, for another order to reuse.
    pub fn into_entries(self) -> Vec<(u64, u32)> {
        self.entries
    }

    /// Every entry, in order.
    pub fn entries(&self) -> &[(u64, u32)] {
        &self.entries
    }

    /// Levels below the node the codes span.
    pub fn bits(&self) -> u32 {
        self.bits
    }

    /// The runs of the eight children of the node whose run is `run`, `depth` levels (fewer
    /// than [`Self::bits`]) below the order's node, by child index.
    pub fn children<'r>(&self, run: &'r [(u64, u32)], depth: u32) -> [&'r [(u64, u32)]; 8] {
        debug_assert!(depth < self.bits);
        let shift = 3 * (self.bits - depth - 1);
        let mut rest = run;
        // Within one node's run the codes share every bit above these three, so they ascend.
        std::array::from_fn(|child| {
            let len = rest.partition_point(|&(code, _)| ((code >> shift) & 7) as usize <= child);
            let (this, after) = rest.split_at(len);
            rest = after;
            this
        })
    }
}

/// The 21 low bits of `v`, two zero bits after each.
fn spread(v: u32) -> u64 {
    let mut x = u64::from(v) & 0x1f_ffff;
    x = (x | (x << 32)) & 0x001f_0000_0000_ffff;
    x = (x | (x << 16)) & 0x001f_0000_ff00_00ff;
    x = (x | (x << 8)) & 0x100f_00f0_0f00_f00f;
    x = (x | (x << 4)) & 0x10c3_0c30_c30c_30c3;
    (x | (x << 2)) & 0x1249_2492_4924_9249
}

/// Sorts `entries` by code, codes of `key_bits` bits, ties in the order they are (a radix
/// sort, least significant digit first: each pass is stable, and one whose digit is the same
/// for every entry is skipped), `scratch` the passes' second buffer: its room is reused, and
/// entries already in it are overwritten rather than zeroed first.
fn sort(entries: &mut Vec<(u64, u32)>, scratch: &mut Vec<(u64, u32)>, key_bits: u32) {
    let n = entries.len();
    if n < RADIX_MIN_ENTRIES {
        // Entries come in index order, so code then index is the stable order.
        entries.sort_unstable();
        return;
    }
    let passes = key_bits.div_ceil(DIGIT_BITS) as usize;
    let mask = (1u64 << DIGIT_BITS) - 1;
    let digit = |code: u64, pass: usize| ((code >> (pass as u32 * DIGIT_BITS)) & mask) as usize;
    let mut counts = vec![[0usize; 1 << DIGIT_BITS]; passes];
    for &(code, _) in entries.iter() {
        for (pass, table) in counts.iter_mut().enumerate() {
            table[digit(code, pass)] += 1;
        }
    }
    for (pass, table) in counts.iter_mut().enumerate() {
        if table.contains(&n) {
            continue;
        }
        let mut start = 0;
        for count in table.iter_mut() {
            let c = *count;
            *count = start;
            start += c;
        }
        if scratch.len() < n {
            scratch.reserve_exact(n - scratch.len());
            scratch.resize(n, (0, 0));
        }
        let out = &mut scratch[..n];
        for &entry in entries.iter() {
            let at = &mut table[digit(entry.0, pass)];
            out[*at] = entry;
            *at += 1;
        }
        std::mem::swap(entries, scratch);
        // A reused buffer may be longer than the entries: what lies past them is stale.
        entries.truncate(n);
    }
}

#[cfg(test)]
mod tests {
    use glam::{DVec3, UVec3};

    use super::*;
    use crate::lod::sampling::tests::unit_random;

    fn naive_code(c: UVec3, bits: u32) -> u64 {
        (0..bits).fold(0, |code, bit| {
            let at = |v: u32, axis: u32| u64::from((v >> bit) & 1) << (3 * bit + axis);
            code | at(c.x, 0) | at(c.y, 1) | at(c.z, 2)
        })
    }

    fn point(position: DVec3) -> RawPoint {
        RawPoint {
            position,
            rgb: [0; 3],
            intensity: 0,
            classification: 0,
            return_number: 0,
            weight: 1,
            row: 0,
        }
    }

    #[test]
    fn codes_interleave_every_bit() {
        for (i, v) in [0u32, 1, 0x15_5555, 0x1f_ffff, 0x0a_bcde, 123_457]
            .iter()
            .enumerate()
        {
            let c = UVec3::new(*v, v.rotate_left(i as u32) & 0x1f_ffff, v ^ 0x1f_ffff);
            let code = spread(c.x) | (spread(c.y) << 1) | (spread(c.z) << 2);
            assert_eq!(code, naive_code(c, 21), "{c}");
        }
    }

    /// The radix sort gives the comparison sort's order, ties by arrival, and each node's run
    /// holds exactly the points of its cube, cut into its children's.
    #[test]
    fn runs_are_the_points_of_each_node() {
        let cube = RootCube {
            min: DVec3::new(-3.5, 100.25, 7.0),
            side: 64.0,
        };
        let key = NodeKey::new(2, UVec3::new(1, 3, 0));
        let (min, side) = (cube.node_min(key), cube.side_at(2));
        let mut next = unit_random(99);
        // Some points on the same spot, so that ties occur.
        let points: Vec<RawPoint> = (0..20_000)
            .map(|i| {
                let t = if i % 5 == 0 {
                    DVec3::splat(0.5)
                } else {
                    DVec3::new(next(), next(), next())
                };
                point(min + t * side)
            })
            .collect();
        for levels in [4u8, 21] {
            let order = MortonOrder::below(&cube, key, &points, levels);
            let mut expected: Vec<(u64, u32)> = order.entries().to_vec();
            expected.sort_unstable();
            assert_eq!(order.entries(), &expected[..]);
            let mut runs = vec![(key, order.entries())];
            for depth in 0..3 {
                let mut next_runs = Vec::new();
                for (node, run) in runs {
                    for (i, child) in order.children(run, depth).into_iter().enumerate() {
                        let child_key = node.child(i);
                        for &(_, p) in child {
                            let at = cube.cell_at(points[p as usize].position, 3 + depth);
                            assert_eq!(at, child_key.cell());
                        }
                        next_runs.push((child_key, child));
                    }
                }
                let total: usize = next_runs.iter().map(|(_, r)| r.len()).sum();
                assert_eq!(total, points.len());
                runs = next_runs;
            }
        }
    }
}
