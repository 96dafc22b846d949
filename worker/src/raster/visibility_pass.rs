//! Screen-space visibility (Pintus et al., section 4; `shaders/visibility.wgsl`): marks the
//! points seen through holes of a nearer surface, and the background pixels enclosed by
//! points, as mutable holes for the filling; everything else is fixed.

use pointfarm_shaders::Shader;

use super::pipeline::{bind_resources, compute_pipeline, dispatch_tiles, shader_module};
use super::screen_params::ScreenUniforms;
use super::targets::FrameTargets;

pub(crate) struct VisibilityPass {
    classify: wgpu::ComputePipeline,
}

impl VisibilityPass {
    pub fn new(device: &wgpu::Device) -> Self {
        let module = shader_module(device, Shader::Visibility);
        let classify = compute_pipeline(device, &module, "classify", &[]);
        Self { classify }
    }

    /// Reads the resolved images; writes the visible pixels into the fill buffers.
    pub fn record(
        &self,
        device: &wgpu::Device,
        pass: &mut wgpu::ComputePass<'_>,
        params: &ScreenUniforms,
        targets: &FrameTargets,
    ) {
        let Some(fill) = targets.fill.as_ref() else {
            return;
        };
        let bind_group = bind_resources(
            device,
            &self.classify,
            "visibility",
            vec![
                (0, params.fill()),
                (1, targets.depth.as_entire_binding()),
                (2, targets.colour.as_entire_binding()),
                (3, fill.depth.as_entire_binding()),
                (4, fill.colour.as_entire_binding()),
                (5, fill.mutable.as_entire_binding()),
            ],
        );
        pass.set_pipeline(&self.classify);
        pass.set_bind_group(0, &bind_group, &[]);
        dispatch_tiles(pass, targets.width, targets.height);
    }
}
