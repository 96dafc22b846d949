//! The cut figures as markdown: a turntable's frames, and `--cuts`' scaling, fidelity and
//! resident-against-cut tables.

use std::fmt::Write;

use super::turntable::TurntableResult;
use super::{CutsResult, ViewFigure};

fn mib(bytes: u64) -> f64 {
    bytes as f64 / (1u64 << 20) as f64
}

/// A turntable: its summary line and a row per frame.
pub fn turntable_table(t: &TurntableResult) -> String {
    let mut md = String::new();
    let o = &t.options;
    let _ = writeln!(
        md,
        "Cut turntable of {} points, {} frames at {}x{}, pixel error {}, memory budget {:.0} MiB \
         (host cache {:.0} MiB, GPU cache {:.0} MiB), from a cold cache with read-ahead: first \
         frame {:.2} s, following frames' median {:.2} s (max {:.2} s); {:.0} MiB read in all; \
         peak RSS during the frames {:.0} MiB ({:.0} MiB before them){}.\n",
        t.points,
        o.frames,
        o.width,
        o.height,
        o.lod_error,
        mib(o.memory_budget_bytes),
        mib(t.host_budget_bytes),
        mib(t.gpu_budget_bytes),
        t.first_ms / 1e3,
        t.following_median_ms / 1e3,
        t.following_max_ms / 1e3,
        mib(t.bytes_read()),
        mib(t.peak_rss_bytes),
        mib(t.before_rss_bytes),
        if t.peak_reset {
            ""
        } else {
            " (the peak could not be reset: the process's since its start)"
        }
    );
    md.push_str(
        "| frame | wall ms | cut nodes | cut points | budget-bound | nodes read | MiB read | \
         read-ahead MiB | host hits | GPU hits | select ms | wait ms | load ms | prepare ms | \
         other stages ms |\n\
         |---:|---:|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|\n",
    );
    for (i, f) in t.frames.iter().enumerate() {
        let c = &f.cut;
        let others: Vec<String> = f
            .stages
            .iter()
            .filter(|s| s.stage != "select" && s.stage != "load")
            .map(|s| format!("{} {:.1}", s.stage, s.ms))
            .collect();
        let _ = writeln!(
            md,
            "| {i} | {:.0} | {} | {} | {} | {} | {:.1} | {:.1} | {} | {} | {:.1} | {:.1} | {:.0} | \
             {:.0} | {} |",
            f.wall_ms,
            c.counts.nodes,
            c.counts.points_rendered,
            if c.counts.limited_by_budget { "yes" } else { "no" },
            c.counts.nodes_read,
            mib(c.counts.bytes_read),
            mib(c.counts.read_ahead_bytes),
            c.counts.host_hits,
            c.counts.gpu_hits,
            c.select_ms,
            c.wait_ms,
            c.load_ms,
            c.prepare_ms,
            others.join(", ")
        );
    }
    md
}

fn view_row(md: &mut String, label: &str, v: &ViewFigure) {
    let _ = writeln!(
        md,
        "| {label} | {} | {} | {} | {} | {:.0} | {:.1} |",
        v.points,
        v.cut_nodes,
        v.cut_points,
        if v.limited_by_budget { "yes" } else { "no" },
        v.cold_ms,
        v.warm_ms
    );
}

/// Every table of `--cuts`.
pub fn cuts_tables(r: &CutsResult) -> String {
    let mut md = String::new();
    let _ = writeln!(
        md,
        "Cuts at {}x{}, pixel error {} px, memory budget {:.0} MiB; wall ms of a render call \
         (median of warm frames).\n",
        r.width,
        r.height,
        r.lod_error,
        mib(r.memory_budget_bytes)
    );
    md.push_str("| store | points | build s | nodes |\n|---|---:|---:|---:|\n");
    for b in &r.builds {
        let _ = writeln!(
            md,
            "| {} | {} | {:.1} | {} |",
            b.name, b.points, b.build_s, b.nodes
        );
    }
    let _ = writeln!(
        md,
        "\nFrame time against points (full views of one terrain density):\n\n\
         | workload | points | cut nodes | cut points | budget-bound | cold ms | warm ms |\n\
         |---|---:|---:|---:|---|---:|---:|"
    );
    for v in &r.scaling {
        view_row(&mut md, &v.workload, v);
    }
    let _ = writeln!(
        md,
        "\nLarge over small: {:.2}x the frame time for {:.1}x the points.",
        r.scaling_ratio(),
        r.scaling[1].points as f64 / r.scaling[0].points.max(1) as f64
    );
    if let Some(t) = &r.out_of_core {
        let _ = writeln!(md, "\nOut of core:\n\n{}", turntable_table(t));
    }
    if let Some(t) = &r.turntable {
        let _ = writeln!(md, "\nWithin the memory budget:\n\n{}", turntable_table(t));
    }
    let modes: Vec<&str> = r
        .fidelity
        .first()
        .map(|f| f.modes.iter().map(|m| m.mode).collect())
        .unwrap_or_default();
    let _ = write!(
        md,
        "\nFidelity: covered pixels within {}/255 per channel of the cut at 0 px:\n\n\
         | workload | points | cut points | points at 0 |",
        super::FIDELITY_TOLERANCE
    );
    for m in &modes {
        let _ = write!(md, " {m} |");
    }
    let _ = write!(md, "\n|---|---:|---:|---:|");
    md.push_str(&"---:|".repeat(modes.len()));
    md.push('\n');
    for f in &r.fidelity {
        let _ = write!(
            md,
            "| {}{} | {} | {} | {} |",
            f.workload,
            if f.limited_by_budget {
                " (budget-bound)"
            } else {
                ""
            },
            f.points,
            f.cut_points,
            f.full_points
        );
        for m in &f.modes {
            let _ = write!(md, " {:.2}% |", m.close_share * 100.0);
        }
        md.push('\n');
    }
    let rc = &r.resident_vs_cut;
    let _ = writeln!(
        md,
        "\nResident against cut ({} points):\n\n\
         | path | cut points | warm ms | / resident |\n|---|---:|---:|---:|\n\
         | resident | {} | {:.1} | 1.00x |\n\
         | cut at {} px | {} | {:.1} | {:.2}x |\n\
         | cut at 0 px | {} | {:.1} | {:.2}x |",
        rc.points,
        rc.points,
        rc.resident_ms,
        r.lod_error,
        rc.cut_default.cut_points,
        rc.cut_default.warm_ms,
        rc.default_over_resident(),
        rc.cut_full.cut_points,
        rc.cut_full.warm_ms,
        rc.cut_full.warm_ms / rc.resident_ms
    );
    if !r.missing_scans.is_empty() {
        let _ = writeln!(md, "\nNot found: {}.", r.missing_scans.join(", "));
    }
    md
}
