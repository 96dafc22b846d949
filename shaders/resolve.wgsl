// Resolves the point framebuffer into an RGBA8 image and a linear depth image, and clears each
// entry as it reads it, so the next frame starts from an empty framebuffer without a pass of
// its own (`clear` is only needed for a framebuffer that was never resolved). Works on both
// rasterizer variants: each framebuffer entry is a pair of u32 words, x = color, y = depth
// bits (the little-endian halves of the 64-bit word), and 0xffffffff in both means "no point".
//
// The resolves visit the frame's run of pixels only: `frame.resolve_pixels` of them, from the
// start of the bindings, which the host offsets to the run's first pixel. Outside it no point
// landed and the images are already clean (`raster/targets.rs`). Index and bound keep the form
// of a plain loop over consecutive pixels: on lavapipe adding an offset to the index, or a 2D
// dispatch over a rectangle, cost 1.2 to 1.5 times as much per pixel.
//
// Each invocation resolves a short run of consecutive pixels, and empties the framebuffer (and
// accumulator) entries of its run only when a point landed on one of them. llvmpipe stores lane
// by lane behind a branch on each lane's mask: per pixel, that branch mispredicted wherever
// covered and empty pixels mix at random (sparse points), while per run it is predictable on
// both solid and sparse surfaces and still skips empty background (docs/perf/resolve-runs.md). The run lengths, `RESOLVE_RUN` and `AVERAGE_RUN`, come from the
// layout prelude; the high-quality resolve holds four words a pixel, and its shorter runs were
// faster.

const EMPTY: u32 = 0xffffffffu;
// Depth where no point landed: the bits of +infinity.
const NO_SURFACE_BITS: u32 = 0x7f800000u;
// False where no later pass reads the depth image and it is not read back: the resolves then
// skip its store, one of the four memory accesses per pixel.
override WRITE_DEPTH: bool = true;

@group(0) @binding(0) var<uniform> frame: FrameUniforms;
@group(0) @binding(1) var<storage, read_write> framebuffer: array<vec2<u32>>;
@group(0) @binding(2) var<storage, read_write> color_out: array<u32>;
@group(0) @binding(3) var<storage, read_write> depth_out: array<f32>;
// High-quality mode only: per pixel the sums of red, green, blue and the count of points (after
// the 64-bit accumulation, the wide sums beside the packed ones); zeroed as they are read, like
// the framebuffer (buffers start zeroed).
@group(0) @binding(4) var<storage, read_write> accumulator: array<vec4<u32>>;

fn pixel_of(id: vec3<u32>, groups: vec3<u32>) -> u32 {
    return id.y * groups.x * RESOLVE_WORKGROUP + id.x;
}

@compute @workgroup_size(RESOLVE_WORKGROUP)
fn clear(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let pixel = pixel_of(id, groups);
    if pixel < arrayLength(&framebuffer) {
        framebuffer[pixel] = vec2<u32>(EMPTY, EMPTY);
    }
}

@compute @workgroup_size(RESOLVE_WORKGROUP)
fn resolve(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let first = pixel_of(id, groups) * RESOLVE_RUN;
    if first >= frame.resolve_pixels {
        return;
    }
    let count = min(RESOLVE_RUN, frame.resolve_pixels - first);
    var entries: array<vec2<u32>, RESOLVE_RUN>;
    var covered = false;
    for (var k = 0u; k < RESOLVE_RUN; k++) {
        if k < count {
            entries[k] = framebuffer[first + k];
            covered = covered || entries[k].y != EMPTY;
        }
    }
    if covered {
        for (var k = 0u; k < RESOLVE_RUN; k++) {
            if k < count {
                framebuffer[first + k] = vec2<u32>(EMPTY, EMPTY);
            }
        }
    }
    // Selects, not branches, for the images: in a CPU's SIMD lanes (lavapipe) both sides of a
    // branch run wherever covered and empty pixels mix, and each side has its own stores.
    for (var k = 0u; k < RESOLVE_RUN; k++) {
        if k < count {
            let empty = entries[k].y == EMPTY;
            color_out[first + k] = select(entries[k].x, frame.background, empty);
            if WRITE_DEPTH {
                depth_out[first + k] = bitcast<f32>(select(entries[k].y, NO_SURFACE_BITS, empty));
            }
        }
    }
}

// a / b rounded down, for b > 0, a / b < 2^16 and a + 2b < 2^32, without integer division,
// which lavapipe runs lane by lane (it made the high-quality resolve 1.6 times as slow). The f32
// quotient is within one of the exact one here, and one correction each way makes it exact.
fn quotient(a: vec3<u32>, b: u32) -> vec3<u32> {
    // The f32 quotient to an integer by a float add and bitcast (`floor_to_i32`), not WGSL's
    // clamping conversion, which lavapipe runs lane by lane too.
    let estimate = floor(vec3<f32>(a) / f32(b)) + 8388608.0;
    var q = bitcast<vec3<u32>>(estimate) - vec3<u32>(0x4b000000u);
    q = select(q, q - 1u, q * b > a);
    q = select(q, q + 1u, (q + 1u) * b <= a);
    return q;
}

// High-quality mode: writes pixel `pixel`'s rounded average of the colors accumulated in
// `sums` (red, green, blue, count), or the background where none was; and its depth.
fn write_average(pixel: u32, sums: vec4<u32>, depth_bits: u32) {
    // Round half up: (sum + count / 2) / count. Selects, not branches (see `resolve`).
    let count = sums.w;
    let divisor = max(count, 1u);
    let average = quotient(sums.xyz + vec3<u32>(count / 2u), divisor);
    let rgba = average.x | (average.y << 8u) | (average.z << 16u) | (255u << 24u);
    color_out[pixel] = select(rgba, frame.background, count == 0u);
    if WRITE_DEPTH {
        depth_out[pixel] = bitcast<f32>(select(depth_bits, NO_SURFACE_BITS, count == 0u));
    }
}

// High-quality mode: the rounded average of the colors accumulated per pixel. The sums come
// from `read_sums` and are emptied by `empty_sums`, which the file composed after this one
// defines: resolve_sums.wgsl for the 32-bit accumulation's, resolve_sums_packed.wgsl for the
// 64-bit one's (hq_sums_atomic32.wgsl, hq_sums_atomic64.wgsl).
@compute @workgroup_size(RESOLVE_WORKGROUP)
fn resolve_average(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let first = pixel_of(id, groups) * AVERAGE_RUN;
    if first >= frame.resolve_pixels {
        return;
    }
    let pixels = min(AVERAGE_RUN, frame.resolve_pixels - first);
    var sums: array<vec4<u32>, AVERAGE_RUN>;
    var depths: array<u32, AVERAGE_RUN>;
    var covered = false;
    for (var k = 0u; k < AVERAGE_RUN; k++) {
        if k < pixels {
            sums[k] = read_sums(first + k);
            depths[k] = framebuffer[first + k].y;
            covered = covered || sums[k].w != 0u || depths[k] != EMPTY;
        }
    }
    // As in `resolve`: only a run where points wrote needs emptying.
    if covered {
        for (var k = 0u; k < AVERAGE_RUN; k++) {
            if k < pixels {
                empty_sums(first + k);
                framebuffer[first + k] = vec2<u32>(EMPTY, EMPTY);
            }
        }
    }
    for (var k = 0u; k < AVERAGE_RUN; k++) {
        if k < pixels {
            write_average(first + k, sums[k], depths[k]);
        }
    }
}
