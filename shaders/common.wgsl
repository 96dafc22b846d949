// Shared by every point pass: the frame's camera, the point layout and the projection.
// Prepended to each pass's source by `pointfarm_shaders::compose` (WGSL has no includes).

struct FrameUniforms {
    // Clip-space transform of positions relative to the dataset origin.
    view_proj: mat4x4<f32>,
    // Linear view depth of a point p: dot(depth_row, vec4(p, 1)). Positive in front.
    depth_row: vec4<f32>,
    // Points are culled unless near <= depth <= far.
    near: f32,
    far: f32,
    width: u32,
    height: u32,
    // RGBA8 written where no point landed.
    background: u32,
    // High-quality mode: points whose depth is at most (1 + depth_band) times the nearest
    // depth of their pixel are averaged.
    depth_band: f32,
    // Eye-Dome Lighting: 0 strength turns it off.
    edl_strength: f32,
    edl_radius: f32,
    // Pixels the resolve visits, from the first of its (offset) bindings.
    resolve_pixels: u32,
    // The first tile of the frame's footprint, where the occlusion tiles are built from.
    occlusion_tile_x0: u32,
    occlusion_tile_y0: u32,
    // Adaptive point size: a point's side in pixels times its linear depth.
    point_size_scale: f32,
    // The pixels frame-wide statistics count (a tile's core, not its apron), end exclusive.
    counted_min: vec2<u32>,
    counted_end: vec2<u32>,
}

// Side of the square each point covers, in pixels. A pipeline constant, not a uniform: with a
// constant trip count the compiler unrolls the per-pixel loop, which lavapipe runs much faster
// (docs/perf/point-size-constant.md). One pipeline per size. With ADAPTIVE_SIZE it is the
// largest side, and each point masks its square down to its own.
override POINT_SIZE: u32 = 1u;
// Potree's adaptive size: a point's side is `point_size_scale` over its depth, rounded, from 1
// to POINT_SIZE.
override ADAPTIVE_SIZE: bool = false;
// Round points: only the pixels whose centres lie in the disc the point's square bounds.
override ROUND_POINTS: bool = false;

// Points are grouped in batches of nearby points (Morton order), each with its bounding box.
// Each frame the host lists the batches that can be in view and a point pass runs one
// workgroup per listed batch (`raster/culling/`), so culled batches cost nothing.
struct Batch {
    min: vec3<f32>,
    first: u32,
    max: vec3<f32>,
    // The batch's points in the low 16 bits; the high 16 bits are its point-size factor
    // (`batch_size_factor`).
    count: u32,
}

fn batch_points(batch: Batch) -> u32 {
    return batch.count & 0xffffu;
}

// What a batch's points' adaptive size is multiplied by: 8.8 fixed point, 0 meaning 1. A
// level-of-detail cut sizes each node's batches by the node's spacing
// (`GpuBatch::with_size_factor`).
fn batch_size_factor(batch: Batch) -> f32 {
    let code = batch.count >> 16u;
    return select(1.0, f32(code) / 256.0, code != 0u);
}

// The batch a frame table's entry lists (`ListedEntry` in `raster/culling/listing.rs`): `batch`, the
// segment's table entry at `entry >> 8`, narrowed to the run of its sub-batches from
// `(entry >> 4) & 15` for `(entry & 15) + 1` of them (the whole batch: 0 and 15).
fn listed_batch(entry: u32, batch: Batch) -> Batch {
    var listed = batch;
    listed.first = batch.first + ((entry >> 4u) & 15u) * SUB_BATCH_POINTS;
    let end = min(listed.first + ((entry & 15u) + 1u) * SUB_BATCH_POINTS, batch.first + batch_points(batch));
    listed.count = (end - listed.first) | (batch.count & 0xffff0000u);
    return listed;
}

// Points are stored quantised (Kanzok et al.), 11 bytes each, in two arrays per segment:
// - positions: array<vec2<u32>>, `POSITION_BITS` of x/y/z as a fraction of the batch's box
//   (bit layout in `quantised_coordinates`);
// - colors: array<u32> holding 3 RGB bytes per point back to back, plus one spare word.
// The color lives apart so that a pass reads it only for points that pass the depth test.

// One quantisation step per axis: extent / (2^bits - 1), with the host's reciprocals
// (`INV_QUANT_MAX` in the layout prelude, also used by `points::quantisation_step`).
fn quantisation_step(batch: Batch) -> vec3<f32> {
    return (batch.max - batch.min) * INV_QUANT_MAX;
}

// The bit layout of a quantised position (`POSITION_BITS`): x in the first word's low bits,
// y's low `Y_LOW_BITS` in the rest of the first word and its high `Y_HIGH_BITS` at the bottom
// of the second, z above them.
const X_MASK: u32 = (1u << POSITION_BITS.x) - 1u;
const Y_LOW_BITS: u32 = 32u - POSITION_BITS.x;
const Y_HIGH_BITS: u32 = POSITION_BITS.y - Y_LOW_BITS;
const Y_HIGH_MASK: u32 = (1u << Y_HIGH_BITS) - 1u;

// The quantised coordinates of a point, as floats: its position is `origin + q * step` in the
// batch with box minimum `origin` and steps `step`.
fn quantised_coordinates(word: vec2<u32>) -> vec3<f32> {
    return vec3<f32>(vec3<u32>(
        word.x & X_MASK,
        (word.x >> POSITION_BITS.x) | ((word.y & Y_HIGH_MASK) << Y_LOW_BITS),
        word.y >> Y_HIGH_BITS,
    ));
}

// Position relative to the dataset origin of a quantised point of a batch with box minimum
// `origin` and steps `step`.
fn dequantise(word: vec2<u32>, origin: vec3<f32>, step: vec3<f32>) -> vec3<f32> {
    return origin + quantised_coordinates(word) * step;
}

// Index of the first of the two color words that hold point `i`'s RGB bytes.
fn color_word_index(i: u32) -> u32 {
    return (3u * i) >> 2u;
}

// The RGBA8 color of point `i` from the two words at `color_word_index(i)`: alpha is 255,
// points are opaque.
fn unpack_color(first: u32, second: u32, i: u32) -> u32 {
    let shift = ((3u * i) & 3u) * 8u;
    // A shift by 32 is undefined in WGSL: only bytes that spill over come from `second`.
    var rgb = first >> shift;
    if shift > 8u {
        rgb |= second << (32u - shift);
    }
    return (rgb & 0xffffffu) | 0xff000000u;
}

// floor(x) as an i32, for |x| < 2^22. WGSL's i32(f32) clamps and maps NaN to 0, which
// lavapipe (LLVM 15) compiles to a scalar conversion, compare and two conditional moves per
// lane; this is three vector instructions. Adding 1.5 * 2^23 puts the integer floor(x) in the
// low mantissa bits of a float whose exponent is fixed, exactly: ulp 1 in [2^23, 2^24).
fn floor_to_i32(x: f32) -> i32 {
    return bitcast<i32>(floor(x) + 12582912.0) - 0x4b400000;
}

// WGSL's pack4x8unorm: each component clamped to [0, 1] and converted to the byte
// floor(0.5 + 255 c). Lavapipe compiles the built-in's float-to-int conversions lane by lane;
// this does them as above (`floor_to_i32`), exact since the bytes are integers below 2^23.
fn pack_unorm4x8(v: vec4<f32>) -> u32 {
    let bytes = bitcast<vec4<u32>>(floor(0.5 + 255.0 * clamp(v, vec4<f32>(0.0), vec4<f32>(1.0))) + 8388608.0) & vec4<u32>(0xffu);
    return bytes.x | (bytes.y << 8u) | (bytes.z << 16u) | (bytes.w << 24u);
}

// A point that survived the frustum test: its pixel square and its depth.
struct Splat {
    // Top-left pixel of the square (may be partly off-screen).
    x0: i32,
    y0: i32,
    depth: f32,
    visible: bool,
    // Side of the square: POINT_SIZE unless ADAPTIVE_SIZE.
    side: u32,
}

// A batch's projection of its quantised points. Each row maps a point's quantised coordinates
// q to `dot(row.xyz, q) + row.w`: the dequantisation and the viewport are folded into the
// camera's rows once per batch, which leaves a point three dot products and one division
// (a third of the arithmetic of dequantising, transforming and mapping it in turn).
struct BatchProjection {
    // Pixel x and y, each times clip-space w.
    x_w: vec4<f32>,
    y_w: vec4<f32>,
    // Clip-space w.
    w: vec4<f32>,
    // Linear view depth (`FrameUniforms::depth_row`).
    depth: vec4<f32>,
    // Adaptive point size: a point's side in pixels times its linear depth.
    size_scale: f32,
}

fn quantised_row(row: vec4<f32>, origin: vec3<f32>, step: vec3<f32>) -> vec4<f32> {
    return vec4<f32>(row.xyz * step, dot(row, vec4<f32>(origin, 1.0)));
}

fn batch_projection(frame: FrameUniforms, batch: Batch) -> BatchProjection {
    let step = quantisation_step(batch);
    let m = transpose(frame.view_proj);
    // Pixel x = (ndc.x * 0.5 + 0.5) * width and y = (0.5 - ndc.y * 0.5) * height, with
    // ndc = clip.xy / clip.w.
    let half = 0.5 * vec2<f32>(f32(frame.width), f32(frame.height));
    var p: BatchProjection;
    p.x_w = quantised_row(half.x * (m[0] + m[3]), batch.min, step);
    p.y_w = quantised_row(half.y * (m[3] - m[1]), batch.min, step);
    p.w = quantised_row(m[3], batch.min, step);
    p.depth = quantised_row(frame.depth_row, batch.min, step);
    p.size_scale = frame.point_size_scale * batch_size_factor(batch);
    return p;
}

fn project_quantised(frame: FrameUniforms, projection: BatchProjection, word: vec2<u32>) -> Splat {
    var s: Splat;
    s.visible = false;
    let q = quantised_coordinates(word);
    let depth = dot(projection.depth.xyz, q) + projection.depth.w;
    // Also rejects NaN: comparisons with NaN are false.
    if !(depth >= frame.near && depth <= frame.far) {
        return s;
    }
    let inv_w = 1.0 / (dot(projection.w.xyz, q) + projection.w.w);
    let px = (dot(projection.x_w.xyz, q) + projection.x_w.w) * inv_w;
    let py = (dot(projection.y_w.xyz, q) + projection.y_w.w) * inv_w;
    // Far outside the image: reject before the float-to-int conversion can saturate.
    let margin = f32(POINT_SIZE);
    if !(px >= -margin && px < f32(frame.width) + margin && py >= -margin && py < f32(frame.height) + margin) {
        return s;
    }
    var side = POINT_SIZE;
    if ADAPTIVE_SIZE {
        // Rounded in f32 and clamped before the conversion, as `FrameSettings::point_side_at`.
        side = u32(clamp(floor(projection.size_scale / depth + 0.5), 1.0, f32(POINT_SIZE)));
    }
    s.side = side;
    let half = i32((side - 1u) / 2u);
    s.x0 = floor_to_i32(px) - half;
    s.y0 = floor_to_i32(py) - half;
    s.depth = depth;
    s.visible = true;
    return s;
}

// Corner `corner` (0 to 7: bit 0 picks max x, bit 1 max y, bit 2 max z) of the batch's box,
// as a point with w = 1.
fn box_corner(batch: Batch, corner: u32) -> vec4<f32> {
    return vec4<f32>(
        select(batch.min.x, batch.max.x, (corner & 1u) != 0u),
        select(batch.min.y, batch.max.y, (corner & 2u) != 0u),
        select(batch.min.z, batch.max.z, (corner & 4u) != 0u),
        1.0,
    );
}

// True when no part of the batch's box can be in view: all eight corners lie outside the
// same frustum plane (clip-space side planes widened by the point size, and near/far).
// The host has culled the batches already; this f32 test is kept because it costs little for
// a batch in view, and without it lavapipe ran the point passes slower
// (docs/perf/shader-box-test.md).
fn batch_outside_view(frame: FrameUniforms, batch: Batch) -> bool {
    let widen = vec2<f32>(
        1.0 + 2.0 * f32(POINT_SIZE) / f32(frame.width),
        1.0 + 2.0 * f32(POINT_SIZE) / f32(frame.height),
    );
    var out_left = true;
    var out_right = true;
    var out_bottom = true;
    var out_top = true;
    var out_near = true;
    var out_far = true;
    for (var corner = 0u; corner < 8u; corner++) {
        let p = box_corner(batch, corner);
        let clip = frame.view_proj * p;
        let depth = dot(frame.depth_row, p);
        let w = clip.w;
        out_left = out_left && clip.x < -w * widen.x;
        out_right = out_right && clip.x > w * widen.x;
        out_bottom = out_bottom && clip.y < -w * widen.y;
        out_top = out_top && clip.y > w * widen.y;
        out_near = out_near && depth < frame.near;
        out_far = out_far && depth > frame.far;
    }
    return out_left || out_right || out_bottom || out_top || out_near || out_far;
}

// Number of pixels a splat covers (before clipping to the image).
override SPLAT_PIXELS: u32 = POINT_SIZE * POINT_SIZE;

// Framebuffer index of the k-th pixel of the splat's square, or -1 when it is off-screen or
// outside the point's own square or disc.
fn splat_pixel(frame: FrameUniforms, splat: Splat, k: u32) -> i32 {
    let dx = k % POINT_SIZE;
    let dy = k / POINT_SIZE;
    if ADAPTIVE_SIZE && (dx >= splat.side || dy >= splat.side) {
        return -1;
    }
    if ROUND_POINTS {
        // Pixel centre to square centre, doubled to stay in integers: inside the disc when
        // (2 dx + 1 - side)^2 + (2 dy + 1 - side)^2 <= side^2.
        let cx = i32(2u * dx + 1u) - i32(splat.side);
        let cy = i32(2u * dy + 1u) - i32(splat.side);
        if cx * cx + cy * cy > i32(splat.side * splat.side) {
            return -1;
        }
    }
    let x = splat.x0 + i32(dx);
    let y = splat.y0 + i32(dy);
    if x < 0 || y < 0 || x >= i32(frame.width) || y >= i32(frame.height) {
        return -1;
    }
    return y * i32(frame.width) + x;
}

// The builtins of an entry point that finds its work by its workgroup and lane: the point
// passes (a batch a workgroup) and the filling (a run of listed pixels a workgroup).
struct GridInvocation {
    @builtin(workgroup_id) workgroup: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) lane: u32,
}

// The invocation's workgroup counted across the dispatch, whose workgroups lie on a 2D grid
// because one dimension holds at most 65535 of them.
fn workgroup_index(invocation: GridInvocation) -> u32 {
    return invocation.workgroup.y * invocation.groups.x + invocation.workgroup.x;
}
