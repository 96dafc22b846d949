//! The `pointfarm.v1` gRPC services: validate and convert requests, call [`Daemon`], convert
//! results. No domain logic lives here. The conversions of frame tasks are public: the remote
//! worker (`remote_worker`) uses them on its side of the wire.

use std::pin::Pin;
use std::sync::Arc;

use pointfarm_proto::v1 as pb;
use pointfarm_proto::v1::dataset_service_server::DatasetService;
use pointfarm_proto::v1::job_service_server::JobService;
use pointfarm_proto::v1::worker_service_server::WorkerService;
use pointfarm_render::raster::{
    FillSettings, Shading as RendererShading, MAX_FILL_KERNEL, MAX_PINTUS_LEVELS, MIN_FILL_KERNEL,
};
use sha2::{Digest, Sha256};
use tokio::io::AsyncWriteExt;
use tokio_stream::wrappers::ReceiverStream;
use tokio_stream::Stream;
use tonic::{Request, Response, Status, Streaming};

use crate::error::DaemonError;
use crate::lease::{FrameOutcome, FrameTask, HeartbeatAnswer, Lease, TaskDataset};
use crate::model::{
    CameraPath, ColorMode, Dataset, Fill, FrameReport, FrameState, Interpolation, Job, JobSpec,
    JobState, Keyframe, Point3, Quality, RenderOptions, Shading, StageTiming, Turntable,
};
use crate::service::{hex, Daemon};

/// Frames are streamed in chunks of this many bytes (well under gRPC's default 4 MiB limit).
const FRAME_CHUNK_BYTES: usize = 1 << 20;
/// Point size limit, as the renderer's.
const MAX_POINT_SIZE: u32 = pointfarm_render::raster::MAX_POINT_SIZE;

impl From<DaemonError> for Status {
    fn from(e: DaemonError) -> Self {
        match e {
            DaemonError::InvalidArgument { .. } => Status::invalid_argument(e.to_string()),
            DaemonError::NotFound(_) => Status::not_found(e.to_string()),
            DaemonError::FailedPrecondition(_) => Status::failed_precondition(e.to_string()),
            DaemonError::ResourceExhausted(_) => Status::resource_exhausted(e.to_string()),
            DaemonError::Internal(_) => Status::internal(e.to_string()),
        }
    }
}

type ResponseStream<T> = Pin<Box<dyn Stream<Item = Result<T, Status>> + Send>>;

/// Both services over one daemon.
#[derive(Clone)]
pub struct Api {
    daemon: Arc<Daemon>,
}

impl Api {
    pub fn new(daemon: Arc<Daemon>) -> Self {
        Self { daemon }
    }
}

// ---------------------------------------------------------------------------- conversions

fn invalid(field: &str, message: impl Into<String>) -> DaemonError {
    DaemonError::invalid(field, message)
}

fn point(field: &str, v: Option<&pb::Vec3>) -> Result<Point3, DaemonError> {
    let v = v.ok_or_else(|| invalid(field, "is required"))?;
    if !(v.x.is_finite() && v.y.is_finite() && v.z.is_finite()) {
        return Err(invalid(field, "must be finite (no NaN or infinity)"));
    }
    Ok(Point3 {
        x: v.x,
        y: v.y,
        z: v.z,
    })
}

fn finite_in<T: Into<f64> + Copy + std::fmt::Display>(
    field: &str,
    value: T,
    range: std::ops::RangeInclusive<f64>,
    what: &str,
) -> Result<T, DaemonError> {
    let wide: f64 = value.into();
    if wide.is_finite() && range.contains(&wide) {
        Ok(value)
    } else {
        Err(invalid(field, format!("must be {what}, got {value}")))
    }
}

fn fov(field: &str, value: f64) -> Result<f64, DaemonError> {
    if value.is_finite() && value > 0.0 && value < 180.0 {
        Ok(value)
    } else {
        Err(invalid(
            field,
            format!("must lie in (0, 180) degrees, got {value}"),
        ))
    }
}

pub fn camera_path(path: Option<&pb::CameraPath>) -> Result<CameraPath, DaemonError> {
    let path = path
        .and_then(|p| p.path.as_ref())
        .ok_or_else(|| invalid("camera_path", "is required (turntable or keyframes)"))?;
    match path {
        pb::camera_path::Path::Turntable(t) => {
            let f = |name: &str| format!("camera_path.turntable.{name}");
            if t.frames == 0 {
                return Err(invalid(&f("frames"), "must be at least 1"));
            }
            let center = t
                .center
                .as_ref()
                .map(|c| point(&f("center"), Some(c)))
                .transpose()?;
            let radius = t
                .radius
                .map(|r| {
                    if r.is_finite() && r > 0.0 {
                        Ok(r)
                    } else {
                        Err(invalid(&f("radius"), format!("must be positive, got {r}")))
                    }
                })
                .transpose()?;
            Ok(CameraPath::Turntable(Turntable {
                frames: t.frames,
                center,
                radius,
                elevation_deg: finite_in(
                    &f("elevation_deg"),
                    t.elevation_deg.unwrap_or(30.0),
                    -89.0..=89.0,
                    "between -89 and 89 degrees",
                )?,
                degrees: finite_in(
                    &f("degrees"),
                    t.degrees.unwrap_or(360.0),
                    -36000.0..=36000.0,
                    "a finite angle",
                )?,
                fov_y_deg: fov(&f("fov_y_deg"), t.fov_y_deg.unwrap_or(50.0))?,
            }))
        }
        pb::camera_path::Path::Keyframes(k) => {
            if k.frames == 0 {
                return Err(invalid(
                    "camera_path.keyframes.frames",
                    "must be at least 1",
                ));
            }
            if k.keyframes.len() < 2 {
                return Err(invalid(
                    "camera_path.keyframes.keyframes",
                    "needs at least 2 keyframes",
                ));
            }
            let keyframes = k
                .keyframes
                .iter()
                .enumerate()
                .map(|(i, key)| {
                    let f = |name: &str| format!("camera_path.keyframes.keyframes[{i}].{name}");
                    let position = point(&f("position"), key.position.as_ref())?;
                    let target = point(&f("target"), key.target.as_ref())?;
                    if position == target {
                        return Err(invalid(&f("target"), "must differ from the position"));
                    }
                    let up = match key.up.as_ref() {
                        Some(up) => point(&f("up"), Some(up))?,
                        None => Point3 {
                            x: 0.0,
                            y: 0.0,
                            z: 1.0,
                        },
                    };
                    Ok(Keyframe {
                        position,
                        target,
                        up,
                        fov_y_deg: fov(&f("fov_y_deg"), key.fov_y_deg)?,
                    })
                })
                .collect::<Result<Vec<_>, _>>()?;
            let interpolation = match pb::Interpolation::try_from(k.interpolation) {
                Ok(pb::Interpolation::Spline) => Interpolation::Spline,
                Ok(pb::Interpolation::Linear | pb::Interpolation::Unspecified) => {
                    Interpolation::Linear
                }
                Err(_) => {
                    return Err(invalid(
                        "camera_path.keyframes.interpolation",
                        format!("unknown value {}", k.interpolation),
                    ))
                }
            };
            Ok(CameraPath::Keyframes {
                keyframes,
                frames: k.frames,
                interpolation,
            })
        }
    }
}

fn rgba(color: &pb::Color) -> [u8; 4] {
    color.rgba.to_be_bytes()
}

pub fn render_options(options: Option<&pb::RenderOptions>) -> Result<RenderOptions, DaemonError> {
    let default = pb::RenderOptions::default();
    let o = options.unwrap_or(&default);
    let point_size = if o.point_size == 0 { 1 } else { o.point_size };
    if point_size > MAX_POINT_SIZE {
        return Err(invalid(
            "render.point_size",
            format!("must be 1 to {MAX_POINT_SIZE}"),
        ));
    }
    let quality = match pb::Quality::try_from(o.quality) {
        Ok(pb::Quality::High) => {
            let band = finite_in(
                "render.depth_band",
                o.depth_band.unwrap_or(0.01),
                0.0..=1.0,
                "0 to 1",
            )?;
            Quality::High { depth_band: band }
        }
        Ok(_) => Quality::Basic,
        Err(_) => {
            return Err(invalid(
                "render.quality",
                format!("unknown value {}", o.quality),
            ))
        }
    };
    let shading = match pb::Shading::try_from(o.shading) {
        Ok(pb::Shading::Edl) => {
            let strength = o
                .edl_strength
                .unwrap_or(RendererShading::DEFAULT_EDL_STRENGTH);
            let radius = o.edl_radius.unwrap_or(RendererShading::DEFAULT_EDL_RADIUS);
            let strength = finite_in("render.edl_strength", strength, 0.0..=100.0, "0 to 100")?;
            let radius = finite_in("render.edl_radius", radius, 0.5..=16.0, "0.5 to 16 pixels")?;
            Shading::Edl { strength, radius }
        }
        Ok(pb::Shading::Pintus) => {
            let levels = o
                .pintus_levels
                .unwrap_or(RendererShading::DEFAULT_PINTUS_LEVELS);
            let exponent = o
                .pintus_exponent
                .unwrap_or(RendererShading::DEFAULT_PINTUS_EXPONENT);
            if !(1..=MAX_PINTUS_LEVELS).contains(&levels) {
                return Err(invalid(
                    "render.pintus_levels",
                    format!("must be 1 to {MAX_PINTUS_LEVELS}, got {levels}"),
                ));
            }
            let exponent = finite_in("render.pintus_exponent", exponent, 0.0..=4.0, "0 to 4")?;
            Shading::Pintus { levels, exponent }
        }
        Ok(_) => Shading::None,
        Err(_) => {
            return Err(invalid(
                "render.shading",
                format!("unknown value {}", o.shading),
            ))
        }
    };
    let color_mode = match pb::ColorMode::try_from(o.color_mode) {
        Ok(pb::ColorMode::Unspecified | pb::ColorMode::Rgb) => ColorMode::Rgb,
        Ok(pb::ColorMode::Intensity) => ColorMode::Intensity,
        Ok(pb::ColorMode::Elevation) => ColorMode::Elevation,
        Ok(pb::ColorMode::Classification) => ColorMode::Classification,
        Ok(pb::ColorMode::ReturnNumber) => ColorMode::ReturnNumber,
        Ok(pb::ColorMode::Fixed) => {
            let [r, g, b, _] = o.fixed_color.as_ref().map(rgba).ok_or_else(|| {
                invalid("render.fixed_color", "is required with COLOR_MODE_FIXED")
            })?;
            ColorMode::Fixed([r, g, b])
        }
        Err(_) => {
            return Err(invalid(
                "render.color_mode",
                format!("unknown value {}", o.color_mode),
            ))
        }
    };
    let background = o.background.as_ref().map(rgba).unwrap_or([24, 24, 28, 255]);
    let fill = match &o.fill {
        None => None,
        Some(f) => {
            let kernel = if f.kernel == 0 {
                FillSettings::DEFAULT_KERNEL
            } else {
                f.kernel
            };
            if !(MIN_FILL_KERNEL..=MAX_FILL_KERNEL).contains(&kernel) || kernel.is_multiple_of(2) {
                return Err(invalid(
                    "render.fill.kernel",
                    format!(
                        "must be an odd number of pixels from {MIN_FILL_KERNEL} to \
                         {MAX_FILL_KERNEL}, got {kernel}"
                    ),
                ));
            }
            Some(Fill { kernel })
        }
    };
    Ok(RenderOptions {
        point_size,
        quality,
        shading,
        color_mode,
        background,
        fill,
    })
}

/// Validates a submission; limits that depend on the server are checked by the daemon.
pub fn job_spec(r: &pb::SubmitJobRequest) -> Result<JobSpec, DaemonError> {
    if r.dataset_id.is_empty() {
        return Err(invalid("dataset_id", "is required"));
    }
    if r.width == 0 {
        return Err(invalid("width", "must be at least 1"));
    }
    if r.height == 0 {
        return Err(invalid("height", "must be at least 1"));
    }
    Ok(JobSpec {
        request_id: r.request_id.clone(),
        dataset_id: r.dataset_id.clone(),
        camera_path: camera_path(r.camera_path.as_ref())?,
        width: r.width,
        height: r.height,
        render: render_options(r.render.as_ref())?,
        priority: r.priority,
    })
}

fn job_state(state: JobState) -> pb::JobState {
    match state {
        JobState::Queued => pb::JobState::Queued,
        JobState::Running => pb::JobState::Running,
        JobState::Succeeded => pb::JobState::Succeeded,
        JobState::Failed => pb::JobState::Failed,
        JobState::Cancelled => pb::JobState::Cancelled,
    }
}

fn state_filter(state: i32) -> Result<Option<JobState>, DaemonError> {
    Ok(match pb::JobState::try_from(state) {
        Ok(pb::JobState::Unspecified) => None,
        Ok(pb::JobState::Queued) => Some(JobState::Queued),
        Ok(pb::JobState::Running) => Some(JobState::Running),
        Ok(pb::JobState::Succeeded) => Some(JobState::Succeeded),
        Ok(pb::JobState::Failed) => Some(JobState::Failed),
        Ok(pb::JobState::Cancelled) => Some(JobState::Cancelled),
        Err(_) => return Err(invalid("state", format!("unknown value {state}"))),
    })
}

fn job_message(job: &Job, original: Option<pb::SubmitJobRequest>) -> pb::Job {
    pb::Job {
        id: job.id.clone(),
        request_id: job.spec.request_id.clone(),
        dataset_id: job.spec.dataset_id.clone(),
        state: job_state(job.state) as i32,
        frames_total: job.frames_total,
        frames_done: job.frames_done,
        error: job.error.clone().unwrap_or_default(),
        priority: job.spec.priority,
        created_unix_ms: job.created_unix_ms,
        updated_unix_ms: job.updated_unix_ms,
        spec: original,
        frames: Vec::new(),
    }
}

fn dataset_message(d: &Dataset) -> pb::Dataset {
    pb::Dataset {
        id: d.id.clone(),
        name: d.name.clone(),
        size_bytes: d.size_bytes,
        sha256: d.sha256.clone(),
        path: d.path.display().to_string(),
        created_unix_ms: d.created_unix_ms,
    }
}

pub fn timings_message(timings: &[StageTiming]) -> Vec<pb::StageTiming> {
    timings
        .iter()
        .map(|t| pb::StageTiming {
            stage: t.stage.clone(),
            ms: t.ms,
            gpu_clock: t.gpu_clock,
        })
        .collect()
}

fn frame_message(report: &FrameReport) -> pb::FrameFinished {
    pb::FrameFinished {
        index: report.index,
        timings: timings_message(&report.timings),
        dataset_cache_hit: report.dataset_cache_hit,
        failed_attempts: report.failed_attempts,
    }
}

/// Runs blocking store work off the async executor.
async fn blocking<T: Send + 'static>(
    f: impl FnOnce() -> Result<T, DaemonError> + Send + 'static,
) -> Result<T, Status> {
    tokio::task::spawn_blocking(f)
        .await
        .map_err(|e| Status::internal(e.to_string()))?
        .map_err(Status::from)
}

// ---------------------------------------------------------------------------- datasets

#[tonic::async_trait]
impl DatasetService for Api {
    async fn register_dataset(
        &self,
        request: Request<pb::RegisterDatasetRequest>,
    ) -> Result<Response<pb::Dataset>, Status> {
        let r = request.into_inner();
        let daemon = self.daemon.clone();
        let dataset = blocking(move || daemon.register_dataset(&r.path, &r.name)).await?;
        Ok(Response::new(dataset_message(&dataset)))
    }

    async fn upload_dataset(
        &self,
        request: Request<Streaming<pb::UploadDatasetRequest>>,
    ) -> Result<Response<pb::Dataset>, Status> {
        let mut stream = request.into_inner();
        let header = match stream.message().await? {
            Some(pb::UploadDatasetRequest {
                part: Some(pb::upload_dataset_request::Part::Header(h)),
            }) => h,
            _ => {
                return Err(invalid("header", "the first message must be the upload header").into())
            }
        };
        let limit = self.daemon.config.max_upload_bytes;
        if header.size_bytes > limit {
            return Err(DaemonError::ResourceExhausted(format!(
                "upload of {} bytes exceeds the limit of {limit} bytes",
                header.size_bytes
            ))
            .into());
        }
        if header.sha256.len() != 64 || !header.sha256.bytes().all(|b| b.is_ascii_hexdigit()) {
            return Err(invalid("header.sha256", "must be 64 hex digits").into());
        }
        // Already known content: no need to keep the bytes.
        let known_id = crate::service::dataset_id(&header.sha256.to_ascii_lowercase());
        let temp = self.daemon.upload_path();
        let mut file = tokio::fs::File::create(&temp)
            .await
            .map_err(|e| Status::internal(e.to_string()))?;
        let mut hasher = Sha256::new();
        let mut received: u64 = 0;
        let result: Result<(), Status> = async {
            while let Some(message) = stream.message().await? {
                let Some(pb::upload_dataset_request::Part::Data(data)) = message.part else {
                    return Err(invalid("data", "only the first message may be a header").into());
                };
                received += data.len() as u64;
                if received > limit.min(header.size_bytes) {
                    return Err(DaemonError::ResourceExhausted(format!(
                        "upload exceeds its declared size of {} bytes",
                        header.size_bytes
                    ))
                    .into());
                }
                hasher.update(&data);
                file.write_all(&data)
                    .await
                    .map_err(|e| Status::internal(e.to_string()))?;
            }
            file.flush()
                .await
                .map_err(|e| Status::internal(e.to_string()))?;
            let sha = hex(&hasher.finalize());
            if received != header.size_bytes {
                return Err(invalid(
                    "header.size_bytes",
                    format!("declared {} bytes, received {received}", header.size_bytes),
                )
                .into());
            }
            if sha != header.sha256.to_ascii_lowercase() {
                return Err(invalid(
                    "header.sha256",
                    format!("does not match the data (got {sha})"),
                )
                .into());
            }
            Ok(())
        }
        .await;
        if let Err(status) = result {
            let _ = tokio::fs::remove_file(&temp).await;
            return Err(status);
        }
        let daemon = self.daemon.clone();
        if let Ok(existing) = daemon.dataset(&known_id) {
            let _ = tokio::fs::remove_file(&temp).await;
            return Ok(Response::new(dataset_message(&existing)));
        }
        let sha = header.sha256.to_ascii_lowercase();
        let dataset =
            blocking(move || daemon.finish_upload(&temp, &header.name, sha, received)).await?;
        Ok(Response::new(dataset_message(&dataset)))
    }

    async fn get_dataset(
        &self,
        request: Request<pb::GetDatasetRequest>,
    ) -> Result<Response<pb::Dataset>, Status> {
        Ok(Response::new(dataset_message(
            &self.daemon.dataset(&request.into_inner().id)?,
        )))
    }

    async fn list_datasets(
        &self,
        request: Request<pb::ListDatasetsRequest>,
    ) -> Result<Response<pb::ListDatasetsResponse>, Status> {
        let r = request.into_inner();
        let page = self.daemon.list_datasets(r.page_size, &r.page_token)?;
        Ok(Response::new(pb::ListDatasetsResponse {
            datasets: page.items.iter().map(dataset_message).collect(),
            next_page_token: page.next_token,
        }))
    }

    async fn delete_dataset(
        &self,
        request: Request<pb::DeleteDatasetRequest>,
    ) -> Result<Response<pb::DeleteDatasetResponse>, Status> {
        self.daemon.delete_dataset(&request.into_inner().id)?;
        Ok(Response::new(pb::DeleteDatasetResponse {}))
    }
}

// ---------------------------------------------------------------------------- jobs

#[tonic::async_trait]
impl JobService for Api {
    async fn submit_job(
        &self,
        request: Request<pb::SubmitJobRequest>,
    ) -> Result<Response<pb::Job>, Status> {
        let r = request.into_inner();
        let spec = job_spec(&r)?;
        let daemon = self.daemon.clone();
        let job = blocking(move || daemon.submit_job(spec)).await?;
        Ok(Response::new(job_message(&job, Some(r))))
    }

    async fn get_job(
        &self,
        request: Request<pb::GetJobRequest>,
    ) -> Result<Response<pb::Job>, Status> {
        let id = request.into_inner().id;
        let daemon = self.daemon.clone();
        let (job, frames) = blocking(move || daemon.job_with_frames(&id)).await?;
        let mut message = job_message(&job, None);
        message.frames = frames.iter().map(frame_message).collect();
        Ok(Response::new(message))
    }

    async fn list_jobs(
        &self,
        request: Request<pb::ListJobsRequest>,
    ) -> Result<Response<pb::ListJobsResponse>, Status> {
        let r = request.into_inner();
        let page = self
            .daemon
            .list_jobs(state_filter(r.state)?, r.page_size, &r.page_token)?;
        Ok(Response::new(pb::ListJobsResponse {
            jobs: page.items.iter().map(|j| job_message(j, None)).collect(),
            next_page_token: page.next_token,
        }))
    }

    async fn cancel_job(
        &self,
        request: Request<pb::CancelJobRequest>,
    ) -> Result<Response<pb::Job>, Status> {
        let daemon = self.daemon.clone();
        let id = request.into_inner().id;
        let job = blocking(move || daemon.cancel_job(&id)).await?;
        Ok(Response::new(job_message(&job, None)))
    }

    type WatchJobStream = ResponseStream<pb::JobEvent>;

    async fn watch_job(
        &self,
        request: Request<pb::WatchJobRequest>,
    ) -> Result<Response<Self::WatchJobStream>, Status> {
        let id = request.into_inner().id;
        // Subscribe before reading the state, so no event falls between the two.
        let mut events = self.daemon.subscribe();
        let daemon = self.daemon.clone();
        let watched = id.clone();
        let (job, finished) = blocking(move || {
            let job = daemon.job(&watched)?;
            let finished = daemon.store.frame_reports(&watched)?;
            Ok((job, finished))
        })
        .await?;
        let (sender, receiver) = tokio::sync::mpsc::channel(64);
        tokio::spawn(async move {
            let ended = job.state.is_terminal();
            // The first event carries the frames finished so far: a watcher that comes late
            // (or back) still learns of every frame, each once.
            let reported: std::collections::HashSet<u32> =
                finished.iter().map(|frame| frame.index).collect();
            let mut snapshot = job_message(&job, None);
            snapshot.frames = finished.iter().map(frame_message).collect();
            if sender
                .send(Ok(pb::JobEvent {
                    job: Some(snapshot),
                    frame: None,
                }))
                .await
                .is_err()
                || ended
            {
                return;
            }
            loop {
                match events.recv().await {
                    Ok(event) if event.job.id == id => {
                        let ended = event.job.state.is_terminal();
                        let frame = event
                            .frame
                            .as_ref()
                            .filter(|frame| !reported.contains(&frame.index))
                            .map(frame_message);
                        if sender
                            .send(Ok(pb::JobEvent {
                                job: Some(job_message(&event.job, None)),
                                frame,
                            }))
                            .await
                            .is_err()
                            || ended
                        {
                            return;
                        }
                    }
                    Ok(_) => {}
                    Err(tokio::sync::broadcast::error::RecvError::Lagged(missed)) => {
                        tracing::warn!(job = %id, missed, "a watcher fell behind; events were skipped");
                    }
                    Err(tokio::sync::broadcast::error::RecvError::Closed) => return,
                }
            }
        });
        Ok(Response::new(Box::pin(ReceiverStream::new(receiver))))
    }

    type FetchFramesStream = ResponseStream<pb::FrameChunk>;

    async fn fetch_frames(
        &self,
        request: Request<pb::FetchFramesRequest>,
    ) -> Result<Response<Self::FetchFramesStream>, Status> {
        let r = request.into_inner();
        let job = self.daemon.job(&r.job_id)?;
        if r.from_index > job.frames_total {
            return Err(invalid(
                "from_index",
                format!("job {} has {} frames", job.id, job.frames_total),
            )
            .into());
        }
        let daemon = self.daemon.clone();
        let (sender, receiver) = tokio::sync::mpsc::channel(4);
        tokio::spawn(async move {
            for index in r.from_index..job.frames_total {
                let done = matches!(
                    daemon.store.frame(&job.id, index),
                    Ok(Some(FrameState::Done { .. }))
                );
                if !done {
                    continue;
                }
                let bytes = match tokio::fs::read(daemon.config.frame_path(&job.id, index)).await {
                    Ok(bytes) => bytes,
                    Err(e) => {
                        let _ = sender
                            .send(Err(Status::internal(format!("frame {index}: {e}"))))
                            .await;
                        return;
                    }
                };
                let chunks: Vec<&[u8]> = bytes.chunks(FRAME_CHUNK_BYTES).collect();
                for (i, chunk) in chunks.iter().enumerate() {
                    let message = pb::FrameChunk {
                        index,
                        png: chunk.to_vec(),
                        last: i + 1 == chunks.len(),
                    };
                    if sender.send(Ok(message)).await.is_err() {
                        return;
                    }
                }
            }
        });
        Ok(Response::new(Box::pin(ReceiverStream::new(receiver))))
    }
}

// ---------------------------------------------------------------------------- workers

/// Longest wait of a `LeaseFrame` long poll.
const MAX_LEASE_WAIT_MS: u32 = 30_000;
/// Longest worker name kept.
const MAX_WORKER_NAME: usize = 128;

fn vec3(p: &Point3) -> pb::Vec3 {
    pb::Vec3 {
        x: p.x,
        y: p.y,
        z: p.z,
    }
}

fn color(rgba: [u8; 4]) -> pb::Color {
    pb::Color {
        rgba: u32::from_be_bytes(rgba),
    }
}

/// The inverse of [`camera_path`].
pub fn camera_path_message(path: &CameraPath) -> pb::CameraPath {
    let path = match path {
        CameraPath::Turntable(t) => pb::camera_path::Path::Turntable(pb::Turntable {
            frames: t.frames,
            center: t.center.as_ref().map(vec3),
            radius: t.radius,
            elevation_deg: Some(t.elevation_deg),
            degrees: Some(t.degrees),
            fov_y_deg: Some(t.fov_y_deg),
        }),
        CameraPath::Keyframes {
            keyframes,
            frames,
            interpolation,
        } => pb::camera_path::Path::Keyframes(pb::KeyframePath {
            keyframes: keyframes
                .iter()
                .map(|k| pb::Keyframe {
                    position: Some(vec3(&k.position)),
                    target: Some(vec3(&k.target)),
                    up: Some(vec3(&k.up)),
                    fov_y_deg: k.fov_y_deg,
                })
                .collect(),
            frames: *frames,
            interpolation: match interpolation {
                Interpolation::Linear => pb::Interpolation::Linear,
                Interpolation::Spline => pb::Interpolation::Spline,
            } as i32,
        }),
    };
    pb::CameraPath { path: Some(path) }
}

/// The inverse of [`render_options`].
pub fn render_options_message(options: &RenderOptions) -> pb::RenderOptions {
    // Destructured so that a new option cannot be forgotten here.
    let RenderOptions {
        point_size,
        quality,
        shading,
        color_mode,
        background,
        fill,
    } = options;
    let mut message = pb::RenderOptions {
        point_size: *point_size,
        background: Some(color(*background)),
        fill: fill.map(|Fill { kernel }| pb::FillOptions { kernel }),
        ..Default::default()
    };
    match *quality {
        Quality::Basic => message.quality = pb::Quality::Basic as i32,
        Quality::High { depth_band } => {
            message.quality = pb::Quality::High as i32;
            message.depth_band = Some(depth_band);
        }
    }
    match *shading {
        Shading::None => message.shading = pb::Shading::None as i32,
        Shading::Edl { strength, radius } => {
            message.shading = pb::Shading::Edl as i32;
            message.edl_strength = Some(strength);
            message.edl_radius = Some(radius);
        }
        Shading::Pintus { levels, exponent } => {
            message.shading = pb::Shading::Pintus as i32;
            message.pintus_levels = Some(levels);
            message.pintus_exponent = Some(exponent);
        }
    }
    message.color_mode = match *color_mode {
        ColorMode::Rgb => pb::ColorMode::Rgb,
        ColorMode::Intensity => pb::ColorMode::Intensity,
        ColorMode::Elevation => pb::ColorMode::Elevation,
        ColorMode::Classification => pb::ColorMode::Classification,
        ColorMode::ReturnNumber => pb::ColorMode::ReturnNumber,
        ColorMode::Fixed([r, g, b]) => {
            message.fixed_color = Some(color([r, g, b, 255]));
            pb::ColorMode::Fixed
        }
    } as i32;
    message
}

pub fn frame_task_message(task: &FrameTask) -> pb::FrameTask {
    pb::FrameTask {
        lease_id: task.lease.id.clone(),
        lease_expires_unix_ms: task.lease.expires_unix_ms,
        lease_timeout_ms: task.lease_timeout.as_millis().min(u32::MAX as u128) as u32,
        job_id: task.lease.job_id.clone(),
        frame_index: task.lease.index,
        dataset: Some(pb::TaskDataset {
            id: task.dataset.id.clone(),
            sha256: task.dataset.sha256.clone(),
            size_bytes: task.dataset.size_bytes,
        }),
        camera_path: Some(camera_path_message(&task.camera_path)),
        width: task.width,
        height: task.height,
        render: Some(render_options_message(&task.render)),
        failed_attempts: task.failed_attempts,
    }
}

/// A task as the worker receives it, validated like a submission.
pub fn frame_task(message: &pb::FrameTask, worker: &str) -> Result<FrameTask, DaemonError> {
    let dataset = message
        .dataset
        .as_ref()
        .ok_or_else(|| invalid("dataset", "is required"))?;
    if message.width == 0 || message.height == 0 {
        return Err(invalid("width", "the frame size must be at least 1x1"));
    }
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
        },
        lease_timeout: std::time::Duration::from_millis(message.lease_timeout_ms as u64),
        dataset: TaskDataset {
            id: dataset.id.clone(),
            sha256: dataset.sha256.clone(),
            size_bytes: dataset.size_bytes,
        },
        camera_path: camera_path(message.camera_path.as_ref())?,
        width: message.width,
        height: message.height,
        render: render_options(message.render.as_ref())?,
        failed_attempts: message.failed_attempts,
    })
}

pub fn stage_timings(timings: &[pb::StageTiming]) -> Vec<StageTiming> {
    timings
        .iter()
        .map(|t| StageTiming {
            stage: t.stage.clone(),
            ms: t.ms,
            gpu_clock: t.gpu_clock,
        })
        .collect()
}

fn lease_message(lease: &Lease) -> pb::Lease {
    pb::Lease {
        lease_id: lease.id.clone(),
        job_id: lease.job_id.clone(),
        frame_index: lease.index,
        worker_name: lease.worker.clone(),
        expires_unix_ms: lease.expires_unix_ms,
        embedded: lease.embedded,
    }
}

/// Largest PNG accepted for a frame: the raw RGBA size and room for PNG's overhead.
fn max_png_bytes(width: u32, height: u32) -> u64 {
    width as u64 * height as u64 * 5 + (1 << 20)
}

/// Where a lease request keeps the lease it is about to answer with, so that a request
/// abandoned meanwhile (the worker hung up or stopped while long-polling) gives the frame back
/// instead of leaving it leased until the lease expires and counting a failed attempt.
#[derive(Default)]
struct LeaseSlot(std::sync::Mutex<(bool, Option<String>)>);

impl LeaseSlot {
    /// Keeps `task`'s lease for the answer, or releases it at once if the request is gone.
    fn keep(&self, daemon: &Daemon, task: FrameTask) -> Option<FrameTask> {
        let Ok(mut slot) = self.0.lock() else {
            return Some(task);
        };
        if slot.0 {
            drop(slot);
            let _ = daemon.release_frame(&task.lease.id);
            return None;
        }
        slot.1 = Some(task.lease.id.clone());
        Some(task)
    }
}

/// Releases the slot's lease when the request future is dropped before answering.
struct LeaseGuard {
    daemon: Arc<Daemon>,
    slot: Arc<LeaseSlot>,
    armed: bool,
}

impl LeaseGuard {
    fn new(daemon: Arc<Daemon>) -> Self {
        Self {
            daemon,
            slot: Arc::default(),
            armed: true,
        }
    }

    fn disarm(mut self) {
        self.armed = false;
    }
}

impl Drop for LeaseGuard {
    fn drop(&mut self) {
        if !self.armed {
            return;
        }
        let lease = match self.slot.0.lock() {
            Ok(mut slot) => {
                slot.0 = true;
                slot.1.take()
            }
            Err(_) => None,
        };
        if let Some(lease_id) = lease {
            tracing::info!(lease = %lease_id, "the lease request was abandoned; frame given back");
            let _ = self.daemon.release_frame(&lease_id);
        }
    }
}

#[tonic::async_trait]
impl WorkerService for Api {
    async fn lease_frame(
        &self,
        request: Request<pb::LeaseFrameRequest>,
    ) -> Result<Response<pb::LeaseFrameResponse>, Status> {
        let peer = request.remote_addr();
        let r = request.into_inner();
        let mut name: String = r.worker_name.chars().take(MAX_WORKER_NAME).collect();
        if name.is_empty() {
            name = peer.map_or_else(|| "unnamed".into(), |a| a.to_string());
        }
        let wait = std::time::Duration::from_millis(r.wait_ms.min(MAX_LEASE_WAIT_MS) as u64);
        let deadline = tokio::time::Instant::now() + wait;
        // Subscribed before looking, so work that arrives in between is not missed.
        let mut work = self.daemon.work.subscribe();
        loop {
            work.borrow_and_update();
            if self.daemon.is_stopping() {
                return Ok(Response::new(pb::LeaseFrameResponse { task: None }));
            }
            let guard = LeaseGuard::new(self.daemon.clone());
            let (daemon, worker, slot) = (self.daemon.clone(), name.clone(), guard.slot.clone());
            let leased = blocking(move || {
                let task = daemon.lease_frame(&worker, false)?;
                Ok(task.and_then(|task| slot.keep(&daemon, task)))
            })
            .await?;
            if let Some(task) = leased {
                guard.disarm();
                return Ok(Response::new(pb::LeaseFrameResponse {
                    task: Some(frame_task_message(&task)),
                }));
            }
            match tokio::time::timeout_at(deadline, work.changed()).await {
                Ok(Ok(())) => {}
                Ok(Err(_)) | Err(_) => {
                    return Ok(Response::new(pb::LeaseFrameResponse { task: None }))
                }
            }
        }
    }

    async fn heartbeat(
        &self,
        request: Request<pb::HeartbeatRequest>,
    ) -> Result<Response<pb::HeartbeatResponse>, Status> {
        let lease_id = request.into_inner().lease_id;
        let daemon = self.daemon.clone();
        let answer = blocking(move || daemon.heartbeat(&lease_id)).await?;
        Ok(Response::new(match answer {
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
        }))
    }

    async fn complete_frame(
        &self,
        request: Request<Streaming<pb::CompleteFrameRequest>>,
    ) -> Result<Response<pb::CompleteFrameResponse>, Status> {
        let mut stream = request.into_inner();
        let result = match stream.message().await? {
            Some(pb::CompleteFrameRequest {
                part: Some(pb::complete_frame_request::Part::Result(result)),
            }) => result,
            _ => {
                return Err(invalid("result", "the first message must be the frame result").into())
            }
        };
        // A stale lease is refused before the image is received.
        let (daemon, lease_id) = (self.daemon.clone(), result.lease_id.clone());
        let (_, width, height) = blocking(move || daemon.held_lease(&lease_id)).await?;
        let limit = max_png_bytes(width, height);
        if result.png_size_bytes > limit {
            return Err(DaemonError::ResourceExhausted(format!(
                "a {width}x{height} frame's PNG may have at most {limit} bytes, got {}",
                result.png_size_bytes
            ))
            .into());
        }
        let mut png = Vec::with_capacity(result.png_size_bytes as usize);
        while let Some(message) = stream.message().await? {
            let Some(pb::complete_frame_request::Part::Png(chunk)) = message.part else {
                return Err(invalid("png", "only the first message may be the result").into());
            };
            if png.len() as u64 + chunk.len() as u64 > result.png_size_bytes {
                return Err(invalid(
                    "result.png_size_bytes",
                    format!("more than the declared {} bytes", result.png_size_bytes),
                )
                .into());
            }
            png.extend_from_slice(&chunk);
        }
        if png.len() as u64 != result.png_size_bytes {
            return Err(invalid(
                "result.png_size_bytes",
                format!(
                    "declared {} bytes, received {}",
                    result.png_size_bytes,
                    png.len()
                ),
            )
            .into());
        }
        let outcome = FrameOutcome {
            timings: stage_timings(&result.timings),
            dataset_cache_hit: result.dataset_cache_hit,
        };
        let daemon = self.daemon.clone();
        blocking(move || daemon.complete_frame(&result.lease_id, &png, outcome)).await?;
        Ok(Response::new(pb::CompleteFrameResponse {}))
    }

    async fn fail_frame(
        &self,
        request: Request<pb::FailFrameRequest>,
    ) -> Result<Response<pb::FailFrameResponse>, Status> {
        let r = request.into_inner();
        let reason = if r.reason.is_empty() {
            "the worker gave no reason".to_string()
        } else {
            r.reason
        };
        let daemon = self.daemon.clone();
        blocking(move || daemon.fail_frame(&r.lease_id, &reason)).await?;
        Ok(Response::new(pb::FailFrameResponse {}))
    }

    async fn release_frame(
        &self,
        request: Request<pb::ReleaseFrameRequest>,
    ) -> Result<Response<pb::ReleaseFrameResponse>, Status> {
        let lease_id = request.into_inner().lease_id;
        let daemon = self.daemon.clone();
        blocking(move || daemon.release_frame(&lease_id)).await?;
        Ok(Response::new(pb::ReleaseFrameResponse {}))
    }

    type FetchDatasetStream = ResponseStream<pb::DatasetChunk>;

    async fn fetch_dataset(
        &self,
        request: Request<pb::FetchDatasetRequest>,
    ) -> Result<Response<Self::FetchDatasetStream>, Status> {
        use tokio::io::AsyncReadExt;
        let dataset = self.daemon.dataset(&request.into_inner().dataset_id)?;
        let mut file = tokio::fs::File::open(&dataset.path)
            .await
            .map_err(|e| Status::internal(format!("dataset {}: {e}", dataset.id)))?;
        let (sender, receiver) = tokio::sync::mpsc::channel(4);
        tokio::spawn(async move {
            loop {
                let mut buffer = vec![0u8; FRAME_CHUNK_BYTES];
                let message = match file.read(&mut buffer).await {
                    Ok(0) => return,
                    Ok(n) => {
                        buffer.truncate(n);
                        Ok(pb::DatasetChunk { data: buffer })
                    }
                    Err(e) => Err(Status::internal(format!("dataset {}: {e}", dataset.id))),
                };
                let failed = message.is_err();
                if sender.send(message).await.is_err() || failed {
                    return;
                }
            }
        });
        Ok(Response::new(Box::pin(ReceiverStream::new(receiver))))
    }

    async fn list_leases(
        &self,
        _request: Request<pb::ListLeasesRequest>,
    ) -> Result<Response<pb::ListLeasesResponse>, Status> {
        let daemon = self.daemon.clone();
        let leases = blocking(move || daemon.leases()).await?;
        Ok(Response::new(pb::ListLeasesResponse {
            leases: leases.iter().map(lease_message).collect(),
        }))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn valid() -> pb::SubmitJobRequest {
        pb::SubmitJobRequest {
            request_id: "r1".into(),
            dataset_id: "ds-1".into(),
            camera_path: Some(pb::CameraPath {
                path: Some(pb::camera_path::Path::Turntable(pb::Turntable {
                    frames: 4,
                    ..Default::default()
                })),
            }),
            width: 64,
            height: 48,
            render: None,
            priority: 0,
        }
    }

    fn field_of(r: &pb::SubmitJobRequest) -> String {
        match job_spec(r) {
            Err(DaemonError::InvalidArgument { field, .. }) => field,
            other => panic!("expected InvalidArgument, got {other:?}"),
        }
    }

    #[test]
    fn invalid_submissions_name_the_field() {
        assert!(job_spec(&valid()).is_ok());
        let mut r = valid();
        r.camera_path = Some(pb::CameraPath {
            path: Some(pb::camera_path::Path::Turntable(pb::Turntable {
                frames: 0,
                ..Default::default()
            })),
        });
        assert_eq!(field_of(&r), "camera_path.turntable.frames");
        let mut r = valid();
        r.camera_path = Some(pb::CameraPath {
            path: Some(pb::camera_path::Path::Turntable(pb::Turntable {
                frames: 2,
                center: Some(pb::Vec3 {
                    x: f64::NAN,
                    y: 0.0,
                    z: 0.0,
                }),
                ..Default::default()
            })),
        });
        assert_eq!(field_of(&r), "camera_path.turntable.center");
        let mut r = valid();
        let key = |x: f64| pb::Keyframe {
            position: Some(pb::Vec3 { x, y: 0.0, z: 10.0 }),
            target: Some(pb::Vec3 {
                x: 0.0,
                y: 0.0,
                z: 0.0,
            }),
            up: None,
            fov_y_deg: 50.0,
        };
        r.camera_path = Some(pb::CameraPath {
            path: Some(pb::camera_path::Path::Keyframes(pb::KeyframePath {
                keyframes: vec![key(1.0), key(f64::NAN)],
                frames: 3,
                interpolation: 0,
            })),
        });
        assert_eq!(field_of(&r), "camera_path.keyframes.keyframes[1].position");
        let mut r = valid();
        r.width = 0;
        assert_eq!(field_of(&r), "width");
        let mut r = valid();
        r.camera_path = None;
        assert_eq!(field_of(&r), "camera_path");
        let mut r = valid();
        r.render = Some(pb::RenderOptions {
            point_size: 1000,
            ..Default::default()
        });
        assert_eq!(field_of(&r), "render.point_size");
        let mut r = valid();
        r.render = Some(pb::RenderOptions {
            quality: pb::Quality::High as i32,
            depth_band: Some(f32::NAN),
            ..Default::default()
        });
        assert_eq!(field_of(&r), "render.depth_band");
        for kernel in [1, 4, 11] {
            let mut r = valid();
            r.render = Some(pb::RenderOptions {
                fill: Some(pb::FillOptions { kernel }),
                ..Default::default()
            });
            assert_eq!(field_of(&r), "render.fill.kernel");
        }
        let mut r = valid();
        r.render = Some(pb::RenderOptions {
            shading: pb::Shading::Pintus as i32,
            pintus_levels: Some(0),
            ..Default::default()
        });
        assert_eq!(field_of(&r), "render.pintus_levels");
        let mut r = valid();
        r.render = Some(pb::RenderOptions {
            shading: pb::Shading::Pintus as i32,
            pintus_exponent: Some(f32::NAN),
            ..Default::default()
        });
        assert_eq!(field_of(&r), "render.pintus_exponent");
    }

    #[test]
    fn fill_and_pintus_shading_convert_with_defaults() {
        let mut r = valid();
        r.render = Some(pb::RenderOptions {
            shading: pb::Shading::Pintus as i32,
            fill: Some(pb::FillOptions { kernel: 0 }),
            ..Default::default()
        });
        let render = job_spec(&r).expect("valid").render;
        assert_eq!(render.fill, Some(Fill { kernel: 7 }));
        assert_eq!(
            render.shading,
            Shading::Pintus {
                levels: 8,
                exponent: 1.5
            }
        );
        assert_eq!(job_spec(&valid()).expect("valid").render.fill, None);
    }

    #[test]
    fn tasks_carry_the_job_spec_unchanged_across_the_wire() {
        let mut r = valid();
        r.render = Some(pb::RenderOptions {
            point_size: 3,
            quality: pb::Quality::High as i32,
            depth_band: Some(0.02),
            shading: pb::Shading::Edl as i32,
            edl_strength: Some(2.0),
            edl_radius: Some(2.5),
            color_mode: pb::ColorMode::Fixed as i32,
            fixed_color: Some(pb::Color { rgba: 0x10203040 }),
            background: Some(pb::Color { rgba: 0x01020304 }),
            fill: Some(pb::FillOptions { kernel: 5 }),
            ..Default::default()
        });
        let key = |x: f64| pb::Keyframe {
            position: Some(pb::Vec3 { x, y: 0.0, z: 10.0 }),
            target: Some(pb::Vec3 {
                x: 0.0,
                y: 1.0,
                z: 0.0,
            }),
            up: None,
            fov_y_deg: 40.0,
        };
        let keyframes = pb::CameraPath {
            path: Some(pb::camera_path::Path::Keyframes(pb::KeyframePath {
                keyframes: vec![key(1.0), key(5.0), key(9.0)],
                frames: 7,
                interpolation: pb::Interpolation::Spline as i32,
            })),
        };
        let turntable = pb::CameraPath {
            path: Some(pb::camera_path::Path::Turntable(pb::Turntable {
                frames: 5,
                center: Some(pb::Vec3 {
                    x: 1e6,
                    y: 2e6,
                    z: 3.0,
                }),
                radius: Some(12.5),
                ..Default::default()
            })),
        };
        for path in [keyframes, turntable] {
            r.camera_path = Some(path);
            let spec = job_spec(&r).expect("valid");
            let task = FrameTask {
                lease: Lease {
                    id: "lease-1".into(),
                    job_id: "job-1".into(),
                    index: 4,
                    worker: "w".into(),
                    embedded: false,
                    expires_unix_ms: 1234,
                },
                lease_timeout: std::time::Duration::from_secs(30),
                dataset: TaskDataset {
                    id: "ds-1".into(),
                    sha256: "ab".repeat(32),
                    size_bytes: 99,
                },
                camera_path: spec.camera_path,
                width: spec.width,
                height: spec.height,
                render: spec.render,
                failed_attempts: 2,
            };
            let received = frame_task(&frame_task_message(&task), "w").expect("valid task");
            assert_eq!(received, task);
        }
    }

    #[test]
    fn every_daemon_error_has_its_status_code() {
        use tonic::Code;
        let cases = [
            (DaemonError::invalid("f", "m"), Code::InvalidArgument),
            (DaemonError::NotFound("x".into()), Code::NotFound),
            (
                DaemonError::FailedPrecondition("x".into()),
                Code::FailedPrecondition,
            ),
            (
                DaemonError::ResourceExhausted("x".into()),
                Code::ResourceExhausted,
            ),
            (DaemonError::Internal("x".into()), Code::Internal),
        ];
        for (error, code) in cases {
            assert_eq!(Status::from(error).code(), code);
        }
    }
}
