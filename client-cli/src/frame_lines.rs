//! What a local render says of its frames: the lines before the first (bounds, camera,
//! point size), a line per frame (or its JSON object with `--json`) above the progress bar,
//! and the median of each stage over a sequence.

use std::path::Path;

use glam::DVec3;
use indicatif::ProgressBar;
use pointfarm_render::camera::{Camera, Projection};
use pointfarm_render::cloud::WorldBounds;
use pointfarm_render::raster::{FrameSettings, Stage, StageTimings};
use pointfarm_render::remote::FetchCounts;
use pointfarm_render::source::SourceFrame;

use crate::output::Reporter;
use crate::render_json::FrameJson;

/// A frame rendered, as its line reports it.
pub struct ReportedFrame<'a> {
    pub index: u32,
    pub path: &'a Path,
    pub settings: &'a FrameSettings,
    pub rendered: &'a SourceFrame,
    /// What reading by URL has fetched so far, where the frames are read by URL.
    pub fetched: Option<FetchCounts>,
}

/// A frame's line (or its JSON object with --json), above the progress bar if there is one.
pub fn report_frame(
    reporter: Reporter,
    frame: &ReportedFrame<'_>,
    bounds: &WorldBounds,
    progress: &ProgressBar,
) {
    let ReportedFrame {
        index,
        path,
        settings,
        rendered,
        fetched,
    } = *frame;
    let line = if reporter.is_json() {
        let json = FrameJson::new(index, path, settings, bounds, rendered);
        let mut value = serde_json::to_value(json).unwrap_or_default();
        if let (Some(counts), Some(object)) = (fetched, value.as_object_mut()) {
            // So far, over every frame: opening the file's reads included.
            object.insert(
                "fetched".into(),
                serde_json::json!({ "requests": counts.requests, "bytes": counts.bytes }),
            );
        }
        value.to_string()
    } else {
        let mut line = format!("{}  {}", path.display(), rendered.frame.timings);
        if rendered.preview.is_some() {
            line.push_str(&format!(
                "  | preview of {} of {} points ({:.3}%)",
                rendered.points_rendered,
                rendered.points_total,
                rendered.points_rendered as f64 * 100.0 / rendered.points_total.max(1) as f64
            ));
        }
        if let Some(cut) = rendered.cut.as_ref().map(|c| &c.counts) {
            line.push_str(&format!(
                "  | cut {} nodes, {} points; read {} nodes ({:.1} MiB), host hits {}, GPU hits {}",
                cut.nodes,
                cut.points_rendered,
                cut.nodes_read,
                cut.bytes_read as f64 / f64::from(1 << 20),
                cut.host_hits,
                cut.gpu_hits
            ));
        }
        line
    };
    if progress.is_hidden() {
        // Not a terminal, or a still: plain lines for logs and scripts.
        outln!("{line}");
    } else {
        progress.println(line);
    }
}

/// The lines said before the first frame: where the points lie, the first frame's camera (as
/// the flags that give it) and its point size.
pub fn framing_lines(
    bounds: &WorldBounds,
    first: &FrameSettings,
    spacing: Option<f64>,
) -> [String; 3] {
    [
        format!("bounds: {}", bounds_text(bounds)),
        format!("camera: {}", camera_flags(&first.camera)),
        point_size_text(first, spacing),
    ]
}

/// The first frame's point size, and for an adaptive one the spacing it came from.
fn point_size_text(settings: &FrameSettings, spacing: Option<f64>) -> String {
    let side = settings.point_size;
    let unit = if side == 1 { "pixel" } else { "pixels" };
    match (settings.adaptive_size, spacing) {
        (Some(_), Some(spacing)) if side > 1 => {
            format!("point size: 1 to {side} {unit} by depth (points about {spacing:.3} apart)")
        }
        _ => format!("point size: {side} {unit}"),
    }
}

/// The bounds in the file's coordinates, to 3 decimals.
fn bounds_text(bounds: &WorldBounds) -> String {
    let axis = |name: &str, min: f64, max: f64| format!("{name} {min:.3} .. {max:.3}");
    [
        axis("x", bounds.min.x, bounds.max.x),
        axis("y", bounds.min.y, bounds.max.y),
        axis("z", bounds.min.z, bounds.max.z),
    ]
    .join(", ")
}

/// The camera as the flags that give it, to adjust from (`--flag=value`, as a value may
/// start with a minus sign).
fn camera_flags(camera: &Camera) -> String {
    // `+ 0.0` turns -0 into 0, which reads better.
    let vector = |v: DVec3| format!("{:.3},{:.3},{:.3}", v.x + 0.0, v.y + 0.0, v.z + 0.0);
    let lens = match camera.projection {
        Projection::Perspective { fov_y_deg } => format!("--fov={fov_y_deg}"),
        Projection::Orthographic { height } => format!("--ortho --ortho-height={height:.3}"),
    };
    format!(
        "--camera-pos={} --camera-target={} --camera-up={} {lens} --near={:.3} --far={:.3}",
        vector(camera.position),
        vector(camera.target),
        vector(camera.up),
        camera.near,
        camera.far
    )
}

pub fn print_summary(dir: &Path, frames: &[StageTimings]) {
    outln!(
        "{} frames in {}; median per stage:",
        frames.len(),
        dir.display()
    );
    for (name, ms) in summary_rows(frames) {
        outln!("  {name:<10} {ms:>9.2} ms");
    }
}

/// The median milliseconds of every stage the frames report, in the order they first ran,
/// then of the frames' totals.
fn summary_rows(frames: &[StageTimings]) -> Vec<(&'static str, f64)> {
    let mut stages: Vec<Stage> = Vec::new();
    for timing in frames.iter().flat_map(|t| &t.stages) {
        if !stages.contains(&timing.stage) {
            stages.push(timing.stage);
        }
    }
    let mut rows: Vec<(&'static str, f64)> = stages
        .into_iter()
        .map(|stage| {
            let ms = frames.iter().filter_map(|t| t.get(stage)).collect();
            (stage.name(), median(ms))
        })
        .collect();
    if !frames.is_empty() {
        rows.push((
            "total",
            median(frames.iter().map(StageTimings::total_ms).collect()),
        ));
    }
    rows
}

fn median(mut ms: Vec<f64>) -> f64 {
    ms.sort_by(f64::total_cmp);
    ms.get(ms.len() / 2).copied().unwrap_or(0.0)
}

#[cfg(test)]
mod tests {
    use super::*;
    use pointfarm_render::raster::Clock;

    #[test]
    fn the_summary_lists_every_stage_the_frames_report_and_a_total() {
        let frame = |fill: f64| {
            let mut timings = StageTimings::default();
            timings.push(Stage::Rasterize, 2.0, Clock::Gpu);
            timings.push(Stage::Accumulate, 1.0, Clock::Gpu);
            timings.push(Stage::Visibility, 0.5, Clock::Gpu);
            timings.push(Stage::Fill, fill, Clock::Gpu);
            timings.push(Stage::Encode, 3.0, Clock::Host);
            timings
        };
        let rows = summary_rows(&[frame(1.0), frame(2.0), frame(4.0)]);
        let names: Vec<&str> = rows.iter().map(|(name, _)| *name).collect();
        assert_eq!(
            names,
            [
                "rasterize",
                "accumulate",
                "visibility",
                "fill",
                "encode",
                "total"
            ]
        );
        assert_eq!(rows[3].1, 2.0);
        assert_eq!(rows[5].1, 8.5);
        assert!(summary_rows(&[]).is_empty());
    }
}
