//! The client side of the render service: connecting, uploading, submitting, following and
//! downloading. Used by `render --server`, `info --server`, `dataset`, `jobs` (`jobs leases`
//! lists the frames workers hold) and `frames`: the client API only, never the workers'.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use indicatif::{ProgressBar, ProgressStyle};
use pointfarm_daemon::grpc::streaming::read_chunk;
use pointfarm_daemon::model::content_sha256_of;
use pointfarm_daemon::service::{dataset_id, hash_files};
use pointfarm_proto::v1 as pb;
use pointfarm_proto::v1::dataset_service_client::DatasetServiceClient;
use pointfarm_proto::v1::job_service_client::JobServiceClient;
use pointfarm_proto::BearerToken;
use tokio_stream::wrappers::ReceiverStream;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::Channel;
use tonic::{Code, Status};

use crate::credentials::ClientCredentials;
use crate::export::ExportTarget;

type Authed = InterceptedService<Channel, BearerToken>;

/// A client of a daemon's client API (datasets and jobs).
pub struct Client {
    pub datasets: DatasetServiceClient<Authed>,
    pub jobs: JobServiceClient<Authed>,
}

impl Client {
    /// Connects to `server` as `credentials` say (TLS trust, bearer token).
    pub async fn connect(server: &str, credentials: &ClientCredentials) -> Result<Self> {
        let endpoint = credentials.endpoint(server)?;
        let auth = BearerToken::new(credentials.token()?.as_deref())?;
        let channel = endpoint.connect().await?;
        Ok(Self {
            datasets: DatasetServiceClient::with_interceptor(channel.clone(), auth.clone()),
            jobs: JobServiceClient::with_interceptor(channel, auth),
        })
    }

    /// The dataset of `files` (in this order): the server's own when it has these files as
    /// one dataset already (registered under its data roots, or uploaded before), otherwise
    /// each file uploaded unless the server has it, and the files composed into one.
    pub async fn ensure_dataset(&mut self, files: &[PathBuf]) -> Result<pb::Dataset> {
        if files.is_empty() {
            bail!("a dataset needs at least one LAS/LAZ file");
        }
        let hashed = hash_all(files).await?;
        let hashes: Vec<&str> = hashed.iter().map(|(sha256, _)| sha256.as_str()).collect();
        if let Some(found) = self.find_dataset(&content_sha256_of(&hashes)).await? {
            return Ok(found);
        }
        let mut datasets = Vec::with_capacity(files.len());
        for (file, (sha256, size_bytes)) in files.iter().zip(hashed.iter().cloned()) {
            datasets.push(match self.find_dataset(&sha256).await? {
                Some(found) => found,
                None => self.upload_file(file, sha256, size_bytes).await?,
            });
        }
        if datasets.len() == 1 {
            return Ok(datasets.remove(0));
        }
        let dataset_ids = datasets.into_iter().map(|dataset| dataset.id).collect();
        let request = pb::ComposeDatasetRequest {
            dataset_ids,
            name: String::new(),
        };
        answer(self.datasets.compose_dataset(request).await)
    }

    /// The server's dataset with content `sha256`, if it has one.
    async fn find_dataset(&mut self, sha256: &str) -> Result<Option<pb::Dataset>> {
        let request = pb::GetDatasetRequest {
            id: dataset_id(sha256),
        };
        match self.datasets.get_dataset(request).await {
            Ok(found) => Ok(Some(found.into_inner())),
            Err(status) if status.code() == Code::NotFound => Ok(None),
            Err(status) => Err(status_error(status)),
        }
    }

    /// Uploads `file`, whose content hashes to `sha256`, as a dataset of its own.
    async fn upload_file(
        &mut self,
        file: &Path,
        sha256: String,
        size_bytes: u64,
    ) -> Result<pb::Dataset> {
        let name = file
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        let header = pb::UploadHeader {
            name,
            size_bytes,
            sha256,
        };
        let bar = ProgressBar::new(size_bytes).with_style(
            ProgressStyle::with_template(
                "uploading {bar:40} {bytes}/{total_bytes} {bytes_per_sec}",
            )
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
        );
        let (messages, sent) = upload_messages(file, header, bar.clone()).await?;
        let uploaded = self.datasets.upload_dataset(messages).await;
        bar.finish_and_clear();
        // A file that could not be read explains a refused upload better than the refusal.
        sent.await?
            .with_context(|| format!("reading {}", file.display()))?;
        Ok(uploaded.map_err(status_error)?.into_inner())
    }

    /// Follows a job with a progress bar until it ends, calling `on_frame` with every frame
    /// reported (previews too); returns the final job.
    pub async fn follow(
        &mut self,
        job_id: &str,
        quiet: bool,
        mut on_frame: impl FnMut(&pb::FrameFinished),
    ) -> Result<pb::Job> {
        let bar = if quiet {
            ProgressBar::hidden()
        } else {
            ProgressBar::new(0)
        };
        bar.set_style(
            ProgressStyle::with_template("{bar:40} {pos}/{len} frames {msg}")
                .unwrap_or_else(|_| ProgressStyle::default_bar()),
        );
        let last = self
            .watch(job_id, |event| {
                let Some(job) = &event.job else {
                    return Ok(());
                };
                // The first event lists the frames finished before the watch began.
                let frames = job.frames.iter().chain(&event.frame);
                bar.set_length(job.frames_total as u64);
                bar.set_position(job.frames_done as u64);
                bar.set_message(state_name(job.state).to_string());
                for frame in frames {
                    on_frame(frame);
                    let mut line =
                        format!("frame {:>5}  {}", frame.index, timings_line(&frame.timings));
                    if frame.preview {
                        line.push_str(&preview_words(frame.completeness));
                    }
                    if bar.is_hidden() && !quiet {
                        outln!("{line}");
                    } else {
                        bar.println(line);
                    }
                }
                Ok(())
            })
            .await;
        bar.finish_and_clear();
        last
    }

    /// Follows a job until it ends, calling `each` with every event that carries the job (its
    /// state and progress after the event, and the frame the event finished; the first event
    /// lists in its job the frames finished before the watch began); returns the final job.
    /// An error from `each` ends the watch.
    pub async fn watch(
        &mut self,
        job_id: &str,
        mut each: impl FnMut(&pb::JobEvent) -> Result<()>,
    ) -> Result<pb::Job> {
        let mut events = self
            .jobs
            .watch_job(pb::WatchJobRequest {
                id: job_id.to_string(),
            })
            .await
            .map_err(status_error)?
            .into_inner();
        let mut last = None;
        while let Some(event) = events.message().await.map_err(status_error)? {
            if event.job.is_none() {
                continue;
            }
            each(&event)?;
            last = event.job;
        }
        last.context("the server ended the watch without any event")
    }

    /// Downloads the finished frames of a job into `out` (frame_00000.png, ...); returns each
    /// frame's index and file.
    pub async fn fetch_frames(
        &mut self,
        job_id: &str,
        from_index: u32,
        out: &Path,
    ) -> Result<Vec<(u32, PathBuf)>> {
        let mut stream = self
            .jobs
            .fetch_frames(pb::FetchFramesRequest {
                job_id: job_id.to_string(),
                from_index,
            })
            .await
            .map_err(status_error)?
            .into_inner();
        // Made only once the server has the job, so that a refused fetch leaves no folder.
        tokio::fs::create_dir_all(out)
            .await
            .with_context(|| format!("creating {}", out.display()))?;
        let mut written = Vec::new();
        let mut buffer = Vec::new();
        while let Some(chunk) = stream.message().await.map_err(status_error)? {
            buffer.extend_from_slice(&chunk.png);
            if chunk.last {
                let path = out.join(format!("frame_{:05}.png", chunk.index));
                tokio::fs::write(&path, &buffer)
                    .await
                    .with_context(|| format!("writing {}", path.display()))?;
                buffer.clear();
                written.push((chunk.index, path));
            }
        }
        Ok(written)
    }

    /// Dataset `id` exported by the server as a COPC file, written to a file through a
    /// temporary file beside it, renamed into place once every byte the summary announced
    /// has arrived, or streamed into a multipart upload that completes only then (and is
    /// aborted otherwise); the summary.
    pub async fn export_dataset(
        &mut self,
        id: &str,
        target: &ExportTarget,
    ) -> Result<pb::ExportSummary> {
        use pb::export_chunk::Part;
        let spinner = crate::progress::spinner(format!("exporting {id} on the server"));
        let stream = self
            .datasets
            .export_dataset(pb::ExportDatasetRequest {
                dataset_id: id.to_string(),
            })
            .await;
        spinner.finish_and_clear();
        let mut stream = stream.map_err(status_error)?.into_inner();
        let Some(Part::Summary(summary)) = stream
            .message()
            .await
            .map_err(status_error)?
            .and_then(|m| m.part)
        else {
            bail!("the server's export did not start with its summary");
        };
        match target {
            ExportTarget::File(out) => receive_file(&mut stream, &summary, out).await?,
            ExportTarget::Url { client, url } => {
                // Each part is sent as it fills; the wait blocks this thread, not the runtime.
                let mut upload = tokio::task::block_in_place(|| client.start_upload(url))
                    .map_err(anyhow::Error::from)?;
                receive(&mut stream, &summary, |data| {
                    tokio::task::block_in_place(|| upload.write(data)).map_err(anyhow::Error::from)
                })
                .await?;
                // An upload dropped on an error above is aborted: no object appears.
                tokio::task::block_in_place(|| upload.finish())?;
            }
        }
        Ok(summary)
    }
}

/// The export's data after its summary, each chunk given to `sink`; refused unless the bytes
/// are as many as the summary announced.
async fn receive(
    stream: &mut tonic::Streaming<pb::ExportChunk>,
    summary: &pb::ExportSummary,
    mut sink: impl FnMut(&[u8]) -> Result<()>,
) -> Result<()> {
    use pb::export_chunk::Part;
    let bar = crate::progress::counter(summary.size_bytes, "bytes", "downloading".into());
    let mut bytes = 0u64;
    while let Some(message) = stream.message().await.map_err(status_error)? {
        let Some(Part::Data(data)) = message.part else {
            bail!("the server sent a second summary");
        };
        sink(&data)?;
        bytes += data.len() as u64;
        bar.set_position(bytes);
    }
    bar.finish_and_clear();
    if bytes != summary.size_bytes {
        bail!(
            "the server sent {bytes} bytes of a {}-byte file",
            summary.size_bytes
        );
    }
    Ok(())
}

/// The export written to `out` through `out.part`, removed when anything fails.
async fn receive_file(
    stream: &mut tonic::Streaming<pb::ExportChunk>,
    summary: &pb::ExportSummary,
    out: &Path,
) -> Result<()> {
    use std::io::Write;
    let mut name = out.file_name().unwrap_or_default().to_os_string();
    name.push(".part");
    let partial = out.with_file_name(name);
    let received = async {
        let file = std::fs::File::create(&partial)
            .with_context(|| format!("writing {}", partial.display()))?;
        let mut file = std::io::BufWriter::new(file);
        receive(stream, summary, |data| {
            file.write_all(data)
                .with_context(|| format!("writing {}", partial.display()))
        })
        .await?;
        let file = file
            .into_inner()
            .map_err(|e| e.into_error())
            .with_context(|| format!("writing {}", partial.display()))?;
        file.sync_all()
            .with_context(|| format!("writing {}", partial.display()))?;
        std::fs::rename(&partial, out).with_context(|| format!("writing {}", out.display()))
    }
    .await;
    if received.is_err() {
        let _ = std::fs::remove_file(&partial);
    }
    received
}

/// Writes the latest image of frame `index` of job `job_id` (its preview while the
/// final frame is pending) to `path`; false when the server has no image of it.
pub async fn fetch_frame(
    jobs: &mut JobServiceClient<Authed>,
    job_id: &str,
    index: u32,
    path: &Path,
) -> Result<bool> {
    let mut stream = jobs
        .fetch_frames(pb::FetchFramesRequest {
            job_id: job_id.to_string(),
            from_index: index,
        })
        .await
        .map_err(status_error)?
        .into_inner();
    let mut png = Vec::new();
    // Frames come in order from `index`: a later frame first means it has no image.
    while let Some(chunk) = stream.message().await.map_err(status_error)? {
        if chunk.index != index {
            return Ok(false);
        }
        png.extend_from_slice(&chunk.png);
        if chunk.last {
            tokio::fs::write(path, &png)
                .await
                .with_context(|| format!("writing {}", path.display()))?;
            return Ok(true);
        }
    }
    Ok(false)
}

/// The SHA-256 and size of each of `files`, in order, read off the async threads with a bar
/// over their bytes (a campaign of many gigabytes takes a while).
async fn hash_all(files: &[PathBuf]) -> Result<Vec<(String, u64)>> {
    let files = files.to_vec();
    tokio::task::spawn_blocking(move || {
        let total = files
            .iter()
            .map(|file| std::fs::metadata(file).map_or(0, |m| m.len()))
            .sum();
        let bar = crate::progress::counter(total, "bytes", "hashing".into());
        let hashed = hash_files(&files, &|size| bar.inc(size));
        bar.finish_and_clear();
        files
            .iter()
            .zip(hashed)
            .map(|(file, hashed)| hashed.with_context(|| format!("reading {}", file.display())))
            .collect()
    })
    .await?
}

/// The messages of an upload: `header`, then the file's bytes read chunk by chunk as the
/// stream is sent (a few chunks in memory, whatever the file's size), counted on `bar`. The
/// task's result says whether the whole file was read.
async fn upload_messages(
    file: &Path,
    header: pb::UploadHeader,
    bar: ProgressBar,
) -> Result<(
    ReceiverStream<pb::UploadDatasetRequest>,
    tokio::task::JoinHandle<std::io::Result<()>>,
)> {
    use pb::upload_dataset_request::Part;
    let mut reader = tokio::fs::File::open(file)
        .await
        .with_context(|| format!("opening {}", file.display()))?;
    let (sender, receiver) = tokio::sync::mpsc::channel(2);
    let sent = tokio::spawn(async move {
        let mut part = Part::Header(header);
        loop {
            let message = pb::UploadDatasetRequest { part: Some(part) };
            if sender.send(message).await.is_err() {
                return Ok(()); // The server ended the call; its answer says why.
            }
            let Some(data) = read_chunk(&mut reader).await? else {
                return Ok(());
            };
            bar.inc(data.len() as u64);
            part = Part::Data(data);
        }
    });
    Ok((ReceiverStream::new(receiver), sent))
}

/// A gRPC error as one readable line: what went wrong in words, then the server's message.
pub fn status_error(status: Status) -> anyhow::Error {
    anyhow::anyhow!(
        "{}: {}",
        pointfarm_proto::code_words(status.code()),
        status.message()
    )
}

/// A unary call's answer, or its status as an error.
pub fn answer<T>(reply: Result<tonic::Response<T>, Status>) -> anyhow::Result<T> {
    reply.map(tonic::Response::into_inner).map_err(status_error)
}

pub fn state_name(state: i32) -> &'static str {
    match pb::JobState::try_from(state) {
        Ok(pb::JobState::Queued) => "queued",
        Ok(pb::JobState::Running) => "running",
        Ok(pb::JobState::Succeeded) => "succeeded",
        Ok(pb::JobState::Failed) => "failed",
        Ok(pb::JobState::Cancelled) => "cancelled",
        Ok(pb::JobState::Paused) => "paused",
        _ => "unknown",
    }
}

pub fn timings_line(timings: &[pb::StageTiming]) -> String {
    timings
        .iter()
        .map(|t| {
            format!(
                "{} {:.2} ms{}",
                t.stage,
                t.ms,
                if t.gpu_clock { " (gpu)" } else { "" }
            )
        })
        .collect::<Vec<_>>()
        .join("  ")
}

/// Fails with the job's reason unless it succeeded.
pub fn require_success(job: &pb::Job) -> Result<()> {
    match pb::JobState::try_from(job.state) {
        Ok(pb::JobState::Succeeded) => Ok(()),
        _ if !job.error.is_empty() => {
            bail!("job {} {}: {}", job.id, state_name(job.state), job.error)
        }
        _ => bail!("job {} {}", job.id, state_name(job.state)),
    }
}

/// How a preview frame is told apart in a listing: what it drew of the dataset.
pub fn preview_words(completeness: f64) -> String {
    format!(
        "  | preview ({:.3}% of the points; the final frame follows)",
        completeness * 100.0
    )
}
