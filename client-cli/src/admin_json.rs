//! The JSON that `dataset`, `jobs` and `frames` print with `--json`: one shape per thing,
//! snake_case fields, the same object wherever the same thing is printed (`jobs show`,
//! `jobs cancel`, the end of `jobs watch`).

use std::path::{Path, PathBuf};

use pointfarm_proto::v1 as pb;
use serde_json::json;

use crate::remote::state_name;

pub fn dataset_json(d: &pb::Dataset) -> serde_json::Value {
    let files: Vec<serde_json::Value> = d
        .files
        .iter()
        .map(|f| json!({ "name": f.name, "size_bytes": f.size_bytes, "sha256": f.sha256, "path": f.path }))
        .collect();
    json!({ "id": d.id, "name": d.name, "size_bytes": d.size_bytes, "sha256": d.sha256, "path": d.path, "files": files })
}

pub fn job_json(j: &pb::Job) -> serde_json::Value {
    json!({
        "id": j.id, "dataset_id": j.dataset_id, "state": state_name(j.state),
        "frames_total": j.frames_total, "frames_done": j.frames_done, "priority": j.priority,
        "error": j.error, "created_unix_ms": j.created_unix_ms, "updated_unix_ms": j.updated_unix_ms,
    })
}

/// A finished frame of `jobs show --json`: its attempts, cache and cut.
pub fn frame_json(f: &pb::FrameFinished) -> serde_json::Value {
    let mut value = json!({ "index": f.index, "failed_attempts": f.failed_attempts, "dataset_cache_hit": f.dataset_cache_hit });
    if let Some(c) = &f.cut {
        value["cut"] = json!({
            "nodes": c.nodes, "points_rendered": c.points_rendered, "points_total": c.points_total,
            "limited_by_budget": c.limited_by_budget, "gpu_hits": c.gpu_hits, "gpu_uploaded": c.gpu_uploaded,
            "gpu_evicted": c.gpu_evicted, "host_hits": c.host_hits, "nodes_read": c.nodes_read,
            "bytes_read": c.bytes_read, "read_ahead_bytes": c.read_ahead_bytes,
        });
    }
    value
}

/// One event of `jobs watch --json`: the job's state and progress after it, and the frames it
/// finished (the first event lists those finished before the watch began).
pub fn progress_json(job: &pb::Job, frames: &[&pb::FrameFinished]) -> serde_json::Value {
    json!({
        "event": "progress", "job": job.id, "state": state_name(job.state),
        "frames_done": job.frames_done, "frames_total": job.frames_total, "error": job.error,
        "frames": frames.iter().map(|f| frame_json(f)).collect::<Vec<_>>(),
    })
}

/// What `frames fetch --json` wrote: each frame's index and file.
pub fn fetched_json(job: &str, out: &Path, written: &[(u32, PathBuf)]) -> serde_json::Value {
    let frames: Vec<serde_json::Value> = written
        .iter()
        .map(|(index, path)| json!({ "index": index, "path": path.display().to_string() }))
        .collect();
    json!({ "job": job, "out": out.display().to_string(), "frames": frames })
}
