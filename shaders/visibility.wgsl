// Pintus et al. 2011, section 4: screen-space visibility. A point is visible when a large
// enough solid angle around its point-to-camera ray holds no other point. The kernel around
// the pixel is cut into 8 sectors (centred on the axes and diagonals); in each, the neighbour
// with the largest dot(v, c) (v: unit vector to the camera, c: unit vector to the neighbour)
// is the horizon, and the sector's open cone has half-angle acos(that dot). The open solid
// angle is the sum over sectors of (2 pi / 8) (1 - cos(half-angle)). An empty sector is open
// all the way round (half-angle pi).
//
// Background pixels go through the same test, as if infinitely far: any point in a sector
// then lies straight towards the camera and closes it. So a background pixel enclosed by
// points becomes fillable, and one beside a silhouette stays background.
//
// Output: the visible pixels unchanged and fixed; the others emptied (+infinity, background
// colour) and marked mutable for the filling.

@group(0) @binding(0) var<uniform> params: ScreenParams;
@group(0) @binding(1) var<storage, read> depth_in: array<f32>;
@group(0) @binding(2) var<storage, read> colour_in: array<u32>;
@group(0) @binding(3) var<storage, read_write> depth_out: array<f32>;
@group(0) @binding(4) var<storage, read_write> colour_out: array<u32>;
@group(0) @binding(5) var<storage, read_write> mutable_pixels: array<u32>;

const SECTORS: u32 = 8u;
const PI: f32 = 3.14159265;
// Marks a sector that holds no point.
const OPEN_SECTOR: f32 = -2.0;

fn sector_of(dx: i32, dy: i32) -> u32 {
    // Image y grows downwards; the sectors only need to be consistent.
    let angle = atan2(f32(dy), f32(dx));
    return u32(i32(round(angle / (PI / 4.0))) + 8) % SECTORS;
}

@compute @workgroup_size(16, 16)
fn classify(@builtin(global_invocation_id) id: vec3<u32>) {
    if id.x >= params.width || id.y >= params.height {
        return;
    }
    let x = i32(id.x);
    let y = i32(id.y);
    let pixel = id.y * params.width + id.x;
    let here = depth_in[pixel];
    let surface = is_surface_depth(here);
    let p0 = view_point(params, x, y, here);
    var to_camera = vec3<f32>(0.0, 0.0, -1.0);
    if params.perspective == 1u {
        to_camera = normalize(-p0);
    }

    var horizon: array<f32, 8>;
    for (var s = 0u; s < SECTORS; s++) {
        horizon[s] = OPEN_SECTOR;
    }
    let r = i32(params.kernel_radius);
    for (var dy = -r; dy <= r; dy++) {
        for (var dx = -r; dx <= r; dx++) {
            let nx = x + dx;
            let ny = y + dy;
            if (dx == 0 && dy == 0) || nx < 0 || ny < 0 || nx >= i32(params.width) || ny >= i32(params.height) {
                continue;
            }
            let there = depth_in[u32(ny) * params.width + u32(nx)];
            if !is_surface_depth(there) {
                continue;
            }
            var cosine = 1.0;
            if surface {
                cosine = dot(to_camera, normalize(view_point(params, nx, ny, there) - p0));
            }
            let s = sector_of(dx, dy);
            horizon[s] = max(horizon[s], cosine);
        }
    }
    var open = 0.0;
    for (var s = 0u; s < SECTORS; s++) {
        open += select(1.0 - horizon[s], 2.0, horizon[s] == OPEN_SECTOR);
    }
    open *= 2.0 * PI / f32(SECTORS);

    if open >= params.min_solid_angle {
        depth_out[pixel] = here;
        colour_out[pixel] = colour_in[pixel];
        mutable_pixels[pixel] = 0u;
    } else {
        depth_out[pixel] = infinite_depth();
        colour_out[pixel] = params.background;
        mutable_pixels[pixel] = 1u;
    }
}
