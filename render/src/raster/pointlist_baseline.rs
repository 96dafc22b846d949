//! The benchmark's fixed-function baseline: the resident points drawn by a render pipeline as
//! a `PointList` with a hardware depth test (what the papers call `GL_POINTS`).
//!
//! It reads the same storage buffers and the same frame uniforms as the compute rasterizer, so
//! a benchmark compares the two methods on identical data. One-pixel points only: WebGPU has
//! no point size. It is a yardstick, not a renderer: where two points share a pixel the
//! hardware depth test (non-linear depth, point order) decides, not the reference's rule.

use std::sync::Arc;
use std::time::Instant;

use image::RgbaImage;
use pointfarm_shaders::Shader;

use super::gpu_data::{FrameUniforms, QuantisedPosition};
use super::pipeline::shader_module;
use super::points::{GpuPointCloud, PointSegment};
use super::timing::GpuTimer;
use super::{Clock, FrameSettings, RenderError, Stage, StageTimings};
use crate::gpu::{read_buffer, GpuContext};

const COLOR_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba8Unorm;
const DEPTH_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Depth32Float;

/// An image drawn by the baseline, with its stage timings (upload, rasterize, readback).
#[derive(Debug, Clone)]
pub struct PointListFrame {
    pub image: RgbaImage,
    pub timings: StageTimings,
}

/// A `PointList` render pipeline and its per-size render targets.
pub struct PointListBaseline {
    gpu: Arc<GpuContext>,
    pipeline: wgpu::RenderPipeline,
    uniforms: wgpu::Buffer,
    timer: Option<GpuTimer>,
    targets: Option<RenderTargets>,
}

/// Color and depth attachments of one image size, and the buffer the color is copied to.
struct RenderTargets {
    width: u32,
    height: u32,
    color: wgpu::Texture,
    depth: wgpu::Texture,
    /// Rows padded to `COPY_BYTES_PER_ROW_ALIGNMENT`.
    readback: wgpu::Buffer,
    readback_staging: wgpu::Buffer,
    padded_row_bytes: u32,
}

impl RenderTargets {
    fn new(device: &wgpu::Device, width: u32, height: u32) -> Self {
        let size = wgpu::Extent3d {
            width,
            height,
            depth_or_array_layers: 1,
        };
        let texture = |label: &str, format, usage| {
            device.create_texture(&wgpu::TextureDescriptor {
                label: Some(label),
                size,
                mip_level_count: 1,
                sample_count: 1,
                dimension: wgpu::TextureDimension::D2,
                format,
                usage,
                view_formats: &[],
            })
        };
        let padded_row_bytes = (width * 4).next_multiple_of(wgpu::COPY_BYTES_PER_ROW_ALIGNMENT);
        Self {
            width,
            height,
            color: texture(
                "pointlist color",
                COLOR_FORMAT,
                wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::COPY_SRC,
            ),
            depth: texture(
                "pointlist depth",
                DEPTH_FORMAT,
                wgpu::TextureUsages::RENDER_ATTACHMENT,
            ),
            readback: device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("pointlist color rows"),
                size: padded_row_bytes as u64 * height as u64,
                usage: wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::COPY_SRC,
                mapped_at_creation: false,
            }),
            readback_staging: crate::gpu::staging_buffer(
                device,
                "pointlist color readback",
                padded_row_bytes as u64 * height as u64,
            ),
            padded_row_bytes,
        }
    }
}

impl PointListBaseline {
    pub fn new(gpu: Arc<GpuContext>) -> Self {
        let device = &gpu.device;
        let module = shader_module(device, Shader::PointListBaseline);
        let pipeline = device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
            label: Some("pointlist baseline"),
            layout: None,
            vertex: wgpu::VertexState {
                module: &module,
                entry_point: Some("vertex_main"),
                compilation_options: wgpu::PipelineCompilationOptions::default(),
                // The points come from a storage buffer, indexed by the vertex index.
                buffers: &[],
            },
            primitive: wgpu::PrimitiveState {
                topology: wgpu::PrimitiveTopology::PointList,
                ..Default::default()
            },
            depth_stencil: Some(wgpu::DepthStencilState {
                format: DEPTH_FORMAT,
                depth_write_enabled: Some(true),
                depth_compare: Some(wgpu::CompareFunction::Less),
                stencil: Default::default(),
                bias: Default::default(),
            }),
            multisample: Default::default(),
            fragment: Some(wgpu::FragmentState {
                module: &module,
                entry_point: Some("fragment_main"),
                compilation_options: Default::default(),
                targets: &[Some(COLOR_FORMAT.into())],
            }),
            multiview_mask: None,
            cache: None,
        });
        Self {
            pipeline,
            uniforms: device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("pointlist frame uniforms"),
                size: std::mem::size_of::<FrameUniforms>() as u64,
                usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            }),
            timer: gpu
                .capabilities
                .timestamps
                .then(|| GpuTimer::new(device, &gpu.queue)),
            targets: None,
            gpu,
        }
    }

    /// Times the pass with host clocks even where the adapter has timestamp queries.
    pub fn use_host_clocks(&mut self) {
        self.timer = None;
    }

    /// Checks what the baseline can draw: image size, 1-pixel points, a valid camera.
    pub fn validate(&self, settings: &FrameSettings) -> Result<(), RenderError> {
        if settings.point_size != 1 {
            return Err(RenderError::PointListPointSize(settings.point_size));
        }
        settings.validate_view(self.gpu.device.limits().max_texture_dimension_2d)
    }

    /// Draws one frame of `cloud`. Ignores `settings.atomics` and `settings.read_depth`.
    pub fn render(
        &mut self,
        cloud: &GpuPointCloud,
        settings: &FrameSettings,
    ) -> Result<PointListFrame, RenderError> {
        self.validate(settings)?;
        let mut timings = StageTimings::default();

        let started = Instant::now();
        let transform = settings
            .camera
            .transform(cloud.origin(), settings.width, settings.height);
        let uniforms = super::frame_uniforms(
            &transform,
            settings,
            super::resolve_pass::PixelRun { first: 0, count: 0 },
            super::pixel_rect::PixelRect::EMPTY,
            crate::camera::ImageWindow::whole(settings.width, settings.height),
        );
        self.gpu
            .queue
            .write_buffer(&self.uniforms, 0, bytemuck::bytes_of(&uniforms));
        let (width, height) = (settings.width, settings.height);
        if self.targets.as_ref().map(|t| (t.width, t.height)) != Some((width, height)) {
            self.targets = Some(RenderTargets::new(&self.gpu.device, width, height));
        }
        timings.push(
            Stage::Upload,
            started.elapsed().as_secs_f64() * 1e3,
            Clock::Host,
        );

        let Some(targets) = self.targets.as_ref() else {
            return Err(RenderError::Gpu("render targets missing".into()));
        };
        self.draw(cloud, settings.background, targets, &mut timings)?;

        let started = Instant::now();
        let image = self.read_color(targets)?;
        timings.push(
            Stage::Readback,
            started.elapsed().as_secs_f64() * 1e3,
            Clock::Host,
        );
        Ok(PointListFrame { image, timings })
    }

    /// Clears the targets and draws every segment in one render pass, timed as "rasterize"
    /// (clear included, as in the compute path) by GPU timestamps or the host clock.
    fn draw(
        &self,
        cloud: &GpuPointCloud,
        background: [u8; 4],
        targets: &RenderTargets,
        timings: &mut StageTimings,
    ) -> Result<(), RenderError> {
        let device = &self.gpu.device;
        let bind_groups: Vec<(wgpu::BindGroup, u32)> = cloud
            .segments
            .iter()
            .map(|segment| (self.bind_group(segment), segment_points(segment)))
            .collect();
        let color_view = targets.color.create_view(&Default::default());
        let depth_view = targets.depth.create_view(&Default::default());
        let [r, g, b, a] = background.map(|c| c as f64 / 255.0);

        let started = Instant::now();
        let mut encoder = device.create_command_encoder(&Default::default());
        {
            let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
                label: Some("pointlist baseline"),
                color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                    view: &color_view,
                    depth_slice: None,
                    resolve_target: None,
                    ops: wgpu::Operations {
                        load: wgpu::LoadOp::Clear(wgpu::Color { r, g, b, a }),
                        store: wgpu::StoreOp::Store,
                    },
                })],
                depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
                    view: &depth_view,
                    depth_ops: Some(wgpu::Operations {
                        load: wgpu::LoadOp::Clear(1.0),
                        store: wgpu::StoreOp::Discard,
                    }),
                    stencil_ops: None,
                }),
                timestamp_writes: self
                    .timer
                    .as_ref()
                    .map(|t| wgpu::RenderPassTimestampWrites {
                        query_set: &t.query_set,
                        beginning_of_pass_write_index: Some(0),
                        end_of_pass_write_index: Some(1),
                    }),
                occlusion_query_set: None,
                multiview_mask: None,
            });
            pass.set_pipeline(&self.pipeline);
            for (bind_group, points) in &bind_groups {
                pass.set_bind_group(0, bind_group, &[]);
                pass.draw(0..*points, 0..1);
            }
        }
        match &self.timer {
            Some(timer) => {
                encoder.resolve_query_set(&timer.query_set, 0..2, &timer.resolved, 0);
                self.gpu.queue.submit([encoder.finish()]);
                let raw = read_buffer(&self.gpu, &timer.resolved, &timer.staging, 2 * 8)?;
                let raw: Vec<u64> = bytemuck::pod_collect_to_vec(&raw);
                timings.push(Stage::Rasterize, timer.pass_ms(&raw, 0), Clock::Gpu);
            }
            None => {
                self.gpu.queue.submit([encoder.finish()]);
                device
                    .poll(wgpu::PollType::wait_indefinitely())
                    .map_err(|e| RenderError::Gpu(e.to_string()))?;
                timings.push(
                    Stage::Rasterize,
                    started.elapsed().as_secs_f64() * 1e3,
                    Clock::Host,
                );
            }
        }
        Ok(())
    }

    fn bind_group(&self, segment: &PointSegment) -> wgpu::BindGroup {
        self.gpu
            .device
            .create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("pointlist baseline"),
                layout: &self.pipeline.get_bind_group_layout(0),
                entries: &[
                    wgpu::BindGroupEntry {
                        binding: 0,
                        resource: self.uniforms.as_entire_binding(),
                    },
                    wgpu::BindGroupEntry {
                        binding: 1,
                        resource: segment.positions.as_entire_binding(),
                    },
                    wgpu::BindGroupEntry {
                        binding: 2,
                        resource: segment.batches.as_entire_binding(),
                    },
                    wgpu::BindGroupEntry {
                        binding: 5,
                        resource: segment.colors.as_entire_binding(),
                    },
                ],
            })
    }

    /// Copies the color attachment to the host, dropping the row padding.
    fn read_color(&self, targets: &RenderTargets) -> Result<RgbaImage, RenderError> {
        let mut encoder = self.gpu.device.create_command_encoder(&Default::default());
        encoder.copy_texture_to_buffer(
            targets.color.as_image_copy(),
            wgpu::TexelCopyBufferInfo {
                buffer: &targets.readback,
                layout: wgpu::TexelCopyBufferLayout {
                    offset: 0,
                    bytes_per_row: Some(targets.padded_row_bytes),
                    rows_per_image: None,
                },
            },
            targets.color.size(),
        );
        self.gpu.queue.submit([encoder.finish()]);
        let padded = read_buffer(
            &self.gpu,
            &targets.readback,
            &targets.readback_staging,
            targets.readback.size(),
        )?;
        let row_bytes = targets.width as usize * 4;
        let pixels: Vec<u8> = padded
            .chunks_exact(targets.padded_row_bytes as usize)
            .flat_map(|row| &row[..row_bytes])
            .copied()
            .collect();
        RgbaImage::from_raw(targets.width, targets.height, pixels)
            .ok_or_else(|| RenderError::Gpu("color readback has the wrong size".into()))
    }
}

/// Points of `segment`: its positions buffer holds exactly one quantised position per point.
fn segment_points(segment: &PointSegment) -> u32 {
    (segment.positions.size() / std::mem::size_of::<QuantisedPosition>() as u64) as u32
}

#[cfg(test)]
mod tests {
    use glam::DVec3;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    use super::*;
    use crate::camera::Camera;
    use crate::cloud::{pack_rgba8, PointCloud};
    use crate::raster::Renderer;
    use crate::testing::gpu;

    /// A random cube of points, sparse enough that most covered pixels hold one point.
    fn random_cube(points: usize, seed: u64) -> PointCloud {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let origin = DVec3::new(515_370.0, 4_918_340.0, 2_200.0);
        let positions: Vec<DVec3> = (0..points)
            .map(|_| origin + DVec3::new(rng.random(), rng.random(), rng.random()) * 20.0)
            .collect();
        let colors = (0..points)
            .map(|_| pack_rgba8(rng.random(), rng.random(), rng.random()))
            .collect();
        PointCloud::from_world_points(&positions, colors)
    }

    /// Fractions of the pixels covered by either method that are covered by both, and of
    /// those that have the same color.
    fn agreement(baseline: &RgbaImage, compute: &RgbaImage, background: [u8; 4]) -> (f64, f64) {
        let (mut either, mut both, mut equal) = (0usize, 0usize, 0usize);
        for (b, c) in baseline.pixels().zip(compute.pixels()) {
            let (b_covered, c_covered) = (b.0 != background, c.0 != background);
            either += usize::from(b_covered || c_covered);
            both += usize::from(b_covered && c_covered);
            equal += usize::from(b_covered && b == c);
        }
        (both as f64 / either as f64, equal as f64 / both as f64)
    }

    #[test]
    fn pointlist_baseline_roughly_agrees_with_the_compute_rasterizer() {
        let gpu = gpu();
        let cloud = random_cube(20_000, 7);
        let mut renderer = Renderer::new(gpu.clone());
        let mut baseline = PointListBaseline::new(gpu);
        let settings = FrameSettings::new(320, 240, Camera::auto(&cloud.bounds, 320.0 / 240.0));
        let resident = renderer.upload(&cloud).expect("upload");
        let compute = renderer
            .render(&resident, &settings)
            .expect("compute frame");
        let drawn = baseline
            .render(&resident, &settings)
            .expect("baseline frame");
        assert!(drawn.timings.get(Stage::Rasterize).is_some());

        let (covered_by_both, equal) = agreement(&drawn.image, &compute.image, settings.background);
        eprintln!(
            "pointlist vs compute: {:.2}% of covered pixels covered by both, {:.2}% of those equal",
            covered_by_both * 100.0,
            equal * 100.0
        );
        // Points on pixel borders may land in a neighbour under the hardware's sub-pixel
        // snapping, and near-equal depths may order differently in non-linear depth.
        assert!(
            covered_by_both >= 0.95,
            "coverage agreement {covered_by_both}"
        );
        assert!(equal >= 0.95, "color agreement {equal}");
    }

    #[test]
    fn pointlist_baseline_host_clock_path_draws_the_same_image() {
        let gpu = gpu();
        let cloud = random_cube(5_000, 8);
        let renderer = Renderer::new(gpu.clone());
        let mut baseline = PointListBaseline::new(gpu);
        // Odd width: the readback must drop the row padding.
        let settings = FrameSettings::new(101, 77, Camera::auto(&cloud.bounds, 101.0 / 77.0));
        let resident = renderer.upload(&cloud).expect("upload");
        let timed_on_gpu = baseline.render(&resident, &settings).expect("frame");
        baseline.use_host_clocks();
        let timed_on_host = baseline.render(&resident, &settings).expect("frame");
        assert_eq!(timed_on_gpu.image, timed_on_host.image);
        let rasterize = timed_on_host
            .timings
            .stages
            .iter()
            .find(|t| t.stage == Stage::Rasterize);
        assert_eq!(rasterize.map(|t| t.clock), Some(Clock::Host));
    }

    #[test]
    fn pointlist_baseline_refuses_point_sizes_above_one() {
        let gpu = gpu();
        let cloud = random_cube(100, 9);
        let baseline = PointListBaseline::new(gpu);
        let settings = FrameSettings {
            point_size: 3,
            ..FrameSettings::new(64, 64, Camera::auto(&cloud.bounds, 1.0))
        };
        assert!(matches!(
            baseline.validate(&settings),
            Err(RenderError::PointListPointSize(3))
        ));
    }
}
