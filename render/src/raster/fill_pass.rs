//! Anisotropic filling (Pintus et al., section 5; `shaders/fill.wgsl`): `iterations` 3x3
//! steps over the mutable pixels, ping-ponging between the fill buffers and the frame's own
//! color and depth buffers, then the result copied back into the frame's buffers. Each
//! dispatch visits only the pixels the visibility pass listed as mutable (an indirect
//! dispatch it prepared): a fixed pixel holds the same value in both pairs from the
//! visibility pass on.

use pointfarm_shaders::Shader;
use wgpu::ComputePass;

use super::pipeline::entry_pipelines;
use super::screen_params::ScreenFrame;

pub(crate) struct FillPass {
    step: wgpu::ComputePipeline,
    finish: wgpu::ComputePipeline,
}

impl FillPass {
    pub fn new(device: &wgpu::Device) -> Self {
        let [step, finish] = entry_pipelines(device, Shader::Fill, ["fill_step", "finish"]);
        Self { step, finish }
    }

    /// Expects the visibility pass's output in the fill buffers; leaves the filled images in
    /// the frame's color and depth buffers.
    pub fn record(&self, pass: &mut ComputePass<'_>, frame: ScreenFrame<'_>, iterations: u32) {
        let targets = frame.targets;
        let Some(fill) = targets.fill.as_ref() else {
            return;
        };
        // Each step reads one pair of buffers and writes the other; wgpu synchronises
        // successive dispatches of a pass.
        let pairs = [(&fill.depth, &fill.color), (&targets.depth, &targets.color)];
        let bind = |pipeline: &wgpu::ComputePipeline, from: usize| {
            let ((depth_in, color_in), (depth_out, color_out)) = (pairs[from], pairs[1 - from]);
            let resources = vec![
                (0, frame.params.fill()),
                (1, depth_in.as_entire_binding()),
                (2, color_in.as_entire_binding()),
                (3, fill.mutable.as_entire_binding()),
                (6, fill.list_args.as_entire_binding()),
                (4, depth_out.as_entire_binding()),
                (5, color_out.as_entire_binding()),
            ];
            frame.bind(pipeline, "fill", resources)
        };
        let steps = [bind(&self.step, 0), bind(&self.step, 1)];
        pass.set_pipeline(&self.step);
        for i in 0..iterations as usize {
            pass.set_bind_group(0, &steps[i % 2], &[]);
            pass.dispatch_workgroups_indirect(&fill.list_args, 0);
        }
        if iterations.is_multiple_of(2) {
            pass.set_pipeline(&self.finish);
            pass.set_bind_group(0, &bind(&self.finish, 0), &[]);
            pass.dispatch_workgroups_indirect(&fill.list_args, 0);
        }
    }
}
