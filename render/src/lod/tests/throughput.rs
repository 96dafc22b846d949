//! The build's throughput and memory on a generated 20M-point terrain, for the record.

use crate::lod::*;

/// Throughput and memory of a 20M-point build with the default options on every core:
/// `cargo test -p pointfarm-render --release --lib lod::tests::throughput -- --ignored --nocapture`
/// (`POINTFARM_LOD_POINTS` and `POINTFARM_LOD_BUDGET_MIB` change the size and the budget).
#[test]
#[ignore = "a measurement, not a check: minutes of CPU"]
fn throughput_of_a_20m_point_terrain() {
    let points = std::env::var("POINTFARM_LOD_POINTS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(20_000_000u64);
    let dir = tempfile::tempdir().expect("tempdir");
    // sled's page cache is outside the builder's budget (it holds only the hierarchy now);
    // kept small so the process's peak shows the builder's own memory.
    let db = sled::Config::new()
        .path(dir.path().join("db"))
        .cache_capacity(64 << 20)
        .open()
        .expect("sled");
    let store = LodStore::open(
        db.open_tree("lod").expect("tree"),
        dir.path().join("lod.bin"),
    )
    .expect("store");
    let source = GeneratedSource::terrain(points, 1);
    let mut options = LodBuildOptions::new(dir.path().join("spill"));
    if let Some(budget) = std::env::var("POINTFARM_LOD_BUDGET_MIB")
        .ok()
        .and_then(|v| v.parse::<u64>().ok())
    {
        options.memory_budget_bytes = budget << 20;
    }
    // The source's own cost: the build reads it twice.
    let reading = std::time::Instant::now();
    source.for_each_batch(&mut |_| Ok(())).expect("read");
    let read_s = reading.elapsed().as_secs_f64();
    let report = build_lod(&source, &store, &options).expect("build");
    let t = report.timings;
    println!(
        "generating the source once: {read_s:.1} s; the build without its two reads: {:.2} M points/s",
        points as f64 / (t.total.as_secs_f64() - 2.0 * read_s) / 1e6
    );
    let rate = points as f64 / t.total.as_secs_f64();
    let vm_hwm = std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmHWM"))
                .map(str::to_string)
        })
        .unwrap_or_default();
    println!(
        "lod build: {points} points, {} threads, {:.2} M points/s ({:.1} s: counting {:.1}, partitions {:.1}, upper {:.1}); \
         {} partitions, {} nodes; tracked peak {:.0} MiB of {:.0} MiB; spilled {:.0} MiB; stored {:.0} MiB ({:.1} B/point on disk, sled's files {:.1} MiB); {vm_hwm}",
        rayon::current_num_threads(),
        rate / 1e6,
        t.total.as_secs_f64(),
        t.counting.as_secs_f64(),
        t.partitions.as_secs_f64(),
        t.upper_levels.as_secs_f64(),
        report.partitions,
        report.hierarchy.nodes().len(),
        report.peak_memory_bytes as f64 / 1048576.0,
        report.memory_budget_bytes as f64 / 1048576.0,
        report.spilled_bytes as f64 / 1048576.0,
        report.stored_bytes as f64 / 1048576.0,
        report.disk_bytes_per_point(),
        db.size_on_disk().unwrap_or(0) as f64 / 1048576.0,
    );
}
