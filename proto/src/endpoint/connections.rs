//! The connections a server accepts. Every accepted socket gets `TCP_NODELAY` (a response
//! written in several segments must not wait for the peer's delayed ACK,
//! docs/perf/tcp-nodelay.md) and TCP keepalive, and each listener bounds what peers that
//! send nothing useful can hold:
//!
//! - A new connection must make an **admitted call** (one its token lets through, see
//!   [`admit_connection`]) within [`ConnectionLimits::first_request_timeout`], TLS handshake
//!   included, or it is closed. At most [`ConnectionLimits::max_unadmitted`] connections wait
//!   like that: past it the oldest is closed for the newest, so a flood of silent sockets
//!   cannot keep a real client out for longer than the flood lasts.
//! - An admitted connection with no request in flight for
//!   [`ConnectionLimits::idle_timeout`] is closed (clients reconnect on their next call).
//! - At most [`ConnectionLimits::max_connections`] are open at once; past it, a new
//!   connection takes a waiting one's place, or is closed at once when none waits. The bound
//!   follows the process's open-file limit, so that files always have descriptors left.
//!
//! Requests are counted by [`ConnectionLayer`], a tower layer around the services, which
//! finds its connection's [`ConnectionInfo`] in the request's extensions.

use std::collections::VecDeque;
use std::future::Future;
use std::io;
use std::net::SocketAddr;
use std::pin::Pin;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, Weak};
use std::task::{Context, Poll, Waker};
use std::time::Duration;

use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::{TcpListener, TcpStream};
use tokio::time::{Instant, Sleep};
use tonic::transport::server::{Connected, TcpConnectInfo};

/// How long an idle TCP connection waits before the kernel probes its peer: a peer that
/// vanished (power cut, cable pulled) is found without any traffic of ours.
pub const TCP_KEEPALIVE_IDLE: Duration = Duration::from_secs(60);

/// What one listener's connections may hold.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ConnectionLimits {
    /// Open connections at once.
    pub max_connections: usize,
    /// Connections that have not made an admitted call yet.
    pub max_unadmitted: usize,
    /// How long a new connection may take to make its first admitted call.
    pub first_request_timeout: Duration,
    /// How long an admitted connection may stay open with no request in flight.
    pub idle_timeout: Duration,
}

impl Default for ConnectionLimits {
    fn default() -> Self {
        Self::for_open_files(DEFAULT_OPEN_FILES)
    }
}

/// The open-file limit [`ConnectionLimits::default`] assumes (a common hard limit).
const DEFAULT_OPEN_FILES: u64 = 8192;
/// Connections never get more than half of the descriptors: the rest are for the store,
/// datasets, frames and the other listeners.
const CONNECTIONS_SHARE_OF_FILES: u64 = 2;
/// The most connections of one listener, whatever the file limit: far more than a farm's
/// clients and workers, and still a bound on the memory their buffers take.
const MAX_CONNECTIONS_CAP: usize = 16_384;

impl ConnectionLimits {
    /// Limits for a process that may open `open_files` descriptors: half of them for
    /// connections, a quarter of those for connections yet to make a call.
    pub fn for_open_files(open_files: u64) -> Self {
        let max_connections = usize::try_from(open_files / CONNECTIONS_SHARE_OF_FILES)
            .unwrap_or(usize::MAX)
            .clamp(16, MAX_CONNECTIONS_CAP);
        Self {
            max_connections,
            max_unadmitted: (max_connections / 4).max(4),
            first_request_timeout: Duration::from_secs(10),
            idle_timeout: Duration::from_secs(300),
        }
    }
}

/// Why a connection was closed by its listener.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum CloseReason {
    NoAdmittedCall,
    Idle,
    Displaced,
}

impl CloseReason {
    fn message(self) -> &'static str {
        match self {
            CloseReason::NoAdmittedCall => "closed: no admitted call in time",
            CloseReason::Idle => "closed: idle",
            CloseReason::Displaced => "closed: too many connections without a call",
        }
    }
}

/// What a listener knows of one connection, shared by its socket and its requests.
#[derive(Debug)]
struct ConnectionState {
    accepted_at: Instant,
    activity: Mutex<Activity>,
}

#[derive(Debug)]
struct Activity {
    admitted: bool,
    in_flight: usize,
    /// When the last request ended (or the connection was admitted).
    quiet_since: Instant,
    closed: Option<CloseReason>,
    /// The connection task's waker: a change here may move its deadline.
    waker: Option<Waker>,
}

impl ConnectionState {
    fn new() -> Self {
        let now = Instant::now();
        Self {
            accepted_at: now,
            activity: Mutex::new(Activity {
                admitted: false,
                in_flight: 0,
                quiet_since: now,
                closed: None,
                waker: None,
            }),
        }
    }

    /// Changes the activity and wakes the connection so that it looks at its deadline again.
    fn update(&self, change: impl FnOnce(&mut Activity)) {
        let waker = {
            let mut activity = self.activity.lock().unwrap_or_else(|e| e.into_inner());
            change(&mut activity);
            activity.waker.take()
        };
        if let Some(waker) = waker {
            waker.wake();
        }
    }

    fn is_admitted(&self) -> bool {
        self.activity
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .admitted
    }

    /// When the connection must be closed (`None`: not while a request is in flight), or
    /// why it already is; registers `waker` for changes.
    fn deadline(
        &self,
        limits: &ConnectionLimits,
        waker: &Waker,
    ) -> Result<Option<Instant>, CloseReason> {
        let mut activity = self.activity.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(reason) = activity.closed {
            return Err(reason);
        }
        if !activity.waker.as_ref().is_some_and(|w| w.will_wake(waker)) {
            activity.waker = Some(waker.clone());
        }
        Ok(if !activity.admitted {
            Some(self.accepted_at + limits.first_request_timeout)
        } else if activity.in_flight > 0 {
            None
        } else {
            Some(activity.quiet_since + limits.idle_timeout)
        })
    }
}

/// The connection a request came in on, in its extensions (tonic puts a connection's
/// [`Connected::ConnectInfo`] into every request's).
#[derive(Debug, Clone)]
pub struct ConnectionInfo {
    tcp: TcpConnectInfo,
    state: Arc<ConnectionState>,
}

impl ConnectionInfo {
    pub fn remote_addr(&self) -> Option<SocketAddr> {
        self.tcp.remote_addr
    }

    /// Counts a request on the connection until the guard is dropped, for servers that do not
    /// go through [`ConnectionLayer`].
    pub fn begin_request(&self) -> RequestInFlight {
        RequestInFlight::begin(self.state.clone())
    }

    /// Marks the connection as one that made an admitted call (see [`admit_connection`]).
    pub fn admit(&self) {
        if !self.state.is_admitted() {
            self.state.update(|activity| {
                activity.admitted = true;
                activity.quiet_since = Instant::now();
            });
        }
    }
}

/// Marks the connection of `request` as admitted: called by the interceptors that check a
/// call's token, once it passes. Requests that did not come through a [`Listener`] (tests
/// over in-memory streams) have no connection to mark.
pub fn admit_connection<T>(request: &tonic::Request<T>) {
    if let Some(info) = request.extensions().get::<ConnectionInfo>() {
        info.admit();
    }
}

/// The connections of one listener, for the bounds.
#[derive(Debug)]
struct Registry {
    limits: ConnectionLimits,
    open: AtomicUsize,
    /// Connections that have made no admitted call yet, oldest first (some may have made
    /// one since, or closed: they are dropped from here as they are met).
    unadmitted: Mutex<VecDeque<Weak<ConnectionState>>>,
}

impl Registry {
    /// Takes a new connection in, closing a waiting one to make room where the bounds ask;
    /// `None` when no room can be made.
    fn admit_new(self: &Arc<Self>) -> Option<(Arc<ConnectionState>, OpenConnection)> {
        let mut waiting = self.unadmitted.lock().unwrap_or_else(|e| e.into_inner());
        waiting.retain(|weak| weak.upgrade().is_some_and(|state| !state.is_admitted()));
        let over_open = self.open.load(Ordering::Acquire) >= self.limits.max_connections;
        if over_open || waiting.len() >= self.limits.max_unadmitted {
            // The oldest waiting connection has had the longest to make its call.
            match waiting.pop_front().and_then(|weak| weak.upgrade()) {
                Some(oldest) => {
                    oldest.update(|activity| activity.closed = Some(CloseReason::Displaced))
                }
                None if over_open => return None,
                None => {}
            }
        }
        let state = Arc::new(ConnectionState::new());
        waiting.push_back(Arc::downgrade(&state));
        self.open.fetch_add(1, Ordering::AcqRel);
        Some((
            state,
            OpenConnection {
                registry: self.clone(),
            },
        ))
    }
}

/// Counts a connection as open until its socket is dropped.
#[derive(Debug)]
struct OpenConnection {
    registry: Arc<Registry>,
}

impl Drop for OpenConnection {
    fn drop(&mut self) {
        self.registry.open.fetch_sub(1, Ordering::AcqRel);
    }
}

/// A TCP listener whose connections are set up and bounded as the module describes: a
/// stream of [`Connection`]s for tonic's `serve_with_incoming`.
pub struct Listener {
    listener: TcpListener,
    registry: Arc<Registry>,
    /// Set after the process ran out of descriptors: accepting waits a moment rather than
    /// spinning on the error.
    backoff: Option<Pin<Box<Sleep>>>,
    refusals: Refusals,
}

/// Connections refused at the limit, logged at most once a second: a flood must not flood
/// the log too.
#[derive(Debug, Default)]
struct Refusals {
    unlogged: u64,
    logged_at: Option<Instant>,
}

impl Refusals {
    fn count(&mut self, peer: SocketAddr, limit: usize) {
        self.unlogged += 1;
        let now = Instant::now();
        if self
            .logged_at
            .is_some_and(|at| now.duration_since(at) < Duration::from_secs(1))
        {
            return;
        }
        tracing::warn!(
            %peer,
            limit,
            refused = self.unlogged,
            "refusing connections: the listener's connections are at their limit"
        );
        self.unlogged = 0;
        self.logged_at = Some(now);
    }
}

/// How long accepting pauses after the process ran out of descriptors.
const OUT_OF_FILES_BACKOFF: Duration = Duration::from_millis(100);

impl Listener {
    pub fn new(listener: TcpListener, limits: ConnectionLimits) -> Self {
        Self {
            listener,
            registry: Arc::new(Registry {
                limits,
                open: AtomicUsize::new(0),
                unadmitted: Mutex::new(VecDeque::new()),
            }),
            backoff: None,
            refusals: Refusals::default(),
        }
    }

    pub fn local_addr(&self) -> io::Result<SocketAddr> {
        self.listener.local_addr()
    }

    /// Connections open now.
    pub fn open_connections(&self) -> usize {
        self.registry.open.load(Ordering::Acquire)
    }

    /// The next connection, set up; errors are the accept's own (the listener goes on).
    pub fn poll_accept(&mut self, cx: &mut Context<'_>) -> Poll<io::Result<Connection>> {
        loop {
            if let Some(backoff) = &mut self.backoff {
                std::task::ready!(backoff.as_mut().poll(cx));
                self.backoff = None;
            }
            let (stream, peer) = match std::task::ready!(self.listener.poll_accept(cx)) {
                Ok(accepted) => accepted,
                Err(error) => {
                    if is_out_of_files(&error) {
                        tracing::warn!(%error, "out of file descriptors: accepting pauses");
                        self.backoff = Some(Box::pin(tokio::time::sleep(OUT_OF_FILES_BACKOFF)));
                    }
                    return Poll::Ready(Err(error));
                }
            };
            let Some((state, open)) = self.registry.admit_new() else {
                self.refusals
                    .count(peer, self.registry.limits.max_connections);
                continue;
            };
            if let Err(error) = set_up(&stream) {
                tracing::debug!(%peer, %error, "setting up an accepted socket");
                continue;
            }
            let tcp = stream.connect_info();
            return Poll::Ready(Ok(Connection {
                stream,
                info: ConnectionInfo { tcp, state },
                limits: self.registry.limits,
                timer: Box::pin(tokio::time::sleep_until(Instant::now())),
                _open: open,
            }));
        }
    }

    /// The next connection, set up.
    pub async fn accept(&mut self) -> io::Result<Connection> {
        std::future::poll_fn(|cx| self.poll_accept(cx)).await
    }
}

impl tokio_stream::Stream for Listener {
    type Item = io::Result<Connection>;

    fn poll_next(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<Self::Item>> {
        self.poll_accept(cx).map(Some)
    }
}

fn is_out_of_files(error: &io::Error) -> bool {
    // EMFILE (the process's limit) and ENFILE (the system's).
    matches!(error.raw_os_error(), Some(23 | 24))
}

/// TCP_NODELAY and keepalive on an accepted or opened socket.
pub fn set_up(stream: &TcpStream) -> io::Result<()> {
    stream.set_nodelay(true)?;
    #[cfg(unix)]
    {
        rustix::net::sockopt::set_socket_keepalive(stream, true)?;
        #[cfg(any(target_os = "linux", target_os = "android"))]
        rustix::net::sockopt::set_tcp_keepidle(stream, TCP_KEEPALIVE_IDLE)?;
    }
    Ok(())
}

/// An accepted socket that closes itself when its listener's bounds say so.
#[derive(Debug)]
pub struct Connection {
    stream: TcpStream,
    info: ConnectionInfo,
    limits: ConnectionLimits,
    timer: Pin<Box<Sleep>>,
    _open: OpenConnection,
}

impl Connection {
    /// The socket, for its options.
    pub fn get_ref(&self) -> &TcpStream {
        &self.stream
    }

    pub fn info(&self) -> &ConnectionInfo {
        &self.info
    }

    /// Fails once the connection is past its deadline or was closed to make room; arms the
    /// timer for the deadline otherwise.
    fn check(&mut self, cx: &mut Context<'_>) -> io::Result<()> {
        loop {
            let deadline = self
                .info
                .state
                .deadline(&self.limits, cx.waker())
                .map_err(closed)?;
            let Some(deadline) = deadline else {
                return Ok(());
            };
            if Instant::now() >= deadline {
                let reason = if self.info.state.is_admitted() {
                    CloseReason::Idle
                } else {
                    CloseReason::NoAdmittedCall
                };
                self.info
                    .state
                    .update(|activity| activity.closed = Some(reason));
                tracing::debug!(peer = ?self.info.remote_addr(), reason = reason.message(), "closing a connection");
                return Err(closed(reason));
            }
            if self.timer.deadline() != deadline {
                self.timer.as_mut().reset(deadline);
            }
            if self.timer.as_mut().poll(cx).is_pending() {
                return Ok(());
            }
        }
    }
}

fn closed(reason: CloseReason) -> io::Error {
    io::Error::new(io::ErrorKind::TimedOut, reason.message())
}

impl AsyncRead for Connection {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        self.check(cx)?;
        Pin::new(&mut self.stream).poll_read(cx, buf)
    }
}

impl AsyncWrite for Connection {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        self.check(cx)?;
        Pin::new(&mut self.stream).poll_write(cx, buf)
    }

    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[io::IoSlice<'_>],
    ) -> Poll<io::Result<usize>> {
        self.check(cx)?;
        Pin::new(&mut self.stream).poll_write_vectored(cx, bufs)
    }

    fn is_write_vectored(&self) -> bool {
        self.stream.is_write_vectored()
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.stream).poll_flush(cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.stream).poll_shutdown(cx)
    }
}

impl Connected for Connection {
    type ConnectInfo = ConnectionInfo;

    fn connect_info(&self) -> ConnectionInfo {
        self.info.clone()
    }
}

/// Counts each request on its connection from its start until its response's body is done
/// or dropped, so that a connection with a call in flight (a long-polled lease, a watched
/// job) is never idle. It also puts tonic's [`TcpConnectInfo`] into the request, which
/// `Request::remote_addr` reads.
#[derive(Debug, Clone, Copy, Default)]
pub struct ConnectionLayer;

impl<S> tower_layer::Layer<S> for ConnectionLayer {
    type Service = CountedRequests<S>;

    fn layer(&self, inner: S) -> Self::Service {
        CountedRequests { inner }
    }
}

/// The service [`ConnectionLayer`] makes.
#[derive(Debug, Clone)]
pub struct CountedRequests<S> {
    inner: S,
}

/// A request in flight on its connection, until dropped.
#[derive(Debug)]
pub struct RequestInFlight(Arc<ConnectionState>);

impl RequestInFlight {
    fn begin(state: Arc<ConnectionState>) -> Self {
        state.update(|activity| activity.in_flight += 1);
        Self(state)
    }
}

impl Drop for RequestInFlight {
    fn drop(&mut self) {
        self.0.update(|activity| {
            activity.in_flight = activity.in_flight.saturating_sub(1);
            activity.quiet_since = Instant::now();
        });
    }
}

impl<S, ReqBody, ResBody> tower_service::Service<http::Request<ReqBody>> for CountedRequests<S>
where
    S: tower_service::Service<http::Request<ReqBody>, Response = http::Response<ResBody>>,
    S::Future: Send + 'static,
{
    type Response = http::Response<CountedBody<ResBody>>;
    type Error = S::Error;
    type Future = Pin<Box<dyn Future<Output = Result<Self::Response, S::Error>> + Send>>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), S::Error>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, mut request: http::Request<ReqBody>) -> Self::Future {
        let info = request.extensions().get::<ConnectionInfo>().cloned();
        if let Some(info) = &info {
            request.extensions_mut().insert(info.tcp.clone());
        }
        let in_flight = info.map(|info| RequestInFlight::begin(info.state));
        let response = self.inner.call(request);
        Box::pin(async move {
            let response = response.await?;
            Ok(response.map(|body| CountedBody {
                body,
                _in_flight: in_flight,
            }))
        })
    }
}

/// A response body that keeps its request counted until it is done.
#[derive(Debug)]
pub struct CountedBody<B> {
    body: B,
    _in_flight: Option<RequestInFlight>,
}

impl<B: http_body::Body + Unpin> http_body::Body for CountedBody<B> {
    type Data = B::Data;
    type Error = B::Error;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<http_body::Frame<B::Data>, B::Error>>> {
        let frame = Pin::new(&mut self.body).poll_frame(cx);
        if let Poll::Ready(None) = frame {
            self._in_flight = None;
        }
        frame
    }

    fn is_end_stream(&self) -> bool {
        self.body.is_end_stream()
    }

    fn size_hint(&self) -> http_body::SizeHint {
        self.body.size_hint()
    }
}

#[cfg(test)]
mod tests;
