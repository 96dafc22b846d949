//! The high-quality mode's accumulation pass (`shaders/hq_accumulate.wgsl`): after the depth
//! pass, every point within the depth band behind its pixel's nearest depth adds its colour and
//! a count; the resolve pass (`resolve_average`) divides.

use pointfarm_shaders::Shader;

use super::basic_pass::{module, pipeline};
use super::points::GpuPointCloud;
use super::targets::FrameTargets;

pub(crate) struct HqAccumulatePass {
    accumulate: wgpu::ComputePipeline,
}

impl HqAccumulatePass {
    pub fn new(device: &wgpu::Device) -> Self {
        let module = module(device, Shader::HqAccumulate);
        Self {
            accumulate: pipeline(device, &module, "accumulate"),
        }
    }

    /// Records the accumulation over every chunk. `targets.accumulator` must exist and be
    /// cleared, and the depth pass must have run.
    pub fn record(
        &self,
        device: &wgpu::Device,
        pass: &mut wgpu::ComputePass<'_>,
        uniforms: &wgpu::Buffer,
        cloud: &GpuPointCloud,
        targets: &FrameTargets,
    ) {
        let Some(accumulator) = targets.accumulator.as_ref() else {
            return;
        };
        pass.set_pipeline(&self.accumulate);
        for chunk in &cloud.chunks {
            let bind_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("accumulate"),
                layout: &self.accumulate.get_bind_group_layout(0),
                entries: &[
                    wgpu::BindGroupEntry {
                        binding: 0,
                        resource: uniforms.as_entire_binding(),
                    },
                    wgpu::BindGroupEntry {
                        binding: 1,
                        resource: chunk.points.as_entire_binding(),
                    },
                    wgpu::BindGroupEntry {
                        binding: 2,
                        resource: chunk.batches.as_entire_binding(),
                    },
                    wgpu::BindGroupEntry {
                        binding: 3,
                        resource: targets.framebuffer.as_entire_binding(),
                    },
                    wgpu::BindGroupEntry {
                        binding: 4,
                        resource: accumulator.as_entire_binding(),
                    },
                ],
            });
            pass.set_bind_group(0, &bind_group, &[]);
            let (x, y) = super::dispatch_grid(chunk.batch_count);
            pass.dispatch_workgroups(x, y, 1);
        }
    }
}
