//! The metrics endpoint: `GET /metrics` over plain HTTP, answered with the text a
//! [`MetricsSource`] writes. Unauthenticated, as Prometheus scrapes usually are: it shows
//! counts and timings, never datasets, jobs' contents or tokens. It listens on loopback
//! unless given another address, and accepts through the same bounded, `TCP_NODELAY`
//! connections as the gRPC servers (`pointfarm_proto::endpoint::connections`): each
//! request admits its connection.

use std::net::SocketAddr;
use std::sync::Arc;

use anyhow::Context;
use axum::extract::connect_info::{ConnectInfo, Connected};
use axum::extract::State;
use axum::http::{header, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use axum::serve::IncomingStream;
use axum::Router;
use pointfarm_proto::endpoint::connections::{self, ConnectionInfo, ConnectionLimits};
use tokio::net::TcpListener;
use tokio::task::JoinHandle;

use super::CONTENT_TYPE;

/// Writes the metrics' text, or says why it cannot. It may block (the daemon reads its
/// state database), so it runs off the async threads.
pub type MetricsSource = Arc<dyn Fn() -> Result<String, String> + Send + Sync>;

/// Listens on `address` (`HOST:PORT`, or a bare port on loopback) and serves `GET /metrics`
/// there (see [`spawn`]); returns the address bound, whose port the system chose when
/// `address` asked for port 0.
pub async fn listen(
    address: &str,
    limits: ConnectionLimits,
    source: MetricsSource,
) -> anyhow::Result<SocketAddr> {
    let address = metrics_address(address);
    let listener = TcpListener::bind(&address)
        .await
        .with_context(|| format!("listening for metrics on {address}"))?;
    let bound = listener.local_addr()?;
    if !bound.ip().is_loopback() {
        tracing::warn!(
            %bound,
            "the metrics endpoint listens beyond loopback: it has no token, so let only the \
             scrapers reach it"
        );
    }
    spawn(listener, limits, source);
    Ok(bound)
}

/// `address` with loopback for a bare port.
fn metrics_address(address: &str) -> String {
    match address.trim().parse::<u16>() {
        Ok(port) => format!("127.0.0.1:{port}"),
        Err(_) => address.to_string(),
    }
}

/// Serves `GET /metrics` on `listener` until the task is aborted or the runtime ends.
pub fn spawn(
    listener: TcpListener,
    limits: ConnectionLimits,
    source: MetricsSource,
) -> JoinHandle<()> {
    let app = Router::new()
        .route("/metrics", get(metrics))
        .with_state(source)
        .into_make_service_with_connect_info::<MetricsConnection>();
    let listener = MetricsListener(connections::Listener::new(listener, limits));
    tokio::spawn(async move {
        if let Err(e) = axum::serve(listener, app).await {
            tracing::error!(error = %e, "the metrics endpoint stopped");
        }
    })
}

/// The bounded listener, as axum takes listeners.
struct MetricsListener(connections::Listener);

impl axum::serve::Listener for MetricsListener {
    type Io = connections::Connection;
    type Addr = ConnectionInfo;

    async fn accept(&mut self) -> (Self::Io, Self::Addr) {
        loop {
            match self.0.accept().await {
                Ok(connection) => {
                    let info = connection.info().clone();
                    return (connection, info);
                }
                // The listener pauses by itself when descriptors run out.
                Err(error) => tracing::debug!(%error, "accepting a metrics connection"),
            }
        }
    }

    fn local_addr(&self) -> std::io::Result<Self::Addr> {
        Err(std::io::Error::other(
            "a metrics listener's address is the one `listen` returns",
        ))
    }
}

/// The connection a metrics request came in on.
#[derive(Clone)]
struct MetricsConnection(ConnectionInfo);

impl Connected<IncomingStream<'_, MetricsListener>> for MetricsConnection {
    fn connect_info(stream: IncomingStream<'_, MetricsListener>) -> Self {
        Self(stream.remote_addr().clone())
    }
}

async fn metrics(
    ConnectInfo(connection): ConnectInfo<MetricsConnection>,
    State(source): State<MetricsSource>,
) -> Response {
    connection.0.admit();
    let _in_flight = connection.0.begin_request();
    match tokio::task::spawn_blocking(move || source()).await {
        Ok(Ok(text)) => ([(header::CONTENT_TYPE, CONTENT_TYPE)], text).into_response(),
        Ok(Err(reason)) => {
            tracing::warn!(%reason, "metrics could not be read");
            (StatusCode::INTERNAL_SERVER_ERROR, reason).into_response()
        }
        Err(e) => (StatusCode::INTERNAL_SERVER_ERROR, e.to_string()).into_response(),
    }
}
