// High-quality mode, second pass (Schütz & Wimmer, after Botsch et al.): after the depth pass
// (`rasterize_depth` of raster_atomic32.wgsl) has stored the nearest depth per pixel, every
// point within the depth band behind it adds its colour and a count. The resolve pass divides,
// so a pixel shows the average of all points near the front surface instead of one arbitrary
// point: less aliasing and flicker under motion.
//
// The per-pixel sums and `add_to_sums` come before this file: `hq_sums_atomic64.wgsl` where
// the adapter has 64-bit atomicAdd (two atomics a point), else `hq_sums_atomic32.wgsl` (four).
// Both hold the same words, so the resolve reads either. Sums of 8-bit channels overflow a
// u32 only beyond 16 million points in one pixel.

// The point framebuffer after the depth pass: y is the nearest depth's bits.
@group(0) @binding(3) var<storage, read> framebuffer: array<vec2<u32>>;

@compute @workgroup_size(WORKGROUP_SIZE)
fn accumulate(
    @builtin(workgroup_id) workgroup: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) lane: u32,
) {
    let band = 1.0 + frame.depth_band;
    let batch = workgroup_batch(workgroup, groups, lane, band, 1u);
    if batch.count == 0u {
        return;
    }
    let projection = batch_projection(frame, batch);
    for (var i = batch.first + lane; i < batch.first + batch.count; i += WORKGROUP_SIZE) {
        let splat = project_quantised(frame, projection, positions[i]);
        if !splat.visible {
            continue;
        }
        for (var k = 0u; k < SPLAT_PIXELS; k++) {
            let pixel = splat_pixel(frame, splat, k);
            if pixel < 0 {
                continue;
            }
            let nearest = bitcast<f32>(framebuffer[pixel].y);
            if splat.depth > nearest * band {
                continue;
            }
            add_to_sums(pixel, color_of(i));
        }
    }
}
