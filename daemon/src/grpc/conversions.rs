//! Conversions between the `pointfarm.v1` messages and the daemon's domain types, both ways,
//! as `From`/`TryFrom` where a conversion needs nothing but its input. Requests are validated
//! on the way in, and an invalid field is named in the error. The conversions of frame tasks
//! are public: the remote worker uses them on its side of the wire.
//!
//! The render request's camera paths and options convert in `request`; datasets in
//! `conversions/datasets.rs`, job submissions in `conversions/submission.rs`, and what
//! `info` and `DescribeDataset` report in `conversions/descriptions.rs`. The tests, one table
//! of cases per message, are in `conversions/tests.rs`.

use pointfarm_proto::v1 as pb;

use super::request::{
    build_unseen_message, camera_path_message, known_enum, render_options_message, render_request,
};
use crate::availability::JobAvailability;
use crate::capabilities::{checked_tags, AdapterKind, WorkerCapabilities, WorkerRequirements};
use crate::error::DaemonError;
use crate::lease::{FailureKind, FrameTask, HeartbeatAnswer};
use crate::lease_record::Lease;
use crate::limits::{truncated, MAX_WORKER_NAME_BYTES};
use crate::model::{FrameCut, FrameReport, Job, JobState, StageTiming};
use crate::state::{JobFilter, Page};
use crate::stores::{CopcServed, PreviewBytes, StoreAnswer};
use crate::worker_presence::ConnectedWorker;
pub use descriptions::{
    copc_description, dataset_description, file_description, point_attributes_message,
};
use pointfarm_render::cloud::WorldBounds;
use pointfarm_render::color::Stretch;
use pointfarm_render::copc::CopcDecoder;
use pointfarm_render::lod::copc_export::CopcExportReport;
use pointfarm_render::lod::{NodeKey, MAX_LEVEL};

pub(super) fn invalid(field: &str, message: impl Into<String>) -> DaemonError {
    DaemonError::invalid(field, message)
}

/// What an export of a dataset as COPC wrote, in `seconds`: the summary `ExportDataset`
/// sends first, and what `pointfarm export` reports of a file written here.
pub fn export_summary(report: &CopcExportReport, seconds: f64) -> pb::ExportSummary {
    pb::ExportSummary {
        points: report.points,
        nodes: report.nodes as u32,
        size_bytes: report.bytes,
        point_format: u32::from(report.point_format),
        scale: report.transform.scale.to_array().to_vec(),
        offset: report.transform.offset.to_array().to_vec(),
        min: report.min.to_array().to_vec(),
        max: report.max.to_array().to_vec(),
        seconds,
    }
}

/// A page of a listing as its items' messages and the token of the page after it.
pub(super) fn page_messages<T, M: for<'a> From<&'a T>>(page: Page<T>) -> (Vec<M>, String) {
    (page.items.iter().map(M::from).collect(), page.next_token)
}

/// Required tags are checked, sorted and kept once.
impl TryFrom<&pb::WorkerRequirements> for WorkerRequirements {
    type Error = DaemonError;

    fn try_from(r: &pb::WorkerRequirements) -> Result<Self, DaemonError> {
        let tags = checked_tags("requirements.tags", r.tags.iter().map(String::as_str))?;
        Ok(WorkerRequirements {
            tags: tags.into_iter().collect(),
            gpu: r.gpu,
        })
    }
}

impl From<&WorkerRequirements> for pb::WorkerRequirements {
    fn from(r: &WorkerRequirements) -> Self {
        pb::WorkerRequirements {
            tags: r.tags.clone(),
            gpu: r.gpu,
        }
    }
}

/// A worker's capabilities as it sends them with a lease request; tags are checked (a worker
/// with a bad tag is refused), none sent is a worker that says nothing of itself.
impl TryFrom<Option<&pb::WorkerCapabilities>> for WorkerCapabilities {
    type Error = DaemonError;

    fn try_from(c: Option<&pb::WorkerCapabilities>) -> Result<Self, DaemonError> {
        let Some(c) = c else {
            return Ok(WorkerCapabilities::default());
        };
        let adapter = match pb::AdapterKind::try_from(c.adapter_kind) {
            Ok(pb::AdapterKind::Hardware) => AdapterKind::Hardware,
            Ok(pb::AdapterKind::Software) => AdapterKind::Software,
            _ => AdapterKind::Unknown,
        };
        Ok(WorkerCapabilities {
            adapter,
            adapter_name: truncated(&c.adapter_name, MAX_WORKER_NAME_BYTES),
            device_memory_bytes: (c.device_memory_bytes > 0).then_some(c.device_memory_bytes),
            int64_atomics: c.shader_int64_atomics,
            max_storage_binding_bytes: c.max_storage_buffer_binding_size,
            max_buffer_bytes: c.max_buffer_size,
            max_frame_side: (c.max_frame_side > 0).then_some(c.max_frame_side),
            tags: checked_tags("capabilities.tags", c.tags.iter().map(String::as_str))?,
            video_encoders: crate::encodes::known_encoders(&c.video_encoders),
        })
    }
}

impl From<&WorkerCapabilities> for pb::WorkerCapabilities {
    fn from(c: &WorkerCapabilities) -> Self {
        pb::WorkerCapabilities {
            adapter_kind: match c.adapter {
                AdapterKind::Unknown => pb::AdapterKind::Unspecified,
                AdapterKind::Hardware => pb::AdapterKind::Hardware,
                AdapterKind::Software => pb::AdapterKind::Software,
            } as i32,
            adapter_name: c.adapter_name.clone(),
            device_memory_bytes: c.device_memory_bytes.unwrap_or(0),
            shader_int64_atomics: c.int64_atomics,
            max_storage_buffer_binding_size: c.max_storage_binding_bytes,
            max_buffer_size: c.max_buffer_bytes,
            max_frame_side: c.max_frame_side.unwrap_or(0),
            tags: c.tags.iter().cloned().collect(),
            video_encoders: c.video_encoders.clone(),
        }
    }
}

impl From<JobState> for pb::JobState {
    fn from(state: JobState) -> Self {
        match state {
            JobState::Queued => pb::JobState::Queued,
            JobState::Running => pb::JobState::Running,
            JobState::Succeeded => pb::JobState::Succeeded,
            JobState::Failed => pb::JobState::Failed,
            JobState::Cancelled => pb::JobState::Cancelled,
            JobState::Paused => pb::JobState::Paused,
        }
    }
}

/// What a listing of jobs asks for: a state (unspecified: every state) and labels.
pub(super) fn job_filter(r: &pb::ListJobsRequest) -> Result<JobFilter, DaemonError> {
    Ok(JobFilter {
        state: state_filter(r.state)?,
        labels: r.labels.clone().into_iter().collect(),
    })
}

/// The state a listing is filtered by; unspecified lists every state.
fn state_filter(state: i32) -> Result<Option<JobState>, DaemonError> {
    Ok(match known_enum("state", state)? {
        pb::JobState::Unspecified => None,
        pb::JobState::Queued => Some(JobState::Queued),
        pb::JobState::Running => Some(JobState::Running),
        pb::JobState::Succeeded => Some(JobState::Succeeded),
        pb::JobState::Failed => Some(JobState::Failed),
        pb::JobState::Cancelled => Some(JobState::Cancelled),
        pb::JobState::Paused => Some(JobState::Paused),
    })
}

/// The workers heard from, as `ListWorkers` answers.
pub fn workers_message(connected: &[ConnectedWorker]) -> pb::ListWorkersResponse {
    pb::ListWorkersResponse {
        workers: connected
            .iter()
            .map(|worker| pb::ConnectedWorker {
                worker_name: worker.name.clone(),
                embedded: worker.embedded,
                capabilities: Some(pb::WorkerCapabilities::from(&worker.capabilities)),
            })
            .collect(),
    }
}

/// A job as `GetJob` answers it: with its finished frames and why it waits.
pub fn job_with_frames_message(
    job: &Job,
    frames: &[FrameReport],
    availability: JobAvailability,
) -> pb::Job {
    let mut message = pb::Job::from(job);
    message.frames = frames.iter().map(pb::FrameFinished::from).collect();
    message.waiting_reason = availability.waiting.unwrap_or_default();
    message.refusals = availability
        .refusals
        .into_iter()
        .map(|(worker_name, reason)| pb::WorkerRefusal {
            worker_name,
            reason,
        })
        .collect();
    message
}

/// A job without its original request and frames; the services add those where they answer
/// with them.
impl From<&Job> for pb::Job {
    fn from(job: &Job) -> Self {
        pb::Job {
            id: job.id.clone(),
            request_id: job.spec.request_id.clone(),
            dataset_id: job.spec.dataset_id.clone(),
            state: pb::JobState::from(job.state) as i32,
            frames_total: job.frames_total,
            frames_done: job.frames_done,
            error: job.error.clone().unwrap_or_default(),
            priority: job.spec.priority,
            created_unix_ms: job.created_unix_ms,
            updated_unix_ms: job.updated_unix_ms,
            spec: None,
            frames: Vec::new(),
            requirements: (!job.spec.requirements.is_empty())
                .then(|| pb::WorkerRequirements::from(&job.spec.requirements)),
            blocklisted_workers: job
                .blocklist
                .iter()
                .map(|worker| pb::BlocklistedWorker {
                    worker_name: worker.clone(),
                    failed_frames: job.worker_failures.get(worker).copied().unwrap_or(0),
                })
                .collect(),
            waiting_reason: String::new(),
            refusals: Vec::new(),
            after_job_ids: job.spec.after.clone(),
            name: job.spec.name.clone(),
            labels: job.spec.labels.clone().into_iter().collect(),
            stage: job.stage().to_owned(),
            video_size_bytes: job.video_size_bytes().unwrap_or(0),
            outputs_uploaded: job.outputs.uploaded,
            output_errors: job.outputs.errors.clone(),
            outputs_pending: job.outputs.pending,
            preview_video: job.preview_video_state().name().to_owned(),
            build_unseen: build_unseen_message(job.spec.build_unseen) as i32,
        }
    }
}

impl From<&StageTiming> for pb::StageTiming {
    fn from(t: &StageTiming) -> Self {
        pb::StageTiming {
            stage: t.stage.clone(),
            ms: t.ms,
            gpu_clock: t.gpu_clock,
        }
    }
}

impl From<&pb::StageTiming> for StageTiming {
    fn from(t: &pb::StageTiming) -> Self {
        StageTiming {
            stage: t.stage.clone(),
            ms: t.ms,
            gpu_clock: t.gpu_clock,
        }
    }
}

pub fn timings_message(timings: &[StageTiming]) -> Vec<pb::StageTiming> {
    timings.iter().map(pb::StageTiming::from).collect()
}

pub fn stage_timings(timings: &[pb::StageTiming]) -> Vec<StageTiming> {
    timings.iter().map(StageTiming::from).collect()
}

impl From<&FrameReport> for pb::FrameFinished {
    fn from(report: &FrameReport) -> Self {
        pb::FrameFinished {
            index: report.index,
            timings: timings_message(&report.timings),
            dataset_cache_hit: report.dataset_cache_hit,
            failed_attempts: report.failed_attempts,
            cut: report.cut.as_ref().map(frame_cut_message),
            worker_name: report.worker.clone(),
            preview: report.preview.is_some(),
            completeness: report.preview.unwrap_or(0.0),
        }
    }
}

/// Both conversions of a message whose fields are a domain type's, one for one. They are
/// functions, not `From`, where both types are other crates'.
macro_rules! same_fields {
    ($to_message:ident, $from_message:ident: $domain:path => $message:path {
        $($field:ident),* $(,)?
    }) => {
        pub fn $to_message(v: &$domain) -> $message {
            $message { $($field: v.$field),* }
        }
        pub fn $from_message(v: &$message) -> $domain {
            $domain { $($field: v.$field),* }
        }
    };
}

same_fields!(frame_cut_message, frame_cut_of_message: FrameCut => pb::FrameCut {
    nodes,
    points_rendered,
    points_total,
    limited_by_budget,
    gpu_hits,
    gpu_uploaded,
    gpu_evicted,
    host_hits,
    nodes_read,
    bytes_read,
    read_ahead_bytes,
    object_requests,
    object_bytes,
    range_cache_bytes,
});

impl From<&Lease> for pb::Lease {
    fn from(lease: &Lease) -> Self {
        pb::Lease {
            lease_id: lease.id.clone(),
            job_id: lease.job_id.clone(),
            frame_index: lease.index,
            worker_name: lease.worker.clone(),
            expires_unix_ms: lease.expires_unix_ms,
            embedded: lease.embedded,
        }
    }
}

impl From<HeartbeatAnswer> for pb::HeartbeatResponse {
    fn from(answer: HeartbeatAnswer) -> Self {
        match answer {
            HeartbeatAnswer::Continue { expires_unix_ms } => pb::HeartbeatResponse {
                action: pb::LeaseAction::Continue as i32,
                reason: String::new(),
                lease_expires_unix_ms: expires_unix_ms,
            },
            HeartbeatAnswer::Stop(reason) => pb::HeartbeatResponse {
                action: pb::LeaseAction::Stop as i32,
                reason,
                lease_expires_unix_ms: 0,
            },
        }
    }
}

impl From<FailureKind> for pb::FailureKind {
    fn from(kind: FailureKind) -> Self {
        match kind {
            FailureKind::Transient => pb::FailureKind::Transient,
            FailureKind::Permanent => pb::FailureKind::Permanent,
        }
    }
}

/// A failed frame's kind; unset and unknown kinds (from older or newer workers) are tried
/// again.
pub(super) fn failure_kind(kind: i32) -> FailureKind {
    match pb::FailureKind::try_from(kind) {
        Ok(pb::FailureKind::Permanent) => FailureKind::Permanent,
        _ => FailureKind::Transient,
    }
}

/// A frame result's preview: its completeness when it is one, checked to lie in 0 to 1.
pub(super) fn preview_completeness(result: &pb::FrameResult) -> Result<Option<f64>, DaemonError> {
    if !result.preview {
        return Ok(None);
    }
    if !(0.0..=1.0).contains(&result.completeness) {
        return Err(invalid(
            "result.completeness",
            format!("{} is not within 0 to 1", result.completeness),
        ));
    }
    Ok(Some(result.completeness))
}

/// What a worker is told of a preview sample before its bytes.
pub(super) fn preview_sample_header(sample: &PreviewBytes) -> pb::PreviewSampleHeader {
    pb::PreviewSampleHeader {
        points_in_files: sample.points_in_files,
        bounds_min: Some(vec3_message(sample.framed.min)),
        bounds_max: Some(vec3_message(sample.framed.max)),
        sample_bytes: sample.cloud.len() as u64,
        version: sample.version,
    }
}

/// A preview sample's header as a worker receives it: the files' bounds, present and finite.
pub fn preview_sample_bounds(header: &pb::PreviewSampleHeader) -> Result<WorldBounds, DaemonError> {
    let (Some(min), Some(max)) = (&header.bounds_min, &header.bounds_max) else {
        return Err(invalid("header.bounds_min", "bounds are required"));
    };
    let (min, max) = (
        glam::DVec3::new(min.x, min.y, min.z),
        glam::DVec3::new(max.x, max.y, max.z),
    );
    if !(min.is_finite() && max.is_finite()) {
        return Err(invalid("header.bounds_min", "bounds must be finite"));
    }
    Ok(WorldBounds { min, max })
}

pub fn frame_task_message(task: &FrameTask) -> pb::FrameTask {
    pb::FrameTask {
        lease_id: task.lease.id.clone(),
        lease_expires_unix_ms: task.lease.expires_unix_ms,
        lease_timeout_ms: task.lease_timeout.as_millis().min(u32::MAX as u128) as u32,
        job_id: task.lease.job_id.clone(),
        frame_index: task.lease.index,
        dataset: Some(datasets::task_dataset_message(&task.dataset)),
        camera_path: Some(camera_path_message(
            &task.request.camera_path,
            &task.request.lens,
        )),
        width: task.request.width,
        height: task.request.height,
        render: Some(render_options_message(&task.request.render)),
        failed_attempts: task.failed_attempts,
        preview: task.preview().is_some(),
        preview_version: task.preview().unwrap_or(0),
    }
}

/// A task as the worker `worker` receives it, validated like a submission.
pub fn frame_task(message: &pb::FrameTask, worker: &str) -> Result<FrameTask, DaemonError> {
    let dataset = message
        .dataset
        .as_ref()
        .ok_or_else(|| invalid("dataset", "is required"))?;
    if message.lease_timeout_ms == 0 {
        return Err(invalid("lease_timeout_ms", "must be positive"));
    }
    Ok(FrameTask {
        lease: Lease {
            id: message.lease_id.clone(),
            job_id: message.job_id.clone(),
            index: message.frame_index,
            worker: worker.to_string(),
            embedded: false,
            expires_unix_ms: message.lease_expires_unix_ms,
            preview_version: message.preview.then_some(message.preview_version),
        },
        lease_timeout: std::time::Duration::from_millis(message.lease_timeout_ms as u64),
        dataset: datasets::task_dataset(dataset)?,
        request: render_request(
            message.width,
            message.height,
            message.camera_path.as_ref(),
            message.render.as_ref(),
        )?,
        failed_attempts: message.failed_attempts,
    })
}

/// A node key as a worker asks for it: a level the octree can have, and a cell of it.
pub(super) fn node_key(key: &pb::NodeKey) -> Result<NodeKey, DaemonError> {
    let level = u8::try_from(key.level)
        .ok()
        .filter(|&level| level <= MAX_LEVEL)
        .ok_or_else(|| {
            invalid(
                "nodes.level",
                format!("{} is deeper than {MAX_LEVEL}", key.level),
            )
        })?;
    let cells = 1u64 << level;
    if [key.x, key.y, key.z].iter().any(|&c| u64::from(c) >= cells) {
        return Err(invalid(
            "nodes",
            format!(
                "cell {}-{}-{} is outside level {level}",
                key.x, key.y, key.z
            ),
        ));
    }
    Ok(NodeKey::new(level, glam::UVec3::new(key.x, key.y, key.z)))
}

pub fn node_key_message(key: NodeKey) -> pb::NodeKey {
    pb::NodeKey {
        level: u32::from(key.level),
        x: key.x,
        y: key.y,
        z: key.z,
    }
}

impl From<&StoreAnswer> for pb::OpenDatasetStoreResponse {
    fn from(answer: &StoreAnswer) -> Self {
        use pb::open_dataset_store_response::State;
        let vec3 = vec3_message;
        match answer {
            StoreAnswer::NotNeeded { points } => Self {
                state: State::NotNeeded as i32,
                point_count: *points,
                ..Self::default()
            },
            StoreAnswer::Building { points } => Self {
                state: State::Building as i32,
                point_count: *points,
                ..Self::default()
            },
            StoreAnswer::Ready(store) => Self {
                state: State::Ready as i32,
                point_count: store.point_count(),
                bounds_min: Some(vec3(store.bounds().min)),
                bounds_max: Some(vec3(store.bounds().max)),
                hierarchy_bytes: store.hierarchy_record.len() as u64,
                build_ms: store.build_ms,
                copc: store.copc.as_ref().map(copc_chunks_message),
                elevation: elevation_message(store.elevation()),
            },
        }
    }
}

fn copc_chunks_message(copc: &CopcServed) -> pb::CopcChunks {
    let decoder = &copc.decoder;
    let [x, y, z] = decoder.scale();
    let [ox, oy, oz] = decoder.offset();
    pb::CopcChunks {
        file_name: copc.file_name.clone(),
        point_format: u32::from(decoder.point_format()),
        point_record_length: u32::from(decoder.record_len()),
        scale: Some(pb::Vec3 { x, y, z }),
        offset: Some(pb::Vec3 {
            x: ox,
            y: oy,
            z: oz,
        }),
        laszip_vlr: decoder.laszip_vlr().to_vec(),
        root_spacing: copc.root_spacing,
        elevation: elevation_message(copc.elevation),
        point_spacing: copc.point_spacing,
        weight_offset: decoder.weight_at().map(u32::from),
    }
}

/// An elevation range as it is sent.
fn elevation_message(elevation: Option<Stretch>) -> Option<pb::ElevationStretch> {
    elevation.map(|e| pb::ElevationStretch {
        low: e.low,
        high: e.high,
    })
}

/// The elevation range in `message` (its field `field`), checked to be one.
fn elevation_range(
    message: Option<&pb::ElevationStretch>,
    field: &str,
) -> Result<Option<Stretch>, DaemonError> {
    match message {
        Some(e) if e.low.is_finite() && e.high.is_finite() && e.low <= e.high => {
            Ok(Some(Stretch {
                low: e.low,
                high: e.high,
            }))
        }
        Some(_) => Err(invalid(field, "not a range")),
        None => Ok(None),
    }
}

/// The elevation range of a ready store's coarsest nodes as the daemon sends it, checked.
pub fn store_elevation(
    answer: &pb::OpenDatasetStoreResponse,
) -> Result<Option<Stretch>, DaemonError> {
    elevation_range(answer.elevation.as_ref(), "elevation")
}

/// What a worker is sent to decode a COPC file's chunks, checked as the file's header is.
pub fn copc_chunks(message: &pb::CopcChunks) -> Result<CopcServed, DaemonError> {
    let field = |name: &str| format!("copc.{name}");
    if message.file_name.is_empty() || message.file_name.len() > 4096 {
        return Err(invalid(&field("file_name"), "not a file name"));
    }
    let point_format = u8::try_from(message.point_format)
        .map_err(|_| invalid(&field("point_format"), "not a LAS point format"))?;
    let record_len = u16::try_from(message.point_record_length)
        .map_err(|_| invalid(&field("point_record_length"), "longer than a LAS record"))?;
    let axes = |v: &Option<pb::Vec3>, name: &str| {
        v.as_ref()
            .map(|v| [v.x, v.y, v.z])
            .ok_or_else(|| invalid(&field(name), "missing"))
    };
    let (scale, offset) = (
        axes(&message.scale, "scale")?,
        axes(&message.offset, "offset")?,
    );
    if !(message.root_spacing.is_finite() && message.root_spacing > 0.0) {
        return Err(invalid(&field("root_spacing"), "not a positive size"));
    }
    let elevation = elevation_range(message.elevation.as_ref(), &field("elevation"))?;
    if message
        .point_spacing
        .is_some_and(|s| !(s.is_finite() && s > 0.0))
    {
        return Err(invalid(&field("point_spacing"), "not a positive size"));
    }
    let weight_at = message
        .weight_offset
        .map(|at| {
            u16::try_from(at).map_err(|_| invalid(&field("weight_offset"), "beyond a LAS record"))
        })
        .transpose()?;
    let decoder = CopcDecoder::from_parts(
        std::path::Path::new(&message.file_name),
        point_format,
        record_len,
        scale,
        offset,
        &message.laszip_vlr,
        weight_at,
    )
    .map_err(|e| invalid(&field("laszip_vlr"), e.to_string()))?;
    Ok(CopcServed {
        file_name: message.file_name.clone(),
        decoder,
        root_spacing: message.root_spacing,
        elevation,
        point_spacing: message.point_spacing,
    })
}

fn vec3_message(v: glam::DVec3) -> pb::Vec3 {
    pb::Vec3 {
        x: v.x,
        y: v.y,
        z: v.z,
    }
}

fn bounds_message(bounds: &WorldBounds) -> pb::Bounds {
    pb::Bounds {
        min: Some(vec3_message(bounds.min)),
        max: Some(vec3_message(bounds.max)),
    }
}

mod datasets;
pub(super) use datasets::dataset_with_publication;
mod descriptions;
mod submission;
#[cfg(test)]
mod tests;
