//! The benchmark's JSON file: the report (or the campaign benchmark's `campaign` section), with
//! the run's context (the command, when it ended, how long it took, the machine). Keys are
//! lowerCamelCase, as in the API's JSON mapping and every other `--json` of the CLI.

use std::path::Path;
use std::time::Instant;

use serde::Serialize;

use crate::campaign::CampaignResult;
use crate::copc::CopcResult;
use crate::cuts::CutsResult;
use crate::report::BenchReport;
use crate::BenchError;

/// How the run was started, recorded beside its figures.
pub struct RunContext {
    /// The command line, as typed.
    pub command: String,
    /// Whether it was the quick run.
    pub quick: bool,
    /// When the run started, for its wall time.
    pub started: Instant,
}

/// The JSON file: the run's context and the report's sections.
#[derive(Serialize)]
struct BenchFile<'a, R: Serialize> {
    command: String,
    quick: bool,
    /// Seconds since the Unix epoch when the run ended.
    finished_unix_s: u64,
    wall_s: f64,
    machine: Machine,
    #[serde(flatten)]
    report: &'a R,
}

/// The campaign benchmark's file: its figures as the `campaign` section.
#[derive(Serialize)]
struct CampaignSection<'a> {
    campaign: &'a CampaignResult,
}

/// The cut benchmark's file: its figures as the `cuts` section.
#[derive(Serialize)]
struct CutsSection<'a> {
    cuts: &'a CutsResult,
}

/// The COPC benchmark's file: its figures as the `copc` section.
#[derive(Serialize)]
struct CopcSection<'a> {
    copc: &'a CopcResult,
}

/// The machine the run was on.
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

/// Writes `report` with its `context` as pretty-printed JSON to `path`.
pub fn write(path: &Path, report: &BenchReport, context: &RunContext) -> Result<(), BenchError> {
    write_file(path, report, context)
}

/// Writes the campaign benchmark's figures, as the file's `campaign` section, with `context`.
pub fn write_campaign(
    path: &Path,
    campaign: &CampaignResult,
    context: &RunContext,
) -> Result<(), BenchError> {
    write_file(path, &CampaignSection { campaign }, context)
}

/// Writes `--copc`'s figures, as the file's `copc` section, with `context`.
pub fn write_copc(path: &Path, copc: &CopcResult, context: &RunContext) -> Result<(), BenchError> {
    write_file(path, &CopcSection { copc }, context)
}

/// Writes `--cuts`' figures, as the file's `cuts` section, with `context`.
pub fn write_cuts(path: &Path, cuts: &CutsResult, context: &RunContext) -> Result<(), BenchError> {
    write_file(path, &CutsSection { cuts }, context)
}

fn write_file<R: Serialize>(
    path: &Path,
    report: &R,
    context: &RunContext,
) -> Result<(), BenchError> {
    let file = BenchFile {
        command: context.command.clone(),
        quick: context.quick,
        finished_unix_s: std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_secs()),
        wall_s: context.started.elapsed().as_secs_f64(),
        machine: Machine::this(),
        report,
    };
    let json = serde_json::to_value(&file)
        .map(camel_case_keys)
        .and_then(|value| serde_json::to_string_pretty(&value))
        .map_err(|e| BenchError::Json(e.to_string()))?;
    std::fs::write(path, json + "\n").map_err(|source| BenchError::Write {
        path: path.to_path_buf(),
        source,
    })
}

/// `value` with every object's keys in lowerCamelCase (`points_rendered` as `pointsRendered`),
/// as the proto3 JSON mapping writes the API's fields: the CLI's own JSON objects, made from
/// snake_case Rust fields, read like its API messages.
pub fn camel_case_keys(value: serde_json::Value) -> serde_json::Value {
    match value {
        serde_json::Value::Object(fields) => fields
            .into_iter()
            .map(|(key, value)| (lower_camel_case(&key), camel_case_keys(value)))
            .collect(),
        serde_json::Value::Array(items) => items.into_iter().map(camel_case_keys).collect(),
        other => other,
    }
}

fn lower_camel_case(snake: &str) -> String {
    let mut words = snake.split('_');
    let first = words.next().unwrap_or_default().to_string();
    words.fold(first, |mut name, word| {
        let mut letters = word.chars();
        name.extend(letters.next().map(|c| c.to_ascii_uppercase()));
        name.push_str(letters.as_str());
        name
    })
}

/// Writes a result with `write` into `dir` as a test run would, and parses it back.
#[cfg(test)]
pub(crate) fn written_in<R>(
    dir: &Path,
    result: &R,
    write: fn(&Path, &R, &RunContext) -> Result<(), BenchError>,
) -> serde_json::Value {
    let path = dir.join("result.json");
    let context = RunContext {
        command: "test".into(),
        quick: true,
        started: Instant::now(),
    };
    write(&path, result, &context).expect("json");
    let bytes = std::fs::read(&path).expect("read");
    std::fs::remove_file(&path).expect("removed");
    serde_json::from_slice(&bytes).expect("parse")
}
