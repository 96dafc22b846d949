//! Shape-depicting shading (Pintus et al., section 6; `shaders/pintus.wgsl`): one dispatch
//! per smoothing level, each adding its weighted term to a per-pixel sum, then the color
//! multiplied by the normalised sum. The frame's depth image is only read.

use pointfarm_shaders::Shader;
use wgpu::ComputePass;

use super::pipeline::{dispatch_tiles, entry_pipelines};
use super::screen_params::ScreenFrame;

pub(crate) struct PintusPass {
    level: wgpu::ComputePipeline,
    apply: wgpu::ComputePipeline,
}

impl PintusPass {
    pub fn new(device: &wgpu::Device) -> Self {
        let [level, apply] = entry_pipelines(device, Shader::PintusShading, ["level", "apply"]);
        Self { level, apply }
    }

    pub fn record(&self, pass: &mut ComputePass<'_>, frame: ScreenFrame<'_>, levels: u32) {
        let (params, targets) = (frame.params, frame.targets);
        let Some(shading) = targets.shading.as_ref() else {
            return;
        };
        pass.set_pipeline(&self.level);
        for k in 0..levels {
            // Level 0 reads the frame's depth; later levels the smoothed depth of the previous.
            let depth_in = match k {
                0 => &targets.depth,
                _ => &shading.depth[(k as usize + 1) % 2],
            };
            let resources = vec![
                (0, params.pintus_level(k)),
                (1, depth_in.as_entire_binding()),
                (2, shading.depth[k as usize % 2].as_entire_binding()),
                (3, shading.sum.as_entire_binding()),
            ];
            pass.set_bind_group(0, &frame.bind(&self.level, "pintus level", resources), &[]);
            dispatch_tiles(pass, targets.width, targets.height);
        }
        let resources = vec![
            (0, params.pintus_level(0)),
            (1, targets.depth.as_entire_binding()),
            (3, shading.sum.as_entire_binding()),
            (4, targets.color.as_entire_binding()),
        ];
        pass.set_pipeline(&self.apply);
        pass.set_bind_group(0, &frame.bind(&self.apply, "pintus apply", resources), &[]);
        dispatch_tiles(pass, targets.width, targets.height);
    }
}
