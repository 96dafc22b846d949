//! Serving the API: the gRPC services with health checking and reflection (v1 and v1alpha, so
//! `grpcurl` and older tools work out of the box), TLS, the roles' tokens (`access`), the
//! embedded worker process on a loopback listener of its own, the sweep that expires the
//! leases of lost workers, and a graceful shutdown that lets the current frame finish.
//!
//! Every listener accepts through `pointfarm_proto::endpoint::connections`: TCP_NODELAY and
//! keepalive on each socket, and bounds on connections that make no admitted call or sit idle.
//! The interceptors that check tokens mark a connection admitted. Reflection needs the
//! client token where one is set: it maps the whole API for whoever asks.
//!
//! Stopping: once asked, the daemon stops accepting, lets calls in flight and the embedded
//! worker's frame finish for at most its shutdown grace, then stops whatever still runs (a
//! call blocked on a hung disk or a stalled upload never holds the process).
//!
//! Health: the overall service ("") and `JobService` are SERVING while some worker can render
//! (the embedded worker is up, or a remote worker was heard from within the lease timeout)
//! and NOT_SERVING otherwise; `DatasetService` and `WorkerService` answer whenever the daemon
//! does, since uploads and workers need them to get going.

use std::future::Future;
use std::net::Ipv4Addr;
use std::sync::Arc;
use std::time::Duration;

use anyhow::Context;
use pointfarm_proto::endpoint::certificate;
use pointfarm_proto::endpoint::connections::{self, ConnectionLimits};
use pointfarm_proto::v1::dataset_service_server::DatasetServiceServer;
use pointfarm_proto::v1::job_service_server::JobServiceServer;
use pointfarm_proto::v1::worker_service_server::WorkerServiceServer;
use pointfarm_proto::v1::FILE_DESCRIPTOR_SET;
use rand::Rng;
use tonic::service::interceptor::InterceptedService;
use tonic::{Request, Status};
use tonic_health::server::HealthReporter;
use tonic_health::ServingStatus;

use crate::access::{bearer_token, Access, Exposure, Role};
use crate::grpc::{Api, EmbeddedWorkerCall};
use crate::service::Daemon;
use crate::supervisor::{Supervisor, WorkerCommand};

/// How the daemon is reached: who may call (tokens per role), TLS, and whether to serve
/// beyond loopback without them.
#[derive(Clone)]
pub struct ServeOptions {
    pub access: Access,
    pub tls: Option<TlsIdentity>,
    /// Listen beyond loopback without a client token or without TLS.
    pub insecure: bool,
    /// Serve the health service alone, in plaintext, on this address too: Kubernetes' gRPC
    /// probes cannot speak TLS, and health statuses are no secret.
    pub health_listen: Option<std::net::SocketAddr>,
    /// The bounds on each listener's connections.
    pub connection_limits: ConnectionLimits,
    /// How long stopping waits for calls in flight and the embedded worker's frame.
    pub shutdown_grace: Duration,
}

/// How long stopping waits by default: longer than a typical frame, shorter than a service
/// manager's stop timeout.
pub const DEFAULT_SHUTDOWN_GRACE: Duration = Duration::from_secs(30);

impl Default for ServeOptions {
    fn default() -> Self {
        Self {
            access: Access::default(),
            tls: None,
            insecure: false,
            health_listen: None,
            connection_limits: ConnectionLimits::default(),
            shutdown_grace: DEFAULT_SHUTDOWN_GRACE,
        }
    }
}

impl ServeOptions {
    /// Refuses to serve on `address` beyond loopback without a client token or TLS, unless
    /// `insecure` ([`Access::check_exposure`]).
    pub fn check_exposure(&self, address: std::net::SocketAddr) -> anyhow::Result<()> {
        self.access
            .check_exposure(Exposure {
                address,
                tls: self.tls.is_some(),
                insecure: self.insecure,
            })
            .map_err(anyhow::Error::msg)
    }
}

/// The server's certificate chain and private key, PEM-encoded.
#[derive(Clone)]
pub struct TlsIdentity {
    pub cert_pem: Vec<u8>,
    pub key_pem: Vec<u8>,
}

/// Refuses a certificate file without a certificate, and says at start when clients will
/// refuse the server's certificate: one marked as a certificate authority is never accepted as
/// a server's own, whoever trusts it.
fn check_certificate(cert_pem: &[u8]) -> anyhow::Result<()> {
    let is_ca = certificate::is_ca_certificate(cert_pem)
        .map_err(|reason| anyhow::anyhow!("the TLS certificate (--tls-cert) {reason}"))?;
    if is_ca {
        tracing::warn!(
            "the TLS certificate (--tls-cert) is a CA certificate (basicConstraints CA:TRUE), \
             which clients refuse as a server's own: {}",
            certificate::SERVER_CERTIFICATE_HOWTO
        );
    }
    Ok(())
}

/// The embedded worker's listener admits only calls with the token made for it at start-up;
/// they carry [`EmbeddedWorkerCall`].
#[derive(Clone)]
struct EmbeddedGate(Arc<str>);

impl tonic::service::Interceptor for EmbeddedGate {
    fn call(&mut self, mut request: Request<()>) -> Result<Request<()>, Status> {
        // The token is random and new for every start; comparing it is no timing oracle for
        // the clients' or workers' tokens, which this listener never accepts.
        if bearer_token(&request) != Some(&*self.0) {
            return Err(Status::unauthenticated(
                "this listener serves only the daemon's embedded worker",
            ));
        }
        connections::admit_connection(&request);
        request.extensions_mut().insert(EmbeddedWorkerCall);
        Ok(request)
    }
}

/// A token for the embedded worker, new for every start of the daemon.
fn embedded_worker_token() -> String {
    let bytes: [u8; 32] = rand::rng().random();
    crate::model::hex(&bytes)
}

/// How often the lease sweep and the health check run: a fraction of the lease timeout.
fn sweep_period(lease_timeout: Duration) -> Duration {
    (lease_timeout / 4).clamp(Duration::from_millis(50), Duration::from_secs(1))
}

/// Serves `daemon` on `listener` until `shutdown` completes, with an embedded worker process
/// started by `embedded_worker` (none: only remote workers render, `pointfarm worker`).
/// Refuses to start beyond loopback without a client token or TLS unless `options.insecure`.
pub async fn serve(
    daemon: Arc<Daemon>,
    embedded_worker: Option<WorkerCommand>,
    listener: tokio::net::TcpListener,
    options: ServeOptions,
    shutdown: impl Future<Output = ()> + Send,
) -> anyhow::Result<()> {
    let address = listener.local_addr()?;
    options.check_exposure(address)?;
    let mut server = pointfarm_proto::endpoint::server_builder();
    if let Some(tls) = &options.tls {
        check_certificate(&tls.cert_pem)?;
        server = server
            .tls_config(pointfarm_proto::endpoint::server_tls(
                &tls.cert_pem,
                &tls.key_pem,
            ))
            .map_err(|e| {
                anyhow::anyhow!(
                    "the TLS certificate and key (--tls-cert, --tls-key): {}",
                    certificate::identity_error(&e)
                )
            })?;
    }
    let limits = options.connection_limits;
    let api = Api::new(daemon.clone());
    let embedded = match embedded_worker {
        Some(command) => {
            Some(EmbeddedListener::start(daemon.clone(), api.clone(), command, limits).await?)
        }
        None => None,
    };

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
                let sweep = move || daemon.expire_leases().and_then(|_| daemon.expire_encodes());
                match tokio::task::spawn_blocking(sweep).await {
                    Ok(Ok(_)) => {}
                    Ok(Err(e)) => tracing::error!(error = %e, "expiring leases"),
                    Err(e) => tracing::error!(error = %e, "the lease sweep panicked"),
                }
            }
        })
    };

    let retention = crate::retention::spawn_sweep(daemon.clone());

    let (health, health_service) = tonic_health::server::health_reporter();
    health.set_serving::<DatasetServiceServer<Api>>().await;
    health.set_serving::<WorkerServiceServer<Api>>().await;
    // Registered before the first connection, so a check never finds them unknown; the
    // watch below sets them SERVING once a worker can render.
    health.set_not_serving::<JobServiceServer<Api>>().await;
    health
        .set_service_status("", ServingStatus::NotServing)
        .await;
    let health_watch = tokio::spawn(report_health(daemon.clone(), health));
    let health_only = match options.health_listen {
        Some(address) => {
            let listener = tokio::net::TcpListener::bind(address)
                .await
                .with_context(|| format!("listening for health checks on {address}"))?;
            tracing::info!(address = %listener.local_addr()?, "serving health checks");
            let server = pointfarm_proto::endpoint::server_builder()
                .add_service(health_service.clone())
                .serve_with_incoming(connections::Listener::new(listener, limits));
            Some(tokio::spawn(async move {
                if let Err(e) = server.await {
                    tracing::error!(error = %e, "the health checks' listener stopped");
                }
            }))
        }
        None => None,
    };
    // grpcurl and grpcio-reflection speak v1; older tools only v1alpha.
    let reflection = tonic_reflection::server::Builder::configure()
        .register_encoded_file_descriptor_set(FILE_DESCRIPTOR_SET)
        .build_v1()
        .context("building the reflection service")?;
    let reflection_v1alpha = tonic_reflection::server::Builder::configure()
        .register_encoded_file_descriptor_set(FILE_DESCRIPTOR_SET)
        .build_v1alpha()
        .context("building the reflection service")?;
    // Long-polling lease requests answer at once when the server begins to stop; the server
    // serves on until the embedded worker has handed in its current frame, within the grace.
    let (stopping, stopped) = tokio::sync::oneshot::channel::<()>();
    let shutdown = {
        let daemon = daemon.clone();
        let grace = options.shutdown_grace;
        async move {
            shutdown.await;
            let _ = stopping.send(());
            tracing::info!(
                grace_s = grace.as_secs_f64(),
                "shutting down: finishing the current frame"
            );
            daemon.begin_shutdown();
            if let Some(embedded) = embedded {
                if tokio::time::timeout(grace, embedded.stop()).await.is_err() {
                    tracing::warn!("the embedded worker did not stop within the shutdown grace");
                }
            }
        }
    };
    let access = &options.access;
    tracing::info!(%address, tls = options.tls.is_some(), "serving pointfarm.v1");
    let served = server
        .add_service(health_service)
        .add_service(InterceptedService::new(
            reflection,
            access.gate(Role::Client),
        ))
        .add_service(InterceptedService::new(
            reflection_v1alpha,
            access.gate(Role::Client),
        ))
        .add_service(DatasetServiceServer::with_interceptor(
            api.clone(),
            access.gate(Role::Client),
        ))
        .add_service(JobServiceServer::with_interceptor(
            api.clone(),
            access.gate(Role::Client),
        ))
        .add_service(WorkerServiceServer::with_interceptor(
            api,
            access.gate(Role::Worker),
        ))
        .serve_with_incoming_shutdown(connections::Listener::new(listener, limits), shutdown);
    // Stopping waits for the calls in flight, but never past the grace after it began.
    let grace = options.shutdown_grace;
    let past_grace = async move {
        if stopped.await.is_ok() {
            tokio::time::sleep(grace).await;
        } else {
            std::future::pending::<()>().await;
        }
    };
    tokio::select! {
        served = served => served.context("gRPC server")?,
        () = past_grace => tracing::warn!(
            grace_s = grace.as_secs_f64(),
            "calls were still in flight at the end of the shutdown grace: stopping without them"
        ),
    }
    sweeper.abort();
    retention.abort();
    health_watch.abort();
    if let Some(health_only) = health_only {
        health_only.abort();
    }
    daemon.state.flush()?;
    Ok(())
}

/// The embedded worker process and the loopback listener only it can use (plaintext: it never
/// leaves the machine, and its token is new for every start).
struct EmbeddedListener {
    supervisor: Supervisor,
    stop: tokio::sync::oneshot::Sender<()>,
    server: tokio::task::JoinHandle<Result<(), tonic::transport::Error>>,
}

impl EmbeddedListener {
    async fn start(
        daemon: Arc<Daemon>,
        api: Api,
        command: WorkerCommand,
        limits: ConnectionLimits,
    ) -> anyhow::Result<Self> {
        let listener = tokio::net::TcpListener::bind((Ipv4Addr::LOCALHOST, 0))
            .await
            .context("listening on loopback for the embedded worker")?;
        let address = listener.local_addr()?;
        let token = embedded_worker_token();
        let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
        let gate = EmbeddedGate(Arc::from(token.as_str()));
        let server = tokio::spawn(
            pointfarm_proto::endpoint::server_builder()
                .add_service(WorkerServiceServer::with_interceptor(api, gate))
                .serve_with_incoming_shutdown(
                    connections::Listener::new(listener, limits),
                    async {
                        let _ = stopped.await;
                    },
                ),
        );
        let supervisor = Supervisor::start(daemon, command, address, token);
        Ok(Self {
            supervisor,
            stop,
            server,
        })
    }

    /// Stops the worker once it has handed in its frame, then the listener.
    async fn stop(self) {
        self.supervisor.stop().await;
        let _ = self.stop.send(());
        match self.server.await {
            Ok(Ok(())) => {}
            Ok(Err(e)) => tracing::error!(error = %e, "the embedded worker's listener"),
            Err(e) => tracing::error!(error = %e, "the embedded worker's listener panicked"),
        }
    }
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
        // A full disk stores no frames: the state database logs it once, health follows it.
        let workers = daemon.workers.can_render(timeout);
        let disk = daemon.state.outage().is_none();
        let can_render = workers && disk && !daemon.is_stopping();
        if reported == Some(can_render) {
            continue;
        }
        let status = if can_render {
            tracing::info!("a worker can render: SERVING");
            ServingStatus::Serving
        } else {
            if daemon.is_stopping() {
                tracing::info!("stopping: NOT_SERVING");
            } else if !disk {
                tracing::warn!("the disk refuses writes: NOT_SERVING until it takes them again");
            } else {
                tracing::warn!("no worker can render: NOT_SERVING until one is back");
            }
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
