//! Listing the point files under a prefix.

use std::sync::Arc;

use futures_util::TryStreamExt;
use object_store::{ObjectMeta, ObjectStore};

use super::error::RemoteError;
use super::url::{ObjectUrl, UrlKind};

/// An object found under a prefix.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ListedObject {
    pub url: ObjectUrl,
    pub size: u64,
}

/// Whether an object's name says it holds points (`.las`, `.laz`, `.copc.laz`), in any case.
pub fn is_point_file(name: &str) -> bool {
    let lowered = name.to_ascii_lowercase();
    lowered.ends_with(".las") || lowered.ends_with(".laz")
}

pub(crate) async fn list_point_files(
    store: Arc<dyn ObjectStore>,
    prefix: &ObjectUrl,
    limit: usize,
) -> Result<Vec<ListedObject>, RemoteError> {
    let path = prefix.object_path();
    let listing_error = |error: object_store::Error| {
        let reason = match prefix.kind() {
            // object_store lists an HTTP server through WebDAV, which a plain server lacks.
            UrlKind::Http => format!(
                "{error} (an HTTP server is listed only through WebDAV; name the files instead)"
            ),
            _ => error.to_string(),
        };
        match RemoteError::from_store(prefix.as_str(), error) {
            denied @ RemoteError::Denied { .. } => denied,
            _ => RemoteError::Listing {
                url: prefix.to_string(),
                reason,
            },
        }
    };
    let mut stream = store.list(if path.as_ref().is_empty() {
        None
    } else {
        Some(&path)
    });
    let mut found: Vec<ObjectMeta> = Vec::new();
    while let Some(meta) = stream.try_next().await.map_err(listing_error)? {
        if !meta.location.filename().is_some_and(is_point_file) {
            continue;
        }
        if found.len() == limit {
            return Err(RemoteError::TooManyObjects {
                url: prefix.to_string(),
                limit,
            });
        }
        found.push(meta);
    }
    found.sort_by(|a, b| a.location.cmp(&b.location));
    found
        .into_iter()
        .map(|meta| {
            Ok(ListedObject {
                url: prefix.with_object_path(&meta.location)?,
                size: meta.size,
            })
        })
        .collect()
}
