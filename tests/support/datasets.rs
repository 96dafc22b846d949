//! Datasets registered by path, as a client of the daemon registers them.

use pointfarm_proto::v1 as pb;
use pointfarm_proto::v1::dataset_service_client::DatasetServiceClient;
use tonic::transport::Channel;

/// Registers the file or folder at `path` (under the daemon's data roots) as a dataset,
/// expecting it taken: the set-up of every test that renders a registered dataset.
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
