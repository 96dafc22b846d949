// Eye-Dome Lighting as Potree does it (Boucheny 2009): shading from depth alone, so clouds
// without colour or normals read as surfaces. Runs on the resolved images and changes the
// colour in place (each pixel reads only its own colour, and its neighbours' depths).
//
// For a pixel with depth d, over 8 neighbours on a circle of `edl_radius` pixels:
// response = (1/8) * sum max(0, log2 d - log2 d_neighbour); a background pixel next to
// geometry gets 100 per such neighbour instead, which draws the silhouette outline.
// shade = exp(-300 * edl_strength * response); colour *= shade.

@group(0) @binding(0) var<uniform> frame: FrameUniforms;
@group(0) @binding(1) var<storage, read_write> color: array<u32>;
@group(0) @binding(2) var<storage, read> depth: array<f32>;

const OUTLINE_RESPONSE: f32 = 100.0;
const INFINITE_DEPTH: u32 = 0x7f800000u;

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

// The eight sample directions, 45 degrees apart: constants rather than a cos and a sin per
// sample, which cost lavapipe more than the rest of the pass (docs/perf/edl-constants.md).
const DIAGONAL: f32 = 0.70710677;
const DIRECTIONS = array<vec2<f32>, 8>(
    vec2<f32>(1.0, 0.0),
    vec2<f32>(DIAGONAL, DIAGONAL),
    vec2<f32>(0.0, 1.0),
    vec2<f32>(-DIAGONAL, DIAGONAL),
    vec2<f32>(-1.0, 0.0),
    vec2<f32>(-DIAGONAL, -DIAGONAL),
    vec2<f32>(0.0, -1.0),
    vec2<f32>(DIAGONAL, -DIAGONAL),
);

@compute @workgroup_size(SCREEN_TILE, SCREEN_TILE)
fn shade(@builtin(global_invocation_id) id: vec3<u32>) {
    if id.x >= frame.width || id.y >= frame.height {
        return;
    }
    let pixel = id.y * frame.width + id.x;
    let here = depth[pixel];
    let surface = is_surface(here);
    let log_here = log2(here);
    var sum = 0.0;
    for (var i = 0u; i < 8u; i++) {
        let offset = round(DIRECTIONS[i] * frame.edl_radius);
        let there = depth_at(i32(id.x) + i32(offset.x), i32(id.y) + i32(offset.y));
        if !is_surface(there) {
            continue;
        }
        if surface {
            sum += max(0.0, log_here - log2(there));
        } else {
            sum += OUTLINE_RESPONSE;
        }
    }
    let shade = exp(-300.0 * frame.edl_strength * sum / 8.0);
    if shade >= 1.0 {
        return;
    }
    let rgba = unpack4x8unorm(color[pixel]);
    // Outlines on a transparent background become opaque as they darken.
    let alpha = select(rgba.a, mix(1.0, rgba.a, shade), !surface);
    color[pixel] = pack_unorm4x8(vec4<f32>(rgba.rgb * shade, alpha));
}
