//! Clearing the point framebuffer before a frame, and resolving it into the RGBA8 and depth
//! images afterwards (`shaders/resolve.wgsl`). Shared by both atomics paths, whose
//! framebuffers have the same layout.

use pointfarm_shaders::Shader;

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
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some(Shader::Resolve.label()),
            source: wgpu::ShaderSource::Wgsl(Shader::Resolve.source().into()),
        });
        let pipeline = |entry_point: &str| {
            device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some(entry_point),
                layout: None,
                module: &module,
                entry_point: Some(entry_point),
                compilation_options: Default::default(),
                cache: None,
            })
        };
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
        let bind_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("clear"),
            layout: &self.clear.get_bind_group_layout(0),
            entries: &[wgpu::BindGroupEntry {
                binding: 1,
                resource: targets.framebuffer.as_entire_binding(),
            }],
        });
        self.dispatch(pass, &self.clear, &bind_group, targets);
    }

    pub fn record_resolve(
        &self,
        device: &wgpu::Device,
        pass: &mut wgpu::ComputePass<'_>,
        uniforms: &wgpu::Buffer,
        targets: &FrameTargets,
    ) {
        let bind_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("resolve"),
            layout: &self.resolve.get_bind_group_layout(0),
            entries: &[
                wgpu::BindGroupEntry {
                    binding: 0,
                    resource: uniforms.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 1,
                    resource: targets.framebuffer.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 2,
                    resource: targets.colour.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 3,
                    resource: targets.depth.as_entire_binding(),
                },
            ],
        });
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
        let bind_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("resolve average"),
            layout: &self.resolve_average.get_bind_group_layout(0),
            entries: &[
                wgpu::BindGroupEntry {
                    binding: 0,
                    resource: uniforms.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 1,
                    resource: targets.framebuffer.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 2,
                    resource: targets.colour.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 3,
                    resource: targets.depth.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 4,
                    resource: accumulator.as_entire_binding(),
                },
            ],
        });
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
