//! `bench`: its figures as JSON and Markdown, decoding and the dataset cache, a huge cloud.

use super::*;

#[test]
fn bench_writes_its_figures_as_json_and_markdown() {
    let Some(autzen) = shared_data("autzen_trim.laz") else {
        return;
    };
    let data = autzen.parent().expect("the scan's directory");
    let options = [
        "--only",
        "autzen_trim.laz",
        "--modes",
        "hq,basic-32",
        "--size",
        "160x120",
    ];
    let (report, table) = quick_bench(data, &options);
    let workload = &report["workloads"][0];
    assert_eq!(workload["workload"], "autzen_trim.laz");
    assert_eq!(workload["points"], 110_000);
    for method in [&workload["pointlist"], &workload["compute"]] {
        assert_positive(method, &["frameMs"]);
    }
    let modes = json_names(&workload["modes"], "method");
    assert_eq!(modes, ["compute-hq", "compute-basic-32"]);
    // The headline figure belongs to the 10M cloud, which this run left out.
    assert!(report["speedupVsPointlist"].is_null(), "{report}");
    assert!(table.contains("| autzen_trim.laz |"), "{table}");
}

/// Runs `pointfarm bench --quick` on the scans in `data` with `options`, and returns the
/// report it wrote as JSON and its Markdown table.
fn quick_bench(data: &Path, options: &[&str]) -> (serde_json::Value, String) {
    let dir = tempfile::tempdir().expect("tempdir");
    let (json, markdown) = (dir.path().join("bench.json"), dir.path().join("bench.md"));
    let (data, json_arg, markdown_arg) = (path_arg(data), path_arg(&json), path_arg(&markdown));
    let mut args = vec!["bench", "--quick", "--data", &data];
    args.extend(["--json", &json_arg, "--markdown", &markdown_arg]);
    args.extend(options);
    assert_ok(&pointfarm(&args));
    let table = std::fs::read_to_string(&markdown).expect("markdown written");
    (read_json(&json), table)
}

/// Asserts that each of `fields` of the report's `object` is a number above 0: a figure
/// that was measured.
fn assert_positive(object: &serde_json::Value, fields: &[&str]) {
    for field in fields {
        assert!(
            object[field].as_f64().is_some_and(|v| v > 0.0),
            "{field}: {object}"
        );
    }
}

/// Runs `pointfarm bench ARGS --json FILE`, which must succeed, and returns its output and
/// the report it wrote.
fn bench_json(args: &[&str]) -> (Output, serde_json::Value) {
    let dir = tempfile::tempdir().expect("tempdir");
    let json = dir.path().join("bench.json");
    let json_arg = path_arg(&json);
    let mut all = vec!["bench"];
    all.extend(args);
    all.extend(["--json", &json_arg]);
    let output = pointfarm(&all);
    assert_ok(&output);
    (output, read_json(&json))
}

/// `--only ingest` measures loading alone: the real scans found and a generated LAZ file of
/// the size asked, each decoded on all cores and on one and given back by the dataset cache.
#[test]
fn bench_measures_decoding_and_the_dataset_cache() {
    let dir = tempfile::tempdir().expect("tempdir");
    let data = shared_data("autzen_trim.laz")
        .and_then(|scan| scan.parent().map(Path::to_path_buf))
        .unwrap_or_else(|| dir.path().join("no-scans"));
    let options = ["--only", "ingest", "--ingest-points", "30_000"];
    let (report, table) = quick_bench(&data, &options);
    assert!(report["workloads"]
        .as_array()
        .expect("workloads")
        .is_empty());
    let ingest = report["ingest"].as_array().expect("ingest");
    let generated = ingest.last().expect("the generated file");
    assert_eq!(generated["workload"], "ingest-uniform-30000.laz");
    assert_eq!(generated["points"], 30_000);
    assert_positive(
        generated,
        &[
            "decodeMs",
            "decodeOneThreadMs",
            "cacheHitMs",
            "cacheSpeedup",
        ],
    );
    assert!(table.contains("| uniform-30000.laz | 30,000 |"), "{table}");
    if shared_data("autzen_trim.laz").is_some() {
        assert_eq!(ingest.len(), 3, "{report}");
        assert_eq!(ingest[1]["workload"], "ingest-autzen_trim.laz");
        assert_eq!(ingest[1]["points"], 110_000);
    } else {
        assert_eq!(
            report["skipped"].as_array().map(Vec::len),
            Some(2),
            "{report}"
        );
    }
}

/// `--huge POINTS` streams a cube of that many points, reports its memory peak and batches,
/// and a count of nothing is refused before any work.
#[test]
fn bench_streams_a_huge_cloud_of_the_size_asked() {
    let (_, report) = bench_json(&[
        "--huge",
        "200_000",
        "--only",
        "uniform-200000",
        "--basic-only",
        "--size",
        "64x48",
    ]);
    let workloads = report["workloads"].as_array().expect("workloads");
    assert_eq!(workloads.len(), 1, "{report}");
    let huge = &workloads[0];
    assert_eq!(huge["workload"], "uniform-200000");
    assert_eq!(huge["points"], 200_000);
    assert!(huge["ingestMemory"]["peakHostBytes"]
        .as_u64()
        .is_some_and(|b| b > 0));
    // 4096-point batches, all in view of the automatic camera.
    assert_eq!(huge["batches"]["total"], 49);
    assert_eq!(huge["batches"]["listed"], 49);
    let stages = json_names(&huge["compute"]["stages"], "stage");
    assert!(stages.contains(&"cull"), "{stages:?}");

    let refused = pointfarm(&["bench", "--huge", "0"]);
    assert_fails_saying(&refused, "at least one point");
}

/// `--service-load` with tiny numbers: a real daemon with its embedded worker renders every
/// frame submitted, a second daemon leases as many frames as asked, both are stopped after
/// SIGTERM and the scratch folder is gone.
#[test]
fn bench_measures_the_service_under_load() {
    let (output, report) = bench_json(&[
        "--service-load",
        "--service-jobs",
        "4",
        "--service-frames-per-job",
        "1",
        "--service-clients",
        "2",
        "--service-leases",
        "5",
    ]);
    let runs = report["serviceLoad"]["runs"].as_array().expect("runs");
    assert_eq!(runs.len(), 1, "{report}");
    let run = &runs[0];
    assert_eq!(run["frames"], 4, "{run}");
    assert_eq!(run["leases"], 5, "{run}");
    assert_eq!(run["stoppedCleanly"], true, "{run}");
    assert_positive(
        run,
        &[
            "framesPerS",
            "submitMedianMs",
            "getJobMedianMs",
            "leaseMedianMs",
            "leaseP95Ms",
        ],
    );
    assert_says(&output, "| LeaseFrame median (ms) |");
    let stderr = String::from_utf8_lossy(&output.stderr);
    let scratch = stderr
        .lines()
        .find_map(|line| line.trim().strip_prefix("scratch: "))
        .expect("the scratch folder is named");
    assert!(!Path::new(scratch).exists(), "{scratch} is left behind");
}
