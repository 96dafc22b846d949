//! Clearing the point framebuffer before a frame, and resolving it into the RGBA8 and depth
//! images afterwards (`shaders/resolve.wgsl`). Shared by both atomics paths, whose
//! framebuffers have the same layout.

use pointfarm_shaders::Shader;

use super::pipeline::{bind_buffers, bind_resources, compute_pipeline, shader_module};
use super::pixel_rect::PixelRect;
use super::targets::FrameTargets;

/// Must match `@workgroup_size` in resolve.wgsl.
const WORKGROUP_SIZE: u32 = 256;

/// The pixels a resolve visits: `count` consecutive pixels from `first` (row-major). Whole
/// rows, from the first row a rectangle touches to its last, the first pixel moved back to a
/// binding-offset boundary: the shader then runs its fastest form, a plain loop over
/// consecutive pixels (`shaders/resolve.wgsl`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct PixelRun {
    pub first: u64,
    pub count: u64,
}

impl PixelRun {
    /// The run over the rows of `rect` in an image `width` pixels wide, for bindings whose
    /// offsets must be multiples of `offset_alignment` bytes.
    pub fn covering(rect: PixelRect, width: u32, offset_alignment: u64) -> Self {
        if rect.is_empty() {
            return PixelRun { first: 0, count: 0 };
        }
        let width = u64::from(width);
        // The narrowest binding holds 4 bytes a pixel.
        let step = (offset_alignment / 4).max(1);
        let first = u64::from(rect.y0) * width / step * step;
        PixelRun {
            first,
            count: u64::from(rect.y1) * width - first,
        }
    }

    /// `bytes_per_pixel` bytes per pixel of `buffer`, for this run.
    fn binding(self, buffer: &wgpu::Buffer, bytes_per_pixel: u64) -> wgpu::BindingResource<'_> {
        wgpu::BindingResource::Buffer(wgpu::BufferBinding {
            buffer,
            offset: self.first * bytes_per_pixel,
            size: wgpu::BufferSize::new(self.count * bytes_per_pixel),
        })
    }
}

pub(crate) struct ResolvePass {
    clear: wgpu::ComputePipeline,
    resolve: ByDepthOutput,
    resolve_average: ByDepthOutput,
}

/// One resolve entry point built twice: with and without the store of the depth image
/// (the shader's `WRITE_DEPTH`), which only some frames need.
struct ByDepthOutput {
    with_depth: wgpu::ComputePipeline,
    colour_only: wgpu::ComputePipeline,
}

impl ByDepthOutput {
    fn new(device: &wgpu::Device, module: &wgpu::ShaderModule, entry_point: &str) -> Self {
        let build = |write_depth: bool| {
            let constants = [("WRITE_DEPTH", f64::from(u8::from(write_depth)))];
            compute_pipeline(device, module, entry_point, &constants)
        };
        Self {
            with_depth: build(true),
            colour_only: build(false),
        }
    }

    fn get(&self, write_depth: bool) -> &wgpu::ComputePipeline {
        if write_depth {
            &self.with_depth
        } else {
            &self.colour_only
        }
    }
}

impl ResolvePass {
    pub fn new(device: &wgpu::Device) -> Self {
        let module = shader_module(device, Shader::Resolve);
        Self {
            clear: compute_pipeline(device, &module, "clear", &[]),
            resolve: ByDepthOutput::new(device, &module, "resolve"),
            resolve_average: ByDepthOutput::new(device, &module, "resolve_average"),
        }
    }

    pub fn record_clear(
        &self,
        device: &wgpu::Device,
        pass: &mut wgpu::ComputePass<'_>,
        targets: &FrameTargets,
    ) {
        let bind_group = bind_buffers(device, &self.clear, "clear", &[(1, &targets.framebuffer)]);
        self.dispatch(pass, &self.clear, &bind_group, targets.pixels());
    }

    /// The nearest point's colour per pixel of `run`, and its depth where `write_depth`.
    pub fn record_resolve(
        &self,
        device: &wgpu::Device,
        pass: &mut wgpu::ComputePass<'_>,
        uniforms: &wgpu::Buffer,
        targets: &FrameTargets,
        run: PixelRun,
        write_depth: bool,
    ) {
        if run.count == 0 {
            return;
        }
        let pipeline = self.resolve.get(write_depth);
        let bind_group = bind_resources(
            device,
            pipeline,
            "resolve",
            vec![
                (0, uniforms.as_entire_binding()),
                (1, run.binding(&targets.framebuffer, 8)),
                (2, run.binding(&targets.colour, 4)),
                (3, run.binding(&targets.depth, 4)),
            ],
        );
        self.dispatch(pass, pipeline, &bind_group, run.count);
    }

    /// High-quality mode: the average of the accumulated colours per pixel of `run`, and the
    /// nearest depth where `write_depth`.
    pub fn record_resolve_average(
        &self,
        device: &wgpu::Device,
        pass: &mut wgpu::ComputePass<'_>,
        uniforms: &wgpu::Buffer,
        targets: &FrameTargets,
        run: PixelRun,
        write_depth: bool,
    ) {
        let Some(accumulator) = targets.accumulator.as_ref() else {
            return;
        };
        if run.count == 0 {
            return;
        }
        let pipeline = self.resolve_average.get(write_depth);
        let bind_group = bind_resources(
            device,
            pipeline,
            "resolve average",
            vec![
                (0, uniforms.as_entire_binding()),
                (1, run.binding(&targets.framebuffer, 8)),
                (2, run.binding(&targets.colour, 4)),
                (3, run.binding(&targets.depth, 4)),
                (4, run.binding(accumulator, 16)),
            ],
        );
        self.dispatch(pass, pipeline, &bind_group, run.count);
    }

    fn dispatch(
        &self,
        pass: &mut wgpu::ComputePass<'_>,
        pipeline: &wgpu::ComputePipeline,
        bind_group: &wgpu::BindGroup,
        pixels: u64,
    ) {
        pass.set_pipeline(pipeline);
        pass.set_bind_group(0, bind_group, &[]);
        let groups = pixels.div_ceil(WORKGROUP_SIZE as u64) as u32;
        let (x, y) = super::dispatch_grid(groups);
        pass.dispatch_workgroups(x, y, 1);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_run_covers_the_rows_of_its_rectangle_from_an_aligned_first_pixel() {
        let rect = PixelRect {
            x0: 30,
            y0: 3,
            x1: 40,
            y1: 5,
        };
        // 100 pixels a row; 256-byte offsets are 64 pixels of colour.
        let run = PixelRun::covering(rect, 100, 256);
        assert_eq!(
            run,
            PixelRun {
                first: 256,
                count: 244
            }
        );
        assert_eq!(run.first % 64, 0);
        assert!(run.first <= 3 * 100 + 30 && run.first + run.count >= 4 * 100 + 40);
        assert_eq!(
            PixelRun::covering(PixelRect::full(100, 50), 100, 256),
            PixelRun {
                first: 0,
                count: 5000
            }
        );
        assert_eq!(PixelRun::covering(PixelRect::EMPTY, 100, 256).count, 0);
    }
}
