// The high-quality accumulation's per-pixel sums with 64-bit atomics: the same four words as
// `hq_sums_atomic32.wgsl` (red, green, blue, count), added as two little-endian pairs, so two
// atomics a point instead of four. A carry into a pair's high half needs a red or blue sum
// beyond a u32, which overflows the 32-bit path too (16 million points in a pixel). On lavapipe the accumulation took 0.8-0.96 of
// the time it took with four on the real scans and a 1M cube, the same on a 10M one
// (BENCHMARKS.md, session 10).

@group(0) @binding(4) var<storage, read_write> accumulator: array<atomic<u64>>;

fn add_to_sums(pixel: i32, colour: u32) {
    let base = 2 * pixel;
    let red_green = u64(colour & 0xffu) | (u64((colour >> 8u) & 0xffu) << 32u);
    let blue_count = u64((colour >> 16u) & 0xffu) | (u64(1u) << 32u);
    atomicAdd(&accumulator[base], red_green);
    atomicAdd(&accumulator[base + 1], blue_count);
}
