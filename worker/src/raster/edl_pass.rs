//! Eye-Dome Lighting (`shaders/edl.wgsl`): depth-based shading of the resolved image, in place.

use pointfarm_shaders::Shader;

use super::basic_pass::module;
use super::targets::FrameTargets;

/// Must match `@workgroup_size` in edl.wgsl.
const TILE: u32 = 16;

pub(crate) struct EdlPass {
    shade: wgpu::ComputePipeline,
}

impl EdlPass {
    pub fn new(device: &wgpu::Device) -> Self {
        let module = module(device, Shader::Edl);
        let shade = device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
            label: Some("edl"),
            layout: None,
            module: &module,
            entry_point: Some("shade"),
            compilation_options: Default::default(),
            cache: None,
        });
        Self { shade }
    }

    pub fn record(
        &self,
        device: &wgpu::Device,
        pass: &mut wgpu::ComputePass<'_>,
        uniforms: &wgpu::Buffer,
        targets: &FrameTargets,
    ) {
        let bind_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("edl"),
            layout: &self.shade.get_bind_group_layout(0),
            entries: &[
                wgpu::BindGroupEntry {
                    binding: 0,
                    resource: uniforms.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 1,
                    resource: targets.colour.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 2,
                    resource: targets.depth.as_entire_binding(),
                },
            ],
        });
        pass.set_pipeline(&self.shade);
        pass.set_bind_group(0, &bind_group, &[]);
        pass.dispatch_workgroups(
            targets.width.div_ceil(TILE),
            targets.height.div_ceil(TILE),
            1,
        );
    }
}
