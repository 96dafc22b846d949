//! `pointfarm demo`: the whole service from one command. Starts a daemon with its embedded
//! worker (a child process) on a loopback port, uploads a cloud (a generated sample unless a file is given),
//! submits a turntable over gRPC, follows it and downloads the frames.

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::Args;
use pointfarm_daemon::model::JobSpec;
use pointfarm_daemon::server::{serve, ServeOptions};
use pointfarm_daemon::service::{Daemon, DaemonConfig};
use pointfarm_proto::v1 as pb;
use pointfarm_render::gpu::AdapterChoice;
use pointfarm_render::ingest::{write_las, LasWriteOptions};
use pointfarm_render::raster::Quality;
use pointfarm_render::request::{RenderOptions, RenderRequest};
use pointfarm_render::sample::{sample_scene, DEFAULT_SAMPLE_POINTS};

use crate::credentials::ClientCredentials;
use crate::remote::{answer, require_success, timings_line, Client};

#[derive(Args)]
pub struct DemoArgs {
    /// LAS/LAZ file to render (default: a generated sample scene).
    input: Option<PathBuf>,
    /// Folder for the frames (and the service's data, in `.pointfarm-data`).
    #[arg(long, short, default_value = "frames")]
    out: PathBuf,
    /// Turntable frames.
    #[arg(long, default_value_t = 12)]
    frames: u32,
    /// Frame size, WIDTHxHEIGHT.
    #[arg(long, default_value = "1280x720", value_parser = crate::parse::size)]
    size: (u32, u32),
    /// The embedded worker's GPU adapter: auto, hardware or software (lavapipe).
    #[arg(long, env = "POINTFARM_ADAPTER", default_value = "auto")]
    adapter: AdapterChoice,
}

pub fn run(args: DemoArgs) -> Result<()> {
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    let input = match &args.input {
        Some(file) => file.clone(),
        None => {
            let file = args.out.join("sample.laz");
            write_las(
                &file,
                &sample_scene(DEFAULT_SAMPLE_POINTS, 1),
                &LasWriteOptions::default(),
            )?;
            outln!(
                "generated {} ({DEFAULT_SAMPLE_POINTS} points)",
                file.display()
            );
            file
        }
    };
    let runtime = tokio::runtime::Runtime::new().context("starting the async runtime")?;
    runtime.block_on(async move {
        let daemon = Daemon::open(DaemonConfig::new(args.out.join(".pointfarm-data")))?;
        let worker = crate::serve::embedded_worker(&daemon.config, args.adapter)?;
        let presence = daemon.clone();
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
            .await
            .context("binding a loopback port")?;
        let address = listener.local_addr()?;
        let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
        let server = tokio::spawn(serve(
            daemon,
            Some(worker),
            listener,
            ServeOptions::default(),
            async {
                let _ = stopped.await;
            },
        ));
        outln!("daemon on {address}");

        let job = async {
            let mut client =
                Client::connect(&address.to_string(), &ClientCredentials::default()).await?;
            let dataset = client.ensure_dataset(std::slice::from_ref(&input)).await?;
            let spec = JobSpec::new(
                format!(
                    "demo-{}-{}-{}x{}",
                    dataset.id, args.frames, args.size.0, args.size.1
                ),
                dataset.id.clone(),
                RenderRequest {
                    render: RenderOptions {
                        quality: Quality::HIGH,
                        ..RenderOptions::default()
                    },
                    ..RenderRequest::turntable(args.size.0, args.size.1, args.frames)
                },
            );
            let request = pb::SubmitJobRequest::from(&spec);
            let job = answer(client.jobs.submit_job(request).await)?;
            outln!(
                "job {} on dataset {}: {} frames",
                job.id,
                dataset.id,
                job.frames_total
            );
            let finished = client.follow(&job.id, false, |_| {}).await?;
            require_success(&finished)?;
            let written = client.fetch_frames(&job.id, 0, &args.out).await?;
            let details = answer(client.jobs.get_job(pb::GetJobRequest { id: job.id }).await)?;
            if let Some(frame) = details.frames.last() {
                outln!("last frame: {}", timings_line(&frame.timings));
            }
            outln!("{} frames in {}", written.len(), args.out.display());
            anyhow::Ok(())
        };
        // The job ends, or the demo is stopped, or no worker ever starts (a worker that starts
        // and then fails frames fails the job): never a wait without end.
        let result = tokio::select! {
            result = job => result,
            () = crate::signals::shutdown_signal() => Err(anyhow::anyhow!("stopped before the job ended")),
            () = worker_never_starts(&presence) => Err(anyhow::anyhow!(
                "the embedded worker did not start within {} s (its error is above; \
                 --adapter hardware needs a GPU)",
                WORKER_START_LIMIT.as_secs()
            )),
        };
        let _ = stop.send(());
        server.await.context("daemon task")??;
        result
    })
}

/// How long the embedded worker may take to start and call in.
const WORKER_START_LIMIT: std::time::Duration = std::time::Duration::from_secs(60);

/// Completes when no worker has been able to render for [`WORKER_START_LIMIT`] since the
/// start; pends forever once one could.
async fn worker_never_starts(daemon: &Daemon) {
    let deadline = tokio::time::Instant::now() + WORKER_START_LIMIT;
    while tokio::time::Instant::now() < deadline {
        if daemon.workers.can_render(daemon.config.lease_timeout) {
            return std::future::pending().await;
        }
        tokio::time::sleep(std::time::Duration::from_millis(200)).await;
    }
}
