//! The compute pipelines of one point-pass entry point, one per splat shape.
//!
//! The side of a point's square is the shaders' pipeline constant `POINT_SIZE`, not a uniform:
//! with a constant trip count the shader compiler unrolls the per-pixel loop, and on lavapipe
//! the runtime loop made the point pass much slower (docs/perf/point-size-constant.md). An
//! adaptive size keeps the loop constant at its largest side and masks each point's square.
//! The default shape (1-pixel squares) is built with the renderer, others on first use, then
//! kept.

use std::collections::HashMap;
use std::sync::{Mutex, PoisonError};

use super::pipeline::compute_pipeline;
use super::FrameSettings;

/// What a point pass's pipeline is built for: the pixels a point may cover.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub(crate) struct SplatShape {
    /// `POINT_SIZE`: the side of every point's square, or the largest with `adaptive`.
    pub side: u32,
    pub adaptive: bool,
    pub round: bool,
}

impl SplatShape {
    pub fn of(settings: &FrameSettings) -> Self {
        Self {
            side: settings.point_size,
            // Points of one pixel at every depth need no per-point sizes.
            adaptive: settings.adaptive_size.is_some() && settings.point_size > 1,
            round: settings.round_points,
        }
    }
}

impl Default for SplatShape {
    fn default() -> Self {
        Self {
            side: 1,
            adaptive: false,
            round: false,
        }
    }
}

pub(crate) struct PointPipelines {
    module: wgpu::ShaderModule,
    entry_point: &'static str,
    workgroup_size: u32,
    by_shape: Mutex<HashMap<SplatShape, wgpu::ComputePipeline>>,
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
            by_shape: Mutex::new(HashMap::new()),
        };
        pipelines.get(device, SplatShape::default());
        pipelines
    }

    /// The pipeline for points of `shape`, built if this is its first use.
    pub fn get(&self, device: &wgpu::Device, shape: SplatShape) -> wgpu::ComputePipeline {
        let mut built = self.by_shape.lock().unwrap_or_else(PoisonError::into_inner);
        built
            .entry(shape)
            .or_insert_with(|| {
                tracing::debug!(
                    entry_point = self.entry_point,
                    ?shape,
                    "building point pipeline"
                );
                let flag = |on: bool| if on { 1.0 } else { 0.0 };
                compute_pipeline(
                    device,
                    &self.module,
                    self.entry_point,
                    &[
                        ("WORKGROUP_SIZE", f64::from(self.workgroup_size)),
                        ("POINT_SIZE", f64::from(shape.side)),
                        ("ADAPTIVE_SIZE", flag(shape.adaptive)),
                        ("ROUND_POINTS", flag(shape.round)),
                    ],
                )
            })
            .clone()
    }
}
