//! Datasets registered by path or by URL, as a client of the daemon registers them.

use pointfarm_daemon::access::Access;
use pointfarm_daemon::service::DaemonConfig;
use pointfarm_proto::v1 as pb;
use pointfarm_proto::v1::dataset_service_client::DatasetServiceClient;
use tonic::transport::Channel;

use crate::nginx::NginxServer;
use crate::service::TestDaemon;

/// Registers `path`, a file or folder under the daemon's data roots or a URL it allows, as a
/// dataset, expecting it taken: the set-up of every test that renders a registered dataset.
pub async fn register_path(
    datasets: &mut DatasetServiceClient<Channel>,
    path: &str,
) -> pb::Dataset {
    datasets
        .register_dataset(pb::RegisterDatasetRequest {
            path: path.into(),
            ..Default::default()
        })
        .await
        .unwrap_or_else(|status| panic!("registering {path}: {status}"))
        .into_inner()
}

/// A daemon that registers what `server` serves both ways: by URL under its `scans/`, and by
/// path under the folder it serves, so a test can compare the two. With `embedded_worker`,
/// the daemon renders itself; without, only worker processes a test starts render for it.
pub async fn daemon_on_served_scans(server: &NginxServer, embedded_worker: bool) -> TestDaemon {
    let allowed = pointfarm_daemon::remote_datasets::url_prefixes(&[server.url("scans/")])
        .expect("valid prefix");
    let data_root = server.root.clone();
    let configure = move |config: &mut DaemonConfig| {
        config.allowed_url_prefixes = allowed;
        config.data_roots = vec![data_root];
    };
    if embedded_worker {
        TestDaemon::start(configure, Access::default()).await
    } else {
        TestDaemon::start_without_worker(configure, Access::default()).await
    }
}
