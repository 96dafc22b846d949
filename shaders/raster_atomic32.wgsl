// Basic-mode rasterizer for adapters without 64-bit atomics: the same image as
// raster_atomic64.wgsl in two passes over the points.
//
// The framebuffer has the same memory layout as the 64-bit one, as pairs of u32 words:
// [2i] = color, [2i + 1] = depth bits. `rasterize_depth` keeps the nearest depth per pixel;
// `rasterize_color` then lets every point whose depth equals the stored one atomicMin its
// color, which picks the same winner as the 64-bit (depth << 32 | color) minimum. Both
// passes compute depths with the same code from the same inputs, so equality is exact.

@group(0) @binding(3) var<storage, read_write> framebuffer: array<atomic<u32>>;

fn depth_word(pixel: i32) -> i32 {
    return 2 * pixel + 1;
}

fn color_word(pixel: i32) -> i32 {
    return 2 * pixel;
}

@compute @workgroup_size(WORKGROUP_SIZE)
fn rasterize_depth(invocation: GridInvocation) {
    draw_batch(invocation, 1.0, WRITES_DEPTHS);
}

@compute @workgroup_size(WORKGROUP_SIZE)
fn rasterize_color(invocation: GridInvocation) {
    draw_batch(invocation, 1.0, READS_DEPTHS);
}

// The two passes walk the same points in the same way; `pass_kind`, a constant in each entry
// point once inlined, picks what they write.
fn draw_splat(i: u32, splat: Splat, band: f32, pass_kind: u32) {
    let depth_bits = bitcast<u32>(splat.depth);
    for (var k = 0u; k < SPLAT_PIXELS; k++) {
        let pixel = splat_pixel(frame, splat, k);
        if pixel < 0 {
            continue;
        }
        let stored_depth = atomicLoad(&framebuffer[depth_word(pixel)]);
        if pass_kind == READS_DEPTHS {
            if stored_depth == depth_bits {
                atomicMin(&framebuffer[color_word(pixel)], color_of(i));
            }
        } else if stored_depth >= depth_bits {
            // Early depth test as in the 64-bit pass: only nearer or equal points try.
            atomicMin(&framebuffer[depth_word(pixel)], depth_bits);
        }
    }
}
