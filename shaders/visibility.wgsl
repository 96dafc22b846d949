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
// color) and listed as mutable for the filling, which then visits only those (fill.wgsl).

@group(0) @binding(2) var<storage, read> color_in: array<u32>;
@group(0) @binding(3) var<storage, read_write> depth_out: array<f32>;
@group(0) @binding(4) var<storage, read_write> color_out: array<u32>;
// The mutable pixels, (y << 16) | x each, in the order the invocations append them.
@group(0) @binding(5) var<storage, read_write> mutable_list: array<u32>;

// The filling's indirect dispatch over `mutable_list`, and the length of the list.
struct FillArgs {
    groups: vec3<u32>,
    count: atomic<u32>,
}
@group(0) @binding(6) var<storage, read_write> fill_args: FillArgs;

// Empties the list: before `classify`.
@compute @workgroup_size(1)
fn reset_list() {
    atomicStore(&fill_args.count, 0u);
}

// The filling's dispatch for the listed pixels: after `classify`. At most 65535 workgroups a
// dimension, so a long list takes rows of them.
@compute @workgroup_size(1)
fn prepare_fill() {
    let groups = (atomicLoad(&fill_args.count) + LIST_WORKGROUP - 1u) / LIST_WORKGROUP;
    fill_args.groups = vec3<u32>(min(groups, 65535u), max(1u, (groups + 65534u) / 65535u), 1u);
}

const SECTORS: u32 = 8u;
const PI: f32 = 3.14159265;
// Marks a sector that holds no point.
const OPEN_SECTOR: f32 = -2.0;

// The sector of offset (dx, dy): round(atan2(dy, dx) / (pi / 4)), from 0 to 7, found by
// comparisons rather than atan2, a rounding and a float-to-int conversion (which lavapipe runs
// lane by lane). Equal for every integer offset: no integer ratio dy / dx is within 0.01 of
// tan(pi / 8), the boundary, for offsets up to 9.
fn sector_of(dx: i32, dy: i32) -> u32 {
    let ax = abs(f32(dx));
    let ay = abs(f32(dy));
    let tan_eighth = 0.41421356;
    let east = dx > 0;
    let south = dy > 0;
    let horizontal = select(4u, 0u, east);
    let vertical = select(6u, 2u, south);
    let diagonal = select(select(5u, 7u, east), select(3u, 1u, east), south);
    return select(select(diagonal, vertical, ax <= tan_eighth * ay), horizontal, ay <= tan_eighth * ax);
}

@compute @workgroup_size(SCREEN_TILE, SCREEN_TILE)
fn classify(@builtin(global_invocation_id) invocation: vec3<u32>) {
    // Dispatched over the visibility area only.
    let id = invocation.xy + params.visibility_area.xy;
    if id.x >= params.visibility_area.z || id.y >= params.visibility_area.w {
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
            // Every sector by a constant index, the one hit by a select: an array indexed by a
            // variable is a per-lane loop through memory on lavapipe.
            let s = sector_of(dx, dy);
            for (var k = 0u; k < SECTORS; k++) {
                horizon[k] = select(horizon[k], max(horizon[k], cosine), s == k);
            }
        }
    }
    var open = 0.0;
    for (var s = 0u; s < SECTORS; s++) {
        open += select(1.0 - horizon[s], 2.0, horizon[s] == OPEN_SECTOR);
    }
    open *= 2.0 * PI / f32(SECTORS);

    if open >= params.min_solid_angle {
        depth_out[pixel] = here;
        color_out[pixel] = color_in[pixel];
    } else {
        depth_out[pixel] = infinite_depth();
        color_out[pixel] = params.background;
        mutable_list[atomicAdd(&fill_args.count, 1u)] = (id.y << 16u) | id.x;
    }
}
