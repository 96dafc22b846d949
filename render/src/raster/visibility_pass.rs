//! Screen-space visibility (Pintus et al., section 4; `shaders/visibility.wgsl`): lists the
//! points seen through holes of a nearer surface, and the background pixels enclosed by
//! points, as mutable holes for the filling, and prepares the filling's indirect dispatch
//! over that list; everything else is fixed.

use pointfarm_shaders::Shader;
use wgpu::ComputePass;

use super::pipeline::{dispatch_tiles, entry_pipelines};
use super::pixel_rect::PixelRect;
use super::screen_params::ScreenFrame;

pub(crate) struct VisibilityPass {
    reset_list: wgpu::ComputePipeline,
    classify: wgpu::ComputePipeline,
    prepare_fill: wgpu::ComputePipeline,
}

impl VisibilityPass {
    pub fn new(device: &wgpu::Device) -> Self {
        let [reset_list, classify, prepare_fill] = entry_pipelines(
            device,
            Shader::Visibility,
            ["reset_list", "classify", "prepare_fill"],
        );
        Self {
            reset_list,
            classify,
            prepare_fill,
        }
    }

    /// Reads the resolved images; writes the visible pixels of `area` (which must be
    /// `visibility_area` of the screen parameters) into the fill buffers.
    pub fn record(&self, pass: &mut ComputePass<'_>, frame: ScreenFrame<'_>, area: PixelRect) {
        let targets = frame.targets;
        let Some(fill) = targets.fill.as_ref() else {
            return;
        };
        let args = || (6, fill.list_args.as_entire_binding());
        let list_only =
            |pipeline: &wgpu::ComputePipeline| frame.bind(pipeline, "fill list", vec![args()]);
        pass.set_pipeline(&self.reset_list);
        pass.set_bind_group(0, &list_only(&self.reset_list), &[]);
        pass.dispatch_workgroups(1, 1, 1);
        let resources = vec![
            (0, frame.params.fill()),
            (1, targets.depth.as_entire_binding()),
            (2, targets.color.as_entire_binding()),
            (3, fill.depth.as_entire_binding()),
            (4, fill.color.as_entire_binding()),
            (5, fill.mutable.as_entire_binding()),
            args(),
        ];
        pass.set_pipeline(&self.classify);
        pass.set_bind_group(0, &frame.bind(&self.classify, "visibility", resources), &[]);
        // Outside `area` (the footprint grown by the kernel's radius) every pixel is fixed
        // background: its fill-buffer value is never read.
        dispatch_tiles(pass, area.width(), area.height());
        pass.set_pipeline(&self.prepare_fill);
        pass.set_bind_group(0, &list_only(&self.prepare_fill), &[]);
        pass.dispatch_workgroups(1, 1, 1);
    }
}
