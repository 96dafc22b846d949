// Pintus et al. 2011, section 5: anisotropic filling of the pixels the visibility pass left
// mutable, one 3x3 step per dispatch (ping-pong buffers). A mutable pixel without a depth
// takes the median depth of its valid neighbours, and that neighbour's colour; one with a
// depth becomes the weighted mean of its valid 3x3 neighbourhood (itself included), with the
// paper's equation 1: w = (1 - r / 2) (1 - min(1, |z - z0| / delta)), r the distance in
// pixels, delta = depth_tolerance * z0. Fixed pixels never change.

@group(0) @binding(0) var<uniform> params: ScreenParams;
@group(0) @binding(1) var<storage, read> depth_in: array<f32>;
@group(0) @binding(2) var<storage, read> colour_in: array<u32>;
@group(0) @binding(3) var<storage, read> mutable_pixels: array<u32>;
@group(0) @binding(4) var<storage, read_write> depth_out: array<f32>;
@group(0) @binding(5) var<storage, read_write> colour_out: array<u32>;

@compute @workgroup_size(16, 16)
fn fill_step(@builtin(global_invocation_id) id: vec3<u32>) {
    if id.x >= params.width || id.y >= params.height {
        return;
    }
    let x = i32(id.x);
    let y = i32(id.y);
    let pixel = id.y * params.width + id.x;
    // A fixed pixel holds the same value in both buffers from the start (the visibility pass
    // copied it unchanged from the frame's buffers into the fill buffers), so no step copies
    // it: on lavapipe the copy was most of a step's time.
    if mutable_pixels[pixel] == 0u {
        return;
    }
    let z0 = depth_in[pixel];
    depth_out[pixel] = z0;
    colour_out[pixel] = colour_in[pixel];

    // The 3x3 neighbourhood in row-major order, each slot valid when it holds a point. Slots
    // stay fixed (no compaction) so that every array index is a constant once the loops are
    // unrolled: an array indexed by a variable is a per-lane loop through memory on lavapipe.
    var depths: array<f32, 9>;
    var colours: array<u32, 9>;
    var valid: array<bool, 9>;
    var count = 0u;
    for (var k = 0u; k < 9u; k++) {
        let nx = x + i32(k % 3u) - 1;
        let ny = y + i32(k / 3u) - 1;
        let inside = nx >= 0 && ny >= 0 && nx < i32(params.width) && ny < i32(params.height);
        // Outside the image the read is clamped to a pixel of it, and the slot stays invalid.
        let n = u32(clamp(ny, 0, i32(params.height) - 1)) * params.width
            + u32(clamp(nx, 0, i32(params.width) - 1));
        depths[k] = depth_in[n];
        colours[k] = colour_in[n];
        valid[k] = inside && is_surface_depth(depths[k]);
        count += select(0u, 1u, valid[k]);
    }
    if count == 0u {
        return;
    }

    if !is_surface_depth(z0) {
        // Median: the valid neighbour with (count - 1) / 2 others before it in (depth, order).
        let wanted = (count - 1u) / 2u;
        for (var i = 0u; i < 9u; i++) {
            var rank = 0u;
            for (var j = 0u; j < 9u; j++) {
                let before = depths[j] < depths[i] || (depths[j] == depths[i] && j < i);
                rank += select(0u, 1u, valid[j] && before);
            }
            if valid[i] && rank == wanted {
                depth_out[pixel] = depths[i];
                colour_out[pixel] = colours[i];
            }
        }
        return;
    }

    let delta = params.depth_tolerance * z0;
    var weight_sum = 0.0;
    var depth_sum = 0.0;
    var colour_sum = vec4<f32>(0.0);
    for (var k = 0u; k < 9u; k++) {
        if valid[k] {
            let offset = vec2<f32>(f32(i32(k % 3u) - 1), f32(i32(k / 3u) - 1));
            let w = (1.0 - length(offset) / 2.0) * (1.0 - min(1.0, abs(depths[k] - z0) / delta));
            weight_sum += w;
            depth_sum += w * depths[k];
            colour_sum += w * unpack4x8unorm(colours[k]);
        }
    }
    // The pixel itself always has weight 1, so the sum is never 0.
    depth_out[pixel] = depth_sum / weight_sum;
    colour_out[pixel] = pack4x8unorm(colour_sum / weight_sum);
}

@compute @workgroup_size(16, 16)
fn finish(@builtin(global_invocation_id) id: vec3<u32>) {
    if id.x >= params.width || id.y >= params.height {
        return;
    }
    let pixel = id.y * params.width + id.x;
    if mutable_pixels[pixel] == 0u {
        return;
    }
    depth_out[pixel] = depth_in[pixel];
    colour_out[pixel] = colour_in[pixel];
}
