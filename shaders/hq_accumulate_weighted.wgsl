// High-quality accumulation for the pages of a level-of-detail cut (`cut/gpu_cache.rs`): as
// hq_accumulate.wgsl, but each point adds its color and count as many times as the original
// points it stands for. Where its node is drawn without the child below it, that is its
// weight (`lod/weights.rs`); where that child is drawn too, the child's points stand for the
// region and the point counts once (docs/perf/hq-band-on-cuts.md). The 32-bit sums of 8-bit
// channels stay exact while a pixel's weights add up to less than 16 million points. The
// framebuffer, the entry point and the depth band's test come before this file (hq_band.wgsl).

// 16 bits a point, two to a word: the weight's 13-bit code and the point's child octant in
// its node above them.
@group(0) @binding(11) var<storage, read> weights: array<u32>;
// Per batch slot of the page (BATCH_POINTS points each): the children of its node this
// frame draws, one bit per octant.
@group(0) @binding(12) var<storage, read> drawn_children: array<u32>;

// The weight a 13-bit code holds: 4 bits of exponent, 9 of mantissa (`lod/weights.rs`).
fn decode_weight(code: u32) -> u32 {
    let e = code >> 9u;
    let m = code & 0x1ffu;
    if e == 0u {
        return m;
    }
    return (512u + m) << (e - 1u);
}

fn weight_of(i: u32) -> u32 {
    let bits = (weights[i >> 1u] >> ((i & 1u) * 16u)) & 0xffffu;
    let octant = bits >> 13u;
    if (drawn_children[i / BATCH_POINTS] & (1u << octant)) != 0u {
        return 1u;
    }
    return decode_weight(bits & 0x1fffu);
}

fn draw_splat(i: u32, splat: Splat, band: f32, pass_kind: u32) {
    var weight = 0u;
    for (var k = 0u; k < SPLAT_PIXELS; k++) {
        let pixel = pixel_in_band(splat, k, band);
        if pixel < 0 {
            continue;
        }
        if weight == 0u {
            weight = weight_of(i);
        }
        add_weighted_to_sums(pixel, color_of(i), weight);
    }
}
