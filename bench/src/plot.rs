//! The benchmark's PNG plot: frame time against points in view (the uniform series) and
//! against overdraw (the k-plane cuboid), one line per method, drawn with plotters' bitmap
//! backend and a TrueType font from the system (pure Rust; no system libraries).

use std::path::Path;

use plotters::prelude::*;

use crate::report::{in_uniform_series, BenchReport, WorkloadResult};
use crate::workloads::CUBOID_PLANES;
use crate::BenchError;

type Result<T> = std::result::Result<T, BenchError>;

/// One line of a panel: a method and its (x, frame ms) points.
type Line = (String, Vec<(f64, f64)>);

/// Writes the two panels side by side to `path` (PNG).
pub fn write(report: &BenchReport, path: &Path) -> Result<()> {
    register_font()?;
    let uniform = lines(report, in_uniform_series);
    let cuboid = lines(report, |w| {
        CUBOID_PLANES
            .iter()
            .any(|k| w.workload == format!("cuboid-k{k}"))
    });
    const SIZE: (u32, u32) = (1600, 640);
    // Drawn into memory and encoded with the `image` crate the workspace already uses, so
    // plotters needs no image encoder of its own.
    let mut pixels = vec![0u8; SIZE.0 as usize * SIZE.1 as usize * 3];
    {
        let root = BitMapBackend::with_buffer(&mut pixels, SIZE).into_drawing_area();
        root.fill(&WHITE).map_err(plot_error)?;
        let (left, right) = root.split_horizontally(800);
        let size = format!("{}x{}", report.rounds.width, report.rounds.height);
        panel(
            &left,
            &format!("Uniform cube, all in view, {size}"),
            "points in view (millions)",
            uniform
                .into_iter()
                .map(|(m, pts)| (m, pts.into_iter().map(|(x, y)| (x / 1e6, y)).collect()))
                .collect(),
        )?;
        panel(
            &right,
            &format!("Overdraw: k-plane cuboid, {size}"),
            "planes k (each covered pixel drawn k times)",
            cuboid,
        )?;
        root.present().map_err(plot_error)?;
    }
    let image = image::RgbImage::from_raw(SIZE.0, SIZE.1, pixels)
        .ok_or_else(|| BenchError::Plot("plot buffer has the wrong size".into()))?;
    image
        .save(path)
        .map_err(|e| BenchError::Plot(format!("writing {}: {e}", path.display())))
}

/// For the workloads that `select` picks: one line per method, x = points in view for the
/// uniform series and planes for the cuboid, y = median frame time.
fn lines(report: &BenchReport, select: impl Fn(&WorkloadResult) -> bool) -> Vec<Line> {
    let mut lines: Vec<Line> = Vec::new();
    let mut add = |method: &str, x: f64, ms: f64| match lines.iter_mut().find(|l| l.0 == method) {
        Some(line) => line.1.push((x, ms)),
        None => lines.push((method.to_string(), vec![(x, ms)])),
    };
    for w in report.workloads.iter().filter(|w| select(w)) {
        let x = match w.workload.strip_prefix("cuboid-k") {
            Some(k) => k.parse().unwrap_or(0.0),
            None => w.points_in_view as f64,
        };
        add(w.pointlist.method, x, w.pointlist.frame_ms);
        add(w.compute.method, x, w.compute.frame_ms);
        for mode in &w.modes {
            add(mode.result.method, x, mode.result.frame_ms);
        }
    }
    for line in &mut lines {
        line.1.sort_by(|a, b| a.0.total_cmp(&b.0));
    }
    lines
}

fn panel(
    area: &DrawingArea<BitMapBackend<'_>, plotters::coord::Shift>,
    title: &str,
    x_label: &str,
    lines: Vec<Line>,
) -> Result<()> {
    let points = lines.iter().flat_map(|l| &l.1);
    let x_max = points.clone().map(|p| p.0).fold(1.0, f64::max);
    let y_max = points.clone().map(|p| p.1).fold(1e-3, f64::max);
    let y_min = points
        .map(|p| p.1)
        .filter(|&y| y > 0.0)
        .fold(y_max, f64::min);
    // Frame times on a log scale: the methods lie 10 to 200 times apart, which a linear axis
    // flattens into the floor on a GPU, and equal ratios look equal.
    let mut chart = ChartBuilder::on(area)
        .caption(title, ("sans-serif", 24))
        .margin(16)
        .x_label_area_size(48)
        .y_label_area_size(72)
        // From a power of ten, where plotters' log axis starts its labels.
        .build_cartesian_2d(
            0.0..x_max * 1.05,
            (10f64.powf((y_min * 0.8).log10().floor())..y_max * 1.25).log_scale(),
        )
        .map_err(plot_error)?;
    chart
        .configure_mesh()
        .x_desc(x_label)
        .y_desc("frame time (ms, median, log scale)")
        .y_labels(24)
        .y_label_formatter(&|v| format!("{v}"))
        .label_style(("sans-serif", 16))
        .draw()
        .map_err(plot_error)?;
    for (i, (method, pts)) in lines.into_iter().enumerate() {
        let color = Palette99::pick(i).to_rgba();
        chart
            .draw_series(LineSeries::new(pts.clone(), color.stroke_width(2)))
            .map_err(plot_error)?
            .label(method)
            .legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 24, y)], color.stroke_width(3))
            });
        chart
            .draw_series(pts.into_iter().map(|p| Circle::new(p, 4, color.filled())))
            .map_err(plot_error)?;
    }
    chart
        .configure_series_labels()
        .label_font(("sans-serif", 18))
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .position(SeriesLabelPosition::UpperLeft)
        .draw()
        .map_err(plot_error)?;
    Ok(())
}

fn plot_error(e: impl std::fmt::Display) -> BenchError {
    BenchError::Plot(format!("drawing the plot: {e}"))
}

/// Fails now, not after a long run, when no font for the plot's labels can be found.
pub fn check_font() -> Result<()> {
    register_font()
}

/// Registers the system font the legends use as plotters' "sans-serif", once.
fn register_font() -> Result<()> {
    pointfarm_render::legend::register_font()
        .map_err(|e| BenchError::Plot(format!("writing the benchmark plot: {e}")))
}
