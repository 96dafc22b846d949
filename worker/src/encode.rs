//! A worker making jobs' videos, beside its frames: at start it looks for ffmpeg and the
//! encoders it has (`ffmpeg -version`, `ffmpeg -encoders`), and while it has some it asks the
//! daemon for encode leases (`LeaseEncode`, saying which encoders), a lease kind of its own
//! that never holds a frame. For each it fetches the job's frames in order from the daemon,
//! pipes them through ffmpeg into a file of its cache folder while renewals keep the lease,
//! and hands the video in; a failed encode is reported with ffmpeg's own error line. A
//! worker without ffmpeg asks for none. Stopping (SIGTERM) ends ffmpeg and gives the lease
//! back (`ReleaseEncode`), so another worker makes the video at once; a video already made
//! is handed in first.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use pointfarm_daemon::encodes::EncodeTask;
use pointfarm_proto::v1 as pb;
use pointfarm_render::encode::video::{ffmpeg_encoders, VideoEncoder};
use tokio::io::AsyncReadExt;
use tokio::sync::{mpsc, watch};
use tonic::Code;

use crate::client::Client;
use crate::lease_renewal::{keep_lease, renewal_interval};
use crate::stopping::stopped_during;

/// How long one encode lease request waits for work on the daemon.
const LEASE_WAIT_MS: u32 = 10_000;
/// Wait after a failed call before asking again.
const RETRY_WAIT: Duration = Duration::from_secs(2);
/// Bytes per message of a handed-in video.
const CHUNK_BYTES: usize = 1 << 20;

/// The encoders of this machine's ffmpeg that the farm's videos use; none (said in the log)
/// when ffmpeg is missing.
pub fn probe_encoders() -> Vec<String> {
    match ffmpeg_encoders() {
        Ok(encoders) if encoders.is_empty() => {
            tracing::info!("ffmpeg has none of the video encoders: this worker makes no videos");
            encoders
        }
        Ok(encoders) => {
            tracing::info!(encoders = %encoders.join(","), "ffmpeg found: this worker makes videos");
            encoders
        }
        Err(reason) => {
            tracing::info!(%reason, "this worker makes no videos");
            Vec::new()
        }
    }
}

/// Leases and makes videos until `stop` turns true; returns at once when `encoders` is empty.
pub async fn run(
    client: Client,
    name: String,
    encoders: Vec<String>,
    dir: PathBuf,
    mut stop: watch::Receiver<bool>,
) {
    if encoders.is_empty() {
        return;
    }
    if let Err(e) = std::fs::create_dir_all(&dir) {
        tracing::error!(error = %e, dir = %dir.display(), "no folder for videos: this worker makes none");
        return;
    }
    while !*stop.borrow() {
        let request = pb::LeaseEncodeRequest {
            worker_name: name.clone(),
            wait_ms: LEASE_WAIT_MS,
            encoders: encoders.clone(),
        };
        let mut lease_client = client.clone();
        let leased = tokio::select! {
            leased = lease_client.lease_encode(request) => leased,
            _ = stop.changed() => break,
        };
        let message = match leased {
            Ok(response) => match response.into_inner().task {
                Some(task) => task,
                None => continue,
            },
            Err(status) if status.code() == Code::Unimplemented => {
                tracing::info!("the daemon makes no videos: this worker makes none");
                return;
            }
            Err(status) => {
                // An unreachable daemon is the frame loop's to tell, in words (a certificate
                // the client refuses among them); this loop only waits for it.
                if status.code() == Code::Unavailable {
                    tracing::debug!(
                        message = status.message(),
                        "the daemon cannot be reached for videos; retrying"
                    );
                } else {
                    tracing::warn!(code = ?status.code(), message = status.message(), "leasing a video failed; retrying");
                }
                if stopped_during(&mut stop, RETRY_WAIT).await {
                    break;
                }
                continue;
            }
        };
        let task = match EncodeTask::try_from(&message) {
            Ok(task) => task,
            Err(e) => {
                let reason = format!("the encode task is invalid: {e}");
                fail(&client, &message.lease_id, &reason).await;
                continue;
            }
        };
        let span = tracing::info_span!("video", job = %task.job_id, lease = %task.lease_id);
        let made = make_video(&client, &task, &dir, stop.clone());
        tracing::Instrument::instrument(made, span).await;
    }
}

/// Resolves once `stop` turns true; never when its sender is gone.
async fn stopping(mut stop: watch::Receiver<bool>) {
    if stop.wait_for(|stopped| *stopped).await.is_err() {
        std::future::pending::<()>().await;
    }
}

/// Makes one leased video and hands it in, or reports why it could not be made; gives the
/// lease back when `stop` turns true before the video is made.
async fn make_video(client: &Client, task: &EncodeTask, dir: &Path, stop: watch::Receiver<bool>) {
    tracing::info!(
        frames = task.frames,
        encoder = task.video.encoder(),
        failed_attempts = task.failed_attempts,
        "video leased"
    );
    let started = Instant::now();
    let output = dir.join(format!(
        "{}.{}",
        task.job_id,
        task.video.container.extension()
    ));
    let abandoned = Arc::new(AtomicBool::new(false));
    let renewals = tokio::spawn(keep_lease(
        "video",
        renewal_interval(task.lease_timeout),
        abandoned.clone(),
        {
            let (client, lease_id) = (client.clone(), task.lease_id.clone());
            move || {
                let mut client = client.clone();
                let request = pb::RenewEncodeRequest {
                    lease_id: lease_id.clone(),
                };
                async move { client.renew_encode(request).await }
            }
        },
    ));
    let stopped = Arc::new(AtomicBool::new(false));
    let made = encode(client, task, &output, stop, stopped.clone()).await;
    let handed = match made {
        _ if abandoned.load(Ordering::SeqCst) => {
            tracing::info!("video dropped on the daemon's word");
            Ok(())
        }
        _ if stopped.load(Ordering::SeqCst) => {
            release(client, &task.lease_id).await;
            Ok(())
        }
        Ok(()) => hand_in(client, task, &output, started.elapsed()).await,
        Err(reason) => {
            tracing::warn!(%reason, "video failed");
            fail(client, &task.lease_id, &reason).await;
            Ok(())
        }
    };
    renewals.abort();
    if let Err(reason) = handed {
        tracing::warn!(%reason, "the video could not be handed in");
        fail(client, &task.lease_id, &reason).await;
    }
    let _ = tokio::fs::remove_file(&output).await;
}

/// Fetches the job's frames and pipes them, in order, through ffmpeg into `output`; the
/// error is what stopped it, ffmpeg's last line when ffmpeg did. When `stop` turns true
/// first, ffmpeg is ended, `stopped` is set, and the video is not made.
async fn encode(
    client: &Client,
    task: &EncodeTask,
    output: &Path,
    stop: watch::Receiver<bool>,
    stopped: Arc<AtomicBool>,
) -> Result<(), String> {
    let mut encoder = VideoEncoder::start(&task.video, "png", output)
        .map_err(|e| format!("starting ffmpeg: {e}"))?;
    let ffmpeg = encoder.stopper();
    // ffmpeg is fed from a thread of its own, so a slow encoder never blocks the runtime;
    // a few frames wait in the channel while the next are fetched.
    let (frames, mut incoming) = mpsc::channel::<Vec<u8>>(4);
    let feeder = tokio::task::spawn_blocking({
        let stopped = stopped.clone();
        move || {
            while let Some(frame) = incoming.blocking_recv() {
                if stopped.load(Ordering::SeqCst) || !encoder.write_frame(&frame) {
                    break;
                }
            }
            if stopped.load(Ordering::SeqCst) {
                // Dropped unfinished, the encoder ends ffmpeg rather than wait for it.
                drop(encoder);
                return Err("the worker is stopping".to_owned());
            }
            encoder.finish()
        }
    });
    let made = async {
        let fetched = fetch_frames(client.clone(), task, frames).await;
        let finished = feeder
            .await
            .map_err(|e| format!("feeding ffmpeg panicked: {e}"))?;
        // ffmpeg's words explain a fetch it cut short, so they come first.
        finished.map_err(|said| last_line(&said))?;
        fetched
    };
    // The flag is set before ffmpeg is ended, so its failure reads as the stop it is.
    tokio::select! {
        made = made => made,
        () = stopping(stop) => {
            stopped.store(true, Ordering::SeqCst);
            ffmpeg.stop();
            Err("the worker is stopping".to_owned())
        }
    }
}

/// Streams frames 0.. of the job into `frames`, whole and in order.
async fn fetch_frames(
    mut client: Client,
    task: &EncodeTask,
    frames: mpsc::Sender<Vec<u8>>,
) -> Result<(), String> {
    let request = pb::FetchEncodeFramesRequest {
        lease_id: task.lease_id.clone(),
        from_index: 0,
    };
    let mut stream = client
        .fetch_encode_frames(request)
        .await
        .map_err(|s| format!("fetching the frames: {}", s.message()))?
        .into_inner();
    let (mut next, mut frame) = (0u32, Vec::new());
    while let Some(chunk) = stream
        .message()
        .await
        .map_err(|s| format!("fetching frame {next}: {}", s.message()))?
    {
        if chunk.index != next {
            return Err(format!(
                "the daemon sent frame {} where frame {next} was due",
                chunk.index
            ));
        }
        frame.extend_from_slice(&chunk.png);
        if chunk.last {
            if frames.send(std::mem::take(&mut frame)).await.is_err() {
                // ffmpeg stopped reading; its error says why.
                return Ok(());
            }
            next += 1;
        }
    }
    if next != task.frames {
        return Err(format!(
            "the daemon sent {next} of the job's {} frames",
            task.frames
        ));
    }
    Ok(())
}

/// Hands the video in: its size first, then its bytes.
async fn hand_in(
    client: &Client,
    task: &EncodeTask,
    output: &Path,
    took: Duration,
) -> Result<(), String> {
    let mut file = tokio::fs::File::open(output)
        .await
        .map_err(|e| format!("opening the video: {e}"))?;
    let size = file
        .metadata()
        .await
        .map_err(|e| format!("reading the video's size: {e}"))?
        .len();
    if size > task.max_video_bytes {
        return Err(format!(
            "the video has {size} bytes; the daemon takes at most {}",
            task.max_video_bytes
        ));
    }
    let header = pb::CompleteEncodeRequest {
        part: Some(pb::complete_encode_request::Part::Result(
            pb::EncodeResult {
                lease_id: task.lease_id.clone(),
                size_bytes: size,
                encode_ms: took.as_secs_f64() * 1e3,
            },
        )),
    };
    // Read as it is sent, so a large video is never held in memory whole.
    let (sender, receiver) = mpsc::channel(4);
    let reader = tokio::spawn(async move {
        if sender.send(header).await.is_err() {
            return Ok(());
        }
        loop {
            let mut data = vec![0u8; CHUNK_BYTES];
            let n = file.read(&mut data).await?;
            if n == 0 {
                return Ok(());
            }
            data.truncate(n);
            let part = pb::complete_encode_request::Part::Data(data);
            let message = pb::CompleteEncodeRequest { part: Some(part) };
            if sender.send(message).await.is_err() {
                return Ok(());
            }
        }
    });
    let mut client = client.clone();
    let sent = client
        .complete_encode(tokio_stream::wrappers::ReceiverStream::new(receiver))
        .await;
    let read: std::io::Result<()> = reader
        .await
        .unwrap_or_else(|e| Err(std::io::Error::other(e.to_string())));
    read.map_err(|e| format!("reading the video: {e}"))?;
    match sent {
        Ok(_) => {
            tracing::info!(
                bytes = size,
                ms = took.as_millis() as u64,
                "video handed in"
            );
            Ok(())
        }
        Err(status) if status.code() == Code::FailedPrecondition => {
            tracing::info!(
                reason = status.message(),
                "the daemon no longer wants the video"
            );
            Ok(())
        }
        Err(status) => Err(format!("handing the video in: {}", status.message())),
    }
}

/// Gives the lease back unmade, counting no attempt; a lease that cannot be given back runs
/// out instead.
async fn release(client: &Client, lease_id: &str) {
    let request = pb::ReleaseEncodeRequest {
        lease_id: lease_id.to_owned(),
    };
    match client.clone().release_encode(request).await {
        Ok(_) => tracing::info!("stopping: the video is handed back unmade"),
        Err(status) => tracing::warn!(
            code = ?status.code(),
            message = status.message(),
            "handing the video back failed; its lease will run out"
        ),
    }
}

/// Reports a failed encode; a daemon that no longer holds the lease has nothing to count.
async fn fail(client: &Client, lease_id: &str, reason: &str) {
    let request = pb::FailEncodeRequest {
        lease_id: lease_id.to_owned(),
        reason: reason.to_owned(),
    };
    if let Err(status) = client.clone().fail_encode(request).await {
        tracing::warn!(code = ?status.code(), message = status.message(), "reporting the failed video");
    }
}

/// The last line ffmpeg wrote: the one that says why it stopped.
fn last_line(said: &str) -> String {
    said.lines()
        .rev()
        .map(str::trim)
        .find(|line| !line.is_empty())
        .unwrap_or("ffmpeg failed")
        .to_owned()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_error_reported_is_ffmpegs_last_line() {
        let said = "[libx264 @ 0x1] width not divisible by 2\nError initializing output stream\n\n";
        assert_eq!(last_line(said), "Error initializing output stream");
        assert_eq!(last_line("  \n"), "ffmpeg failed");
    }
}
