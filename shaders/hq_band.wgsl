// What both high-quality accumulations (hq_accumulate.wgsl, hq_accumulate_weighted.wgsl) share,
// after their per-pixel sums: the point framebuffer after the depth pass, the entry point, and
// which pixels of a splat lie within the depth band. Each file says what its point adds there
// (`draw_splat`).

// The point framebuffer after the depth pass: y is the nearest depth's bits.
@group(0) @binding(3) var<storage, read> framebuffer: array<vec2<u32>>;

@compute @workgroup_size(WORKGROUP_SIZE)
fn accumulate(invocation: GridInvocation) {
    draw_batch(invocation, 1.0 + frame.depth_band, READS_DEPTHS);
}

// The pixel of `splat`'s k-th where its point lies within `band` times the nearest depth; -1
// where that pixel is off the image or the point lies behind the band.
fn pixel_in_band(splat: Splat, k: u32, band: f32) -> i32 {
    let pixel = splat_pixel(frame, splat, k);
    if pixel < 0 {
        return -1;
    }
    let nearest = bitcast<f32>(framebuffer[pixel].y);
    if splat.depth > nearest * band {
        return -1;
    }
    return pixel;
}
