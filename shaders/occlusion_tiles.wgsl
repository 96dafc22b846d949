// The occlusion tiles between point dispatches (see occlusion.wgsl): mark them all unknown
// (and zero the counts of skipped batches) before a frame's first point pass, and build them
// from the framebuffer before a dispatch that tests against them. Composed after common.wgsl.

const UNKNOWN: u32 = 0xffffffffu;

@group(0) @binding(0) var<uniform> frame: FrameUniforms;
// y of each entry is the pixel's depth bits, 0xffffffff where no point landed.
@group(0) @binding(1) var<storage, read> framebuffer: array<vec2<u32>>;
@group(0) @binding(2) var<storage, read_write> tiles: array<u32>;
// The counts of batches skipped (occlusion.wgsl).
@group(0) @binding(3) var<storage, read_write> skipped: array<u32>;

@compute @workgroup_size(OCCLUSION_CLEAR_WORKGROUP)
fn clear_tiles(@builtin(global_invocation_id) id: vec3<u32>) {
    if id.x < arrayLength(&tiles) {
        tiles[id.x] = UNKNOWN;
    }
    if id.x < arrayLength(&skipped) {
        skipped[id.x] = 0u;
    }
}

// One invocation per tile of the frame's footprint (dispatched over it from its first tile):
// the largest depth bits of the tile's pixels. Positive depths order like their bits, and an
// empty pixel's bits are the largest of all. Tiles outside the footprint stay unknown: no
// listed batch reaches them.
@compute @workgroup_size(OCCLUSION_BUILD_WORKGROUP_SIDE, OCCLUSION_BUILD_WORKGROUP_SIDE)
fn build_tiles(@builtin(global_invocation_id) id: vec3<u32>) {
    let across = (frame.width + OCCLUSION_TILE - 1u) / OCCLUSION_TILE;
    let down = (frame.height + OCCLUSION_TILE - 1u) / OCCLUSION_TILE;
    let tx = frame.occlusion_tile_x0 + id.x;
    let ty = frame.occlusion_tile_y0 + id.y;
    if tx >= across || ty >= down {
        return;
    }
    let x0 = tx * OCCLUSION_TILE;
    let y0 = ty * OCCLUSION_TILE;
    let x1 = min(x0 + OCCLUSION_TILE, frame.width);
    let y1 = min(y0 + OCCLUSION_TILE, frame.height);
    var deepest = 0u;
    for (var y = y0; y < y1; y++) {
        for (var x = x0; x < x1; x++) {
            deepest = max(deepest, framebuffer[y * frame.width + x].y);
        }
    }
    tiles[ty * across + tx] = deepest;
}
