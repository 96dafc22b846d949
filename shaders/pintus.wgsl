// Pintus et al. 2011, section 6: multi-level shape-depicting shading from depth alone.
// On level k, over the valid pixels of each 3x3 neighbourhood of the depth D^k: mean mu and
// standard deviation sigma, d_min = mu - sigma, d_max = mu + sigma, and (equation 2)
//     w^k = clamp(1 - |d - d_min| / (d_max - d_min + eps), 0, 1);
// the next level's depth is (mu + d_min) / 2. The levels are summed with weights
// 1 / (k + 1)^xi (equation 3) and normalised by the sum of the weights, so a flat surface
// facing the camera keeps its color; the color is multiplied by the result.
//
// eps is one pixel's footprint at the pixel's depth: the paper's "very small" epsilon makes
// every non-flat pixel exactly 1/2, while a footprint-sized one turns the term into the
// directional light the paper describes (1 facing the camera, towards 1/2 at grazing angles)
// and makes it independent of the scene's units.

@group(0) @binding(2) var<storage, read_write> depth_out: array<f32>;
@group(0) @binding(3) var<storage, read_write> shade_sum: array<f32>;

fn pixel_footprint(d: f32) -> f32 {
    let height = 2.0 * params.unproject.y / f32(params.frame_size.y);
    return select(height, height * d, params.perspective == 1u);
}

@compute @workgroup_size(SCREEN_TILE, SCREEN_TILE)
fn level(@builtin(global_invocation_id) id: vec3<u32>) {
    if id.x >= params.width || id.y >= params.height {
        return;
    }
    let x = i32(id.x);
    let y = i32(id.y);
    let pixel = id.y * params.width + id.x;
    let d = depth_in[pixel];
    depth_out[pixel] = d;
    if params.first_level == 1u {
        shade_sum[pixel] = 0.0;
    }
    if !is_surface_depth(d) {
        return;
    }
    // The 3x3 neighbourhood in fixed slots (`neighbour`).
    var depths: array<f32, 9>;
    var valid: array<bool, 9>;
    var count = 0u;
    var total = 0.0;
    for (var k = 0u; k < 9u; k++) {
        // Outside the image the read is clamped to a pixel of it, and the slot stays invalid.
        let n = neighbour(params, x, y, k);
        depths[k] = depth_in[n.pixel];
        valid[k] = n.inside && is_surface_depth(depths[k]);
        if valid[k] {
            total += depths[k];
            count++;
        }
    }
    let mean = total / f32(count);
    var squares = 0.0;
    for (var k = 0u; k < 9u; k++) {
        if valid[k] {
            squares += (depths[k] - mean) * (depths[k] - mean);
        }
    }
    let sigma = sqrt(squares / f32(count));
    let d_min = mean - sigma;
    let shade = clamp(1.0 - abs(d - d_min) / (2.0 * sigma + pixel_footprint(d)), 0.0, 1.0);
    shade_sum[pixel] += params.level_weight * shade;
    depth_out[pixel] = (mean + d_min) / 2.0;
}

@group(0) @binding(4) var<storage, read_write> color: array<u32>;

// Multiplies the color of every surface pixel by its normalised shading term.
@compute @workgroup_size(SCREEN_TILE, SCREEN_TILE)
fn apply(@builtin(global_invocation_id) id: vec3<u32>) {
    if id.x >= params.width || id.y >= params.height {
        return;
    }
    let pixel = id.y * params.width + id.x;
    if !is_surface_depth(depth_in[pixel]) {
        return;
    }
    let shade = shade_sum[pixel] * params.inverse_total_weight;
    let rgba = unpack4x8unorm(color[pixel]);
    color[pixel] = pack_unorm4x8(vec4<f32>(rgba.rgb * shade, rgba.a));
}
