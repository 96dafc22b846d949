//! The compute-shader rasterizer (Schütz & Wimmer; Günther et al.).
//!
//! A frame is: write the frame uniforms; run the point pass over every segment of the resident
//! cloud (batch frustum culling, dequantisation, per-point projection, early depth test,
//! atomic minimum of depth and color); resolve the framebuffer into an RGBA8 image and a
//! depth image, emptying it for the next frame (only a new framebuffer is cleared first), over
//! the rows this frame's and the last frame's points can touch;
//! optionally remove the points seen through holes and fill the holes (visibility and
//! filling, Pintus et al.); optionally shade (Eye-Dome Lighting or Pintus's shape depiction);
//! read both images back. Each stage is timed.
//!
//! [`Renderer`] owns the pipelines and the per-size frame buffers; [`GpuPointCloud`] owns a
//! cloud's GPU buffers and outlives any number of frames.

mod basic_pass;
pub(crate) mod culling;
mod downsample;
mod draw_order;
mod edl_pass;
mod error;
pub mod exposure;
mod fill_pass;
mod frame;
pub(crate) mod gpu_data;
mod hq_pass;
pub(crate) mod morton;
mod occlusion;
mod phases;
mod pintus_pass;
mod pipeline;
mod pixel_rect;
mod point_pipelines;
mod point_workgroup;
#[cfg(feature = "pointlist-baseline")]
mod pointlist_baseline;
pub(crate) mod points;
mod resolve_pass;
mod screen_params;
mod settings;
mod targets;
mod tiles;
mod timing;
mod uniforms;
mod visibility_pass;

use std::sync::Arc;
use std::time::Instant;

use image::RgbaImage;

pub use basic_pass::AtomicsPath;
pub use downsample::downsample;
pub use error::RenderError;
pub use frame::Frame;
pub use occlusion::OcclusionSkipped;
pub use point_workgroup::WORKGROUP_SIZE_ENV;
#[cfg(feature = "pointlist-baseline")]
pub use pointlist_baseline::{PointListBaseline, PointListFrame};
pub use points::{GpuPointCloud, BATCH_POINTS, POINT_BYTES};
pub use settings::*;
pub use tiles::largest_drawn_side;
pub use timing::{Clock, Stage, StageTiming, StageTimings};

use crate::cloud::PointCloud;
use crate::gpu::{read_buffer, GpuContext};
use basic_pass::{BasicPass, PointFrame};
use culling::FrameBatches;
use edl_pass::EdlPass;
use fill_pass::FillPass;
use gpu_data::FrameUniforms;
use hq_pass::HqAccumulatePass;
use pintus_pass::PintusPass;
use point_pipelines::SplatShape;
use resolve_pass::{PixelRun, ResolveFrame, ResolvePass};
use screen_params::{ScreenFrame, ScreenUniforms};
use targets::FrameTargets;
use tiles::{FrameWindow, TileGrid, TiledCounts};
use timing::GpuTimer;
use uniforms::frame_uniforms;
use visibility_pass::VisibilityPass;

/// Renders frames of resident point clouds on one GPU.
pub struct Renderer {
    gpu: Arc<GpuContext>,
    basic: BasicPass,
    hq: HqAccumulatePass,
    edl: EdlPass,
    visibility: VisibilityPass,
    fill: FillPass,
    pintus: PintusPass,
    resolve: ResolvePass,
    /// This frame's batch tables: the batches that can be in view, per segment.
    batches: FrameBatches,
    uniforms: wgpu::Buffer,
    screen_uniforms: ScreenUniforms,
    timer: Option<GpuTimer>,
    targets: Option<FrameTargets>,
    max_segment_points: usize,
    /// The most bytes one per-pixel buffer may take: larger frames are drawn in tiles.
    tile_limit_bytes: u64,
    /// The last frame's counts when it was drawn in tiles, summed over them.
    tiled: Option<TiledCounts>,
}

impl Renderer {
    pub fn new(gpu: Arc<GpuContext>) -> Self {
        let workgroup_size = point_workgroup::point_workgroup_size(
            &gpu.adapter_info,
            gpu.device.limits().max_compute_invocations_per_workgroup,
        );
        Self::with_point_workgroup_size(gpu, workgroup_size)
    }

    /// A renderer whose point passes run `workgroup_size` invocations per workgroup, whatever
    /// the adapter (tests run the GPUs' size on lavapipe with this).
    pub(crate) fn with_point_workgroup_size(gpu: Arc<GpuContext>, workgroup_size: u32) -> Self {
        let device = &gpu.device;
        let caps = gpu.capabilities;
        // The largest per-point binding is the positions buffer.
        let max_segment_points = (caps.max_storage_binding_bytes.min(caps.max_buffer_bytes)
            / std::mem::size_of::<gpu_data::QuantisedPosition>() as u64)
            as usize;
        tracing::debug!(workgroup_size, "point pass workgroups");
        Self {
            basic: BasicPass::new(device, caps.int64_atomics, workgroup_size),
            hq: HqAccumulatePass::new(device, caps.int64_atomic_add, workgroup_size),
            edl: EdlPass::new(device),
            visibility: VisibilityPass::new(device),
            fill: FillPass::new(device),
            pintus: PintusPass::new(device),
            resolve: ResolvePass::new(device),
            batches: FrameBatches::new(gpu.adapter_info.device_type == wgpu::DeviceType::Cpu),
            screen_uniforms: ScreenUniforms::new(device),
            uniforms: device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("frame uniforms"),
                size: std::mem::size_of::<FrameUniforms>() as u64,
                usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            }),
            timer: caps.timestamps.then(|| GpuTimer::new(device, &gpu.queue)),
            targets: None,
            max_segment_points,
            tile_limit_bytes: caps.max_storage_binding_bytes.min(caps.max_buffer_bytes),
            tiled: None,
            gpu,
        }
    }

    /// The most points one segment (one storage binding) may hold on this adapter.
    pub(crate) fn max_segment_points(&self) -> usize {
        self.max_segment_points
    }

    pub fn gpu(&self) -> &GpuContext {
        &self.gpu
    }

    /// Lowers the number of points per segment below what the binding limit allows, so that
    /// tests can exercise many segments with small clouds. Affects later uploads only.
    pub fn set_max_segment_points(&mut self, points: usize) {
        self.max_segment_points = self.max_segment_points.min(points.max(1));
    }

    /// Lowers the bytes a per-pixel buffer may take below the adapter's limits, so that tests
    /// can draw small frames in tiles.
    #[cfg(test)]
    pub(crate) fn set_tile_limit_bytes(&mut self, bytes: u64) {
        self.tile_limit_bytes = self.tile_limit_bytes.min(bytes);
    }

    /// Times passes with host clocks even where the adapter has timestamp queries (for
    /// adapters whose timestamps are unreliable, and to test that path).
    pub fn use_host_clocks(&mut self) {
        self.timer = None;
    }

    /// Batches the last frame skipped whole because they were hidden behind points drawn
    /// before them (occlusion culling); zero before the first frame. A readback: for tests
    /// and the benchmark, outside any timed frame. Summed over the tiles of a tiled frame.
    pub fn occlusion_skipped(&self) -> Result<OcclusionSkipped, RenderError> {
        if let Some(tiled) = &self.tiled {
            return Ok(tiled.occlusion_skipped);
        }
        match &self.targets {
            Some(targets) => Ok(occlusion::read_skipped(&self.gpu, &targets.occlusion)?),
            None => Ok(OcclusionSkipped::default()),
        }
    }

    /// Entries of the last frame's batch tables: the batches that could be in view, a batch
    /// at the view's edge once per run of it listed; zero before the first frame. Summed over
    /// the tiles of a tiled frame (a batch in view of two tiles counts twice).
    pub fn listed_batches(&self) -> u32 {
        self.tiled
            .map_or_else(|| self.batches.total(), |tiled| tiled.listed_batches)
    }

    /// Points of the last frame's listed entries: what the point passes read (summed over the
    /// tiles of a tiled frame).
    pub fn listed_points(&self) -> u64 {
        self.tiled
            .map_or_else(|| self.batches.listed_points(), |tiled| tiled.listed_points)
    }

    /// How the frame of `settings` is split in tiles; `None` when it is drawn in one pass.
    #[cfg(test)]
    pub(crate) fn tile_grid(&self, settings: &FrameSettings) -> Option<TileGrid> {
        TileGrid::plan(settings, self.tile_limit_bytes).expect("tileable")
    }

    /// Uploads a cloud; its buffers stay resident for as many frames as needed.
    pub fn upload(&self, cloud: &PointCloud) -> Result<GpuPointCloud, RenderError> {
        GpuPointCloud::upload(&self.gpu, cloud, self.max_segment_points)
    }

    /// Uploads a cloud that arrives segment by segment, already in a spatially coherent order (a
    /// generator or a streaming reader), holding at most one segment on the host at a time.
    /// `next_segment(n)` returns up to `n` points (positions relative to `origin`, RGBA8
    /// colors) or `None` at the end.
    pub fn upload_segments(
        &self,
        origin: glam::DVec3,
        next_segment: &mut dyn FnMut(usize) -> Option<(Vec<glam::Vec3>, Vec<u32>)>,
    ) -> Result<GpuPointCloud, RenderError> {
        GpuPointCloud::upload_segments(&self.gpu, origin, self.max_segment_points, next_segment)
    }

    /// Checks settings before any GPU work, so bad requests fail with a clear reason.
    pub fn validate(&self, settings: &FrameSettings) -> Result<(), RenderError> {
        if !(1..=MAX_SUPERSAMPLE).contains(&settings.supersample) {
            return Err(RenderError::Supersample(settings.supersample));
        }
        if let Some(FillSettings { kernel }) = settings.fill {
            if !(MIN_FILL_KERNEL..=MAX_FILL_KERNEL).contains(&kernel) || kernel.is_multiple_of(2) {
                return Err(RenderError::FillKernel(kernel));
            }
        }
        if let Shading::Pintus { levels, exponent } = settings.shading {
            if !((1..=MAX_PINTUS_LEVELS).contains(&levels)
                && PINTUS_EXPONENT_RANGE.contains(&exponent))
            {
                return Err(RenderError::Pintus { levels, exponent });
            }
        }
        let unscaled = settings;
        let settings = &settings.scaled_for_supersampling();
        settings.validate_view(MAX_IMAGE_SIDE)?;
        if settings.point_size == 0 || settings.point_size > MAX_POINT_SIZE {
            return Err(RenderError::PointSize(settings.point_size));
        }
        if let Some(scale) = settings.adaptive_size {
            if !(scale.is_finite() && scale > 0.0) {
                return Err(RenderError::AdaptivePointSize(scale));
            }
        }
        if let Quality::High { depth_band } = settings.quality {
            if !(depth_band.is_finite() && DEPTH_BAND_RANGE.contains(&depth_band)) {
                return Err(RenderError::DepthBand(depth_band));
            }
        }
        if let Shading::Edl { strength, radius } = settings.shading {
            if !(EDL_STRENGTH_RANGE.contains(&strength) && EDL_RADIUS_RANGE.contains(&radius)) {
                return Err(RenderError::Edl { strength, radius });
            }
        }
        if let Exposure::Held(gain) = settings.exposure {
            if !(gain.is_finite() && exposure::GAIN_RANGE.contains(&gain)) {
                return Err(RenderError::ExposureGain(gain));
            }
        }
        // A frame too large for one pass is drawn in tiles, unless not even they fit.
        TileGrid::plan(unscaled, self.tile_limit_bytes)?;
        Ok(())
    }

    /// Renders one frame of `cloud`: in one pass, or in tiles where its buffers would exceed
    /// the adapter's binding limit (`tiles.rs`).
    pub fn render(
        &mut self,
        cloud: &GpuPointCloud,
        settings: &FrameSettings,
    ) -> Result<Frame, RenderError> {
        self.validate(settings)?;
        let Shading::Edl { .. } = settings.shading else {
            return self.render_shaded(cloud, settings);
        };
        // The exposure brightens the surface only, which the depth image tells apart.
        self.edl.clear_luma_counts(&self.gpu.queue);
        let with_depth = FrameSettings {
            read_depth: true,
            ..*settings
        };
        let mut frame = self.render_shaded(cloud, &with_depth)?;
        let started = Instant::now();
        let gain = match settings.exposure {
            Exposure::Measured => self.edl.read_luma_counts(&self.gpu)?.gain(),
            Exposure::Held(gain) => gain,
        };
        frame.gain = Some(gain);
        if let Some(depth) = &frame.depth {
            exposure::expose(&mut frame.image, depth, gain);
        }
        if !settings.read_depth {
            frame.depth = None;
        }
        let ms = started.elapsed().as_secs_f64() * 1e3;
        frame.timings.push(Stage::Expose, ms, Clock::Host);
        tracing::debug!(gain, exposure = ?settings.exposure, "frame exposed after eye-dome lighting");
        Ok(frame)
    }

    /// Renders and shades one frame, before any exposure.
    fn render_shaded(
        &mut self,
        cloud: &GpuPointCloud,
        settings: &FrameSettings,
    ) -> Result<Frame, RenderError> {
        self.tiled = None;
        if let Some(grid) = TileGrid::plan(settings, self.tile_limit_bytes)? {
            let (frame, counts) = tiles::render(self, cloud, settings, &grid)?;
            self.tiled = Some(counts);
            return Ok(frame);
        }
        if settings.supersample > 1 {
            let scaled = settings.scaled_for_supersampling();
            let whole = FrameWindow::whole(scaled.width, scaled.height);
            let mut frame = self.render_once(cloud, &scaled, whole)?;
            let started = Instant::now();
            frame = downsample(frame, settings.supersample);
            let ms = started.elapsed().as_secs_f64() * 1e3;
            frame.timings.push(Stage::Downsample, ms, Clock::Host);
            return Ok(frame);
        }
        let whole = FrameWindow::whole(settings.width, settings.height);
        self.render_once(cloud, settings, whole)
    }

    /// Renders at the settings' own size: `view`, all of the frame or one of its tiles.
    fn render_once(
        &mut self,
        cloud: &GpuPointCloud,
        settings: &FrameSettings,
        view: FrameWindow,
    ) -> Result<Frame, RenderError> {
        let _span = tracing::debug_span!("frame", width = settings.width, height = settings.height)
            .entered();
        let mut timings = StageTimings::default();

        let started = Instant::now();
        let transform = view.transform(&settings.camera, cloud.origin());
        self.batches.update(
            &self.gpu.device,
            &self.gpu.queue,
            cloud.segments.iter().map(|segment| segment.tables()),
            &transform,
            settings.point_size,
        );
        let cull_ms = started.elapsed().as_secs_f64() * 1e3;

        let started = Instant::now();
        let (width, height) = (settings.width, settings.height);
        if self.targets.as_ref().map(|t| (t.width, t.height)) != Some((width, height)) {
            self.targets = Some(FrameTargets::new(&self.gpu.device, width, height));
        }
        if let (Quality::High { .. }, Some(targets)) = (settings.quality, self.targets.as_mut()) {
            let packed_sums = self.hq.packs_sums(settings.atomics == AtomicsMode::Auto);
            targets.ensure_accumulator(&self.gpu.device, packed_sums);
        }
        if let Some(targets) = self.targets.as_mut() {
            if settings.fill.is_some() {
                targets.ensure_fill(&self.gpu.device);
            }
            if let Shading::Pintus { .. } = settings.shading {
                targets.ensure_shading(&self.gpu.device);
            }
        }
        if settings.fill.is_some() || matches!(settings.shading, Shading::Pintus { .. }) {
            self.screen_uniforms
                .write(&self.gpu.queue, settings, self.batches.footprint(), view);
        }
        let footprint = self.batches.footprint();
        let Some(resolve_area) = self
            .targets
            .as_mut()
            .map(|targets| targets.begin_resolve(footprint, settings))
        else {
            return Err(RenderError::Gpu("frame targets missing".into()));
        };
        let resolve_run = PixelRun::covering(
            resolve_area,
            settings.width,
            u64::from(self.gpu.device.limits().min_storage_buffer_offset_alignment),
        );
        let uniforms = frame_uniforms(&transform, settings, resolve_run, footprint, view.counted);
        self.gpu
            .queue
            .write_buffer(&self.uniforms, 0, bytemuck::bytes_of(&uniforms));
        let upload_ms = started.elapsed().as_secs_f64() * 1e3 + cloud.take_upload_ms();
        timings.push(Stage::Upload, upload_ms, Clock::Host);
        timings.push(Stage::Cull, cull_ms, Clock::Host);

        let path = self.basic.path(settings.atomics == AtomicsMode::Auto);
        self.run_passes(cloud, settings, path, resolve_run, &mut timings)?;
        if let Some(targets) = self.targets.as_mut() {
            targets.needs_clear = false;
            targets.record_resolved(footprint, settings);
        }

        let started = Instant::now();
        let Some(targets) = self.targets.as_ref() else {
            return Err(RenderError::Gpu("frame targets missing".into()));
        };
        let pixels = targets.pixels();
        let color = read_buffer(
            &self.gpu,
            &targets.color,
            &targets.color_staging,
            pixels * 4,
        )?;
        let depth = if settings.read_depth {
            let bytes = read_buffer(
                &self.gpu,
                &targets.depth,
                &targets.depth_staging,
                pixels * 4,
            )?;
            Some(bytemuck::pod_collect_to_vec::<u8, f32>(&bytes))
        } else {
            None
        };
        let image = RgbaImage::from_raw(settings.width, settings.height, color)
            .ok_or_else(|| RenderError::Gpu("color readback has the wrong size".into()))?;
        timings.push(
            Stage::Readback,
            started.elapsed().as_secs_f64() * 1e3,
            Clock::Host,
        );

        tracing::debug!(%timings, ?path, "frame rendered");
        Ok(Frame {
            image,
            depth,
            timings,
            atomics: path,
            gain: None,
        })
    }

    /// Records and runs the frame's compute passes. With timestamp queries everything goes in
    /// one submission and the GPU times each pass; without, each pass is submitted and waited
    /// for on its own and timed by the host clock.
    fn run_passes(
        &self,
        cloud: &GpuPointCloud,
        settings: &FrameSettings,
        path: AtomicsPath,
        resolve_run: PixelRun,
        timings: &mut StageTimings,
    ) -> Result<(), RenderError> {
        let device = &self.gpu.device;
        let Some(targets) = self.targets.as_ref() else {
            return Err(RenderError::Gpu("frame targets missing".into()));
        };
        let uniforms = &self.uniforms;
        let points = PointFrame {
            uniforms,
            shape: SplatShape::of(settings),
            cloud,
            batches: &self.batches,
            targets,
        };
        let resolve = ResolveFrame {
            uniforms,
            targets,
            run: resolve_run,
            write_depth: settings.needs_depth_image(),
        };
        let allow_64 = settings.atomics == AtomicsMode::Auto;
        type Record<'a> = Box<dyn Fn(&mut wgpu::ComputePass<'_>) + 'a>;
        let mut passes: Vec<(Stage, Record<'_>)> = match settings.quality {
            // The resolve empties the framebuffer for the next frame: only a new one is
            // cleared here.
            Quality::Basic => vec![
                (
                    Stage::Rasterize,
                    Box::new(move |pass| {
                        if targets.needs_clear {
                            self.resolve.record_clear(device, pass, targets);
                        }
                        self.basic.record(device, pass, path, points);
                    }),
                ),
                (
                    Stage::Resolve,
                    Box::new(move |pass| self.resolve.record_resolve(device, pass, resolve)),
                ),
            ],
            Quality::High { .. } => vec![
                (
                    Stage::Rasterize,
                    Box::new(move |pass| {
                        if targets.needs_clear {
                            self.resolve.record_clear(device, pass, targets);
                        }
                        self.basic.record_depth(device, pass, points);
                    }),
                ),
                (
                    Stage::Accumulate,
                    Box::new(move |pass| self.hq.record(device, pass, points, allow_64)),
                ),
                (
                    Stage::Resolve,
                    Box::new(move |pass| {
                        let packed_sums = self.hq.packs_sums(allow_64);
                        self.resolve
                            .record_resolve_average(device, pass, resolve, packed_sums)
                    }),
                ),
            ],
        };
        let screen = ScreenFrame {
            device,
            params: &self.screen_uniforms,
            targets,
        };
        let visibility_area = screen_params::visibility_area(settings, self.batches.footprint());
        if let Some(fill) = settings.fill {
            passes.push((
                Stage::Visibility,
                Box::new(move |pass| self.visibility.record(pass, screen, visibility_area)),
            ));
            passes.push((
                Stage::Fill,
                Box::new(move |pass| self.fill.record(pass, screen, fill.iterations())),
            ));
        }
        match settings.shading {
            Shading::None => {}
            Shading::Edl { .. } => passes.push((
                Stage::Shade,
                Box::new(|pass| self.edl.record(device, pass, uniforms, targets)),
            )),
            Shading::Pintus { levels, .. } => passes.push((
                Stage::Shade,
                Box::new(move |pass| self.pintus.record(pass, screen, levels)),
            )),
        }
        let run = |encoder: &mut wgpu::CommandEncoder,
                   index: usize,
                   (stage, record): &(Stage, Record<'_>)| {
            let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some(stage.name()),
                timestamp_writes: self.timer.as_ref().map(|t| t.writes(index as u32)),
            });
            record(&mut pass);
        };

        match &self.timer {
            Some(timer) => {
                let queries = 2 * passes.len() as u32;
                let mut encoder = device.create_command_encoder(&Default::default());
                for (index, plan) in passes.iter().enumerate() {
                    run(&mut encoder, index, plan);
                }
                encoder.resolve_query_set(&timer.query_set, 0..queries, &timer.resolved, 0);
                self.gpu.queue.submit([encoder.finish()]);
                let raw = read_buffer(
                    &self.gpu,
                    &timer.resolved,
                    &timer.staging,
                    queries as u64 * 8,
                )?;
                let raw: Vec<u64> = bytemuck::pod_collect_to_vec(&raw);
                for (index, (stage, _)) in passes.iter().enumerate() {
                    timings.push(*stage, timer.pass_ms(&raw, index as u32), Clock::Gpu);
                }
            }
            None => {
                for (index, plan) in passes.iter().enumerate() {
                    let started = Instant::now();
                    let mut encoder = device.create_command_encoder(&Default::default());
                    run(&mut encoder, index, plan);
                    self.gpu.queue.submit([encoder.finish()]);
                    device
                        .poll(wgpu::PollType::wait_indefinitely())
                        .map_err(|e| RenderError::Gpu(e.to_string()))?;
                    let ms = started.elapsed().as_secs_f64() * 1e3;
                    timings.push(plan.0, ms, Clock::Host);
                }
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests;
