// The high-quality accumulation's per-pixel sums with 64-bit atomics: one atomicAdd a point
// on a packed word per pixel, `packed_sums` (red, green and blue sums and the count, 16 bits
// each, little end first), while it holds fewer than PACKED_POINTS points, where no channel's
// sum can overflow its 16 bits (256 x 255 < 2^16). A point that finds the word full takes its
// add back and adds to the wide sums instead, the four words of `hq_sums_atomic32.wgsl` as two
// little-endian pairs, and flags the packed word so that the resolve (resolve_sums_packed.wgsl)
// reads them too. The sums are integers, so the image does not depend on which points went
// where: it is the same as the 32-bit path's to the bit (tested). Half the bytes a pixel make
// both the accumulation and its resolve faster than two atomics a point on the wide sums
// alone (docs/perf/hq-accumulation.md).
//
// Another point's add, not yet taken back, can make a point find the word full early (it then
// goes to the wide sums, which is still exact); a carry between the packed fields while adds
// are in flight is undone with them, as integer addition is exact modulo 2^64. Only some
// 32000 adds in flight on one pixel at once could carry into the flag bit.

const PACKED_POINTS: u32 = 256u;
const PACKED_COUNT_SHIFT: u32 = 48u;
const PACKED_COUNT_MASK: u32 = 0x7fffu;
const WIDE_SUMS_USED: u64 = 0x8000000000000000lu;

@group(0) @binding(4) var<storage, read_write> accumulator: array<atomic<u64>>;
@group(0) @binding(10) var<storage, read_write> packed_sums: array<atomic<u64>>;

fn add_to_sums(pixel: i32, color: u32) {
    let red = u64(color & 0xffu);
    let green = u64((color >> 8u) & 0xffu);
    let blue = u64((color >> 16u) & 0xffu);
    let packed = red | (green << 16u) | (blue << 32u) | (1lu << PACKED_COUNT_SHIFT);
    let before = atomicAdd(&packed_sums[pixel], packed);
    if (u32(before >> PACKED_COUNT_SHIFT) & PACKED_COUNT_MASK) < PACKED_POINTS {
        return;
    }
    atomicSub(&packed_sums[pixel], packed);
    atomicOr(&packed_sums[pixel], WIDE_SUMS_USED);
    let base = 2 * pixel;
    atomicAdd(&accumulator[base], red | (green << 32u));
    atomicAdd(&accumulator[base + 1], blue | (1lu << 32u));
}

// The most a weighted point may add to the packed word's count: the word still holds at most
// PACKED_POINTS points' worth once the add is kept, and only some 2000 such adds in flight on
// one pixel at once could carry into the flag bit.
const PACKED_MAX_WEIGHT: u32 = 16u;

// The same for a point that stands for `weight` points (a level-of-detail cut's,
// hq_accumulate_weighted.wgsl): its color and count `weight` times. The packed word keeps
// an add only while its count stays within PACKED_POINTS, so no channel's sum can overflow
// its 16 bits; a heavier point goes to the wide sums at once.
fn add_weighted_to_sums(pixel: i32, color: u32, weight: u32) {
    let red = u64(color & 0xffu);
    let green = u64((color >> 8u) & 0xffu);
    let blue = u64((color >> 16u) & 0xffu);
    if weight <= PACKED_MAX_WEIGHT {
        let packed = (red | (green << 16u) | (blue << 32u) | (1lu << PACKED_COUNT_SHIFT)) * u64(weight);
        let before = atomicAdd(&packed_sums[pixel], packed);
        if (u32(before >> PACKED_COUNT_SHIFT) & PACKED_COUNT_MASK) + weight <= PACKED_POINTS {
            return;
        }
        atomicSub(&packed_sums[pixel], packed);
    }
    atomicOr(&packed_sums[pixel], WIDE_SUMS_USED);
    let base = 2 * pixel;
    let w = u64(weight);
    atomicAdd(&accumulator[base], (red | (green << 32u)) * w);
    atomicAdd(&accumulator[base + 1], (blue | (1lu << 32u)) * w);
}
