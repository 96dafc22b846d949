// Occlusion culling of whole batches: an early depth test for a batch's box before any of its
// points is read. Composed after common.wgsl into the point passes.
//
// Between dispatches, `build_tiles` (occlusion_tiles.wgsl) cuts the framebuffer into tiles of
// OCCLUSION_TILE x OCCLUSION_TILE pixels and stores per tile the largest depth of its pixels,
// or "empty" when any pixel has no point yet. Depths in the framebuffer only fall, so a batch
// whose nearest possible depth lies behind that on every tile its points can reach has no
// point that could pass the depth test, and is skipped whole.

// A box that reaches more tiles than this is drawn untested: the test would cost more than it
// can save (and such a box is near the camera, rarely hidden).
const MAX_TESTED_TILES: u32 = 256u;

// Per tile, the bits of the largest depth of its pixels (0xffffffff: a pixel is empty, or the
// tiles were not built yet this frame).
@group(0) @binding(6) var<storage, read> occlusion_tiles: array<u32>;

// Batches skipped whole this frame, for tests and the benchmark: [0] by the pass that writes
// depths, [1] by the passes that read them (32-bit color, high-quality accumulation).
@group(0) @binding(7) var<storage, read_write> occlusion_skipped: array<atomic<u32>>;

fn count_skipped(pass_kind: u32, lane: u32) {
    if lane == 0u {
        atomicAdd(&occlusion_skipped[pass_kind], 1u);
    }
}

// True when every point of the batch's box lands behind `band` times the depth the tiles
// hold where it lands (band 1: behind it; the high-quality accumulation passes its band).
fn batch_occluded(frame: FrameUniforms, batch: Batch, band: f32) -> bool {
    var nearest = 3.0e38;
    var low = vec2<f32>(3.0e38);
    var high = vec2<f32>(-3.0e38);
    for (var corner = 0u; corner < 8u; corner++) {
        let p = box_corner(batch, corner);
        let depth = dot(frame.depth_row, p);
        let clip = frame.view_proj * p;
        // A corner before the near plane: the box's image is unbounded.
        if !(depth >= frame.near && clip.w > 0.0) {
            return false;
        }
        nearest = min(nearest, depth);
        let pixel = vec2<f32>(
            (clip.x / clip.w * 0.5 + 0.5) * f32(frame.width),
            (0.5 - clip.y / clip.w * 0.5) * f32(frame.height),
        );
        low = min(low, pixel);
        high = max(high, pixel);
    }
    // A splat reaches POINT_SIZE pixels beyond its centre, and f32 rounding a pixel more.
    let margin = f32(POINT_SIZE) + 1.0;
    let size = vec2<f32>(f32(frame.width), f32(frame.height));
    if any(high + margin < vec2<f32>(0.0)) || any(low - margin >= size) {
        return false;
    }
    let first = vec2<u32>(clamp(low - margin, vec2<f32>(0.0), size - 1.0)) / OCCLUSION_TILE;
    let last = vec2<u32>(clamp(high + margin, vec2<f32>(0.0), size - 1.0)) / OCCLUSION_TILE;
    let span = last - first + 1u;
    if span.x * span.y > MAX_TESTED_TILES {
        return false;
    }
    // The points' own depths are computed in f32 and may fall a few ulp short of the corners'.
    let limit = nearest * (1.0 - 1e-5);
    let across = (frame.width + OCCLUSION_TILE - 1u) / OCCLUSION_TILE;
    for (var ty = first.y; ty <= last.y; ty++) {
        for (var tx = first.x; tx <= last.x; tx++) {
            // An empty tile's bits are a NaN: the comparison fails.
            if !(bitcast<f32>(occlusion_tiles[ty * across + tx]) * band < limit) {
                return false;
            }
        }
    }
    return true;
}
