// Basic-mode rasterizer with 64-bit atomics (Schütz & Wimmer 2021).
//
// Each framebuffer word holds (depth bits << 32 | RGBA8). Depths are positive f32, whose bit
// patterns order like the values, so one atomicMin keeps the nearest point, and among points
// at exactly the same depth the smallest colour word: the image does not depend on the order
// in which points arrive.
//
// One workgroup per batch. Needs SHADER_INT64 and SHADER_INT64_ATOMIC_MIN_MAX.

@group(0) @binding(3) var<storage, read_write> framebuffer: array<atomic<u64>>;
// The same buffer as `framebuffer`, read without atomics for the early depth test: a stale
// read only costs an unneeded atomicMin, never a wrong pixel. y is the depth word.
@group(0) @binding(4) var<storage, read_write> framebuffer_words: array<vec2<u32>>;

@compute @workgroup_size(WORKGROUP_SIZE)
fn rasterize(
    @builtin(workgroup_id) workgroup: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) lane: u32,
) {
    let batch = workgroup_batch(workgroup, groups, lane, 1.0, 0u);
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
        // Read only once a pixel passed the early depth test.
        var color = 0u;
        var have_color = false;
        for (var k = 0u; k < SPLAT_PIXELS; k++) {
            let pixel = splat_pixel(frame, splat, k);
            if pixel < 0 {
                continue;
            }
            // Early depth test: skip the atomic when a nearer point is already stored.
            if framebuffer_words[pixel].y < depth_bits {
                continue;
            }
            if !have_color {
                color = color_of(i);
                have_color = true;
            }
            atomicMin(&framebuffer[pixel], (u64(depth_bits) << 32u) | u64(color));
        }
    }
}
