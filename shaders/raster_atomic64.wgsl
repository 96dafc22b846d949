// Basic-mode rasterizer with 64-bit atomics (Schütz & Wimmer 2021).
//
// Each framebuffer word holds (depth bits << 32 | RGBA8). Depths are positive f32, whose bit
// patterns order like the values, so one atomicMin keeps the nearest point, and among points
// at exactly the same depth the smallest color word: the image does not depend on the order
// in which points arrive.
//
// One workgroup per batch. Needs SHADER_INT64 and SHADER_INT64_ATOMIC_MIN_MAX.

@group(0) @binding(3) var<storage, read_write> framebuffer: array<atomic<u64>>;
// The same buffer as `framebuffer`, read without atomics for the early depth test: a stale
// read only costs an unneeded atomicMin, never a wrong pixel. y is the depth word.
@group(0) @binding(4) var<storage, read_write> framebuffer_words: array<vec2<u32>>;

@compute @workgroup_size(WORKGROUP_SIZE)
fn rasterize(invocation: GridInvocation) {
    draw_batch(invocation, 1.0, WRITES_DEPTHS);
}

// Keeps point `i` in every pixel of its splat where it is the nearest.
fn draw_splat(i: u32, splat: Splat, band: f32, pass_kind: u32) {
    let depth_bits = bitcast<u32>(splat.depth);
    // Read only once a pixel passed the early depth test.
    var color = 0u;
    var have_color = false;
    for (var k = 0u; k < SPLAT_PIXELS; k++) {
        let pixel = splat_pixel(frame, splat, k);
        if pixel < 0 {
            continue;
        }
        // Early depth test: skip the atomic when a nearer point is already stored.
        if framebuffer_words[pixel].y < depth_bits {
            continue;
        }
        if !have_color {
            color = color_of(i);
            have_color = true;
        }
        atomicMin(&framebuffer[pixel], (u64(depth_bits) << 32u) | u64(color));
    }
}
