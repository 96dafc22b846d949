//! Listing the point files under a prefix.

use std::sync::Arc;

use futures_util::TryStreamExt;
use object_store::{ObjectMeta, ObjectStore};

use super::error::{missing_bucket, names_missing_bucket, RemoteError};
use super::url::{ObjectUrl, UrlKind};

/// An object found under a prefix.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ListedObject {
    pub url: ObjectUrl,
    pub size: u64,
    /// The version listed (the store's version id, else the ETag), which a read of the object
    /// is held to.
    pub version: Option<String>,
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
            // S3 and Azure answer a listing of a missing bucket with a 404 that object_store
            // passes on as a generic error, the code in its body.
            _ if names_missing_bucket(&error.to_string()) => {
                missing_bucket(prefix.as_str()).to_owned()
            }
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
                version: meta.version.or(meta.e_tag),
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use object_store::memory::InMemory;
    use object_store::path::Path as ObjectPath;
    use object_store::{ObjectStoreExt, PutPayload};

    use super::*;

    /// Lists `prefix` of an in-memory store holding `names`, within `limit` objects.
    fn listed(names: &[&str], prefix: &str, limit: usize) -> Result<Vec<String>, RemoteError> {
        let runtime = tokio::runtime::Builder::new_current_thread()
            .build()
            .expect("runtime");
        runtime.block_on(async {
            let store = Arc::new(InMemory::new());
            for name in names {
                let payload = PutPayload::from_static(b"LASF");
                store
                    .put(&ObjectPath::from(*name), payload)
                    .await
                    .expect("put");
            }
            let prefix = ObjectUrl::parse(prefix).expect("prefix");
            let found = list_point_files(store, &prefix, limit).await?;
            Ok(found.iter().map(|object| object.url.to_string()).collect())
        })
    }

    #[test]
    fn a_prefix_lists_its_point_files_in_any_case_sorted_and_bounded() {
        let names = [
            "tiles/b.LAZ",
            "tiles/sub/c.laz",
            "tiles/a.las",
            "tiles/readme.txt",
            "other/d.laz",
        ];
        let found = listed(&names, "s3://bucket/tiles/", 10).expect("listed");
        assert_eq!(
            found,
            [
                "s3://bucket/tiles/a.las",
                "s3://bucket/tiles/b.LAZ",
                "s3://bucket/tiles/sub/c.laz"
            ]
        );
        let error = listed(&names, "s3://bucket/tiles/", 2).expect_err("too many");
        assert!(
            matches!(error, RemoteError::TooManyObjects { limit: 2, .. }),
            "{error}"
        );
        assert_eq!(
            error.to_string(),
            "s3://bucket/tiles/: more than 2 objects under this prefix"
        );
    }
}
