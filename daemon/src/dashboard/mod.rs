//! The dashboard: the farm in a browser, on a listener of its own (`serve --dashboard-listen`).
//!
//! Server-rendered pages (jobs, a job's frames as thumbnails, a frame, workers, datasets) with
//! a little vanilla JavaScript that follows the daemon's job events over server-sent events,
//! and a JSON API beside them whose bodies are the proto3 JSON mapping of the gRPC messages,
//! for scripts. Everything it shows comes from the same `Daemon` methods the gRPC handlers
//! call; it never speaks gRPC.
//!
//! - `auth`: the client token, given once to a login form (a signed session cookie follows)
//!   or as `Authorization: Bearer` by scripts; the worker token opens nothing here; a state
//!   change made with a cookie must come from the dashboard's own origin; `login_limit`
//!   slows then refuses an address that gives wrong tokens.
//! - `listener`: the bounded connections of `pointfarm_proto::endpoint::connections`, with
//!   TLS when the API has it.
//! - `filter`: which jobs a list shows (state, labels, a part of the name), from the URL.
//! - `api` (JSON), `actions` (cancel, pause, resume, retry, priority, delete), `events`
//!   (server-sent events), `pages` (the jobs), `workers` and `datasets` (their page, and the
//!   workers' JSON), `html` (what the pages share), `frames` (frame images and thumbnails),
//!   `assets/` (CSS and JavaScript, built into the binary).

use std::net::SocketAddr;
use std::sync::Arc;

use anyhow::Context;
use axum::extract::connect_info::ConnectInfo;
use axum::extract::Request;
use axum::http::header;
use axum::middleware::{self, Next};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use axum::Router;
use pointfarm_proto::endpoint::connections::{ConnectionLayer, ConnectionLimits};
use tokio::net::TcpListener;

use crate::access::{Access, Exposure};
use crate::server::TlsIdentity;
use crate::service::Daemon;

mod actions;
mod api;
mod auth;
mod datasets;
mod events;
mod failure;
mod filter;
mod frames;
mod html;
mod listener;
mod login_limit;
mod pages;
mod workers;

use auth::Sessions;
use listener::{DashboardConnection, DashboardListener};
pub use login_limit::LoginLimit;

/// Who may open the dashboard and how it is reached.
#[derive(Clone)]
pub struct DashboardOptions {
    /// The API's tokens: the client token opens the dashboard.
    pub access: Access,
    /// The API's certificate and key: the dashboard serves HTTPS with them.
    pub tls: Option<TlsIdentity>,
    /// Listen beyond loopback without a client token or without TLS, knowingly.
    pub insecure: bool,
    pub connection_limits: ConnectionLimits,
}

/// What every handler shares.
#[derive(Clone)]
struct Dashboard {
    daemon: Arc<Daemon>,
    sessions: Arc<Sessions>,
    tls: bool,
}

/// Listens on `address` and serves the dashboard there until the process ends; returns the
/// address bound and the URL scheme (`http` or `https`). Refuses to listen beyond loopback
/// without a client token or TLS, as the API does, unless `options.insecure`.
pub async fn listen(
    address: &str,
    daemon: Arc<Daemon>,
    options: DashboardOptions,
) -> anyhow::Result<(SocketAddr, &'static str)> {
    listen_limiting_logins(address, daemon, options, LoginLimit::DEFAULT).await
}

/// [`listen`] with wrong tokens slowed and refused as `login_limit` says.
pub async fn listen_limiting_logins(
    address: &str,
    daemon: Arc<Daemon>,
    options: DashboardOptions,
    login_limit: LoginLimit,
) -> anyhow::Result<(SocketAddr, &'static str)> {
    let tls = match &options.tls {
        Some(identity) => Some(listener::tls_acceptor(identity)?),
        None => None,
    };
    let scheme = if tls.is_some() { "https" } else { "http" };
    let socket = TcpListener::bind(address)
        .await
        .with_context(|| format!("listening for the dashboard on {address}"))?;
    let bound = socket.local_addr()?;
    options
        .access
        .check_exposure(Exposure {
            address: bound,
            tls: tls.is_some(),
            insecure: options.insecure,
        })
        .map_err(|refusal| anyhow::anyhow!("the dashboard (--dashboard-listen): {refusal}"))?;
    let dashboard = Dashboard {
        daemon,
        sessions: Arc::new(Sessions::new(options.access, login_limit)),
        tls: tls.is_some(),
    };
    let listener = DashboardListener::start(socket, options.connection_limits, tls);
    let app = router(dashboard).into_make_service_with_connect_info::<DashboardConnection>();
    tokio::spawn(async move {
        if let Err(e) = axum::serve(listener, app).await {
            tracing::error!(error = %e, "the dashboard stopped");
        }
    });
    Ok((bound, scheme))
}

/// Every route: the login form and the assets are open, everything else needs the client
/// token. Each module routes the paths its handlers answer.
fn router(dashboard: Dashboard) -> Router {
    let guarded = [
        pages::routes(),
        frames::routes(),
        actions::routes(),
        api::routes(),
        events::routes(),
        workers::routes(),
        datasets::routes(),
        auth::routes(),
    ]
    .into_iter()
    .fold(Router::new(), Router::merge)
    .route_layer(middleware::from_fn_with_state(
        dashboard.clone(),
        auth::require_client,
    ));
    Router::new()
        .route("/login", get(auth::login_form).post(auth::login))
        .route("/assets/dashboard.css", get(stylesheet))
        .route("/assets/dashboard.js", get(script))
        .merge(guarded)
        .with_state(dashboard)
        .layer(ConnectionLayer)
        .layer(middleware::from_fn(connection_info))
}

/// Puts the connection's record where [`ConnectionLayer`] reads it, so that a request in
/// flight (an event stream) keeps its connection from being closed as idle.
async fn connection_info(
    ConnectInfo(connection): ConnectInfo<DashboardConnection>,
    mut request: Request,
    next: Next,
) -> Response {
    request.extensions_mut().insert(connection.0);
    next.run(request).await
}

const STYLESHEET: &str = include_str!("assets/dashboard.css");
const SCRIPT: &str = include_str!("assets/dashboard.js");

/// Static code, no data: served without a token so that the login form is styled.
async fn stylesheet() -> Response {
    asset("text/css; charset=utf-8", STYLESHEET)
}

async fn script() -> Response {
    asset("text/javascript; charset=utf-8", SCRIPT)
}

fn asset(content_type: &'static str, body: &'static str) -> Response {
    (
        [
            (header::CONTENT_TYPE, content_type),
            (header::CACHE_CONTROL, "no-cache"),
        ],
        body,
    )
        .into_response()
}
