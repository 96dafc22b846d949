//! The JSON that `dataset`, `jobs` and `frames` print with `--json`. What the API returns is
//! printed as its message in the proto3 JSON mapping (`pointfarm-proto`'s serde impls:
//! lowerCamelCase names, enums by name, 64-bit integers as strings, default values left out),
//! so a dataset, a job, a frame or a job event reads the same here as from the API. What the
//! CLI adds, which no message holds, is in small wrapper objects with lowerCamelCase keys.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use pointfarm_proto::v1 as pb;
use serde::Serialize;

/// `value` as one line of JSON.
pub fn json_line<T: Serialize + ?Sized>(value: &T) -> Result<String> {
    serde_json::to_string(value).context("encoding the JSON output")
}

/// `dataset rm --json`: the id of the dataset deleted (the API answers a deletion with an
/// empty message).
#[derive(Serialize)]
#[serde(rename_all = "camelCase")]
pub struct Deleted<'a> {
    pub deleted: &'a str,
}

/// `dataset export --json`: where the file was written, and the API's summary of it.
#[derive(Serialize)]
#[serde(rename_all = "camelCase")]
pub struct ExportedDataset<'a> {
    pub file: String,
    pub summary: &'a pb::ExportSummary,
}

/// `jobs show --json`: the job as the API returns it (its finished frames and their timings
/// included), and the median and 95th percentile of each stage over those frames.
#[derive(Serialize)]
#[serde(rename_all = "camelCase")]
pub struct JobDetails<'a> {
    pub job: &'a pb::Job,
    pub stage_statistics: Vec<StageStatistics>,
}

/// One stage's statistics over a job's frames.
#[derive(Debug, Clone, PartialEq, Serialize)]
#[serde(rename_all = "camelCase")]
pub struct StageStatistics {
    pub stage: String,
    pub median_ms: f64,
    pub p95_ms: f64,
}

/// `frames fetch --json`: where each frame was written (the API's `FrameChunk`s carry the
/// image, which is in the file).
#[derive(Serialize)]
#[serde(rename_all = "camelCase")]
pub struct FetchedFrames {
    pub job_id: String,
    pub out: String,
    pub frames: Vec<FetchedFrame>,
}

#[derive(Serialize)]
#[serde(rename_all = "camelCase")]
pub struct FetchedFrame {
    pub index: u32,
    pub path: String,
}

impl FetchedFrames {
    pub fn new(job_id: &str, out: &Path, written: &[(u32, PathBuf)]) -> Self {
        Self {
            job_id: job_id.to_string(),
            out: out.display().to_string(),
            frames: written
                .iter()
                .map(|(index, path)| FetchedFrame {
                    index: *index,
                    path: path.display().to_string(),
                })
                .collect(),
        }
    }
}

/// `jobs video --json`: where the job's video (or its preview video) was written, and its
/// size, a 64-bit count written as a string as the API writes its own.
#[derive(Serialize)]
#[serde(rename_all = "camelCase")]
pub struct FetchedVideo {
    pub job_id: String,
    pub out: String,
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub preview: bool,
    pub size_bytes: String,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn wrappers_have_lower_camel_case_keys_around_the_messages() {
        let job = pb::Job {
            id: "job-1".into(),
            state: pb::JobState::Running as i32,
            updated_unix_ms: 5,
            ..Default::default()
        };
        let details = JobDetails {
            job: &job,
            stage_statistics: vec![StageStatistics {
                stage: "rasterize".into(),
                median_ms: 2.0,
                p95_ms: 3.5,
            }],
        };
        let value: serde_json::Value =
            serde_json::from_str(&json_line(&details).expect("encodes")).expect("JSON");
        assert_eq!(
            value,
            serde_json::json!({
                "job": { "id": "job-1", "state": "JOB_STATE_RUNNING", "updatedUnixMs": "5" },
                "stageStatistics": [{ "stage": "rasterize", "medianMs": 2.0, "p95Ms": 3.5 }],
            })
        );
        let fetched = FetchedFrames::new("job-1", Path::new("out"), &[(0, "out/f0.png".into())]);
        assert_eq!(
            serde_json::to_value(&fetched).expect("encodes"),
            serde_json::json!({
                "jobId": "job-1", "out": "out", "frames": [{ "index": 0, "path": "out/f0.png" }],
            })
        );
        let video = |preview| FetchedVideo {
            job_id: "job-1".into(),
            out: "spin.mp4".into(),
            preview,
            size_bytes: 16953.to_string(),
        };
        assert_eq!(
            serde_json::to_value(video(false)).expect("encodes"),
            serde_json::json!({ "jobId": "job-1", "out": "spin.mp4", "sizeBytes": "16953" })
        );
        assert_eq!(
            serde_json::to_value(video(true)).expect("encodes")["preview"],
            serde_json::json!(true)
        );
    }
}
