// What the point passes (raster_atomic64.wgsl, raster_atomic32.wgsl, hq_accumulate.wgsl)
// share: their common bindings, their workgroup size, and the batch a workgroup draws.
// Composed after common.wgsl and occlusion.wgsl.

// Invocations per workgroup, which the host picks for the adapter and sets on every
// pipeline (`raster/point_workgroup.rs`).
override WORKGROUP_SIZE: u32;

@group(0) @binding(0) var<uniform> frame: FrameUniforms;
@group(0) @binding(1) var<storage, read> positions: array<vec2<u32>>;
// This frame's entries for the chunk (`listed_batch`), and the chunk's batch table.
@group(0) @binding(2) var<storage, read> listed: array<u32>;
@group(0) @binding(8) var<storage, read> batches: array<Batch>;
@group(0) @binding(5) var<storage, read> colors: array<u32>;

fn color_of(i: u32) -> u32 {
    let w = color_word_index(i);
    return unpack_color(colors[w], colors[w + 1u], i);
}

// The batch of this workgroup's listed entry, or none (`count` 0): past the end of the list,
// outside the view, or behind the occlusion tiles by `band` (`batch_occluded`), which counts
// it as skipped by `pass_kind` (`count_skipped`).
fn workgroup_batch(workgroup: vec3<u32>, groups: vec3<u32>, lane: u32, band: f32, pass_kind: u32) -> Batch {
    var none: Batch;
    let b = batch_index(workgroup, groups);
    if b >= arrayLength(&listed) {
        return none;
    }
    let entry = listed[b];
    let batch = listed_batch(entry, batches[entry >> 8u]);
    if batch_outside_view(frame, batch) {
        return none;
    }
    if batch_occluded(frame, batch, band) {
        count_skipped(pass_kind, lane);
        return none;
    }
    return batch;
}
