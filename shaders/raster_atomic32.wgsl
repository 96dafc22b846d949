// Basic-mode rasterizer for adapters without 64-bit atomics: the same image as
// raster_atomic64.wgsl in two passes over the points.
//
// The framebuffer has the same memory layout as the 64-bit one, as pairs of u32 words:
// [2i] = colour, [2i + 1] = depth bits. `rasterize_depth` keeps the nearest depth per pixel;
// `rasterize_color` then lets every point whose depth equals the stored one atomicMin its
// colour, which picks the same winner as the 64-bit (depth << 32 | colour) minimum. Both
// passes compute depths with the same code from the same inputs, so equality is exact.

@group(0) @binding(3) var<storage, read_write> framebuffer: array<atomic<u32>>;

fn depth_word(pixel: i32) -> i32 {
    return 2 * pixel + 1;
}

fn color_word(pixel: i32) -> i32 {
    return 2 * pixel;
}

// The two passes walk the same points in the same way; `color_pass` picks what they write.
fn rasterize_batch(workgroup: vec3<u32>, groups: vec3<u32>, lane: u32, color_pass: bool) {
    let batch = workgroup_batch(workgroup, groups, lane, 1.0, select(0u, 1u, color_pass));
    if batch.count == 0u {
        return;
    }
    let projection = batch_projection(frame, batch);
    for (var i = batch.first + lane; i < batch.first + batch.count; i += WORKGROUP_SIZE) {
        let splat = project_quantised(frame, projection, positions[i]);
        if !splat.visible {
            continue;
        }
        let depth_bits = bitcast<u32>(splat.depth);
        for (var k = 0u; k < SPLAT_PIXELS; k++) {
            let pixel = splat_pixel(frame, splat, k);
            if pixel < 0 {
                continue;
            }
            let stored_depth = atomicLoad(&framebuffer[depth_word(pixel)]);
            if color_pass {
                if stored_depth == depth_bits {
                    atomicMin(&framebuffer[color_word(pixel)], color_of(i));
                }
            } else if stored_depth >= depth_bits {
                // Early depth test as in the 64-bit pass: only nearer or equal points try.
                atomicMin(&framebuffer[depth_word(pixel)], depth_bits);
            }
        }
    }
}

@compute @workgroup_size(WORKGROUP_SIZE)
fn rasterize_depth(
    @builtin(workgroup_id) workgroup: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) lane: u32,
) {
    rasterize_batch(workgroup, groups, lane, false);
}

@compute @workgroup_size(WORKGROUP_SIZE)
fn rasterize_color(
    @builtin(workgroup_id) workgroup: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) lane: u32,
) {
    rasterize_batch(workgroup, groups, lane, true);
}
