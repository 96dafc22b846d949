//! The high-quality mode's accumulation pass (`shaders/hq_accumulate.wgsl`): after the depth
//! pass, every point within the depth band behind its pixel's nearest depth adds its colour and
//! a count; the resolve pass (`resolve_average`) divides.

use pointfarm_shaders::Shader;

use super::basic_pass::PointFrame;
use super::pipeline::{bind_resources, shader_module};
use super::point_pipelines::PointPipelines;

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
        frame: PointFrame<'_>,
    ) {
        let Some(accumulator) = frame.targets.accumulator.as_ref() else {
            return;
        };
        let pipeline = self.accumulate.get(device, frame.point_size);
        pass.set_pipeline(&pipeline);
        // One dispatch per phase of the depth pass (`phases.rs`): over the whole table, the
        // near phases' batches, where most points add colours, came first and the hidden far
        // ones last, and lavapipe's threads shared that work unevenly (the 10M-point cube's
        // accumulation took 52-58 ms against 36 ms phase by phase).
        let parts =
            (0..frame.batches.phase_count()).flat_map(|phase| frame.batches.phase_parts(phase));
        for (index, (table, entries)) in parts {
            let chunk = &frame.cloud.chunks[index];
            let bind_group = bind_resources(
                device,
                &pipeline,
                "accumulate",
                vec![
                    (0, frame.uniforms.as_entire_binding()),
                    (1, chunk.positions.as_entire_binding()),
                    (2, wgpu::BindingResource::Buffer(table)),
                    (8, chunk.batches.as_entire_binding()),
                    (3, frame.targets.framebuffer.as_entire_binding()),
                    (4, accumulator.as_entire_binding()),
                    (5, chunk.colours.as_entire_binding()),
                    // The tiles after the depth pass: batches behind the depth band are skipped.
                    (6, frame.targets.occlusion.tiles.as_entire_binding()),
                    (7, frame.targets.occlusion.skipped.as_entire_binding()),
                ],
            );
            pass.set_bind_group(0, &bind_group, &[]);
            let (x, y) = super::dispatch_grid(entries);
            pass.dispatch_workgroups(x, y, 1);
        }
    }
}
