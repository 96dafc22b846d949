//! Clearing the point framebuffer before a frame, and resolving it into the RGBA8 and depth
//! images afterwards (`shaders/resolve.wgsl`). Shared by both atomics paths, whose
//! framebuffers have the same layout.

use pointfarm_shaders::layout::{self, RESOLVE_WORKGROUP};
use pointfarm_shaders::Shader;

use super::pipeline::{
    bind_buffers, bind_resources, compute_pipeline, dispatch_grid, shader_module,
};
use super::pixel_rect::PixelRect;
use super::targets::FrameTargets;

/// Consecutive pixels per invocation of `resolve` and of `resolve_average` (resolve.wgsl says
/// why).
const RESOLVE_RUN: u64 = layout::RESOLVE_RUN as u64;
const AVERAGE_RUN: u64 = layout::AVERAGE_RUN as u64;

/// The pixels a resolve visits: `count` consecutive pixels from `first` (row-major). Whole
/// rows, from the first row a rectangle touches to its last, the first pixel moved back to a
/// binding-offset boundary: the shader then runs its fastest form, a plain loop over
/// consecutive pixels (`shaders/resolve.wgsl`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct PixelRun {
    pub first: u64,
    pub count: u64,
}

impl PixelRun {
    /// The run over the rows of `rect` in an image `width` pixels wide, for bindings whose
    /// offsets must be multiples of `offset_alignment` bytes.
    pub fn covering(rect: PixelRect, width: u32, offset_alignment: u64) -> Self {
        if rect.is_empty() {
            return PixelRun { first: 0, count: 0 };
        }
        let width = u64::from(width);
        // The narrowest binding holds 4 bytes a pixel.
        let step = (offset_alignment / 4).max(1);
        let first = u64::from(rect.y0) * width / step * step;
        PixelRun {
            first,
            count: u64::from(rect.y1) * width - first,
        }
    }

    /// `bytes_per_pixel` bytes per pixel of `buffer`, for this run.
    fn binding(self, buffer: &wgpu::Buffer, bytes_per_pixel: u64) -> wgpu::BindingResource<'_> {
        wgpu::BindingResource::Buffer(wgpu::BufferBinding {
            buffer,
            offset: self.first * bytes_per_pixel,
            size: wgpu::BufferSize::new(self.count * bytes_per_pixel),
        })
    }
}

/// What one frame's resolve reads and writes.
#[derive(Clone, Copy)]
pub(crate) struct ResolveFrame<'a> {
    pub uniforms: &'a wgpu::Buffer,
    pub targets: &'a FrameTargets,
    /// The pixels to visit.
    pub run: PixelRun,
    /// Whether to write the depth image (`FrameSettings::needs_depth_image`).
    pub write_depth: bool,
}

pub(crate) struct ResolvePass {
    clear: wgpu::ComputePipeline,
    resolve: ByDepthOutput,
    resolve_average: ByDepthOutput,
    resolve_average_packed: ByDepthOutput,
}

/// One resolve entry point built twice: with and without the store of the depth image
/// (the shader's `WRITE_DEPTH`), which only some frames need.
struct ByDepthOutput {
    with_depth: wgpu::ComputePipeline,
    color_only: wgpu::ComputePipeline,
}

impl ByDepthOutput {
    fn new(device: &wgpu::Device, module: &wgpu::ShaderModule, entry_point: &str) -> Self {
        let build = |write_depth: bool| {
            let constants = [("WRITE_DEPTH", f64::from(u8::from(write_depth)))];
            compute_pipeline(device, module, entry_point, &constants)
        };
        Self {
            with_depth: build(true),
            color_only: build(false),
        }
    }

    fn get(&self, write_depth: bool) -> &wgpu::ComputePipeline {
        if write_depth {
            &self.with_depth
        } else {
            &self.color_only
        }
    }
}

impl ResolvePass {
    pub fn new(device: &wgpu::Device) -> Self {
        let module = shader_module(device, Shader::Resolve);
        let packed = shader_module(device, Shader::ResolvePacked);
        Self {
            clear: compute_pipeline(device, &module, "clear", &[]),
            resolve: ByDepthOutput::new(device, &module, "resolve"),
            resolve_average: ByDepthOutput::new(device, &module, "resolve_average"),
            resolve_average_packed: ByDepthOutput::new(device, &packed, "resolve_average"),
        }
    }

    pub fn record_clear(
        &self,
        device: &wgpu::Device,
        pass: &mut wgpu::ComputePass<'_>,
        targets: &FrameTargets,
    ) {
        let bind_group = bind_buffers(device, &self.clear, "clear", &[(1, &targets.framebuffer)]);
        self.dispatch(pass, &self.clear, &bind_group, targets.pixels());
    }

    /// The nearest point's color per pixel of the frame's run, and its depth where needed.
    pub fn record_resolve(
        &self,
        device: &wgpu::Device,
        pass: &mut wgpu::ComputePass<'_>,
        frame: ResolveFrame<'_>,
    ) {
        let pipeline = self.resolve.get(frame.write_depth);
        self.record(device, pass, (pipeline, RESOLVE_RUN), frame, None);
    }

    /// High-quality mode: the average of the accumulated colors per pixel of the frame's run,
    /// and the nearest depth where needed; from the packed sums too where `packed_sums` (the
    /// accumulation added to them, `HqAccumulatePass::packs_sums`).
    pub fn record_resolve_average(
        &self,
        device: &wgpu::Device,
        pass: &mut wgpu::ComputePass<'_>,
        frame: ResolveFrame<'_>,
        packed_sums: bool,
    ) {
        let targets = frame.targets;
        let Some(accumulator) = targets.accumulator.as_ref() else {
            return;
        };
        let (pipeline, packed_sums) = match (packed_sums, &targets.packed_sums) {
            (true, Some(packed)) => (&self.resolve_average_packed, Some(packed)),
            _ => (&self.resolve_average, None),
        };
        self.record(
            device,
            pass,
            (pipeline.get(frame.write_depth), AVERAGE_RUN),
            frame,
            Some((accumulator, packed_sums)),
        );
    }

    fn record(
        &self,
        device: &wgpu::Device,
        pass: &mut wgpu::ComputePass<'_>,
        (pipeline, pixels_per_invocation): (&wgpu::ComputePipeline, u64),
        frame: ResolveFrame<'_>,
        sums: Option<(&wgpu::Buffer, Option<&wgpu::Buffer>)>,
    ) {
        let (run, targets) = (frame.run, frame.targets);
        if run.count == 0 {
            return;
        }
        let mut resources = vec![
            (0, frame.uniforms.as_entire_binding()),
            (1, run.binding(&targets.framebuffer, 8)),
            (2, run.binding(&targets.color, 4)),
            (3, run.binding(&targets.depth, 4)),
        ];
        if let Some((accumulator, packed_sums)) = sums {
            resources.push((4, run.binding(accumulator, 16)));
            if let Some(packed_sums) = packed_sums {
                resources.push((5, run.binding(packed_sums, 8)));
            }
        }
        let bind_group = bind_resources(device, pipeline, "resolve", resources);
        let invocations = run.count.div_ceil(pixels_per_invocation);
        self.dispatch(pass, pipeline, &bind_group, invocations);
    }

    fn dispatch(
        &self,
        pass: &mut wgpu::ComputePass<'_>,
        pipeline: &wgpu::ComputePipeline,
        bind_group: &wgpu::BindGroup,
        invocations: u64,
    ) {
        pass.set_pipeline(pipeline);
        pass.set_bind_group(0, bind_group, &[]);
        let groups = invocations.div_ceil(u64::from(RESOLVE_WORKGROUP)) as u32;
        let (x, y) = dispatch_grid(groups);
        pass.dispatch_workgroups(x, y, 1);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::gpu::{read_buffer, staging_buffer};
    use wgpu::util::DeviceExt;

    /// `quotient` of resolve.wgsl, the high-quality average's division without integer
    /// division, equals integer division on this adapter over the range it is used in.
    #[test]
    fn the_shaders_quotient_is_exact_integer_division() {
        let gpu = crate::testing::gpu();
        let source = Shader::Resolve.source();
        let start = source
            .find("fn quotient(")
            .expect("resolve.wgsl has quotient");
        let end = start + source[start..].find("\n}\n").expect("end of quotient") + 3;
        let wgsl = format!(
            "{}\n@group(0) @binding(0) var<storage, read> pairs: array<vec2<u32>>;\n\
             @group(0) @binding(1) var<storage, read_write> out: array<u32>;\n\
             @compute @workgroup_size(64)\n\
             fn main(@builtin(global_invocation_id) id: vec3<u32>) {{\n\
                 if id.x < arrayLength(&pairs) {{\n\
                     let p = pairs[id.x];\n\
                     out[id.x] = quotient(vec3<u32>(p.x, p.x + 1u, p.x / 2u), p.y).x;\n\
                 }}\n\
             }}\n",
            &source[start..end]
        );
        // Sums of 255 levels and counts as the resolve forms them, the exact multiples and
        // their neighbours (where a wrong rounding shows first), up to 16 million points.
        let mut pairs: Vec<[u32; 2]> = Vec::new();
        let mut rng = 0x2545_f491_4f6c_dd1d_u64;
        let mut next = |limit: u64| {
            rng ^= rng << 13;
            rng ^= rng >> 7;
            rng ^= rng << 17;
            (rng % limit) as u32
        };
        for count in (1u32..300).chain([1 << 12, 65_535, 65_536, 1 << 20, 16_000_000]) {
            for level in [0u32, 1, 127, 128, 254, 255] {
                let exact = level * count;
                for a in [exact.saturating_sub(1), exact, exact + 1, exact + count / 2] {
                    pairs.push([a, count]);
                }
            }
        }
        for _ in 0..20_000 {
            let count = 1 + next(1 << 24);
            let a = next(255 * u64::from(count) + u64::from(count / 2) + 1);
            pairs.push([a, count]);
        }
        let input = gpu
            .device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("pairs"),
                contents: bytemuck::cast_slice(&pairs),
                usage: wgpu::BufferUsages::STORAGE,
            });
        let bytes = pairs.len() as u64 * 4;
        let output = gpu.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("quotients"),
            size: bytes,
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
            mapped_at_creation: false,
        });
        let module = gpu
            .device
            .create_shader_module(wgpu::ShaderModuleDescriptor {
                label: Some("quotient test"),
                source: wgpu::ShaderSource::Wgsl(wgsl.into()),
            });
        let pipeline = compute_pipeline(&gpu.device, &module, "main", &[]);
        let bind_group = bind_buffers(
            &gpu.device,
            &pipeline,
            "quotient test",
            &[(0, &input), (1, &output)],
        );
        let mut encoder = gpu.device.create_command_encoder(&Default::default());
        {
            let mut pass = encoder.begin_compute_pass(&Default::default());
            pass.set_pipeline(&pipeline);
            pass.set_bind_group(0, &bind_group, &[]);
            pass.dispatch_workgroups((pairs.len() as u32).div_ceil(64), 1, 1);
        }
        gpu.queue.submit([encoder.finish()]);
        let staging = staging_buffer(&gpu.device, "quotients", bytes);
        let quotients: Vec<u32> = bytemuck::pod_collect_to_vec(
            &read_buffer(&gpu, &output, &staging, bytes).expect("read"),
        );
        for (&[a, b], &q) in pairs.iter().zip(&quotients) {
            assert_eq!(q, a / b, "{a} / {b}");
        }
    }

    #[test]
    fn a_run_covers_the_rows_of_its_rectangle_from_an_aligned_first_pixel() {
        let rect = PixelRect {
            x0: 30,
            y0: 3,
            x1: 40,
            y1: 5,
        };
        // 100 pixels a row; 256-byte offsets are 64 pixels of color.
        let run = PixelRun::covering(rect, 100, 256);
        assert_eq!(
            run,
            PixelRun {
                first: 256,
                count: 244
            }
        );
        assert_eq!(run.first % 64, 0);
        assert!(run.first <= 3 * 100 + 30 && run.first + run.count >= 4 * 100 + 40);
        assert_eq!(
            PixelRun::covering(PixelRect::full(100, 50), 100, 256),
            PixelRun {
                first: 0,
                count: 5000
            }
        );
        assert_eq!(PixelRun::covering(PixelRect::EMPTY, 100, 256).count, 0);
    }
}
