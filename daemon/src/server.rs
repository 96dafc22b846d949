//! Serving the API: the gRPC services with health checking and reflection (so `grpcurl` works
//! out of the box), optional bearer-token authentication (workers included), the embedded
//! worker thread, the sweep that expires the leases of lost workers, and a graceful shutdown
//! that lets the current frame finish.

use std::future::Future;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use anyhow::Context;
use pointfarm_proto::v1::dataset_service_server::DatasetServiceServer;
use pointfarm_proto::v1::job_service_server::JobServiceServer;
use pointfarm_proto::v1::worker_service_server::WorkerServiceServer;
use pointfarm_proto::v1::FILE_DESCRIPTOR_SET;
use pointfarm_render::gpu::GpuContext;
use tokio_stream::wrappers::TcpListenerStream;
use tonic::{Request, Status};

use crate::grpc::Api;
use crate::service::Daemon;

/// Requires `authorization: Bearer <token>` on every API call when a token is configured.
#[derive(Clone)]
struct BearerAuth {
    expected: Option<Arc<str>>,
}

impl tonic::service::Interceptor for BearerAuth {
    fn call(&mut self, request: Request<()>) -> Result<Request<()>, Status> {
        let Some(expected) = &self.expected else {
            return Ok(request);
        };
        let given = request
            .metadata()
            .get("authorization")
            .and_then(|v| v.to_str().ok());
        match given.and_then(|v| v.strip_prefix("Bearer ")) {
            Some(token) if token == &**expected => Ok(request),
            Some(_) => Err(Status::unauthenticated("invalid bearer token")),
            None => Err(Status::unauthenticated(
                "missing 'authorization: Bearer <token>' header",
            )),
        }
    }
}

/// Serves `daemon` on `listener` until `shutdown` completes, with an embedded worker rendering
/// on `gpu` (none: only remote workers render, `pointfarm worker`).
pub async fn serve(
    daemon: Arc<Daemon>,
    gpu: Option<Arc<GpuContext>>,
    listener: tokio::net::TcpListener,
    auth_token: Option<String>,
    shutdown: impl Future<Output = ()> + Send,
) -> anyhow::Result<()> {
    let stop = Arc::new(AtomicBool::new(false));
    let worker = gpu.map(|gpu| {
        let (daemon, stop) = (daemon.clone(), stop.clone());
        std::thread::Builder::new()
            .name("pointfarm-worker".into())
            .spawn(move || crate::worker::embedded::run(daemon, gpu, stop))
    });
    let worker = worker.transpose().context("starting the embedded worker")?;

    // Lost workers' frames go back to the queue within a fraction of the lease timeout.
    let sweeper = {
        let daemon = daemon.clone();
        let period = (daemon.config.lease_timeout / 4).clamp(
            std::time::Duration::from_millis(50),
            std::time::Duration::from_secs(1),
        );
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
    health.set_serving::<JobServiceServer<Api>>().await;
    health.set_serving::<WorkerServiceServer<Api>>().await;
    let reflection = tonic_reflection::server::Builder::configure()
        .register_encoded_file_descriptor_set(FILE_DESCRIPTOR_SET)
        .build_v1()
        .context("building the reflection service")?;

    let api = Api::new(daemon.clone());
    let auth = BearerAuth {
        expected: auth_token.map(Arc::from),
    };
    // Long-polling lease requests answer at once when the server begins to stop.
    let shutdown = {
        let daemon = daemon.clone();
        async move {
            shutdown.await;
            daemon.begin_shutdown();
        }
    };
    let address = listener.local_addr()?;
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

    tracing::info!("shutting down: finishing the current frame");
    stop.store(true, Ordering::SeqCst);
    daemon.work.notify();
    if let Some(worker) = worker {
        let joined = tokio::task::spawn_blocking(move || worker.join()).await;
        if !matches!(joined, Ok(Ok(()))) {
            tracing::error!("the worker thread ended abnormally");
        }
    }
    daemon.store.flush()?;
    Ok(())
}
