// The high-quality accumulation's per-pixel sums with 32-bit atomics (any adapter): four
// words a pixel, the sums of red, green and blue and the number of points added.

@group(0) @binding(4) var<storage, read_write> accumulator: array<atomic<u32>>;

fn add_to_sums(pixel: i32, color: u32) {
    let base = 4 * pixel;
    atomicAdd(&accumulator[base], color & 0xffu);
    atomicAdd(&accumulator[base + 1], (color >> 8u) & 0xffu);
    atomicAdd(&accumulator[base + 2], (color >> 16u) & 0xffu);
    atomicAdd(&accumulator[base + 3], 1u);
}

// The same for a point that stands for `weight` points (a level-of-detail cut's,
// hq_accumulate_weighted.wgsl): its color and count `weight` times.
fn add_weighted_to_sums(pixel: i32, color: u32, weight: u32) {
    let base = 4 * pixel;
    atomicAdd(&accumulator[base], (color & 0xffu) * weight);
    atomicAdd(&accumulator[base + 1], ((color >> 8u) & 0xffu) * weight);
    atomicAdd(&accumulator[base + 2], ((color >> 16u) & 0xffu) * weight);
    atomicAdd(&accumulator[base + 3], weight);
}
