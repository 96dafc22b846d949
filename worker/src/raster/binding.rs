//! Bind groups of the compute passes: every pass binds whole buffers to group 0 of a pipeline
//! whose layout wgpu derived from the shader.

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

/// Dispatches one 16 x 16 workgroup per tile of the image (the screen-space passes).
pub(crate) fn dispatch_tiles(pass: &mut wgpu::ComputePass<'_>, width: u32, height: u32) {
    const TILE: u32 = 16;
    pass.dispatch_workgroups(width.div_ceil(TILE), height.div_ceil(TILE), 1);
}
