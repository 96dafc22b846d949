// The fixed-function baseline of the benchmark (what the papers call GL_POINTS): the same
// points, read from the same storage buffers as the compute passes, drawn as a PointList with
// a hardware depth test. One-pixel points only: WebGPU has no point size.
//
// The vertex index is the point's index within its segment. Points outside near..far are
// clipped by the hardware against clip-space z in [0, 1] (the DirectX-style projection of
// `camera.rs`), which matches `project_quantised`'s depth test up to rounding.

@group(0) @binding(0) var<uniform> frame: FrameUniforms;
@group(0) @binding(1) var<storage, read> positions: array<vec2<u32>>;
@group(0) @binding(2) var<storage, read> batches: array<Batch>;
@group(0) @binding(5) var<storage, read> colors: array<u32>;

struct VertexOutput {
    @builtin(position) clip: vec4<f32>,
    @location(0) @interpolate(flat) color: vec4<f32>,
}

@vertex
fn vertex_main(@builtin(vertex_index) index: u32) -> VertexOutput {
    // The same quantised points as the compute passes; dequantising is a few ALU operations.
    let batch = batches[index / BATCH_POINTS];
    let position = dequantise(positions[index], batch.min, quantisation_step(batch));
    let w = color_word_index(index);
    var out: VertexOutput;
    out.clip = frame.view_proj * vec4<f32>(position, 1.0);
    out.color = unpack4x8unorm(unpack_color(colors[w], colors[w + 1u], index));
    return out;
}

@fragment
fn fragment_main(in: VertexOutput) -> @location(0) vec4<f32> {
    return in.color;
}
