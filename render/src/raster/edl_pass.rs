//! Eye-Dome Lighting (`shaders/edl.wgsl`): depth-based shading of the resolved image, in place,
//! counting the surface's luma before and after for the exposure (`exposure.rs`).

use pointfarm_shaders::Shader;

use super::exposure::{LumaHistograms, LUMA_BINS};
use super::pipeline::{bind_buffers, compute_pipeline, dispatch_tiles, shader_module};
use super::targets::FrameTargets;
use crate::gpu::{read_buffer, staging_buffer, GpuContext, GpuError};

const LUMA_COUNTS_BYTES: u64 = (2 * LUMA_BINS * std::mem::size_of::<u32>()) as u64;

pub(crate) struct EdlPass {
    shade: wgpu::ComputePipeline,
    /// The luma histograms of the frame so far: a frame drawn in tiles adds every tile's.
    luma_counts: wgpu::Buffer,
    luma_staging: wgpu::Buffer,
}

impl EdlPass {
    pub fn new(device: &wgpu::Device) -> Self {
        let module = shader_module(device, Shader::Edl);
        let shade = compute_pipeline(device, &module, "shade", &[]);
        let luma_counts = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("edl luma counts"),
            size: LUMA_COUNTS_BYTES,
            usage: wgpu::BufferUsages::STORAGE
                | wgpu::BufferUsages::COPY_SRC
                | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let luma_staging = staging_buffer(device, "edl luma staging", LUMA_COUNTS_BYTES);
        Self {
            shade,
            luma_counts,
            luma_staging,
        }
    }

    /// Empties the histograms at the start of a frame.
    pub fn clear_luma_counts(&self, queue: &wgpu::Queue) {
        queue.write_buffer(&self.luma_counts, 0, &[0; LUMA_COUNTS_BYTES as usize]);
    }

    pub fn record(
        &self,
        device: &wgpu::Device,
        pass: &mut wgpu::ComputePass<'_>,
        uniforms: &wgpu::Buffer,
        targets: &FrameTargets,
    ) {
        let bind_group = bind_buffers(
            device,
            &self.shade,
            "edl",
            &[
                (0, uniforms),
                (1, &targets.color),
                (2, &targets.depth),
                (3, &self.luma_counts),
            ],
        );
        pass.set_pipeline(&self.shade);
        pass.set_bind_group(0, &bind_group, &[]);
        dispatch_tiles(pass, targets.width, targets.height);
    }

    /// The histograms counted since they were last emptied.
    pub fn read_luma_counts(&self, gpu: &GpuContext) -> Result<LumaHistograms, GpuError> {
        let bytes = read_buffer(
            gpu,
            &self.luma_counts,
            &self.luma_staging,
            LUMA_COUNTS_BYTES,
        )?;
        let words: Vec<u32> = bytemuck::pod_collect_to_vec(&bytes);
        LumaHistograms::from_words(&words)
            .ok_or_else(|| GpuError::Readback("the luma counts have the wrong size".into()))
    }
}
