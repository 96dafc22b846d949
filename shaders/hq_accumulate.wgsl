// High-quality mode, second pass (Schütz & Wimmer, after Botsch et al.): after the depth pass
// (`rasterize_depth` of raster_atomic32.wgsl) has stored the nearest depth per pixel, every
// point within the depth band behind it adds its color and a count. The resolve pass divides,
// so a pixel shows the average of all points near the front surface instead of one arbitrary
// point: less aliasing and flicker under motion.
//
// The per-pixel sums and `add_to_sums` come before this file: `hq_sums_atomic64.wgsl` where
// the adapter has 64-bit atomicAdd (two atomics a point), else `hq_sums_atomic32.wgsl` (four).
// Both hold the same words, so the resolve reads either. Sums of 8-bit channels overflow a
// u32 only beyond 16 million points in one pixel. The framebuffer, the entry point and the
// depth band's test come before this file too (hq_band.wgsl).

// Adds point `i`'s color to every pixel of its splat where it lies within `band` times the
// nearest depth.
fn draw_splat(i: u32, splat: Splat, band: f32, pass_kind: u32) {
    for (var k = 0u; k < SPLAT_PIXELS; k++) {
        let pixel = pixel_in_band(splat, k, band);
        if pixel >= 0 {
            add_to_sums(pixel, color_of(i));
        }
    }
}
