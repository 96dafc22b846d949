//! The dashboard's connections: accepted through the bounded listener every server of the
//! daemon uses (`TCP_NODELAY`, keepalive, bounds on silent and idle connections), and with
//! TLS when the API has a certificate. Handshakes run each in a task of its own, so a slow
//! client never holds the others' accepts; one that never finishes is closed by the
//! connection's first-request bound.

use std::sync::Arc;

use anyhow::Context;
use axum::extract::connect_info::Connected;
use axum::serve::IncomingStream;
use pointfarm_proto::endpoint::connections::{self, ConnectionInfo, ConnectionLimits};
use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, PrivateKeyDer};
use tokio::io::{AsyncRead, AsyncWrite};
use tokio::net::TcpListener;
use tokio::sync::mpsc;
use tokio_rustls::TlsAcceptor;

use crate::server::TlsIdentity;

/// A connection's byte stream, plain or TLS.
pub trait Stream: AsyncRead + AsyncWrite + Send + Unpin {}

impl<T: AsyncRead + AsyncWrite + Send + Unpin> Stream for T {}

/// Connections ready for HTTP, as axum takes listeners.
pub struct DashboardListener {
    ready: mpsc::Receiver<(Box<dyn Stream>, ConnectionInfo)>,
}

/// How many connections may wait, handshaken, for axum to take them.
const READY_QUEUE: usize = 64;

impl DashboardListener {
    /// Accepts on `socket` in a task of its own, handshaking TLS with `tls` when given.
    pub fn start(socket: TcpListener, limits: ConnectionLimits, tls: Option<TlsAcceptor>) -> Self {
        let (sender, ready) = mpsc::channel(READY_QUEUE);
        let mut bounded = connections::Listener::new(socket, limits);
        tokio::spawn(async move {
            loop {
                let connection = match bounded.accept().await {
                    Ok(connection) => connection,
                    // The listener pauses by itself when descriptors run out.
                    Err(error) => {
                        tracing::debug!(%error, "accepting a dashboard connection");
                        continue;
                    }
                };
                let info = connection.info().clone();
                match &tls {
                    None => {
                        let stream: Box<dyn Stream> = Box::new(connection);
                        if sender.send((stream, info)).await.is_err() {
                            return;
                        }
                    }
                    Some(acceptor) => {
                        let handshake = acceptor.accept(connection);
                        let sender = sender.clone();
                        tokio::spawn(async move {
                            match handshake.await {
                                Ok(stream) => {
                                    let stream: Box<dyn Stream> = Box::new(stream);
                                    let _ = sender.send((stream, info)).await;
                                }
                                Err(error) => {
                                    tracing::debug!(%error, "a dashboard TLS handshake failed")
                                }
                            }
                        });
                    }
                }
            }
        });
        Self { ready }
    }
}

impl axum::serve::Listener for DashboardListener {
    type Io = Box<dyn Stream>;
    type Addr = ConnectionInfo;

    async fn accept(&mut self) -> (Self::Io, Self::Addr) {
        match self.ready.recv().await {
            Some(ready) => ready,
            // The accepting task ended with the runtime: nothing more comes.
            None => std::future::pending().await,
        }
    }

    fn local_addr(&self) -> std::io::Result<Self::Addr> {
        Err(std::io::Error::other(
            "the dashboard's address is the one `dashboard::listen` returns",
        ))
    }
}

/// The connection a request came in on.
#[derive(Clone)]
pub struct DashboardConnection(pub ConnectionInfo);

impl Connected<IncomingStream<'_, DashboardListener>> for DashboardConnection {
    fn connect_info(stream: IncomingStream<'_, DashboardListener>) -> Self {
        Self(stream.remote_addr().clone())
    }
}

/// The TLS side of the dashboard, with the API's certificate and key; HTTP/1.1 only.
pub fn tls_acceptor(identity: &TlsIdentity) -> anyhow::Result<TlsAcceptor> {
    let chain = CertificateDer::pem_slice_iter(&identity.cert_pem)
        .collect::<Result<Vec<_>, _>>()
        .context("the TLS certificate (--tls-cert) for the dashboard")?;
    let key = PrivateKeyDer::from_pem_slice(&identity.key_pem)
        .context("the TLS key (--tls-key) for the dashboard")?;
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let mut config = rustls::ServerConfig::builder_with_provider(provider)
        .with_safe_default_protocol_versions()
        .context("the dashboard's TLS versions")?
        .with_no_client_auth()
        .with_single_cert(chain, key)
        .context("the TLS certificate and key (--tls-cert, --tls-key) for the dashboard")?;
    config.alpn_protocols = vec![b"http/1.1".to_vec()];
    Ok(TlsAcceptor::from(Arc::new(config)))
}
