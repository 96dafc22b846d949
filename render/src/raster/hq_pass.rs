//! The high-quality mode's accumulation pass (`shaders/hq_accumulate.wgsl`): after the depth
//! pass, every point within the depth band behind its pixel's nearest depth adds its color and
//! a count; the resolve pass (`resolve_average`) divides. A level-of-detail cut's pages add
//! each point as many times as the points it stands for (`hq_accumulate_weighted.wgsl`); a
//! resident cloud's segments keep the unweighted shader.

use pointfarm_shaders::Shader;

use super::basic_pass::PointFrame;
use super::pipeline::{bind_resources, dispatch_grid, shader_module};
use super::point_pipelines::PointPipelines;

pub(crate) struct HqAccumulatePass {
    /// Four 32-bit atomics a point: any adapter.
    atomic32: PointPipelines,
    /// Two 64-bit atomics a point, where the device has 64-bit atomicAdd.
    atomic64: Option<PointPipelines>,
    /// The same two for a cut's pages, each point weighted.
    weighted32: PointPipelines,
    weighted64: Option<PointPipelines>,
}

impl HqAccumulatePass {
    pub fn new(device: &wgpu::Device, int64_atomic_add: bool, workgroup_size: u32) -> Self {
        let pipelines = |shader| {
            let module = shader_module(device, shader);
            PointPipelines::new(device, &module, "accumulate", workgroup_size)
        };
        Self {
            atomic32: pipelines(Shader::HqAccumulate),
            atomic64: int64_atomic_add.then(|| pipelines(Shader::HqAccumulate64)),
            weighted32: pipelines(Shader::HqAccumulateWeighted),
            weighted64: int64_atomic_add.then(|| pipelines(Shader::HqAccumulateWeighted64)),
        }
    }

    /// Whether the accumulation adds to the packed sums (`FrameTargets::packed_sums`): with
    /// 64-bit atomics where the device has them and `allow_64`.
    pub fn packs_sums(&self, allow_64: bool) -> bool {
        allow_64 && self.atomic64.is_some()
    }

    /// Records the accumulation over every segment, with 64-bit atomics where the device has
    /// them and `allow_64`. `targets.accumulator` must exist and be cleared, and the depth pass
    /// must have run.
    pub fn record(
        &self,
        device: &wgpu::Device,
        pass: &mut wgpu::ComputePass<'_>,
        frame: PointFrame<'_>,
        allow_64: bool,
    ) {
        let Some(accumulator) = frame.targets.accumulator.as_ref() else {
            return;
        };
        let packed_sums = match (&self.atomic64, &frame.targets.packed_sums) {
            (Some(atomic64), Some(packed_sums)) if allow_64 => Some((atomic64, packed_sums)),
            _ => None,
        };
        let pipelines = packed_sums.map_or(&self.atomic32, |(atomic64, _)| atomic64);
        let pipeline = pipelines.get(device, frame.shape);
        let weighted_pipelines = match (&packed_sums, &self.weighted64) {
            (Some(_), Some(weighted64)) => weighted64,
            _ => &self.weighted32,
        };
        let weighted_pipeline = frame
            .cloud
            .segments
            .iter()
            .any(|c| c.weights.is_some())
            .then(|| weighted_pipelines.get(device, frame.shape));
        // One dispatch per phase of the depth pass (`phases.rs`): over the whole table, the
        // near phases' batches, where most points add colors, came first and the hidden far
        // ones last, and lavapipe's threads shared that work unevenly
        // (docs/perf/depth-phases.md).
        let parts =
            (0..frame.batches.phase_count()).flat_map(|phase| frame.batches.phase_parts(phase));
        for (index, (table, entries)) in parts {
            let segment = &frame.cloud.segments[index];
            let pipeline = match (&segment.weights, &weighted_pipeline) {
                (Some(_), Some(weighted)) => weighted,
                _ => &pipeline,
            };
            pass.set_pipeline(pipeline);
            let mut resources = vec![
                (0, frame.uniforms.as_entire_binding()),
                (1, segment.positions.as_entire_binding()),
                (2, wgpu::BindingResource::Buffer(table)),
                (8, segment.batches.as_entire_binding()),
                (3, frame.targets.framebuffer.as_entire_binding()),
                (4, accumulator.as_entire_binding()),
                (5, segment.colors.as_entire_binding()),
                // The tiles after the depth pass: batches behind the depth band are skipped.
                (6, frame.targets.occlusion.tiles.as_entire_binding()),
                (7, frame.targets.occlusion.skipped.as_entire_binding()),
            ];
            if let Some((_, packed_sums)) = packed_sums {
                resources.push((10, packed_sums.as_entire_binding()));
            }
            if let Some(weights) = &segment.weights {
                resources.push((11, weights.codes.as_entire_binding()));
                resources.push((12, weights.drawn_children.as_entire_binding()));
            }
            let bind_group = bind_resources(device, pipeline, "accumulate", resources);
            pass.set_bind_group(0, &bind_group, &[]);
            let (x, y) = dispatch_grid(entries);
            pass.dispatch_workgroups(x, y, 1);
        }
    }
}
