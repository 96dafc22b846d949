//! Writing objects by URL: a `RemoteUpload` streams an object of any size as a multipart
//! upload, holding at most a few parts in memory, `put` stores a small object whole and
//! `delete` removes one. A multipart object appears only when its upload completes; one that
//! fails or is dropped unfinished is aborted, so no half object is ever visible.

use std::future::Future;
use std::io::Read;
use std::path::Path;

use object_store::path::Path as ObjectPath;
use object_store::{ObjectStoreExt, PutPayload, WriteMultipart};

use super::client::RemoteClient;
use super::error::RemoteError;
use super::url::ObjectUrl;

impl RemoteClient {
    /// Whether an object exists at `url` (a HEAD request).
    pub fn exists(&self, url: &ObjectUrl) -> Result<bool, RemoteError> {
        let store = self.store(url)?;
        let path = writable_path(url)?;
        let shown = url.to_string();
        self.run(url, async move {
            match store.head(&path).await {
                Ok(_) => Ok(true),
                Err(object_store::Error::NotFound { .. }) => Ok(false),
                Err(error) => Err(RemoteError::from_upload(&shown, error)),
            }
        })
    }

    /// Refuses a write to a bucket that does not exist, before any work is done for it (some
    /// stores make a bucket on a first write, where S3 refuses it). A listing of the object's
    /// folder asks; credentials that may write but not list are let through.
    pub fn check_bucket(&self, url: &ObjectUrl) -> Result<(), RemoteError> {
        let store = self.store(url)?;
        let path = writable_path(url)?;
        let folder: ObjectPath = path
            .parts()
            .take(path.parts().count().saturating_sub(1))
            .collect();
        let shown = url.to_string();
        self.run(url, async move {
            let prefix = (!folder.as_ref().is_empty()).then_some(&folder);
            match store.list_with_delimiter(prefix).await {
                Ok(_) => Ok(()),
                Err(error) => match RemoteError::from_upload(&shown, error) {
                    RemoteError::Denied { .. } => Ok(()),
                    other => Err(other),
                },
            }
        })
    }

    /// Stores `bytes` as the object at `url` in one request, replacing any object there.
    pub fn put(&self, url: &ObjectUrl, bytes: Vec<u8>) -> Result<(), RemoteError> {
        let store = self.store(url)?;
        let path = writable_path(url)?;
        self.run_write(url, async move {
            store.put(&path, PutPayload::from(bytes)).await.map(drop)
        })
    }

    /// Deletes the object at `url`; one already gone is no error, so a deletion can be
    /// tried again.
    pub fn delete(&self, url: &ObjectUrl) -> Result<(), RemoteError> {
        let store = self.store(url)?;
        let path = writable_path(url)?;
        self.run_write(url, async move {
            match store.delete(&path).await {
                Err(object_store::Error::NotFound { .. }) => Ok(()),
                done => done,
            }
        })
    }

    /// Starts a multipart upload to `url`; the object appears, replacing any there, when
    /// `finish` returns.
    pub fn start_upload(&self, url: &ObjectUrl) -> Result<RemoteUpload, RemoteError> {
        let store = self.store(url)?;
        let path = writable_path(url)?;
        let upload = self.run_write(url, async move { store.put_multipart(&path).await })?;
        let part_bytes = self.settings().upload_part_bytes;
        Ok(RemoteUpload {
            client: self.clone(),
            url: url.clone(),
            writer: Some(WriteMultipart::new_with_chunk_size(upload, part_bytes)),
            bytes: 0,
        })
    }

    /// Uploads the file at `path` to `url`, reading it a part at a time; the bytes written.
    pub fn upload_file(&self, path: &Path, url: &ObjectUrl) -> Result<u64, RemoteError> {
        let io_error = |error: std::io::Error| RemoteError::Transport {
            url: url.to_string(),
            message: format!("reading {}: {error}", path.display()),
        };
        let mut file = std::fs::File::open(path).map_err(io_error)?;
        let mut upload = self.start_upload(url)?;
        let mut buffer = vec![0u8; self.settings().upload_part_bytes];
        loop {
            let read = match file.read(&mut buffer) {
                Ok(0) => break,
                Ok(read) => read,
                Err(error) if error.kind() == std::io::ErrorKind::Interrupted => continue,
                // Dropping the upload aborts it.
                Err(error) => return Err(io_error(error)),
            };
            upload.write(&buffer[..read])?;
        }
        upload.finish()
    }

    /// Runs one write request for the object at `url`, its failure sorted as a write's.
    fn run_write<T: Send + 'static>(
        &self,
        url: &ObjectUrl,
        request: impl Future<Output = object_store::Result<T>> + Send + 'static,
    ) -> Result<T, RemoteError> {
        let shown = url.to_string();
        self.run(url, async move {
            request
                .await
                .map_err(|error| RemoteError::from_upload(&shown, error))
        })
    }
}

/// An object being written by a multipart upload. Each `write` waits while the settings'
/// `upload_parts_in_flight` parts are being sent, so memory stays within that many parts and
/// one being filled. Dropped before `finish`, it is aborted.
pub struct RemoteUpload {
    client: RemoteClient,
    url: ObjectUrl,
    writer: Option<WriteMultipart>,
    bytes: u64,
}

impl RemoteUpload {
    pub fn url(&self) -> &ObjectUrl {
        &self.url
    }

    /// Bytes written so far.
    pub fn bytes(&self) -> u64 {
        self.bytes
    }

    /// Adds `data` to the object; a failed part aborts the upload and is the error.
    pub fn write(&mut self, data: &[u8]) -> Result<(), RemoteError> {
        let mut writer = self.take_writer()?;
        let in_flight = self.client.settings().upload_parts_in_flight.max(1);
        let owned = data.to_vec();
        let shown = self.url.to_string();
        let answer = self.client.run(&self.url, async move {
            match writer.wait_for_capacity(in_flight).await {
                Ok(()) => {
                    writer.write(&owned);
                    Ok(Ok(writer))
                }
                Err(error) => {
                    // The part's own error says what failed; the abort's would hide it.
                    let _ = writer.abort().await;
                    Ok(Err(RemoteError::from_upload(&shown, error)))
                }
            }
        });
        match answer {
            Ok(Ok(writer)) => {
                self.writer = Some(writer);
                self.bytes += data.len() as u64;
                Ok(())
            }
            Ok(Err(error)) | Err(error) => Err(error),
        }
    }

    /// Sends the last part and completes the upload: the object appears whole. The bytes
    /// written.
    pub fn finish(mut self) -> Result<u64, RemoteError> {
        let writer = self.take_writer()?;
        self.client.run_write(&self.url, writer.finish())?;
        Ok(self.bytes)
    }

    /// Gives the upload up: the parts sent are deleted and no object appears.
    pub fn abort(mut self) -> Result<(), RemoteError> {
        self.abort_now()
    }

    fn abort_now(&mut self) -> Result<(), RemoteError> {
        let Some(writer) = self.writer.take() else {
            return Ok(());
        };
        self.client.run_write(&self.url, writer.abort())
    }

    fn take_writer(&mut self) -> Result<WriteMultipart, RemoteError> {
        self.writer.take().ok_or_else(|| RemoteError::Transport {
            url: self.url.to_string(),
            message: "the upload was already given up after an error".to_owned(),
        })
    }
}

impl Drop for RemoteUpload {
    fn drop(&mut self) {
        if let Err(error) = self.abort_now() {
            // The store removes unfinished uploads by its own lifecycle rules; nothing was
            // made visible either way.
            tracing::warn!(%error, "aborting an unfinished upload");
        }
    }
}

/// The object path of a URL that can be written: an object of an object store, not a prefix
/// or a plain web server's file.
fn writable_path(url: &ObjectUrl) -> Result<ObjectPath, RemoteError> {
    if url.is_prefix() {
        return Err(RemoteError::InvalidUrl {
            url: url.to_string(),
            reason: "names a prefix, not an object to write".to_owned(),
        });
    }
    Ok(url.object_path())
}
