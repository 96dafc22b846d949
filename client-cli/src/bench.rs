//! `pointfarm bench`: the PointList baseline and the compute rasterizer's modes on the same
//! workloads, in one run on one adapter; prints tables and writes JSON, markdown and a plot.

use std::fmt::Write as _;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

use anyhow::{Context, Result};
use clap::Args;
use pointfarm_render::bench::{
    self, BenchOptions, BenchReport, ComputeMode, MethodResult, HEADLINE_WORKLOAD,
};
use pointfarm_render::gpu::{AdapterChoice, GpuContext};
use serde::Serialize;

use crate::parse;

#[derive(Args)]
pub struct BenchArgs {
    /// A run of a few minutes on a 2-core software adapter: fewer frames, smaller cuboid planes.
    #[arg(long)]
    quick: bool,
    /// Write the figures as JSON to FILE.
    #[arg(long, value_name = "FILE")]
    json: Option<PathBuf>,
    /// Write the tables as markdown to FILE.
    #[arg(long, value_name = "FILE")]
    markdown: Option<PathBuf>,
    /// Write a PNG plot of frame time against points in view and against overdraw to FILE.
    #[arg(long, value_name = "FILE")]
    plot: Option<PathBuf>,
    /// Only these workloads (comma-separated), e.g. `uniform-10m,cuboid-k64`; a name also
    /// selects its other views (`uniform-10m` selects `uniform-10m-corner` and `uniform-10m-partial`).
    #[arg(long, value_delimiter = ',', value_name = "NAMES")]
    only: Vec<String>,
    /// Also render a cube of POINTS points (100 million when no count is given), generated and
    /// uploaded chunk by chunk, and report the host's memory peak during its ingest (100M
    /// points need about 4 GiB on a software adapter). Accepts `1000000000`, `1_000_000_000`.
    #[arg(long, value_name = "POINTS", value_parser = parse_point_count)]
    huge: Option<Option<usize>>,
    /// Points of the cube written as LAZ for the ingest figures (decoding on all cores and on
    /// one, and loading from the dataset cache), besides the real scans: 10 million by
    /// default, 2 million with `--quick`. Select only those figures with `--only ingest`.
    #[arg(long, value_name = "POINTS", value_parser = parse_point_count)]
    ingest_points: Option<usize>,
    /// Measure the basic mode only (not high quality, the 32-bit atomics path, nor fill with
    /// EDL or Pintus shading).
    #[arg(long, conflicts_with = "modes")]
    basic_only: bool,
    /// The compute modes measured besides the basic mode (comma-separated); all by default.
    #[arg(long, value_delimiter = ',', value_name = "MODES")]
    modes: Vec<BenchMode>,
    /// Image size in pixels.
    #[arg(long, default_value = "1920x1080", value_parser = parse::size)]
    size: (u32, u32),
    /// Directory of the real scans (lone-star.laz, autzen_trim.laz); missing ones are skipped.
    #[arg(long, default_value = "../shared/data")]
    data: PathBuf,
    /// Time every stage with host clocks, even where the adapter has GPU timestamps (always so
    /// on a software adapter, whose timestamps under-report compute passes).
    #[arg(long)]
    host_clocks: bool,
    /// Adapter: auto (hardware GPU if present, else lavapipe), hardware or software.
    #[arg(long, env = "POINTFARM_ADAPTER", default_value = "auto")]
    adapter: AdapterChoice,
}

/// A compute mode besides the basic one, as `--modes` names it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum BenchMode {
    /// High quality (Schütz & Wimmer's averaging).
    Hq,
    /// The basic mode on the 32-bit atomics path.
    #[value(name = "basic-32")]
    Basic32,
    /// Fill (Pintus et al.) and Eye-Dome Lighting.
    FillEdl,
    /// Fill and Pintus et al.'s shading.
    FillPintus,
}

impl From<BenchMode> for ComputeMode {
    fn from(mode: BenchMode) -> Self {
        match mode {
            BenchMode::Hq => ComputeMode::HighQuality,
            BenchMode::Basic32 => ComputeMode::BasicAtomic32,
            BenchMode::FillEdl => ComputeMode::FillEdl,
            BenchMode::FillPintus => ComputeMode::FillPintus,
        }
    }
}

/// A point count, with optional `_` separators; at least one point.
fn parse_point_count(text: &str) -> Result<usize, String> {
    match text.replace('_', "").parse::<usize>() {
        Ok(0) => Err("the huge cloud needs at least one point".into()),
        Ok(n) => Ok(n),
        Err(e) => Err(format!("'{text}' is not a point count: {e}")),
    }
}

/// The JSON file: the run's context and the report.
#[derive(Serialize)]
struct BenchFile<'a> {
    command: String,
    quick: bool,
    /// Seconds since the Unix epoch when the run ended.
    finished_unix_s: u64,
    wall_s: f64,
    machine: Machine,
    #[serde(flatten)]
    report: &'a BenchReport,
}

#[derive(Serialize)]
struct Machine {
    cores: usize,
    cpu: Option<String>,
    os: &'static str,
    arch: &'static str,
}

impl Machine {
    fn this() -> Self {
        let cpu = std::fs::read_to_string("/proc/cpuinfo")
            .ok()
            .and_then(|info| {
                info.lines()
                    .find(|l| l.starts_with("model name"))
                    .and_then(|l| l.split_once(':'))
                    .map(|(_, name)| name.trim().to_string())
            });
        Self {
            cores: std::thread::available_parallelism().map_or(1, |n| n.get()),
            cpu,
            os: std::env::consts::OS,
            arch: std::env::consts::ARCH,
        }
    }
}

pub fn run(args: BenchArgs) -> Result<()> {
    let started = Instant::now();
    let (width, height) = args.size;
    let defaults = if args.quick {
        BenchOptions::quick(width, height, args.data.clone())
    } else {
        BenchOptions::full(width, height, args.data.clone())
    };
    let options = BenchOptions {
        ingest_points: args.ingest_points.or(defaults.ingest_points),
        host_clocks: args.host_clocks,
        modes: if args.basic_only {
            Vec::new()
        } else if args.modes.is_empty() {
            ComputeMode::ALL.to_vec()
        } else {
            args.modes.iter().map(|&mode| mode.into()).collect()
        },
        only: args.only.clone(),
        huge: args.huge.map(|points| points.unwrap_or(bench::HUGE_POINTS)),
        ..defaults.clone()
    };
    if args.plot.is_some() {
        crate::bench_plot::check_font()?;
    }
    let gpu = Arc::new(GpuContext::new(args.adapter)?);
    println!("adapter: {}", gpu.describe());
    let settle = match bench::settle_after_baseline(gpu.adapter_info.device_type) {
        Some(settle) => format!(
            "; the first compute method after PointList for {} ms",
            settle.as_millis()
        ),
        None => String::new(),
    };
    println!(
        "{width}x{height}, {} warm-up + {} measured rounds per workload; in a round each method \
         renders unmeasured frames for {} ms (1 to {} frames{settle}), then the measured one",
        options.warmup_frames,
        options.frames,
        bench::WARM_IN_A_ROW.as_millis(),
        bench::MAX_WARM_FRAMES,
    );
    let report = bench::run(gpu, &options, &mut |line| eprintln!("  {line}"))?;

    let markdown = markdown_tables(&report);
    println!("\n{markdown}");
    if let Some(speedup) = report.speedup_vs_pointlist {
        println!("speedup_vs_pointlist ({HEADLINE_WORKLOAD}): {speedup:.2}x");
    }
    warn_about_timestamps(&report);

    if let Some(path) = &args.markdown {
        std::fs::write(path, &markdown).with_context(|| format!("writing {}", path.display()))?;
    }
    if let Some(path) = &args.json {
        let file = BenchFile {
            command: std::env::args().collect::<Vec<_>>().join(" "),
            quick: args.quick,
            finished_unix_s: std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(0, |d| d.as_secs()),
            wall_s: started.elapsed().as_secs_f64(),
            machine: Machine::this(),
            report: &report,
        };
        let json = serde_json::to_string_pretty(&file)?;
        std::fs::write(path, json + "\n").with_context(|| format!("writing {}", path.display()))?;
    }
    if let Some(path) = &args.plot {
        crate::bench_plot::write(&report, path)?;
    }
    println!("done in {:.0} s", started.elapsed().as_secs_f64());
    Ok(())
}

/// Milliseconds to three significant digits where that takes more than one decimal: a GPU
/// renders in a tenth of a millisecond what lavapipe renders in a hundred.
/// `value` to three significant digits, however small (a GPU's ns per point is ~0.01).
fn significant(value: f64) -> String {
    if value == 0.0 || !value.is_finite() {
        return format!("{value}");
    }
    let decimals = (2 - value.abs().log10().floor() as i32).clamp(0, 9) as usize;
    format!("{value:.decimals$}")
}

fn ms(value: f64) -> String {
    match value {
        v if v < 1.0 => format!("{v:.3}"),
        v if v < 10.0 => format!("{v:.2}"),
        v => format!("{v:.1}"),
    }
}

/// The render tables (when any workload was rendered), the ingest table and what was skipped.
fn markdown_tables(report: &BenchReport) -> String {
    let mut md = String::new();
    if !report.workloads.is_empty() {
        render_tables(&mut md, report);
    }
    ingest_table(&mut md, report);
    for s in &report.skipped {
        let _ = writeln!(md, "\nSkipped {}: {}.", s.workload, s.reason);
    }
    md
}

/// The summary table (frame time, throughput, speed-up, other modes' cost), the per-stage
/// table, the scaling fits and the huge workload's memory.
fn render_tables(md: &mut String, report: &BenchReport) {
    let modes: Vec<&'static str> = report
        .workloads
        .first()
        .map(|w| w.modes.iter().map(|m| m.result.method).collect())
        .unwrap_or_default();
    // Writing to a String cannot fail.
    let _ = write!(
        md,
        "| workload | points | in view | PointList ms | PointList Mpts/s | compute ms | \
         compute Mpts/s | speed-up |"
    );
    for mode in &modes {
        let _ = write!(md, " {mode} ms | {mode} / basic |");
    }
    let _ = writeln!(
        md,
        " wall ms PointList / compute | same colour | GPU B/point |\n\
         |---|---:|---:|---:|---:|---:|---:|---:|{}---:|---:|---:|",
        "---:|---:|".repeat(modes.len())
    );
    for w in &report.workloads {
        let (pointlist, compute) = (&w.pointlist, &w.compute);
        let _ = write!(
            md,
            "| {} | {} | {} | {} | {:.1} | {} | {:.1} | {:.2}x |",
            w.workload,
            thousands(w.points),
            thousands(w.points_in_view),
            ms(pointlist.frame_ms),
            pointlist.mpoints_per_s,
            ms(compute.frame_ms),
            compute.mpoints_per_s,
            w.speedup_vs_pointlist,
        );
        for mode in &w.modes {
            let _ = write!(
                md,
                " {} | {:.2}x |",
                ms(mode.result.frame_ms),
                mode.cost_vs_basic
            );
        }
        let _ = writeln!(
            md,
            " {:.1} / {:.1} | {:.1}% | {:.2} |",
            pointlist.wall_ms,
            compute.wall_ms,
            w.image_agreement * 100.0,
            w.gpu_bytes_per_point,
        );
    }

    // Every stage that any method reported, in order of first appearance.
    let methods = |w: &'_ bench::WorkloadResult| -> Vec<MethodResult> {
        let mut all = vec![w.pointlist.clone(), w.compute.clone()];
        all.extend(w.modes.iter().map(|m| m.result.clone()));
        all
    };
    let mut stage_names: Vec<&'static str> = Vec::new();
    for w in &report.workloads {
        for m in methods(w) {
            for s in &m.stages {
                if !stage_names.contains(&s.stage) {
                    stage_names.push(s.stage);
                }
            }
        }
    }
    // In the order a frame runs them.
    const ORDER: [&str; 9] = [
        "upload",
        "cull",
        "rasterize",
        "accumulate",
        "resolve",
        "shade",
        "downsample",
        "readback",
        "encode",
    ];
    stage_names.sort_by_key(|name| ORDER.iter().position(|o| o == name).unwrap_or(ORDER.len()));
    let _ = writeln!(
        md,
        "\nMedian per stage (ms; clock in brackets):\n\n| workload | method | {} |\n|---|---|{}",
        stage_names.join(" | "),
        "---:|".repeat(stage_names.len())
    );
    for w in &report.workloads {
        for m in methods(w) {
            let cells: Vec<String> = stage_names.iter().map(|name| stage(&m, name)).collect();
            let _ = writeln!(
                md,
                "| {} | {} ({}) | {} |",
                w.workload,
                m.method,
                m.variant,
                cells.join(" | ")
            );
        }
    }

    if !report.scaling.is_empty() {
        let _ = writeln!(
            md,
            "\nFrame time against points in view ({}), least-squares line:\n\n\
             | method | ns per point | intercept ms | R² |\n|---|---:|---:|---:|",
            report.scaling[0].workloads.join(", ")
        );
        for fit in &report.scaling {
            let _ = writeln!(
                md,
                "| {} | {} | {} | {:.4} |",
                fit.method,
                significant(fit.ns_per_point),
                significant(fit.intercept_ms),
                fit.r_squared
            );
        }
    }
    let _ = writeln!(
        md,
        "\nBatches of 4096 points in the basic mode's last frame: listed by the host's culling \
         (a batch at the view's edge once per run of it listed) with their points, then skipped \
         by the depth pass as hidden:\n\n| workload | batches | listed | points listed | points \
         in view | occluded |\n|---|---:|---:|---:|---:|---:|"
    );
    for w in &report.workloads {
        let b = &w.batches;
        let _ = writeln!(
            md,
            "| {} | {} | {} | {} | {} | {} |",
            w.workload,
            thousands(b.total),
            thousands(b.listed as usize),
            thousands(b.listed_points as usize),
            thousands(w.points_in_view),
            thousands(b.occluded as usize)
        );
    }
    for w in &report.workloads {
        if let Some(memory) = &w.ingest_memory {
            let mib = |b: u64| b as f64 / (1u64 << 20) as f64;
            let _ = writeln!(
                md,
                "\n{}: host memory peak during ingest {:.0} MiB, {:.0} MiB above the {:.0} MiB \
                 before it; GPU data {:.0} MiB: the ingest's peak / GPU data = {:.2}.",
                w.workload,
                mib(memory.peak_host_bytes),
                mib(memory
                    .peak_host_bytes
                    .saturating_sub(memory.before_host_bytes)),
                mib(memory.before_host_bytes),
                mib(memory.gpu_bytes),
                memory.ingest_over_gpu
            );
        }
    }
}

/// Loading datasets: decoding on all cores and on one, and from the dataset cache.
fn ingest_table(md: &mut String, report: &BenchReport) {
    if report.ingest.is_empty() {
        return;
    }
    let _ = writeln!(
        md,
        "\nLoading datasets (medians; the files in the page cache): LAZ decoding on all cores \
         and on one, and a dataset-cache hit just after the cache was opened again:\n\n\
         | file | points | MB | decode ms | M points/s | threads | one thread ms | parallel \
         speed-up | cache open ms | cache hit ms | hit vs decode |\n\
         |---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"
    );
    for i in &report.ingest {
        let _ = writeln!(
            md,
            "| {} | {} | {:.1} | {} | {:.1} | {} | {} | {:.2}x | {} | {} | {:.0}x |",
            i.workload.trim_start_matches("ingest-"),
            thousands(i.points),
            i.file_bytes as f64 / 1e6,
            significant(i.decode_ms),
            i.decode_mpoints_per_s,
            i.threads,
            significant(i.decode_one_thread_ms),
            i.parallel_speedup,
            significant(i.cache_open_ms),
            significant(i.cache_hit_ms),
            i.cache_speedup
        );
    }
}

/// Frames whose wall-clock time exceeds their stages by much mean the GPU timestamps missed
/// work (lavapipe under-reports the resolve pass): say so, and how to get honest figures.
fn warn_about_timestamps(report: &BenchReport) {
    if report.host_clocks {
        return;
    }
    let suspect: Vec<String> = report
        .workloads
        .iter()
        .flat_map(|w| {
            [(&w.workload, &w.pointlist), (&w.workload, &w.compute)]
                .into_iter()
                .chain(w.modes.iter().map(move |m| (&w.workload, &m.result)))
        })
        .filter(|(_, m)| m.unaccounted_ms() > 2.0_f64.max(0.2 * m.wall_ms))
        .map(|(workload, m)| {
            format!(
                "{workload} {}: {:.1} of {:.1} ms",
                m.method,
                m.unaccounted_ms(),
                m.wall_ms
            )
        })
        .collect();
    if !suspect.is_empty() {
        eprintln!(
            "warning: wall-clock time that no stage accounts for ({}); this adapter's GPU \
             timestamps may under-report; rerun with --host-clocks",
            suspect.join(", ")
        );
    }
}

fn stage(method: &MethodResult, name: &str) -> String {
    method
        .stages
        .iter()
        .find(|s| s.stage == name)
        .map_or("–".into(), |s| format!("{} ({})", ms(s.ms), s.clock))
}

/// 10000000 as 10,000,000.
fn thousands(n: usize) -> String {
    let digits = n.to_string();
    let mut out = String::new();
    for (i, c) in digits.chars().enumerate() {
        if i > 0 && (digits.len() - i).is_multiple_of(3) {
            out.push(',');
        }
        out.push(c);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::{significant, thousands};

    #[test]
    fn thousands_separators() {
        assert_eq!(thousands(0), "0");
        assert_eq!(thousands(999), "999");
        assert_eq!(thousands(1000), "1,000");
        assert_eq!(thousands(10_000_000), "10,000,000");
    }

    #[test]
    fn three_significant_digits_at_any_scale() {
        assert_eq!(significant(0.009_412), "0.00941");
        assert_eq!(significant(4.891), "4.89");
        assert_eq!(significant(215.63), "216");
        assert_eq!(significant(-0.25), "-0.250");
        assert_eq!(significant(0.0), "0");
    }
}
