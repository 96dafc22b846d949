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
        assert!(
            method["frameMs"].as_f64().is_some_and(|ms| ms > 0.0),
            "{method}"
        );
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
    for field in [
        "decodeMs",
        "decodeOneThreadMs",
        "cacheHitMs",
        "cacheSpeedup",
    ] {
        assert!(
            generated[field].as_f64().is_some_and(|v| v > 0.0),
            "{field}: {generated}"
        );
    }
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
    let dir = tempfile::tempdir().expect("tempdir");
    let json = dir.path().join("bench.json");
    let output = pointfarm(&[
        "bench",
        "--huge",
        "200_000",
        "--only",
        "uniform-200000",
        "--basic-only",
        "--size",
        "64x48",
        "--json",
        &path_arg(&json),
    ]);
    assert_ok(&output);
    let report = read_json(&json);
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
    let dir = tempfile::tempdir().expect("tempdir");
    let json = dir.path().join("service.json");
    let output = pointfarm(&[
        "bench",
        "--service-load",
        "--service-jobs",
        "4",
        "--service-frames-per-job",
        "1",
        "--service-clients",
        "2",
        "--service-leases",
        "5",
        "--json",
        &path_arg(&json),
    ]);
    assert_ok(&output);
    let report = read_json(&json);
    let runs = report["serviceLoad"]["runs"].as_array().expect("runs");
    assert_eq!(runs.len(), 1, "{report}");
    let run = &runs[0];
    assert_eq!(run["frames"], 4, "{run}");
    assert_eq!(run["leases"], 5, "{run}");
    assert_eq!(run["stoppedCleanly"], true, "{run}");
    for figure in [
        "framesPerS",
        "submitMedianMs",
        "getJobMedianMs",
        "leaseMedianMs",
        "leaseP95Ms",
    ] {
        assert!(
            run[figure].as_f64().is_some_and(|v| v > 0.0),
            "{figure}: {run}"
        );
    }
    assert_says(&output, "| LeaseFrame median (ms) |");
    let stderr = String::from_utf8_lossy(&output.stderr);
    let scratch = stderr
        .lines()
        .find_map(|line| line.trim().strip_prefix("scratch: "))
        .expect("the scratch folder is named");
    assert!(!Path::new(scratch).exists(), "{scratch} is left behind");
}
