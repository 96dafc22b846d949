//! What a service-load run reports: each binary's medians against the first's, a Markdown
//! table, and the `serviceLoad` section of `--json`.

use std::path::{Path, PathBuf};

use serde::Serialize;

use super::{ServiceLoadError, ServiceLoadResult, ServiceLoadRun, ServiceLoadSummary};
use crate::json::{camel_case_keys, RunContext};
use crate::stats::median;

/// Per binary, the medians of its runs' figures and their ratios to the first binary's.
pub(super) fn summarise(binaries: &[PathBuf], runs: &[ServiceLoadRun]) -> Vec<ServiceLoadSummary> {
    let mut summaries: Vec<ServiceLoadSummary> = Vec::new();
    for binary in binaries {
        let name = binary.display().to_string();
        let own: Vec<&ServiceLoadRun> = runs.iter().filter(|r| r.daemon == name).collect();
        let of =
            |figure: fn(&ServiceLoadRun) -> f64| median(own.iter().map(|r| figure(r)).collect());
        let (frames_per_s, submit_median_ms, lease_median_ms) = (
            of(|r| r.frames_per_s),
            of(|r| r.submit_median_ms),
            of(|r| r.lease_median_ms),
        );
        let baseline = summaries.first();
        summaries.push(ServiceLoadSummary {
            runs: own.len(),
            frames_per_s,
            submit_median_ms,
            get_job_median_ms: of(|r| r.get_job_median_ms),
            lease_median_ms,
            frames_per_s_over_baseline: baseline.map_or(1.0, |b| frames_per_s / b.frames_per_s),
            submit_speedup: baseline.map_or(1.0, |b| b.submit_median_ms / submit_median_ms),
            lease_speedup: baseline.map_or(1.0, |b| b.lease_median_ms / lease_median_ms),
            daemon: name,
        });
    }
    summaries
}

/// The runs' table and, for more than one binary, the summary against the first.
pub fn markdown(result: &ServiceLoadResult) -> String {
    let mut md = format!(
        "{} jobs x {} frames at {}x{} from {} clients (a generated dataset of {} points); \
         {} leases handed back\n\n\
         | daemon | run | load | adapter | frames/s | SubmitJob median (ms) | p95 (ms) | \
         GetJob median (ms) | LeaseFrame median (ms) | p95 (ms) | ReleaseFrame median (ms) |\n\
         |---|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|\n",
        result.load.jobs,
        result.load.frames_per_job,
        result.load.width,
        result.load.height,
        result.load.clients,
        result.dataset_points,
        result.load.leases,
    );
    for r in &result.runs {
        let load = r
            .load_average
            .map_or_else(String::new, |l| format!("{l:.2}"));
        md.push_str(&format!(
            "| {} | {} | {load} | {} | {:.1} | {:.2} | {:.2} | {:.2} | {:.2} | {:.2} | {:.2} |\n",
            r.daemon,
            r.run,
            r.adapter,
            r.frames_per_s,
            r.submit_median_ms,
            r.submit_p95_ms,
            r.get_job_median_ms,
            r.lease_median_ms,
            r.lease_p95_ms,
            r.release_median_ms,
        ));
    }
    if result.summaries.len() > 1 {
        md.push_str(
            "\n| daemon | runs | frames/s | against the first | SubmitJob median (ms) | \
             speed-up | GetJob median (ms) | LeaseFrame median (ms) | speed-up |\n\
             |---|---:|---:|---:|---:|---:|---:|---:|---:|\n",
        );
        for s in &result.summaries {
            md.push_str(&format!(
                "| {} | {} | {:.1} | {:.2}x | {:.2} | {:.2}x | {:.2} | {:.2} | {:.2}x |\n",
                s.daemon,
                s.runs,
                s.frames_per_s,
                s.frames_per_s_over_baseline,
                s.submit_median_ms,
                s.submit_speedup,
                s.get_job_median_ms,
                s.lease_median_ms,
                s.lease_speedup,
            ));
        }
    }
    md
}

/// Writes the figures with the run's `context` as pretty-printed JSON (lowerCamelCase keys,
/// as every `--json` of the CLI) to `path`, as the file's `serviceLoad` section.
pub fn write_json(
    path: &Path,
    result: &ServiceLoadResult,
    context: &RunContext,
) -> Result<(), ServiceLoadError> {
    #[derive(Serialize)]
    struct ServiceLoadFile<'a> {
        command: &'a str,
        finished_unix_s: u64,
        wall_s: f64,
        cores: usize,
        service_load: &'a ServiceLoadResult,
    }
    let file = ServiceLoadFile {
        command: &context.command,
        finished_unix_s: std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_secs()),
        wall_s: context.started.elapsed().as_secs_f64(),
        cores: std::thread::available_parallelism().map_or(1, |n| n.get()),
        service_load: result,
    };
    let json = serde_json::to_value(&file)
        .map(camel_case_keys)
        .and_then(|value| serde_json::to_string_pretty(&value))
        .map_err(|e| ServiceLoadError::Setup(format!("the JSON: {e}")))?;
    std::fs::write(path, json + "\n").map_err(|source| ServiceLoadError::Write {
        path: path.to_path_buf(),
        source,
    })
}
