// Pintus et al. 2011, section 5: anisotropic filling of the pixels the visibility pass left
// mutable, one 3x3 step per dispatch (ping-pong buffers). A mutable pixel without a depth
// takes the median depth of its valid neighbours, and that neighbour's color; one with a
// depth becomes the weighted mean of its valid 3x3 neighbourhood (itself included), with the
// paper's equation 1: w = (1 - r / 2) (1 - min(1, |z - z0| / delta)), r the distance in
// pixels, delta = depth_tolerance * z0. Fixed pixels never change.

@group(0) @binding(2) var<storage, read> color_in: array<u32>;
// The mutable pixels, (y << 16) | x each, and their count (visibility.wgsl): the passes run
// one invocation per listed pixel; fixed pixels are never visited.
@group(0) @binding(3) var<storage, read> mutable_list: array<u32>;
@group(0) @binding(4) var<storage, read_write> depth_out: array<f32>;
@group(0) @binding(5) var<storage, read_write> color_out: array<u32>;
// The same words as visibility.wgsl's `FillArgs`, read once the count is final.
struct FillArgs {
    groups: vec3<u32>,
    count: u32,
}
@group(0) @binding(6) var<storage, read> fill_args: FillArgs;

// The listed pixel of this invocation (x, y and its index), or false past the end of the list.
struct ListedPixel {
    x: u32,
    y: u32,
    pixel: u32,
    listed: bool,
}

fn listed_pixel(invocation: GridInvocation) -> ListedPixel {
    let index = workgroup_index(invocation) * LIST_WORKGROUP + invocation.lane;
    var listed: ListedPixel;
    listed.listed = index < fill_args.count;
    if listed.listed {
        let packed = mutable_list[index];
        listed.x = packed & 0xffffu;
        listed.y = packed >> 16u;
        listed.pixel = listed.y * params.width + listed.x;
    }
    return listed;
}

@compute @workgroup_size(LIST_WORKGROUP)
fn fill_step(invocation: GridInvocation) {
    // Fixed pixels hold the same value in both buffer pairs from the start (the visibility
    // pass copied them unchanged into the fill buffers) and are not listed: on lavapipe,
    // visiting every pixel to skip the fixed ones was much of the filling's time
    // (docs/perf/fill-and-shading.md).
    let listed = listed_pixel(invocation);
    if !listed.listed {
        return;
    }
    let x = i32(listed.x);
    let y = i32(listed.y);
    let pixel = listed.pixel;
    let z0 = depth_in[pixel];

    // The 3x3 neighbourhood in fixed slots (`neighbour`, no compaction), each valid when it
    // holds a point. Colors are read only where used: one for the median, the valid ones for the mean.
    var depths: array<f32, 9>;
    var neighbours: array<u32, 9>;
    var valid: array<bool, 9>;
    var count = 0u;
    for (var k = 0u; k < 9u; k++) {
        // Outside the image the read is clamped to a pixel of it, and the slot stays invalid.
        let n = neighbour(params, x, y, k);
        neighbours[k] = n.pixel;
        depths[k] = depth_in[n.pixel];
        valid[k] = n.inside && is_surface_depth(depths[k]);
        count += select(0u, 1u, valid[k]);
    }
    if count == 0u {
        depth_out[pixel] = z0;
        color_out[pixel] = color_in[pixel];
        return;
    }

    if !is_surface_depth(z0) {
        // Median: the valid neighbour with (count - 1) / 2 others before it in (depth, order).
        let wanted = (count - 1u) / 2u;
        var median = 0u;
        var median_depth = z0;
        for (var i = 0u; i < 9u; i++) {
            var rank = 0u;
            for (var j = 0u; j < 9u; j++) {
                let before = depths[j] < depths[i] || (depths[j] == depths[i] && j < i);
                rank += select(0u, 1u, valid[j] && before);
            }
            let chosen = valid[i] && rank == wanted;
            median = select(median, neighbours[i], chosen);
            median_depth = select(median_depth, depths[i], chosen);
        }
        depth_out[pixel] = median_depth;
        color_out[pixel] = color_in[median];
        return;
    }

    let delta = params.depth_tolerance * z0;
    var weight_sum = 0.0;
    var depth_sum = 0.0;
    var color_sum = vec4<f32>(0.0);
    for (var k = 0u; k < 9u; k++) {
        if valid[k] {
            let offset = vec2<f32>(f32(i32(k % 3u) - 1), f32(i32(k / 3u) - 1));
            let w = (1.0 - length(offset) / 2.0) * (1.0 - min(1.0, abs(depths[k] - z0) / delta));
            weight_sum += w;
            depth_sum += w * depths[k];
            color_sum += w * unpack4x8unorm(color_in[neighbours[k]]);
        }
    }
    // The pixel itself always has weight 1, so the sum is never 0.
    depth_out[pixel] = depth_sum / weight_sum;
    color_out[pixel] = pack_unorm4x8(color_sum / weight_sum);
}

// Copies the listed pixels of the last step's output into the other pair.
@compute @workgroup_size(LIST_WORKGROUP)
fn finish(invocation: GridInvocation) {
    let listed = listed_pixel(invocation);
    if listed.listed {
        depth_out[listed.pixel] = depth_in[listed.pixel];
        color_out[listed.pixel] = color_in[listed.pixel];
    }
}
