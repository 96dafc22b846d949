//! Serving the API: the gRPC services with health checking and reflection (so `grpcurl` works
//! out of the box), optional bearer-token authentication (workers included), the embedded
//! worker process and its supervisor, the sweep that expires the leases of lost workers, and
//! a graceful shutdown that lets the current frame finish.
//!
//! Health: the overall service ("") and `JobService` are SERVING while some worker can render
//! (the embedded worker is up, or a remote worker was heard from within the lease timeout)
//! and NOT_SERVING otherwise; `DatasetService` and `WorkerService` answer whenever the daemon
//! does, since uploads and workers need them to get going.

use std::future::Future;
use std::sync::Arc;
use std::time::Duration;

use anyhow::Context;
use pointfarm_proto::v1::dataset_service_server::DatasetServiceServer;
use pointfarm_proto::v1::job_service_server::JobServiceServer;
use pointfarm_proto::v1::worker_service_server::WorkerServiceServer;
use pointfarm_proto::v1::FILE_DESCRIPTOR_SET;
use rand::Rng;
use tokio_stream::wrappers::TcpListenerStream;
use tonic::{Request, Status};
use tonic_health::server::HealthReporter;
use tonic_health::ServingStatus;

use crate::grpc::{Api, EmbeddedWorkerCall};
use crate::service::Daemon;
use crate::worker::supervisor::{Supervisor, WorkerCommand};

/// The one authentication hook: requires `authorization: Bearer <token>` on every API call
/// when a token is configured, and knows the embedded worker's calls by the token made for it
/// at start-up.
#[derive(Clone)]
struct BearerAuth {
    expected: Option<Arc<str>>,
    embedded_worker: Arc<str>,
}

impl tonic::service::Interceptor for BearerAuth {
    fn call(&mut self, mut request: Request<()>) -> Result<Request<()>, Status> {
        let given = request
            .metadata()
            .get("authorization")
            .and_then(|v| v.to_str().ok())
            .and_then(|v| v.strip_prefix("Bearer "));
        if given == Some(&*self.embedded_worker) {
            request.extensions_mut().insert(EmbeddedWorkerCall);
            return Ok(request);
        }
        let Some(expected) = &self.expected else {
            return Ok(request);
        };
        match given {
            Some(token) if token == &**expected => Ok(request),
            Some(_) => Err(Status::unauthenticated("invalid bearer token")),
            None => Err(Status::unauthenticated(
                "missing 'authorization: Bearer <token>' header",
            )),
        }
    }
}

/// A token for the embedded worker, new for every start of the daemon.
fn embedded_worker_token() -> String {
    let bytes: [u8; 32] = rand::rng().random();
    crate::service::hex(&bytes)
}

/// How often the lease sweep and the health check run: a fraction of the lease timeout.
fn sweep_period(lease_timeout: Duration) -> Duration {
    (lease_timeout / 4).clamp(Duration::from_millis(50), Duration::from_secs(1))
}

/// Serves `daemon` on `listener` until `shutdown` completes, with an embedded worker process
/// started by `embedded_worker` (none: only remote workers render, `pointfarm worker`).
pub async fn serve(
    daemon: Arc<Daemon>,
    embedded_worker: Option<WorkerCommand>,
    listener: tokio::net::TcpListener,
    auth_token: Option<String>,
    shutdown: impl Future<Output = ()> + Send,
) -> anyhow::Result<()> {
    let address = listener.local_addr()?;
    let embedded_token = embedded_worker_token();
    let supervisor = embedded_worker
        .map(|command| Supervisor::start(daemon.clone(), command, address, embedded_token.clone()));

    // Lost workers' frames go back to the queue within a fraction of the lease timeout.
    let sweeper = {
        let daemon = daemon.clone();
        let period = sweep_period(daemon.config.lease_timeout);
        tokio::spawn(async move {
            let mut tick = tokio::time::interval(period);
            tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
            loop {
                tick.tick().await;
                let daemon = daemon.clone();
                match tokio::task::spawn_blocking(move || daemon.expire_leases()).await {
                    Ok(Ok(_)) => {}
                    Ok(Err(e)) => tracing::error!(error = %e, "expiring leases"),
                    Err(e) => tracing::error!(error = %e, "the lease sweep panicked"),
                }
            }
        })
    };

    let (health, health_service) = tonic_health::server::health_reporter();
    health.set_serving::<DatasetServiceServer<Api>>().await;
    health.set_serving::<WorkerServiceServer<Api>>().await;
    let health_watch = tokio::spawn(report_health(daemon.clone(), health));
    let reflection = tonic_reflection::server::Builder::configure()
        .register_encoded_file_descriptor_set(FILE_DESCRIPTOR_SET)
        .build_v1()
        .context("building the reflection service")?;

    let api = Api::new(daemon.clone());
    let auth = BearerAuth {
        expected: auth_token.map(Arc::from),
        embedded_worker: Arc::from(embedded_token),
    };
    // Long-polling lease requests answer at once when the server begins to stop; the server
    // serves on until the embedded worker has handed in its current frame.
    let shutdown = {
        let daemon = daemon.clone();
        async move {
            shutdown.await;
            tracing::info!("shutting down: finishing the current frame");
            daemon.begin_shutdown();
            if let Some(supervisor) = supervisor {
                supervisor.stop().await;
            }
        }
    };
    tracing::info!(%address, "serving pointfarm.v1");
    tonic::transport::Server::builder()
        .add_service(health_service)
        .add_service(reflection)
        .add_service(DatasetServiceServer::with_interceptor(
            api.clone(),
            auth.clone(),
        ))
        .add_service(JobServiceServer::with_interceptor(
            api.clone(),
            auth.clone(),
        ))
        .add_service(WorkerServiceServer::with_interceptor(api, auth))
        .serve_with_incoming_shutdown(TcpListenerStream::new(listener), shutdown)
        .await
        .context("gRPC server")?;
    sweeper.abort();
    health_watch.abort();
    daemon.store.flush()?;
    Ok(())
}

/// Keeps the health of "" and `JobService` at whether some worker can render.
async fn report_health(daemon: Arc<Daemon>, health: HealthReporter) {
    let timeout = daemon.config.lease_timeout;
    let mut tick = tokio::time::interval(sweep_period(timeout));
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let mut reported = None;
    loop {
        // Time makes remote workers stale; calls and the embedded worker's exits change it.
        tokio::select! {
            _ = tick.tick() => {}
            _ = daemon.workers.changed() => {}
        }
        // A full disk stores no frames: the store logs it once, health follows it.
        let can_render = daemon.workers.can_render(timeout) && daemon.store.outage().is_none();
        if reported == Some(can_render) {
            continue;
        }
        let status = if can_render {
            tracing::info!("a worker can render: SERVING");
            ServingStatus::Serving
        } else {
            tracing::warn!(
                "no worker can render or the disk is full: NOT_SERVING until both are back"
            );
            ServingStatus::NotServing
        };
        health.set_service_status("", status).await;
        health
            .set_service_status(
                <JobServiceServer<Api> as tonic::server::NamedService>::NAME,
                status,
            )
            .await;
        reported = Some(can_render);
    }
}
