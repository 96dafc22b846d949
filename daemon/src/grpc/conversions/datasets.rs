//! A dataset as clients are shown it: its files on the server, or the object it is read
//! from by URL.

use pointfarm_proto::v1 as pb;

use crate::model::{Dataset, DatasetFile};

impl From<&Dataset> for pb::Dataset {
    fn from(d: &Dataset) -> Self {
        let (url, version) = remote_fields(d);
        pb::Dataset {
            id: d.id.clone(),
            name: d.name.clone(),
            size_bytes: d.size_bytes,
            // A dataset by URL's key is no hash of its content: it is not shown as one.
            sha256: if d.remote.is_some() {
                String::new()
            } else {
                d.sha256.clone()
            },
            path: d.path.display().to_string(),
            created_unix_ms: d.created_unix_ms,
            files: d.files().iter().map(|f| file_message(d, f)).collect(),
            url,
            version,
        }
    }
}

/// One file of `dataset`; the one object of a dataset by URL carries its URL and version.
fn file_message(dataset: &Dataset, file: &DatasetFile) -> pb::DatasetFile {
    let (url, version) = remote_fields(dataset);
    pb::DatasetFile {
        name: file.name.clone(),
        size_bytes: file.size_bytes,
        sha256: if dataset.remote.is_some() {
            String::new()
        } else {
            file.sha256.clone()
        },
        path: file.path.display().to_string(),
        url,
        version,
    }
}

fn remote_fields(dataset: &Dataset) -> (String, String) {
    dataset
        .remote
        .as_ref()
        .map(|remote| (remote.url.clone(), remote.version.clone()))
        .unwrap_or_default()
}
