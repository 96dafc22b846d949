// Eye-Dome Lighting after Boucheny (2009) and Potree: shading from depth alone, so clouds
// without color or normals read as surfaces. Runs on the resolved images and changes the
// color in place (each pixel reads only its own color, and its neighbours' depths).
//
// For a pixel with linear depth d, over 4 pairs of opposite neighbours on a circle of
// `edl_radius` pixels: a pair on the surface adds 2 max(0, log2(d (1/d_a + 1/d_b) / 2)), how far
// the pixel lies behind the plane through the two (inverse depth is linear across a plane in
// screen space, so a slanted plane adds nothing, unlike Potree's sum over single neighbours);
// a lone surface neighbour adds max(0, log2 d - log2 d_neighbour); a background pixel next to
// geometry gets 100 per surface neighbour, which draws the silhouette outline.
// shade = exp(-300 * edl_strength * response / 8); color *= shade.
//
// Every surface pixel's luma is counted before and after shading, for the exposure the host
// applies afterwards (`raster/exposure.rs`).

@group(0) @binding(0) var<uniform> frame: FrameUniforms;
@group(0) @binding(1) var<storage, read_write> color: array<u32>;
@group(0) @binding(2) var<storage, read> depth: array<f32>;
// LUMA_BINS counts before shading, then LUMA_BINS after.
@group(0) @binding(3) var<storage, read_write> luma_counts: array<atomic<u32>>;

const OUTLINE_RESPONSE: f32 = 100.0;
const INFINITE_DEPTH: u32 = 0x7f800000u;
const LUMA_BINS: u32 = 256u;

fn is_surface(d: f32) -> bool {
    return bitcast<u32>(d) != INFINITE_DEPTH;
}

// Depth at pixel (x, y); +infinity (background) outside the image.
fn depth_at(x: i32, y: i32) -> f32 {
    if x < 0 || y < 0 || x >= i32(frame.width) || y >= i32(frame.height) {
        return bitcast<f32>(INFINITE_DEPTH);
    }
    return depth[u32(y) * frame.width + u32(x)];
}

// Four sample directions, 45 degrees apart, each taken with its opposite: constants rather
// than a cos and a sin per sample, which cost lavapipe more than the rest of the pass
// (docs/perf/edl-constants.md).
const DIAGONAL: f32 = 0.70710677;
const DIRECTIONS = array<vec2<f32>, 4>(
    vec2<f32>(1.0, 0.0),
    vec2<f32>(DIAGONAL, DIAGONAL),
    vec2<f32>(0.0, 1.0),
    vec2<f32>(-DIAGONAL, DIAGONAL),
);

// The luma bin of a packed RGBA8 color (`luma_bin` in `raster/exposure.rs`).
fn luma_bin(rgba: u32) -> u32 {
    let r = f32(rgba & 0xffu);
    let g = f32((rgba >> 8u) & 0xffu);
    let b = f32((rgba >> 16u) & 0xffu);
    return min(u32(0.2126 * r + 0.7152 * g + 0.0722 * b), LUMA_BINS - 1u);
}

@compute @workgroup_size(SCREEN_TILE, SCREEN_TILE)
fn shade(@builtin(global_invocation_id) id: vec3<u32>) {
    if id.x >= frame.width || id.y >= frame.height {
        return;
    }
    let pixel = id.y * frame.width + id.x;
    let here = depth[pixel];
    let surface = is_surface(here);
    var sum = 0.0;
    for (var i = 0u; i < 4u; i++) {
        let offset = vec2<i32>(round(DIRECTIONS[i] * frame.edl_radius));
        let a = depth_at(i32(id.x) + offset.x, i32(id.y) + offset.y);
        let b = depth_at(i32(id.x) - offset.x, i32(id.y) - offset.y);
        let a_surface = is_surface(a);
        let b_surface = is_surface(b);
        if !surface {
            sum += OUTLINE_RESPONSE * (f32(a_surface) + f32(b_surface));
        } else if a_surface && b_surface {
            sum += 2.0 * max(0.0, log2(here * (1.0 / a + 1.0 / b) * 0.5));
        } else if a_surface {
            sum += max(0.0, log2(here) - log2(a));
        } else if b_surface {
            sum += max(0.0, log2(here) - log2(b));
        }
    }
    let shade = exp(-300.0 * frame.edl_strength * sum / 8.0);
    let before = color[pixel];
    var after = before;
    if shade < 1.0 {
        let rgba = unpack4x8unorm(before);
        // Outlines on a transparent background become opaque as they darken.
        let alpha = select(rgba.a, mix(1.0, rgba.a, shade), !surface);
        after = pack_unorm4x8(vec4<f32>(rgba.rgb * shade, alpha));
        color[pixel] = after;
    }
    let counted = all(id.xy >= frame.counted_min) && all(id.xy < frame.counted_end);
    if surface && counted {
        atomicAdd(&luma_counts[luma_bin(before)], 1u);
        atomicAdd(&luma_counts[LUMA_BINS + luma_bin(after)], 1u);
    }
}
