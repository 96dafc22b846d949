//! A turntable of a level-of-detail store rendered cut by cut from a cold cache, as
//! `pointfarm render --turntable` renders one: a new [`CutRenderer`], each frame rendered, then
//! the next frame's nodes read ahead while the caller would encode this one.

use std::sync::Arc;
use std::time::Instant;

use pointfarm_render::cut::{CutOptions, CutRenderer, CutReport, LodDataset};
use pointfarm_render::filter::PointFilter;
use pointfarm_render::gpu::GpuContext;
use pointfarm_render::raster::{FrameSettings, Renderer, Shading};
use pointfarm_render::request::{
    CameraPath, Lens, PointSize, RenderOptions, RenderRequest, Turntable,
};
use serde::Serialize;

use crate::stats::median;
use crate::{memory, BenchError};

/// Frames of a turntable unless asked otherwise.
pub const TURNTABLE_FRAMES: usize = 12;
/// The memory budget of the turntable unless asked otherwise.
pub const TURNTABLE_MEMORY_BUDGET: u64 = 4 << 30;

/// What to render.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct TurntableOptions {
    pub width: u32,
    pub height: u32,
    pub frames: usize,
    pub memory_budget_bytes: u64,
    pub lod_error: f64,
}

impl TurntableOptions {
    /// `frames` frames at 1920x1080 with the turntable's default budget and pixel error.
    pub fn new(frames: usize) -> Self {
        Self {
            width: 1920,
            height: 1080,
            frames,
            memory_budget_bytes: TURNTABLE_MEMORY_BUDGET,
            lod_error: pointfarm_render::cut::DEFAULT_LOD_ERROR_PX,
        }
    }
}

/// A stage of a frame, in ms.
#[derive(Debug, Clone, Serialize)]
pub struct StageMs {
    pub stage: &'static str,
    pub ms: f64,
}

/// One frame of the turntable.
#[derive(Debug, Clone, Serialize)]
pub struct CutFrame {
    /// Wall time of `CutRenderer::render`: waiting for the read-ahead, selecting, loading,
    /// uploading, drawing and reading the image back.
    pub wall_ms: f64,
    /// The frame's stages ("select" and "load" first).
    pub stages: Vec<StageMs>,
    pub cut: CutReport,
}

/// A turntable's figures.
#[derive(Debug, Clone, Serialize)]
pub struct TurntableResult {
    pub options: TurntableOptions,
    pub points: u64,
    /// The caches' budgets on this adapter.
    pub host_budget_bytes: u64,
    pub gpu_budget_bytes: u64,
    /// The first frame's wall time, from a cold cache.
    pub first_ms: f64,
    /// The median wall time of the following frames (NaN with one frame).
    pub following_median_ms: f64,
    pub following_max_ms: f64,
    pub frames: Vec<CutFrame>,
    /// The process's resident memory before the first frame, and its peak during the frames
    /// (`VmHWM`, reset before them unless `peak_reset` is false).
    pub before_rss_bytes: u64,
    pub peak_rss_bytes: u64,
    pub peak_reset: bool,
    /// The turntable's wall time, frames and read-aheads.
    pub wall_s: f64,
}

impl TurntableResult {
    pub fn bytes_read(&self) -> u64 {
        self.frames
            .iter()
            .map(|f| f.cut.counts.bytes_read + f.cut.counts.read_ahead_bytes)
            .sum()
    }
}

/// The settings of frame `index` of an `frames`-frame turntable around `dataset`, with the
/// request's defaults otherwise (as `pointfarm render --turntable`) but one-pixel points and
/// no shading, as the recorded figures were measured.
pub fn turntable_settings(
    dataset: &LodDataset,
    width: u32,
    height: u32,
    frames: usize,
    index: usize,
) -> FrameSettings {
    let request = RenderRequest {
        width,
        height,
        camera_path: CameraPath::Turntable(Turntable::around_the_cloud(frames as u32)),
        lens: Lens::default(),
        render: RenderOptions {
            point_size: PointSize::Fixed(1),
            shading: Shading::None,
            ..RenderOptions::default()
        },
    };
    request.frame_settings(index as u32, &dataset.bounds(), None)
}

/// Renders the turntable of `options` of `dataset` from a cold cache.
pub fn render_turntable(
    gpu: &Arc<GpuContext>,
    dataset: &LodDataset,
    options: &TurntableOptions,
    progress: &mut dyn FnMut(&str),
) -> Result<TurntableResult, BenchError> {
    if options.frames == 0 {
        return Err(BenchError::NoFrames);
    }
    let mut renderer = Renderer::new(Arc::clone(gpu));
    let cut_options = CutOptions {
        lod_error: options.lod_error,
        memory_budget_bytes: options.memory_budget_bytes,
        gpu_budget_bytes: None,
    };
    let mut cut = CutRenderer::new(&renderer, dataset, cut_options)?;
    let budgets = cut.budgets();
    let settings =
        |i: usize| turntable_settings(dataset, options.width, options.height, options.frames, i);
    let _measuring = memory::measuring();
    let before_rss_bytes = memory::resident_bytes();
    let peak_reset = memory::reset_peak();
    let started = Instant::now();
    let mut frames = Vec::with_capacity(options.frames);
    for i in 0..options.frames {
        let frame_settings = settings(i);
        let begun = Instant::now();
        let (frame, report) = cut.render_rgb(&mut renderer, dataset, &frame_settings)?;
        let wall_ms = begun.elapsed().as_secs_f64() * 1e3;
        if i + 1 < options.frames {
            cut.read_ahead(dataset, &settings(i + 1), &PointFilter::default());
        }
        progress(&format!(
            "cut frame {i}: {wall_ms:.0} ms, {} nodes, {} points; read {} nodes ({:.1} MiB), \
             host hits {}, GPU hits {}; {}",
            report.counts.nodes,
            report.counts.points_rendered,
            report.counts.nodes_read,
            report.counts.bytes_read as f64 / (1u64 << 20) as f64,
            report.counts.host_hits,
            report.counts.gpu_hits,
            frame.timings
        ));
        frames.push(CutFrame {
            wall_ms,
            stages: frame
                .timings
                .stages
                .iter()
                .map(|s| StageMs {
                    stage: s.stage.name(),
                    ms: s.ms,
                })
                .collect(),
            cut: report,
        });
    }
    let wall_s = started.elapsed().as_secs_f64();
    let peak_rss_bytes = memory::peak_resident_bytes();
    let following: Vec<f64> = frames.iter().skip(1).map(|f| f.wall_ms).collect();
    Ok(TurntableResult {
        options: *options,
        points: dataset.point_count(),
        host_budget_bytes: budgets.host_bytes,
        gpu_budget_bytes: budgets.gpu_bytes,
        first_ms: frames[0].wall_ms,
        following_max_ms: following.iter().copied().fold(f64::NAN, f64::max),
        following_median_ms: median(following),
        frames,
        before_rss_bytes,
        peak_rss_bytes,
        peak_reset,
        wall_s,
    })
}
