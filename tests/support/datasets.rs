//! Datasets registered by path or by URL, as a client of the daemon registers them.

use std::path::Path;

use pointfarm_daemon::access::Access;
use pointfarm_daemon::service::DaemonConfig;
use pointfarm_proto::v1 as pb;
use pointfarm_proto::v1::dataset_service_client::DatasetServiceClient;
use tonic::transport::Channel;

use crate::nginx::NginxServer;
use crate::service::TestDaemon;
use crate::{path_arg, pointfarm_ok, stdout};

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

/// Registers the file `path` on the daemon at `address` as a user does, with `pointfarm
/// dataset add --json`, expecting it taken.
pub fn add_with_cli(address: &str, path: &Path) -> pb::Dataset {
    add_files_with_cli(address, &[path])
}

/// [`add_with_cli`] of the files `paths`, as one dataset.
pub fn add_files_with_cli(address: &str, paths: &[&Path]) -> pb::Dataset {
    let mut args = vec!["dataset", "add"];
    args.extend(paths.iter().map(|path| path_arg(path)));
    args.extend(["--server", address, "--json"]);
    let added = pointfarm_ok(&args);
    serde_json::from_str(stdout(&added).trim()).expect("a Dataset")
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

/// Runs the jobs `requests` (the same frames of two datasets registered two ways) to success
/// and asserts that each has `frames` frames showing points, equal pixel for pixel, as `what`.
pub async fn assert_jobs_render_alike(
    jobs: &mut pointfarm_proto::v1::job_service_client::JobServiceClient<Channel>,
    requests: [pb::SubmitJobRequest; 2],
    frames: usize,
    what: &str,
) {
    let mut images = Vec::new();
    for request in requests {
        let name = request.request_id.clone();
        let job = crate::service::submit(jobs, request).await;
        crate::service::watch_to_success(jobs, &job.id, || format!("the {name} job")).await;
        images.push(crate::service::fetch_images(jobs, &job.id, 0).await);
    }
    assert_eq!(images[0].len(), frames);
    let (_, first) = &images[0][0];
    assert!(
        first.pixels().any(|pixel| pixel != first.get_pixel(0, 0)),
        "frame 0 shows the points"
    );
    assert!(images[0] == images[1], "{what} differ");
}
