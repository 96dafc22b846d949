//! What every compute pass builds the same way: its shader module, its pipelines (layouts
//! derived by wgpu from the shader), bind groups for group 0 and its workgroup grid.

use pointfarm_shaders::layout::SCREEN_TILE;
use pointfarm_shaders::Shader;

/// The compiled module of one of our shaders.
pub(crate) fn shader_module(device: &wgpu::Device, shader: Shader) -> wgpu::ShaderModule {
    device.create_shader_module(wgpu::ShaderModuleDescriptor {
        label: Some(shader.label()),
        source: wgpu::ShaderSource::Wgsl(shader.source().into()),
    })
}

/// A compute pipeline for `entry_point` of `module`, with its layout derived from the shader
/// and `constants` overriding the shader's pipeline-overridable constants.
pub(crate) fn compute_pipeline(
    device: &wgpu::Device,
    module: &wgpu::ShaderModule,
    entry_point: &str,
    constants: &[(&str, f64)],
) -> wgpu::ComputePipeline {
    device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
        label: Some(entry_point),
        layout: None,
        module,
        entry_point: Some(entry_point),
        compilation_options: wgpu::PipelineCompilationOptions {
            constants,
            ..Default::default()
        },
        cache: None,
    })
}

/// The pipelines of `entry_points` of `shader`, in that order, without overridden constants
/// (the screen-space passes).
pub(crate) fn entry_pipelines<const N: usize>(
    device: &wgpu::Device,
    shader: Shader,
    entry_points: [&str; N],
) -> [wgpu::ComputePipeline; N] {
    let module = shader_module(device, shader);
    entry_points.map(|entry_point| compute_pipeline(device, &module, entry_point, &[]))
}

/// Splits a workgroup count over two dimensions: one dimension holds at most 65535.
pub(crate) fn dispatch_grid(groups: u32) -> (u32, u32) {
    const MAX: u32 = 65535;
    if groups <= MAX {
        (groups, 1)
    } else {
        (MAX, groups.div_ceil(MAX))
    }
}

/// A bind group for group 0 of `pipeline`, with each buffer bound whole at its binding index.
pub(crate) fn bind_buffers(
    device: &wgpu::Device,
    pipeline: &wgpu::ComputePipeline,
    label: &str,
    buffers: &[(u32, &wgpu::Buffer)],
) -> wgpu::BindGroup {
    let entries: Vec<wgpu::BindGroupEntry<'_>> = buffers
        .iter()
        .map(|&(binding, buffer)| wgpu::BindGroupEntry {
            binding,
            resource: buffer.as_entire_binding(),
        })
        .collect();
    device.create_bind_group(&wgpu::BindGroupDescriptor {
        label: Some(label),
        layout: &pipeline.get_bind_group_layout(0),
        entries: &entries,
    })
}

/// A bind group for group 0 of `pipeline` from arbitrary resources (a buffer slot, say).
pub(crate) fn bind_resources(
    device: &wgpu::Device,
    pipeline: &wgpu::ComputePipeline,
    label: &str,
    resources: Vec<(u32, wgpu::BindingResource<'_>)>,
) -> wgpu::BindGroup {
    let entries: Vec<wgpu::BindGroupEntry<'_>> = resources
        .into_iter()
        .map(|(binding, resource)| wgpu::BindGroupEntry { binding, resource })
        .collect();
    device.create_bind_group(&wgpu::BindGroupDescriptor {
        label: Some(label),
        layout: &pipeline.get_bind_group_layout(0),
        entries: &entries,
    })
}

/// Dispatches one workgroup per [`SCREEN_TILE`] x [`SCREEN_TILE`] tile of the image (the
/// screen-space passes).
pub(crate) fn dispatch_tiles(pass: &mut wgpu::ComputePass<'_>, width: u32, height: u32) {
    pass.dispatch_workgroups(width.div_ceil(SCREEN_TILE), height.div_ceil(SCREEN_TILE), 1);
}
