//! The high-quality mode's accumulation pass (`shaders/hq_accumulate.wgsl`): after the depth
//! pass, every point within the depth band behind its pixel's nearest depth adds its colour and
//! a count; the resolve pass (`resolve_average`) divides.

use pointfarm_shaders::Shader;

use super::culling::FrameBatches;
use super::pipeline::{bind_resources, shader_module};
use super::point_pipelines::PointPipelines;
use super::points::GpuPointCloud;
use super::targets::FrameTargets;

pub(crate) struct HqAccumulatePass {
    accumulate: PointPipelines,
}

impl HqAccumulatePass {
    pub fn new(device: &wgpu::Device, workgroup_size: u32) -> Self {
        let module = shader_module(device, Shader::HqAccumulate);
        Self {
            accumulate: PointPipelines::new(device, &module, "accumulate", workgroup_size),
        }
    }

    /// Records the accumulation over every chunk. `targets.accumulator` must exist and be
    /// cleared, and the depth pass must have run.
    pub fn record(
        &self,
        device: &wgpu::Device,
        pass: &mut wgpu::ComputePass<'_>,
        point_size: u32,
        uniforms: &wgpu::Buffer,
        (cloud, batches): (&GpuPointCloud, &FrameBatches),
        targets: &FrameTargets,
    ) {
        let Some(accumulator) = targets.accumulator.as_ref() else {
            return;
        };
        let pipeline = self.accumulate.get(device, point_size);
        pass.set_pipeline(&pipeline);
        for (index, chunk) in cloud.chunks.iter().enumerate() {
            let Some(table) = batches.binding(index) else {
                continue;
            };
            let bind_group = bind_resources(
                device,
                &pipeline,
                "accumulate",
                vec![
                    (0, uniforms.as_entire_binding()),
                    (1, chunk.positions.as_entire_binding()),
                    (2, wgpu::BindingResource::Buffer(table)),
                    (3, targets.framebuffer.as_entire_binding()),
                    (4, accumulator.as_entire_binding()),
                    (5, chunk.colours.as_entire_binding()),
                ],
            );
            pass.set_bind_group(0, &bind_group, &[]);
            let (x, y) = super::dispatch_grid(batches.count(index));
            pass.dispatch_workgroups(x, y, 1);
        }
    }
}
