//! The metrics endpoint: `GET /metrics` over plain HTTP, answered with the text a
//! [`MetricsSource`] writes. Unauthenticated, as Prometheus scrapes usually are: it shows
//! counts and timings, never datasets, jobs' contents or tokens.

use std::net::SocketAddr;
use std::sync::Arc;

use anyhow::Context;
use axum::extract::State;
use axum::http::{header, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use axum::Router;
use tokio::net::TcpListener;
use tokio::task::JoinHandle;

use super::CONTENT_TYPE;

/// Writes the metrics' text, or says why it cannot. It may block (the daemon reads its
/// store), so it runs off the async threads.
pub type MetricsSource = Arc<dyn Fn() -> Result<String, String> + Send + Sync>;

/// Listens on `address` and serves `GET /metrics` there (see [`spawn`]); returns the address
/// bound, whose port the system chose when `address` asked for port 0.
pub async fn listen(address: &str, source: MetricsSource) -> anyhow::Result<SocketAddr> {
    let listener = TcpListener::bind(address)
        .await
        .with_context(|| format!("listening for metrics on {address}"))?;
    let bound = listener.local_addr()?;
    spawn(listener, source);
    Ok(bound)
}

/// Serves `GET /metrics` on `listener` until the task is aborted or the runtime ends.
pub fn spawn(listener: TcpListener, source: MetricsSource) -> JoinHandle<()> {
    let app = Router::new()
        .route("/metrics", get(metrics))
        .with_state(source);
    tokio::spawn(async move {
        if let Err(e) = axum::serve(listener, app).await {
            tracing::error!(error = %e, "the metrics endpoint stopped");
        }
    })
}

async fn metrics(State(source): State<MetricsSource>) -> Response {
    match tokio::task::spawn_blocking(move || source()).await {
        Ok(Ok(text)) => ([(header::CONTENT_TYPE, CONTENT_TYPE)], text).into_response(),
        Ok(Err(reason)) => {
            tracing::warn!(%reason, "metrics could not be read");
            (StatusCode::INTERNAL_SERVER_ERROR, reason).into_response()
        }
        Err(e) => (StatusCode::INTERNAL_SERVER_ERROR, e.to_string()).into_response(),
    }
}
