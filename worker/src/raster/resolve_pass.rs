//! Clearing the point framebuffer before a frame, and resolving it into the RGBA8 and depth
//! images afterwards (`shaders/resolve.wgsl`). Shared by both atomics paths, whose
//! framebuffers have the same layout.

use pointfarm_shaders::Shader;

use super::pipeline::{bind_buffers, compute_pipeline, shader_module};
use super::targets::FrameTargets;

/// Must match `@workgroup_size` in resolve.wgsl.
const WORKGROUP_SIZE: u32 = 256;

pub(crate) struct ResolvePass {
    clear: wgpu::ComputePipeline,
    resolve: wgpu::ComputePipeline,
    resolve_average: wgpu::ComputePipeline,
}

impl ResolvePass {
    pub fn new(device: &wgpu::Device) -> Self {
        let module = shader_module(device, Shader::Resolve);
        let pipeline = |entry_point: &str| compute_pipeline(device, &module, entry_point, &[]);
        Self {
            clear: pipeline("clear"),
            resolve: pipeline("resolve"),
            resolve_average: pipeline("resolve_average"),
        }
    }

    pub fn record_clear(
        &self,
        device: &wgpu::Device,
        pass: &mut wgpu::ComputePass<'_>,
        targets: &FrameTargets,
    ) {
        let bind_group = bind_buffers(device, &self.clear, "clear", &[(1, &targets.framebuffer)]);
        self.dispatch(pass, &self.clear, &bind_group, targets);
    }

    pub fn record_resolve(
        &self,
        device: &wgpu::Device,
        pass: &mut wgpu::ComputePass<'_>,
        uniforms: &wgpu::Buffer,
        targets: &FrameTargets,
    ) {
        let bind_group = bind_buffers(
            device,
            &self.resolve,
            "resolve",
            &[
                (0, uniforms),
                (1, &targets.framebuffer),
                (2, &targets.colour),
                (3, &targets.depth),
            ],
        );
        self.dispatch(pass, &self.resolve, &bind_group, targets);
    }

    /// High-quality mode: the average of the accumulated colours per pixel.
    pub fn record_resolve_average(
        &self,
        device: &wgpu::Device,
        pass: &mut wgpu::ComputePass<'_>,
        uniforms: &wgpu::Buffer,
        targets: &FrameTargets,
    ) {
        let Some(accumulator) = targets.accumulator.as_ref() else {
            return;
        };
        let bind_group = bind_buffers(
            device,
            &self.resolve_average,
            "resolve average",
            &[
                (0, uniforms),
                (1, &targets.framebuffer),
                (2, &targets.colour),
                (3, &targets.depth),
                (4, accumulator),
            ],
        );
        self.dispatch(pass, &self.resolve_average, &bind_group, targets);
    }

    fn dispatch(
        &self,
        pass: &mut wgpu::ComputePass<'_>,
        pipeline: &wgpu::ComputePipeline,
        bind_group: &wgpu::BindGroup,
        targets: &FrameTargets,
    ) {
        pass.set_pipeline(pipeline);
        pass.set_bind_group(0, bind_group, &[]);
        let groups = targets.pixels().div_ceil(WORKGROUP_SIZE as u64) as u32;
        let (x, y) = super::dispatch_grid(groups);
        pass.dispatch_workgroups(x, y, 1);
    }
}
