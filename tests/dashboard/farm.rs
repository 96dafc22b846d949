//! A daemon in this process with its API and its dashboard on loopback ports, for the tests
//! that set what `serve` does not offer: the gates that hold a store build, the login limit's
//! numbers.

use std::path::Path;
use std::sync::Arc;

use pointfarm_daemon::access::Access;
use pointfarm_daemon::dashboard::{self, DashboardOptions, LoginLimit};
use pointfarm_daemon::service::{Daemon, DaemonConfig};
use pointfarm_proto::endpoint::connections::ConnectionLimits;
use pointfarm_tests::service::serve_on_loopback;

/// The daemon's API and dashboard addresses (`127.0.0.1:PORT`); served until dropped.
pub struct Farm {
    pub address: String,
    pub dashboard: String,
    stop: Option<tokio::sync::oneshot::Sender<()>>,
}

impl Farm {
    /// A daemon with its data in `data`, as `configure` sets it, its tokens those of
    /// `access`, and wrong tokens limited as `login_limit` says; no embedded worker.
    pub async fn start(
        data: &Path,
        configure: impl FnOnce(&mut DaemonConfig),
        access: Access,
        login_limit: LoginLimit,
    ) -> Self {
        let mut config = DaemonConfig::new(data.to_path_buf());
        configure(&mut config);
        let daemon: Arc<Daemon> = Daemon::open(config).expect("open the daemon");
        let options = DashboardOptions {
            access: access.clone(),
            tls: None,
            insecure: false,
            connection_limits: ConnectionLimits::default(),
        };
        let (bound, _) =
            dashboard::listen_limiting_logins("127.0.0.1:0", daemon.clone(), options, login_limit)
                .await
                .expect("the dashboard listening");
        let (address, stop, _) = serve_on_loopback(daemon, None, access).await;
        Self {
            address: address.to_string(),
            dashboard: bound.to_string(),
            stop: Some(stop),
        }
    }
}

impl Drop for Farm {
    fn drop(&mut self) {
        if let Some(stop) = self.stop.take() {
            let _ = stop.send(());
        }
    }
}
