//! A dataset as clients are shown it (its files on the server, the object it is read from by
//! URL, or its tiles by URL, each with its size and version), and as a frame task hands it to
//! a worker.

use pointfarm_proto::v1 as pb;
use pointfarm_render::remote::ObjectUrl;

use super::invalid;
use crate::datasets::MAX_DATASET_FILES;
use crate::error::DaemonError;
use crate::lease::{PublishedStore, TaskDataset, TaskFile};
use crate::model::{Dataset, DatasetFile, RemoteSource, RemoteTile};
use crate::remote_datasets::object_name;
use crate::stores::StorePublication;

impl From<&Dataset> for pb::Dataset {
    fn from(d: &Dataset) -> Self {
        let (url, version) = remote_fields(d.remote.as_ref());
        pb::Dataset {
            id: d.id.clone(),
            name: d.name.clone(),
            size_bytes: d.size_bytes,
            sha256: shown_sha256(d, &d.sha256),
            path: d.path.display().to_string(),
            created_unix_ms: d.created_unix_ms,
            files: match d.tiles.as_slice() {
                [] => d.files().iter().map(|f| file_message(d, f)).collect(),
                tiles => tiles.iter().map(tile_message).collect(),
            },
            url,
            version,
            store_publication: None,
        }
    }
}

/// A dataset as `GetDataset` shows it, with how its store stands with object storage.
pub(in crate::grpc) fn dataset_with_publication(
    dataset: &Dataset,
    publication: &StorePublication,
) -> pb::Dataset {
    pb::Dataset {
        store_publication: Some(publication_message(publication)),
        ..pb::Dataset::from(dataset)
    }
}

fn publication_message(publication: &StorePublication) -> pb::StorePublication {
    use pb::store_publication::State;
    let not_published = |reason: &str| pb::StorePublication {
        state: State::NotPublished as i32,
        reason: reason.to_owned(),
        ..Default::default()
    };
    match publication {
        StorePublication::NoStoreUrl => {
            not_published("the server publishes no stores (serve --store-url)")
        }
        StorePublication::NotPublished => {
            not_published("no store is built to publish, or it is a COPC file's own hierarchy")
        }
        StorePublication::Publishing => pb::StorePublication {
            state: State::Publishing as i32,
            ..Default::default()
        },
        StorePublication::Published { url } => pb::StorePublication {
            state: State::Published as i32,
            url: url.clone(),
            ..Default::default()
        },
        StorePublication::Failed { failure } => pb::StorePublication {
            state: State::Failed as i32,
            url: failure.url.clone(),
            reason: failure.reason.clone(),
            failed_unix_ms: failure.failed_unix_ms,
        },
    }
}

/// One file of `dataset`; the one object of a dataset by URL carries its URL and version.
fn file_message(dataset: &Dataset, file: &DatasetFile) -> pb::DatasetFile {
    let (url, version) = remote_fields(dataset.remote.as_ref());
    pb::DatasetFile {
        name: file.name.clone(),
        size_bytes: file.size_bytes,
        sha256: shown_sha256(dataset, &file.sha256),
        path: file.path.display().to_string(),
        url,
        version,
    }
}

/// One tile of a dataset of tiles by URL: its URL (which never holds credentials), size and
/// the version its reads are pinned to; named by its last segment, as a file by its name.
fn tile_message(tile: &RemoteTile) -> pb::DatasetFile {
    pb::DatasetFile {
        name: object_name(&tile.url),
        size_bytes: tile.size_bytes,
        sha256: String::new(),
        path: String::new(),
        url: tile.url.clone(),
        version: tile.version.clone(),
    }
}

/// A hash of `dataset`'s as clients are shown it: a dataset by URL's key is no hash of its
/// content, so it is not shown as one.
fn shown_sha256(dataset: &Dataset, sha256: &str) -> String {
    match (&dataset.remote, dataset.tiles.is_empty()) {
        (None, true) => sha256.to_owned(),
        _ => String::new(),
    }
}

/// The URL and version of the object a dataset by URL is read from; empty for any other.
fn remote_fields(remote: Option<&RemoteSource>) -> (String, String) {
    remote
        .map(|remote| (remote.url.clone(), remote.version.clone()))
        .unwrap_or_default()
}

pub(super) fn task_dataset_message(dataset: &TaskDataset) -> pb::TaskDataset {
    let (url, version) = remote_fields(dataset.remote.as_ref());
    pb::TaskDataset {
        id: dataset.id.clone(),
        sha256: dataset.sha256.clone(),
        size_bytes: dataset.size_bytes,
        files: dataset
            .files
            .iter()
            .map(|f| pb::TaskFile {
                sha256: f.sha256.clone(),
                size_bytes: f.size_bytes,
            })
            .collect(),
        url,
        version,
        published_store: dataset
            .published
            .as_ref()
            .map(|published| pb::PublishedStore {
                url: published.url.clone(),
                hierarchy_version: published.hierarchy_version.clone(),
                payload_version: published.payload_version.clone(),
            }),
    }
}

/// Longest object version a published store may name: an ETag or a version id is far
/// shorter.
const MAX_OBJECT_VERSION_BYTES: usize = 1024;

/// A published store as a task names it: a prefix URL checked as every URL is, and
/// versions of a bounded length.
fn published_store(message: &pb::PublishedStore) -> Result<PublishedStore, DaemonError> {
    let url = ObjectUrl::parse(&message.url)?;
    if !url.is_prefix() {
        return Err(invalid(
            "dataset.published_store.url",
            "names an object, not a store's prefix",
        ));
    }
    for (field, version) in [
        ("hierarchy_version", &message.hierarchy_version),
        ("payload_version", &message.payload_version),
    ] {
        if version.is_empty() || version.len() > MAX_OBJECT_VERSION_BYTES {
            return Err(invalid(
                &format!("dataset.published_store.{field}"),
                format!("1 to {MAX_OBJECT_VERSION_BYTES} bytes"),
            ));
        }
    }
    Ok(PublishedStore {
        url: url.to_string(),
        hierarchy_version: message.hierarchy_version.clone(),
        payload_version: message.payload_version.clone(),
    })
}

/// A task's dataset as the worker receives it; a URL is checked as the daemon checked it
/// when the dataset was registered.
pub(super) fn task_dataset(message: &pb::TaskDataset) -> Result<TaskDataset, DaemonError> {
    if message.files.len() > MAX_DATASET_FILES {
        return Err(invalid(
            "dataset.files",
            format!("at most {MAX_DATASET_FILES} files"),
        ));
    }
    if !message.url.is_empty() {
        let url = ObjectUrl::parse(&message.url)?;
        return Ok(TaskDataset {
            id: message.id.clone(),
            sha256: message.sha256.clone(),
            size_bytes: message.size_bytes,
            files: Vec::new(),
            remote: Some(RemoteSource {
                url: url.to_string(),
                version: message.version.clone(),
            }),
            published: None,
        });
    }
    // A daemon that knew only datasets of one file sent none.
    let files = if message.files.is_empty() {
        vec![TaskFile {
            sha256: message.sha256.clone(),
            size_bytes: message.size_bytes,
        }]
    } else {
        message
            .files
            .iter()
            .map(|f| TaskFile {
                sha256: f.sha256.clone(),
                size_bytes: f.size_bytes,
            })
            .collect()
    };
    Ok(TaskDataset {
        id: message.id.clone(),
        sha256: message.sha256.clone(),
        size_bytes: message.size_bytes,
        files,
        remote: None,
        published: message
            .published_store
            .as_ref()
            .map(published_store)
            .transpose()?,
    })
}
