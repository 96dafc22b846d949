// What the point passes (raster_atomic64.wgsl, raster_atomic32.wgsl, hq_accumulate.wgsl)
// share: their common bindings, their workgroup size, and the
// walk over the points of the batch a workgroup draws. Composed after common.wgsl and
// occlusion.wgsl; each pass's own file defines `draw_splat`, what it does with one point.

// Invocations per workgroup, which the host picks for the adapter and sets on every
// pipeline (`raster/point_workgroup.rs`).
override WORKGROUP_SIZE: u32;

@group(0) @binding(0) var<uniform> frame: FrameUniforms;
@group(0) @binding(1) var<storage, read> positions: array<vec2<u32>>;
// This frame's entries for the segment (`listed_batch`), and the segment's batch table.
@group(0) @binding(2) var<storage, read> listed: array<u32>;
@group(0) @binding(8) var<storage, read> batches: array<Batch>;
@group(0) @binding(5) var<storage, read> colors: array<u32>;

fn color_of(i: u32) -> u32 {
    let w = color_word_index(i);
    return unpack_color(colors[w], colors[w + 1u], i);
}

// Which kind of pass draws, as `occlusion_skipped` counts them (occlusion.wgsl): the one that
// writes depths, or one that reads them (32-bit color, high-quality accumulation).
const WRITES_DEPTHS: u32 = 0u;
const READS_DEPTHS: u32 = 1u;

// The batch of this workgroup's listed entry, or none (no points): past the end of the list,
// outside the view, or behind the occlusion tiles by `band` (`batch_occluded`), which counts
// it as skipped by `pass_kind` (`count_skipped`).
fn workgroup_batch(invocation: GridInvocation, band: f32, pass_kind: u32) -> Batch {
    var none: Batch;
    let b = workgroup_index(invocation);
    if b >= arrayLength(&listed) {
        return none;
    }
    let entry = listed[b];
    let batch = listed_batch(entry, batches[entry >> 8u]);
    if batch_outside_view(frame, batch) {
        return none;
    }
    if batch_occluded(frame, batch, band) {
        count_skipped(pass_kind, invocation.lane);
        return none;
    }
    return batch;
}

// Hands each point of the workgroup's batch that lies in the view to the pass's
// `draw_splat(point, splat, band, pass_kind)`, a point per lane at a time. Every pass walks its
// points this way; the call is inlined, so each pass's loop is the one it had written out.
fn draw_batch(invocation: GridInvocation, band: f32, pass_kind: u32) {
    let batch = workgroup_batch(invocation, band, pass_kind);
    let points = batch_points(batch);
    if points == 0u {
        return;
    }
    let projection = batch_projection(frame, batch);
    for (var i = batch.first + invocation.lane; i < batch.first + points; i += WORKGROUP_SIZE) {
        let splat = project_quantised(frame, projection, positions[i]);
        if !splat.visible {
            continue;
        }
        draw_splat(i, splat, band, pass_kind);
    }
}
