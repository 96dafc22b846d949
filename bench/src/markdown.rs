//! The benchmark's figures as markdown: the render tables (frame times, throughput, speed-ups,
//! per-stage medians, scaling fits, batch counts, the huge cloud's memory), the ingest table,
//! what was skipped, and the campaign benchmark's tables.

use std::fmt::Write as _;

use crate::campaign::CampaignResult;
use crate::report::{BenchReport, MethodResult, WorkloadResult};

/// `value` to three significant digits, however small (a GPU's ns per point is ~0.01).
fn significant(value: f64) -> String {
    if value == 0.0 || !value.is_finite() {
        return format!("{value}");
    }
    let decimals = (2 - value.abs().log10().floor() as i32).clamp(0, 9) as usize;
    format!("{value:.decimals$}")
}

/// Milliseconds to three significant digits where that takes more than one decimal: a GPU
/// renders in a tenth of a millisecond what lavapipe renders in a hundred.
fn ms(value: f64) -> String {
    stepped(value, [(1.0, 3), (10.0, 2)], 1)
}

/// `value` with the decimals of the first `(below, decimals)` step it is below, else with
/// `beyond` decimals.
fn stepped(value: f64, steps: [(f64, usize); 2], beyond: usize) -> String {
    let decimals = steps
        .iter()
        .find(|&&(below, _)| value < below)
        .map_or(beyond, |&(_, decimals)| decimals);
    format!("{value:.decimals$}")
}

/// The render tables (when any workload was rendered), the ingest table and what was skipped.
pub fn tables(report: &BenchReport) -> String {
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
        " wall ms PointList / compute | same color | GPU B/point |\n\
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
    let methods = |w: &'_ WorkloadResult| -> Vec<MethodResult> {
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
    const ORDER: [&str; 10] = [
        "upload",
        "cull",
        "rasterize",
        "accumulate",
        "resolve",
        "shade",
        "downsample",
        "expose",
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

/// Seconds to two decimals, or three below a tenth.
fn seconds(value: f64) -> String {
    stepped(value, [(0.1, 3), (100.0, 2)], 0)
}

/// The campaign benchmark: reading and building per kind of files, the builder's stages and
/// memory, the store's disk.
pub fn campaign_tables(c: &CampaignResult) -> String {
    let mut md = String::new();
    let mib = |b: u64| b as f64 / (1u64 << 20) as f64;
    let _ = writeln!(
        md,
        "Campaign ingest: {} points of generated terrain in {} files ({}x{} tiles), written in \
         {:.1} s; {} threads.\n\n\
         | input | files MB | file B/point | read s | read M points/s | build s | build M \
         points/s | build / read | peak RSS MiB | builder's tracked peak MiB | store B/point |\n\
         |---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
        thousands(c.points as usize),
        c.files,
        c.grid[0],
        c.grid[1],
        c.write_s,
        c.threads
    );
    for b in &c.builds {
        let Some(read) = c.decode_of(b.input) else {
            continue;
        };
        let _ = writeln!(
            md,
            "| {} | {:.1} | {:.2} | {} | {:.2} | {} | {:.2} | {:.0}% | {:.0} | {:.0} | {:.2} |",
            b.input.to_uppercase(),
            read.file_bytes as f64 / 1e6,
            read.file_bytes_per_point,
            seconds(read.read_s),
            read.mpoints_per_s,
            seconds(b.build_s),
            b.mpoints_per_s,
            b.over_decode * 100.0,
            mib(b.peak_rss_bytes),
            mib(b.builder_peak_bytes),
            b.store_disk_bytes_per_point
        );
    }
    let _ = writeln!(
        md,
        "\nThe builder's stages (s), the partitions, the nodes, what was spilled and stored:\n\n\
         | input | counting | partitions | upper levels | total | partitions | nodes | \
         spilled MiB (B a record) | node records MiB | store on disk MiB | RSS before MiB |\n\
         |---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"
    );
    for b in &c.builds {
        let s = &b.stages;
        let _ = writeln!(
            md,
            "| {} | {} | {} | {} | {} | {} | {} | {:.0} ({}) | {:.0} | {:.0} | {:.0} |",
            b.input.to_uppercase(),
            seconds(s.counting_s),
            seconds(s.partitions_s),
            seconds(s.upper_levels_s),
            seconds(s.total_s),
            b.partitions,
            thousands(b.nodes),
            mib(b.spilled_bytes),
            b.spill_record_bytes,
            mib(b.stored_bytes),
            mib(b.store_disk_bytes),
            mib(b.before_rss_bytes)
        );
    }
    if let Some([before, after]) = c.load_average {
        let _ = writeln!(
            md,
            "\nLoad average {before:.1} at the start, {after:.1} at the end ({} threads).",
            c.threads
        );
    }
    if let Some(reason) = &c.las_skipped {
        let _ = writeln!(md, "\nNo LAS: {reason}.");
    }
    if !c.peak_reset {
        let _ = writeln!(
            md,
            "\nThe peak resident memory could not be reset before the builds: each peak is the \
             process's since its start."
        );
    }
    if let Some(turntable) = &c.turntable {
        let _ = writeln!(
            md,
            "\n{}",
            crate::cuts::markdown::turntable_table(turntable)
        );
    }
    md
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
