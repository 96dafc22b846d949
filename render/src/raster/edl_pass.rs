//! Eye-Dome Lighting (`shaders/edl.wgsl`): depth-based shading of the resolved image, in place.

use pointfarm_shaders::Shader;

use super::pipeline::{bind_buffers, compute_pipeline, dispatch_tiles, shader_module};
use super::targets::FrameTargets;

pub(crate) struct EdlPass {
    shade: wgpu::ComputePipeline,
}

impl EdlPass {
    pub fn new(device: &wgpu::Device) -> Self {
        let module = shader_module(device, Shader::Edl);
        let shade = compute_pipeline(device, &module, "shade", &[]);
        Self { shade }
    }

    pub fn record(
        &self,
        device: &wgpu::Device,
        pass: &mut wgpu::ComputePass<'_>,
        uniforms: &wgpu::Buffer,
        targets: &FrameTargets,
    ) {
        let bind_group = bind_buffers(
            device,
            &self.shade,
            "edl",
            &[(0, uniforms), (1, &targets.color), (2, &targets.depth)],
        );
        pass.set_pipeline(&self.shade);
        pass.set_bind_group(0, &bind_group, &[]);
        dispatch_tiles(pass, targets.width, targets.height);
    }
}
