//! Who may open the dashboard: whoever holds the client token, as for the gRPC API.
//!
//! - Scripts send `Authorization: Bearer TOKEN` with every request.
//! - A browser gives the token once to the login form and gets a session cookie
//!   (`HttpOnly`, `SameSite=Strict`, `Secure` over TLS): an expiry and a random nonce, signed
//!   with HMAC-SHA256 under a key drawn at start, so it holds no part of the token, cannot be
//!   forged and ends with the daemon or after [`SESSION_SECONDS`].
//! - The tokens are checked by the gRPC API's own client gate (`access.rs`): the worker token
//!   opens nothing here, and a daemon without a client token (loopback development) is open
//!   as its API is.
//! - A request that changes state (anything but GET and HEAD) made with a cookie, or without
//!   any credential on an open daemon, must carry an `Origin` equal to the dashboard's own:
//!   with the `SameSite=Strict` cookie this refuses cross-site forms and scripts. A bearer
//!   token is never sent by a browser on its own, so scripts that send one need no `Origin`.
//! - Wrong tokens, to the form or as a bearer, are slowed then refused per client address
//!   (`login_limit`).

use std::net::IpAddr;
use std::time::Instant;

use axum::body::Bytes;
use axum::extract::{ConnectInfo, Request, State};
use axum::http::{header, HeaderMap, HeaderValue, Method, StatusCode};
use axum::middleware::Next;
use axum::response::{Html, IntoResponse, Response};
use axum::routing::post;
use axum::Router;
use hmac::{Hmac, Mac};
use pointfarm_proto::endpoint::connections::ConnectionInfo;
use rand::Rng;
use sha2::Sha256;
use tonic::metadata::MetadataValue;
use tonic::service::Interceptor;

use super::listener::DashboardConnection;
use super::login_limit::{LoginAttempts, LoginLimit, Refused};
use super::{html, Dashboard};
use crate::access::{Access, Role};
use crate::model::{hex, now_unix_ms};

/// The session cookie's name.
pub const COOKIE: &str = "pointfarm_session";

/// How long a session lasts: a working day.
pub const SESSION_SECONDS: i64 = 12 * 3600;

/// The tokens, the key that signs sessions, and the wrong tokens given by each address.
pub struct Sessions {
    access: Access,
    key: [u8; 32],
    attempts: LoginAttempts,
}

/// How a request was let in.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Admission {
    /// The daemon has no client token.
    Open,
    Bearer,
    Cookie,
}

/// Why a request was refused.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Refusal {
    /// No credential, or a session that is not (or no longer) valid.
    NoSession,
    /// A bearer token that is no token of this daemon.
    InvalidToken,
    /// The worker token, which opens nothing here.
    WorkerToken,
}

impl Sessions {
    pub fn new(access: Access, login_limit: LoginLimit) -> Self {
        Self {
            access,
            key: rand::rng().random(),
            attempts: LoginAttempts::new(login_limit),
        }
    }

    /// Checks `token`, given by `address`, counting it against the address when it is wrong:
    /// `Err(Err(refused))` when the address may give no token now, `Err(Ok(refusal))` (after
    /// the address's delay) for a wrong one.
    async fn check_token_from(
        &self,
        address: Option<IpAddr>,
        token: Option<&str>,
    ) -> Result<(), Result<Refusal, Refused>> {
        let Some(address) = address else {
            return self.check_token(token).map_err(Ok);
        };
        self.attempts
            .check(address, Instant::now())
            .map_err(|refused| {
                tracing::debug!(%address, "a token refused: too many wrong ones from the address");
                Err(refused)
            })?;
        match self.check_token(token) {
            Ok(()) => {
                self.attempts.succeeded(address);
                Ok(())
            }
            Err(Refusal::InvalidToken) => {
                let (failures, delay) = self.attempts.failed(address, Instant::now());
                tracing::warn!(%address, failures, "a wrong dashboard token");
                tokio::time::sleep(delay).await;
                Err(Ok(Refusal::InvalidToken))
            }
            Err(refusal) => Err(Ok(refusal)),
        }
    }

    /// Checks `token` (or its absence) with the gRPC API's client gate.
    fn check_token(&self, token: Option<&str>) -> Result<(), Refusal> {
        let mut request = tonic::Request::new(());
        if let Some(token) = token {
            let value = MetadataValue::try_from(format!("Bearer {token}"))
                .map_err(|_| Refusal::InvalidToken)?;
            request.metadata_mut().insert("authorization", value);
        }
        match self.access.gate(Role::Client).call(request) {
            Ok(_) => Ok(()),
            Err(status) if status.code() == tonic::Code::PermissionDenied => {
                Err(Refusal::WorkerToken)
            }
            Err(_) if token.is_none() => Err(Refusal::NoSession),
            Err(_) => Err(Refusal::InvalidToken),
        }
    }

    /// Whether the daemon has no client token, so that anyone on loopback may use it.
    fn is_open(&self) -> bool {
        self.check_token(None).is_ok()
    }

    /// Lets in a request by its bearer token (counted against `address` when wrong), its
    /// session, or an open daemon.
    async fn admit_from(
        &self,
        address: Option<IpAddr>,
        headers: &HeaderMap,
    ) -> Result<Admission, Result<Refusal, Refused>> {
        match bearer_token(headers) {
            Some(token) => self
                .check_token_from(address, token)
                .await
                .map(|()| Admission::Bearer),
            None => self.admit(headers).map_err(Ok),
        }
    }

    fn admit(&self, headers: &HeaderMap) -> Result<Admission, Refusal> {
        if let Some(token) = bearer_token(headers) {
            let token = token.ok_or(Refusal::InvalidToken)?;
            return self.check_token(Some(token)).map(|()| Admission::Bearer);
        }
        if self.is_open() {
            return Ok(Admission::Open);
        }
        match session_cookie(headers) {
            Some(value) if self.verify(value, now_unix_ms() / 1000) => Ok(Admission::Cookie),
            _ => Err(Refusal::NoSession),
        }
    }

    fn mac(&self) -> Hmac<Sha256> {
        Hmac::<Sha256>::new_from_slice(&self.key).expect("HMAC takes keys of any length")
    }

    /// A new session's cookie value, valid until `now_s` + [`SESSION_SECONDS`]:
    /// `EXPIRY.NONCE.MAC`.
    fn new_session(&self, now_s: i64) -> String {
        let nonce: [u8; 16] = rand::rng().random();
        let claims = format!("{}.{}", now_s + SESSION_SECONDS, hex(&nonce));
        let mut mac = self.mac();
        mac.update(claims.as_bytes());
        format!("{claims}.{}", hex(&mac.finalize().into_bytes()))
    }

    /// Whether `value` is a session this daemon signed that has not expired at `now_s`; the
    /// signature is compared in constant time.
    fn verify(&self, value: &str, now_s: i64) -> bool {
        let Some((claims, signature)) = value.rsplit_once('.') else {
            return false;
        };
        let Some(signature) = unhex(signature) else {
            return false;
        };
        let mut mac = self.mac();
        mac.update(claims.as_bytes());
        if mac.verify_slice(&signature).is_err() {
            return false;
        }
        claims
            .split_once('.')
            .and_then(|(expiry, _)| expiry.parse::<i64>().ok())
            .is_some_and(|expiry| now_s < expiry)
    }

    /// The `Set-Cookie` value of a new session.
    fn session_header(&self, secure: bool) -> String {
        format!(
            "{COOKIE}={}; Path=/; Max-Age={SESSION_SECONDS}; HttpOnly; SameSite=Strict{}",
            self.new_session(now_unix_ms() / 1000),
            if secure { "; Secure" } else { "" }
        )
    }
}

/// The token of an `Authorization` header: `None` without one, `Some(None)` when it is no
/// bearer token.
fn bearer_token(headers: &HeaderMap) -> Option<Option<&str>> {
    let value = headers.get(header::AUTHORIZATION)?;
    Some(
        value
            .to_str()
            .ok()
            .and_then(|value| value.strip_prefix("Bearer ")),
    )
}

/// The client address of a request, as its connection was accepted.
fn client_address(request: &Request) -> Option<IpAddr> {
    let connection = request.extensions().get::<ConnectionInfo>()?;
    connection.remote_addr().map(|address| address.ip())
}

/// An address refused for its wrong tokens: 429 with `Retry-After`, as a page of the login
/// form for a browser.
fn too_many(refused: Refused, page: Option<&str>) -> Response {
    let seconds = refused.retry_after_seconds();
    let message = format!(
        "Too many wrong tokens from this address: try again in {}.",
        html::duration(seconds as f64)
    );
    let retry_after = [(header::RETRY_AFTER, seconds.to_string())];
    match page {
        Some(next) => (
            StatusCode::TOO_MANY_REQUESTS,
            retry_after,
            Html(html::login_page(Some(&message), next)),
        )
            .into_response(),
        None => (StatusCode::TOO_MANY_REQUESTS, retry_after, message).into_response(),
    }
}

fn unhex(text: &str) -> Option<Vec<u8>> {
    if !text.len().is_multiple_of(2) {
        return None;
    }
    (0..text.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(text.get(i..i + 2)?, 16).ok())
        .collect()
}

/// The session cookie of a request, if it sends one.
fn session_cookie(headers: &HeaderMap) -> Option<&str> {
    headers
        .get_all(header::COOKIE)
        .iter()
        .filter_map(|value| value.to_str().ok())
        .flat_map(|cookies| cookies.split(';'))
        .filter_map(|cookie| cookie.trim().split_once('='))
        .find(|(name, _)| *name == COOKIE)
        .map(|(_, value)| value)
}

/// Whether the request's `Origin` is the dashboard itself, as the browser reached it.
fn same_origin(headers: &HeaderMap, tls: bool) -> bool {
    let header_text = |name| {
        headers
            .get(name)
            .and_then(|v: &HeaderValue| v.to_str().ok())
    };
    let (Some(origin), Some(host)) = (header_text(header::ORIGIN), header_text(header::HOST))
    else {
        return false;
    };
    let scheme = if tls { "https" } else { "http" };
    origin.eq_ignore_ascii_case(&format!("{scheme}://{host}"))
}

/// Lets a request through with the client token (or on an open daemon), and a state change
/// only from the dashboard's own origin; admits its connection.
pub async fn require_client(
    State(dashboard): State<Dashboard>,
    request: Request,
    next: Next,
) -> Response {
    let address = client_address(&request);
    let admitted = dashboard
        .sessions
        .admit_from(address, request.headers())
        .await;
    let admission = match admitted {
        Ok(admission) => admission,
        Err(Ok(refusal)) => return refused(&request, refusal),
        Err(Err(limited)) => return too_many(limited, None),
    };
    if let Some(connection) = request.extensions().get::<ConnectionInfo>() {
        connection.admit();
    }
    let changes_state = !matches!(*request.method(), Method::GET | Method::HEAD);
    if changes_state
        && admission != Admission::Bearer
        && !same_origin(request.headers(), dashboard.tls)
    {
        return (
            StatusCode::FORBIDDEN,
            "refused: a change must come from the dashboard's own page (its Origin), or \
             carry 'Authorization: Bearer <token>'",
        )
            .into_response();
    }
    next.run(request).await
}

/// A refused request: pages send browsers to the login form; the API and bearer tokens are
/// answered with their status.
fn refused(request: &Request, refusal: Refusal) -> Response {
    let path = request.uri().path();
    match refusal {
        Refusal::NoSession if !path.starts_with("/api/") && request.method() == Method::GET => {
            let next = request.uri().path_and_query().map_or("/", |p| p.as_str());
            let location = format!(
                "/login?next={}",
                form_urlencoded::byte_serialize(next.as_bytes()).collect::<String>()
            );
            (StatusCode::SEE_OTHER, [(header::LOCATION, location)]).into_response()
        }
        Refusal::NoSession => (
            StatusCode::UNAUTHORIZED,
            [(header::WWW_AUTHENTICATE, "Bearer")],
            "missing 'Authorization: Bearer <token>' header or session",
        )
            .into_response(),
        Refusal::InvalidToken => (
            StatusCode::UNAUTHORIZED,
            [(header::WWW_AUTHENTICATE, "Bearer")],
            "invalid bearer token",
        )
            .into_response(),
        Refusal::WorkerToken => (
            StatusCode::FORBIDDEN,
            "the worker token (--worker-token) opens nothing on the dashboard: use the client \
             token",
        )
            .into_response(),
    }
}

/// A path of this dashboard to go to after logging in; anything else goes to the jobs.
fn local_path(next: Option<&str>) -> String {
    match next {
        Some(path) if path.starts_with('/') && !path.starts_with("//") && !path.contains('\\') => {
            path.to_string()
        }
        _ => "/".to_string(),
    }
}

fn redirect(location: &str) -> Response {
    (StatusCode::SEE_OTHER, [(header::LOCATION, location)]).into_response()
}

/// The login form; a browser that already has a session (or an open daemon) goes on.
pub async fn login_form(
    State(dashboard): State<Dashboard>,
    axum::extract::RawQuery(query): axum::extract::RawQuery,
    headers: HeaderMap,
) -> Response {
    let next = query
        .as_deref()
        .and_then(|query| field(query.as_bytes(), "next"));
    let next = local_path(next.as_deref());
    if dashboard.sessions.admit(&headers).is_ok() {
        return redirect(&next);
    }
    Html(html::login_page(None, &next)).into_response()
}

/// Takes the token from the login form; sets the session cookie when it is the client token.
pub async fn login(
    State(dashboard): State<Dashboard>,
    ConnectInfo(connection): ConnectInfo<DashboardConnection>,
    headers: HeaderMap,
    body: Bytes,
) -> Response {
    if !same_origin(&headers, dashboard.tls) {
        return (
            StatusCode::FORBIDDEN,
            "refused: log in from the dashboard's own login page",
        )
            .into_response();
    }
    let next = local_path(field(&body, "next").as_deref());
    let sessions = &dashboard.sessions;
    if sessions.is_open() {
        return redirect(&next);
    }
    let token = field(&body, "token").unwrap_or_default();
    let address = connection.0.remote_addr().map(|address| address.ip());
    let checked = sessions.check_token_from(address, Some(token.trim())).await;
    let (status, message) = match checked {
        Ok(()) => {
            let cookie = sessions.session_header(dashboard.tls);
            return (
                StatusCode::SEE_OTHER,
                [(header::LOCATION, next), (header::SET_COOKIE, cookie)],
            )
                .into_response();
        }
        Err(Err(limited)) => return too_many(limited, Some(&next)),
        Err(Ok(Refusal::WorkerToken)) => (
            StatusCode::FORBIDDEN,
            "That is the worker token, which opens nothing here: give the client token.",
        ),
        Err(Ok(_)) => (StatusCode::UNAUTHORIZED, "That is not this farm's token."),
    };
    (status, Html(html::login_page(Some(message), &next))).into_response()
}

/// Logging out; the login form is open, so `mod.rs` routes it beside the assets.
pub(super) fn routes() -> Router<Dashboard> {
    Router::new().route("/logout", post(logout))
}

/// Ends the browser's session.
pub async fn logout(State(dashboard): State<Dashboard>) -> Response {
    let cookie = format!(
        "{COOKIE}=; Path=/; Max-Age=0; HttpOnly; SameSite=Strict{}",
        if dashboard.tls { "; Secure" } else { "" }
    );
    (
        StatusCode::SEE_OTHER,
        [
            (header::LOCATION, "/login".to_string()),
            (header::SET_COOKIE, cookie),
        ],
    )
        .into_response()
}

/// The first value of `name` in a URL-encoded form or query.
pub fn field(form: &[u8], name: &str) -> Option<String> {
    form_urlencoded::parse(form)
        .find(|(key, _)| key == name)
        .map(|(_, value)| value.into_owned())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_session_verifies_until_it_expires_and_not_when_altered() {
        let sessions = Sessions::new(
            Access::new(Some("client"), Some("worker")),
            LoginLimit::DEFAULT,
        );
        let value = sessions.new_session(1_000);
        assert!(sessions.verify(&value, 1_000));
        assert!(!sessions.verify(&value, 1_000 + SESSION_SECONDS));
        let later = value.replacen("1", "9", 1);
        assert!(!sessions.verify(&later, 1_000), "{later}");
        let other = Sessions::new(
            Access::new(Some("client"), Some("worker")),
            LoginLimit::DEFAULT,
        );
        assert!(!other.verify(&value, 1_000), "another start's key");
        assert!(!sessions.verify("", 1_000));
        assert!(!sessions.verify("1.2.zz", 1_000));
    }

    #[test]
    fn tokens_are_checked_by_role() {
        let sessions = Sessions::new(
            Access::new(Some("client"), Some("worker")),
            LoginLimit::DEFAULT,
        );
        assert_eq!(sessions.check_token(Some("client")), Ok(()));
        assert_eq!(
            sessions.check_token(Some("worker")),
            Err(Refusal::WorkerToken)
        );
        assert_eq!(
            sessions.check_token(Some("guess")),
            Err(Refusal::InvalidToken)
        );
        assert_eq!(sessions.check_token(None), Err(Refusal::NoSession));
        assert!(!sessions.is_open());
        assert!(Sessions::new(Access::default(), LoginLimit::DEFAULT).is_open());
    }

    #[test]
    fn only_the_dashboards_own_origin_may_change_state() {
        let headers = |origin: &str| {
            let mut headers = HeaderMap::new();
            headers.insert(header::HOST, HeaderValue::from_static("127.0.0.1:8080"));
            if !origin.is_empty() {
                headers.insert(
                    header::ORIGIN,
                    HeaderValue::from_str(origin).expect("a header value"),
                );
            }
            headers
        };
        assert!(same_origin(&headers("http://127.0.0.1:8080"), false));
        assert!(!same_origin(&headers("http://127.0.0.1:8080"), true));
        assert!(!same_origin(&headers("https://evil.example"), false));
        assert!(!same_origin(&headers(""), false));
    }

    #[test]
    fn logins_go_on_only_to_the_dashboards_own_paths() {
        assert_eq!(local_path(Some("/jobs/job-1")), "/jobs/job-1");
        assert_eq!(local_path(Some("//evil.example/")), "/");
        assert_eq!(local_path(Some("https://evil.example/")), "/");
        assert_eq!(local_path(Some("/\\evil.example")), "/");
        assert_eq!(local_path(None), "/");
    }
}
