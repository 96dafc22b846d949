//! Clearing the point framebuffer before a frame, and resolving it into the RGBA8 and depth
//! images afterwards (`shaders/resolve.wgsl`). Shared by both atomics paths, whose
//! framebuffers have the same layout.

use pointfarm_shaders::Shader;

use super::culling::PixelRect;
use super::pipeline::{bind_buffers, compute_pipeline, shader_module};
use super::targets::FrameTargets;

/// Must match `@workgroup_size` in resolve.wgsl.
const WORKGROUP_SIZE: u32 = 256;

pub(crate) struct ResolvePass {
    clear: wgpu::ComputePipeline,
    resolve: ByDepthOutput,
    resolve_average: ByDepthOutput,
}

/// One resolve entry point built twice: with and without the store of the depth image
/// (the shader's `WRITE_DEPTH`), which only some frames need.
struct ByDepthOutput {
    with_depth: wgpu::ComputePipeline,
    colour_only: wgpu::ComputePipeline,
}

impl ByDepthOutput {
    fn new(device: &wgpu::Device, module: &wgpu::ShaderModule, entry_point: &str) -> Self {
        let build = |write_depth: bool| {
            let constants = [("WRITE_DEPTH", f64::from(u8::from(write_depth)))];
            compute_pipeline(device, module, entry_point, &constants)
        };
        Self {
            with_depth: build(true),
            colour_only: build(false),
        }
    }

    fn get(&self, write_depth: bool) -> &wgpu::ComputePipeline {
        if write_depth {
            &self.with_depth
        } else {
            &self.colour_only
        }
    }
}

impl ResolvePass {
    pub fn new(device: &wgpu::Device) -> Self {
        let module = shader_module(device, Shader::Resolve);
        Self {
            clear: compute_pipeline(device, &module, "clear", &[]),
            resolve: ByDepthOutput::new(device, &module, "resolve"),
            resolve_average: ByDepthOutput::new(device, &module, "resolve_average"),
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

    /// The nearest point's colour per pixel of `rect`, and its depth where `write_depth`.
    pub fn record_resolve(
        &self,
        device: &wgpu::Device,
        pass: &mut wgpu::ComputePass<'_>,
        uniforms: &wgpu::Buffer,
        targets: &FrameTargets,
        rect: PixelRect,
        write_depth: bool,
    ) {
        if rect.is_empty() {
            return;
        }
        let pipeline = self.resolve.get(write_depth);
        let bind_group = bind_buffers(
            device,
            pipeline,
            "resolve",
            &[
                (0, uniforms),
                (1, &targets.framebuffer),
                (2, &targets.colour),
                (3, &targets.depth),
            ],
        );
        self.dispatch(pass, pipeline, &bind_group, rect.pixels());
    }

    /// High-quality mode: the average of the accumulated colours per pixel of `rect`, and the
    /// nearest depth where `write_depth`.
    pub fn record_resolve_average(
        &self,
        device: &wgpu::Device,
        pass: &mut wgpu::ComputePass<'_>,
        uniforms: &wgpu::Buffer,
        targets: &FrameTargets,
        rect: PixelRect,
        write_depth: bool,
    ) {
        let Some(accumulator) = targets.accumulator.as_ref() else {
            return;
        };
        if rect.is_empty() {
            return;
        }
        let pipeline = self.resolve_average.get(write_depth);
        let bind_group = bind_buffers(
            device,
            pipeline,
            "resolve average",
            &[
                (0, uniforms),
                (1, &targets.framebuffer),
                (2, &targets.colour),
                (3, &targets.depth),
                (4, accumulator),
            ],
        );
        self.dispatch(pass, pipeline, &bind_group, rect.pixels());
    }

    fn dispatch(
        &self,
        pass: &mut wgpu::ComputePass<'_>,
        pipeline: &wgpu::ComputePipeline,
        bind_group: &wgpu::BindGroup,
        pixels: u64,
    ) {
        pass.set_pipeline(pipeline);
        pass.set_bind_group(0, bind_group, &[]);
        let groups = pixels.div_ceil(WORKGROUP_SIZE as u64) as u32;
        let (x, y) = super::dispatch_grid(groups);
        pass.dispatch_workgroups(x, y, 1);
    }
}
