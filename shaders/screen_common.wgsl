// Shared by the screen-space passes that run on the resolved images (visibility, filling,
// Pintus shading): their parameters, the depth image they read, and how a pixel and its depth
// become a view-space point.

struct ScreenParams {
    width: u32,
    height: u32,
    // Visibility kernel: (2 kernel_radius + 1)^2 pixels around each pixel.
    kernel_radius: u32,
    // 1 for a perspective camera, 0 for an orthographic one.
    perspective: u32,
    // View-space x and y of a pixel: ndc * unproject, times the depth in perspective (ndc of
    // the whole frame, `frame_offset` and `frame_size`).
    unproject: vec2<f32>,
    // Visibility: a pixel is visible when the solid angle left open around its
    // point-to-camera ray is at least this (steradians).
    min_solid_angle: f32,
    // Filling: a neighbour whose depth differs from the pixel's by depth_tolerance times the
    // pixel's depth (the paper's delta, relative) has no weight.
    depth_tolerance: f32,
    // RGBA8 of pixels that stay empty.
    background: u32,
    // Pintus shading, per level: 1 on the first level (the sum starts there).
    first_level: u32,
    // Pintus shading: this level's weight 1 / (k + 1)^xi ...
    level_weight: f32,
    // ... and one over the sum of all levels' weights (a flat, facing surface keeps its color).
    inverse_total_weight: f32,
    // Visibility: the pixels it classifies, x0, y0, x1, y1 (the footprint grown by the
    // kernel's radius and a pixel); all others are fixed background.
    visibility_area: vec4<u32>,
    // Where these images lie in the frame they belong to: pixel (0, 0)'s position in it, and
    // its size (a tile of a frame too large for one pass; else 0, 0 and width, height).
    frame_offset: vec2<u32>,
    frame_size: vec2<u32>,
}

@group(0) @binding(0) var<uniform> params: ScreenParams;
@group(0) @binding(1) var<storage, read> depth_in: array<f32>;

const INFINITE_DEPTH_BITS: u32 = 0x7f800000u;

fn is_surface_depth(d: f32) -> bool {
    return bitcast<u32>(d) != INFINITE_DEPTH_BITS;
}

fn infinite_depth() -> f32 {
    return bitcast<f32>(INFINITE_DEPTH_BITS);
}

// The view-space point of pixel (x, y) at linear depth d: camera at the origin, looking
// along +z, x right and y up.
fn view_point(params: ScreenParams, x: i32, y: i32, d: f32) -> vec3<f32> {
    // The frame's pixel in integers first, so that a tile computes what the whole frame would.
    let frame_x = x + i32(params.frame_offset.x);
    let frame_y = y + i32(params.frame_offset.y);
    let ndc = vec2<f32>(
        (f32(frame_x) + 0.5) / f32(params.frame_size.x) * 2.0 - 1.0,
        1.0 - (f32(frame_y) + 0.5) / f32(params.frame_size.y) * 2.0,
    );
    let scale = select(1.0, d, params.perspective == 1u);
    return vec3<f32>(ndc * params.unproject * scale, d);
}

// Slot k (0 to 8, row-major) of the 3x3 neighbourhood of pixel (x, y): its pixel index, clamped
// to the image so that it can always be read, and whether it lies inside the image. Fixed slots
// with constant k keep every private array index a constant once loops are unrolled (lavapipe
// runs a variable index lane by lane).
struct Neighbour {
    pixel: u32,
    inside: bool,
}

fn neighbour(params: ScreenParams, x: i32, y: i32, k: u32) -> Neighbour {
    let nx = x + i32(k % 3u) - 1;
    let ny = y + i32(k / 3u) - 1;
    var n: Neighbour;
    n.inside = nx >= 0 && ny >= 0 && nx < i32(params.width) && ny < i32(params.height);
    n.pixel = u32(clamp(ny, 0, i32(params.height) - 1)) * params.width
        + u32(clamp(nx, 0, i32(params.width) - 1));
    return n;
}
