//! The compute pipelines of one point-pass entry point, one per point size.
//!
//! The side of a point's square is the shaders' pipeline constant `POINT_SIZE`, not a uniform:
//! with a constant trip count the shader compiler unrolls the per-pixel loop, and on lavapipe
//! the runtime loop made the point pass much slower (docs/perf/point-size-constant.md). The default size 1
//! is built with the renderer, other sizes on first use, then kept.

use std::collections::HashMap;
use std::sync::{Mutex, PoisonError};

use super::pipeline::compute_pipeline;

pub(crate) struct PointPipelines {
    module: wgpu::ShaderModule,
    entry_point: &'static str,
    workgroup_size: u32,
    by_point_size: Mutex<HashMap<u32, wgpu::ComputePipeline>>,
}

impl PointPipelines {
    /// Pipelines for `entry_point` of `module`, `workgroup_size` invocations a group.
    pub fn new(
        device: &wgpu::Device,
        module: &wgpu::ShaderModule,
        entry_point: &'static str,
        workgroup_size: u32,
    ) -> Self {
        let pipelines = Self {
            module: module.clone(),
            entry_point,
            workgroup_size,
            by_point_size: Mutex::new(HashMap::new()),
        };
        pipelines.get(device, 1);
        pipelines
    }

    /// The pipeline for points of `point_size` pixels, built if this is its first use.
    pub fn get(&self, device: &wgpu::Device, point_size: u32) -> wgpu::ComputePipeline {
        let mut built = self
            .by_point_size
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        built
            .entry(point_size)
            .or_insert_with(|| {
                tracing::debug!(
                    entry_point = self.entry_point,
                    point_size,
                    "building point pipeline"
                );
                compute_pipeline(
                    device,
                    &self.module,
                    self.entry_point,
                    &[
                        ("WORKGROUP_SIZE", f64::from(self.workgroup_size)),
                        ("POINT_SIZE", f64::from(point_size)),
                    ],
                )
            })
            .clone()
    }
}
