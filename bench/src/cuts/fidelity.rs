//! Fidelity of a cut at a pixel error against the cut at 0 (every point in view, the resident
//! cloud's image): the share of the covered pixels, those not background in the full-detail
//! image, within [`FIDELITY_TOLERANCE`] per channel, per compute mode.

use std::sync::Arc;

use pointfarm_render::cut::{CutOptions, CutRenderer, CutReport, LodDataset};
use pointfarm_render::gpu::GpuContext;
use pointfarm_render::raster::{Frame, FrameSettings, Renderer};
use serde::Serialize;

use crate::{BenchError, ComputeMode};

/// Per channel, out of 255.
pub const FIDELITY_TOLERANCE: u8 = 8;

/// The modes compared: the basic mode and the modes that change the image (the 32-bit path
/// draws the basic mode's image by another route).
pub const FIDELITY_MODES: [Option<ComputeMode>; 4] = [
    None,
    Some(ComputeMode::HighQuality),
    Some(ComputeMode::FillEdl),
    Some(ComputeMode::FillPintus),
];

/// One workload in one mode.
#[derive(Debug, Clone, Serialize)]
pub struct ModeFidelity {
    pub mode: &'static str,
    /// Pixels not background in the full-detail image.
    pub covered_pixels: u64,
    /// Of those, the share within the tolerance in the cut at the pixel error.
    pub close_share: f64,
    /// The cut's frame at the pixel error drawn again from its warm caches, in milliseconds.
    pub cut_warm_ms: f64,
}

impl ModeFidelity {
    /// From the covered pixels and those of them within the tolerance ([`close_pixels`]).
    fn new(mode: &'static str, (covered, close): (u64, u64), cut_warm_ms: f64) -> Self {
        Self {
            mode,
            covered_pixels: covered,
            close_share: if covered == 0 {
                1.0
            } else {
                close as f64 / covered as f64
            },
            cut_warm_ms,
        }
    }
}

/// One workload's fidelity in every mode.
#[derive(Debug, Clone, Serialize)]
pub struct FidelityResult {
    pub workload: String,
    pub points: u64,
    pub lod_error: f64,
    /// Points of the cut at the pixel error and at 0 (the basic mode's frame).
    pub cut_points: u64,
    pub full_points: u64,
    /// Whether the GPU node cache bounded either cut.
    pub limited_by_budget: bool,
    pub modes: Vec<ModeFidelity>,
}

impl FidelityResult {
    pub fn worst(&self) -> f64 {
        self.modes
            .iter()
            .map(|m| m.close_share)
            .fold(f64::INFINITY, f64::min)
    }
}

pub fn mode_name(mode: Option<ComputeMode>) -> &'static str {
    mode.map_or("compute-basic", ComputeMode::name)
}

/// Renders `dataset` in every [`FIDELITY_MODES`] at `lod_error` and at 0, each with a cache of
/// its own, and compares.
pub fn measure_fidelity(
    gpu: &Arc<GpuContext>,
    workload: &str,
    dataset: &LodDataset,
    basic: &FrameSettings,
    lod_error: f64,
    memory_budget_bytes: u64,
) -> Result<FidelityResult, BenchError> {
    let mut renderer = Renderer::new(Arc::clone(gpu));
    let options = |lod_error| CutOptions {
        lod_error,
        memory_budget_bytes,
        gpu_budget_bytes: None,
    };
    let mut full = CutRenderer::new(&renderer, dataset, options(0.0))?;
    let mut cut = CutRenderer::new(&renderer, dataset, options(lod_error))?;
    let mut result = FidelityResult {
        workload: workload.to_string(),
        points: dataset.point_count(),
        lod_error,
        cut_points: 0,
        full_points: 0,
        limited_by_budget: false,
        modes: Vec::new(),
    };
    let mut high_quality = None;
    for mode in FIDELITY_MODES {
        let settings = mode.map_or(*basic, |m| m.settings(basic));
        let (expected, full_report) = full.render_rgb(&mut renderer, dataset, &settings)?;
        let (actual, cut_report, cut_warm_ms) =
            draw_then_warm(&mut cut, &mut renderer, dataset, &settings)?;
        if mode.is_none() {
            result.cut_points = cut_report.counts.points_rendered;
            result.full_points = full_report.counts.points_rendered;
        }
        result.limited_by_budget |=
            full_report.counts.limited_by_budget || cut_report.counts.limited_by_budget;
        let (covered, close) = close_pixels(&actual.image, &expected.image, settings.background);
        if mode == Some(ComputeMode::HighQuality) {
            high_quality = Some((settings, expected.image.clone()));
        }
        result.modes.push(ModeFidelity::new(
            mode_name(mode),
            (covered, close),
            cut_warm_ms,
        ));
    }
    // High quality again with every point counting once, as before points had weights.
    if let Some((settings, expected)) = high_quality {
        cut.set_weighted_high_quality(false);
        let (actual, _, cut_warm_ms) = draw_then_warm(&mut cut, &mut renderer, dataset, &settings)?;
        let (covered, close) = close_pixels(&actual.image, &expected, settings.background);
        result.modes.push(ModeFidelity::new(
            UNWEIGHTED_HIGH_QUALITY,
            (covered, close),
            cut_warm_ms,
        ));
    }
    Ok(result)
}

/// The high-quality cut drawn with every point counting once (`set_weighted_high_quality`).
pub const UNWEIGHTED_HIGH_QUALITY: &str = "compute-high-quality-unweighted";

/// [`draw`], then the same frame again from the warm caches, in milliseconds.
fn draw_then_warm(
    cut: &mut CutRenderer,
    renderer: &mut Renderer,
    dataset: &LodDataset,
    settings: &FrameSettings,
) -> Result<(Frame, CutReport, f64), BenchError> {
    let (frame, report) = cut.render_rgb(renderer, dataset, settings)?;
    let started = std::time::Instant::now();
    cut.render_rgb(renderer, dataset, settings)?;
    Ok((frame, report, started.elapsed().as_secs_f64() * 1e3))
}

/// The pixels not `background` in `expected`, and of those the ones within
/// [`FIDELITY_TOLERANCE`] of `expected` in every channel of `actual`.
pub fn close_pixels(
    actual: &image::RgbaImage,
    expected: &image::RgbaImage,
    background: [u8; 4],
) -> (u64, u64) {
    let (mut covered, mut close) = (0u64, 0u64);
    for (a, e) in actual.pixels().zip(expected.pixels()) {
        if e.0 == background {
            continue;
        }
        covered += 1;
        let within =
            a.0.iter()
                .zip(e.0)
                .take(3)
                .all(|(&x, y)| x.abs_diff(y) <= FIDELITY_TOLERANCE);
        close += u64::from(within);
    }
    (covered, close)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn background_pixels_of_the_full_image_are_not_counted() {
        let bg = [24, 24, 28, 255];
        let mut expected = image::RgbaImage::from_pixel(2, 2, image::Rgba(bg));
        let mut actual = expected.clone();
        expected.put_pixel(0, 0, image::Rgba([100, 100, 100, 255]));
        expected.put_pixel(1, 0, image::Rgba([100, 100, 100, 255]));
        actual.put_pixel(0, 0, image::Rgba([108, 92, 100, 255]));
        actual.put_pixel(1, 0, image::Rgba([109, 100, 100, 255]));
        // A point the cut drew where the full image has background is not counted.
        actual.put_pixel(0, 1, image::Rgba([1, 2, 3, 255]));
        assert_eq!(close_pixels(&actual, &expected, bg), (2, 1));
    }
}
