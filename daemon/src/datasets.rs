//! Datasets: files registered from the server's data roots (files or folders of them),
//! uploaded files, and datasets composed of the files of others (a campaign uploaded file by
//! file). More `Daemon` methods.
//!
//! A dataset's id comes from its content ([`content_sha256`]): the same files in the same
//! order are always the same dataset. Uploaded files live once under the uploads folder and
//! may belong to several datasets; deleting a dataset removes an uploaded file only when no
//! other dataset has it.

use std::collections::HashSet;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use pointfarm_render::ingest::{dataset_files_in, FileScope};

use crate::dataset_files::{file_name, DatasetFolders};
use crate::error::DaemonError;
use crate::limits::{check_id, check_length, MAX_NAME_BYTES, MAX_PATH_BYTES};
use crate::model::{content_sha256, now_unix_ms, Dataset, DatasetFile};
use crate::remote_datasets::local_path;
use crate::service::{dataset_id, hash_files_opened_by, lookup, unique_suffix, Daemon};
use crate::state::Page;
use crate::stores::{PreviewBytes, ReadyStore, StoreAnswer};

/// Most files in one dataset: a campaign of hundreds of tiles fits, a record that breaks the
/// listing does not.
pub const MAX_DATASET_FILES: usize = 10_000;

/// `count` paths, ids or files (of the request's `field`) make a dataset: one at least, and
/// at most [`MAX_DATASET_FILES`].
fn check_count(field: &str, count: usize) -> Result<(), DaemonError> {
    match count {
        0 => Err(DaemonError::invalid(field, "names no file")),
        n if n > MAX_DATASET_FILES => Err(DaemonError::invalid(
            field,
            format!("{n} files; a dataset has at most {MAX_DATASET_FILES}"),
        )),
        _ => Ok(()),
    }
}

/// What a registration found under the data roots, before its files are hashed.
pub struct Registration {
    /// Every file, resolved (canonical) and inside the data roots, in the dataset's order.
    pub files: Vec<PathBuf>,
    /// The dataset's name.
    pub name: String,
    /// The files' bytes together, as the walk found them: what hashing them reads.
    pub bytes: u64,
}

impl Daemon {
    /// Registers files already on the server, under its data roots, as one dataset
    /// ([`Daemon::find_registration`], then [`Daemon::register`]).
    pub fn register_dataset(&self, paths: &[String], name: &str) -> Result<Dataset, DaemonError> {
        let registration = self.find_registration(paths, name)?;
        self.register(registration)
    }

    /// The files `paths` name under the data roots: each path a file or a folder of
    /// `.las`/`.laz` files (relative paths are taken from the first data root). Every symbolic
    /// link is resolved, and a file or folder it leads to outside the data roots is refused
    /// naming the link, as is a `.las`/`.laz` name that is not a regular file (a FIFO, a
    /// socket, a device: never opened); a link loop is walked once. Errors name files by their
    /// path under their data root; the log has the full path.
    pub fn find_registration(
        &self,
        paths: &[String],
        name: &str,
    ) -> Result<Registration, DaemonError> {
        check_count("paths", paths.len())?;
        check_length("name", name, MAX_NAME_BYTES)?;
        let resolved = paths
            .iter()
            .map(|path| self.resolve_under_data_roots(path))
            .collect::<Result<Vec<_>, _>>()?;
        let files = dataset_files_in(&resolved, FileScope::Within(&self.config.data_roots))
            .map_err(|e| {
                tracing::warn!(error = %e, "a registration is refused");
                DaemonError::invalid("path", self.without_server_folders(&e.to_string()))
            })?;
        check_count("path", files.len())?;
        let name = match (name, paths) {
            ("", [one]) => file_name(Path::new(one)),
            ("", many) => format!("{} paths", many.len()),
            (name, _) => name.to_string(),
        };
        let bytes = files
            .iter()
            .filter_map(|file| std::fs::metadata(file).ok())
            .map(|metadata| metadata.len())
            .sum();
        Ok(Registration { files, name, bytes })
    }

    /// Adds the dataset of a registration's files, each hashed (read whole: this takes as
    /// long as the files are large).
    pub fn register(&self, registration: Registration) -> Result<Dataset, DaemonError> {
        let Registration { files, name, .. } = registration;
        let hashed = hash_files_opened_by(&files, &|path| self.open_dataset_file(path), &|_| {});
        let files = files
            .into_iter()
            .zip(hashed)
            .map(|(path, hashed)| {
                let (sha256, size_bytes) = hashed.map_err(|error| {
                    tracing::warn!(path = %path.display(), %error, "a registered file cannot be read");
                    DaemonError::invalid("path", format!("{}: {error}", self.shown_path(&path)))
                })?;
                Ok(DatasetFile {
                    name: file_name(&path),
                    path,
                    size_bytes,
                    sha256,
                })
            })
            .collect::<Result<Vec<_>, DaemonError>>()?;
        self.add_dataset(name, files)
    }

    /// The folders this daemon reads datasets' files from.
    pub fn dataset_folders(&self) -> DatasetFolders {
        DatasetFolders::new(self.config.data_roots.clone(), self.config.uploads_dir())
    }

    /// Opens a dataset's stored file to read it, as [`DatasetFolders::open`] does.
    pub fn open_dataset_file(&self, path: &Path) -> std::io::Result<std::fs::File> {
        self.dataset_folders().open(path)
    }

    /// Refuses dataset `dataset` unless every file of it still opens as
    /// [`Daemon::open_dataset_file`] opens it, before the render crate's readers (which follow
    /// links, as the CLI's must) read them; the error names the dataset and the file.
    pub(crate) fn check_dataset_files(&self, dataset: &Dataset) -> Result<(), DaemonError> {
        self.dataset_folders().check(dataset)
    }

    /// How a client is shown the server's file `path` ([`DatasetFolders::shown`]).
    pub(crate) fn shown_path(&self, path: &Path) -> String {
        self.dataset_folders().shown(path)
    }

    /// `path` as a canonical path under one of the data roots.
    fn resolve_under_data_roots(&self, path: &str) -> Result<PathBuf, DaemonError> {
        if path.is_empty() {
            return Err(DaemonError::invalid("path", "is empty"));
        }
        check_length("path", path, MAX_PATH_BYTES)?;
        let path = &local_path(path)?;
        let Some(first_root) = self.config.data_roots.first() else {
            return Err(DaemonError::FailedPrecondition(
                "this server has no data roots configured; upload the file instead".into(),
            ));
        };
        let requested = Path::new(path);
        let requested = if requested.is_absolute() {
            requested.to_path_buf()
        } else {
            first_root.join(requested)
        };
        let resolved = requested
            .canonicalize()
            .map_err(|_| DaemonError::NotFound(format!("file {path}")))?;
        if !resolved.is_file() && !resolved.is_dir() {
            return Err(DaemonError::invalid(
                "path",
                format!("{path} is not a file or a folder"),
            ));
        }
        let allowed = self
            .config
            .data_roots
            .iter()
            .filter_map(|root| root.canonicalize().ok())
            .any(|root| resolved.starts_with(root));
        if !allowed {
            return Err(DaemonError::invalid(
                "path",
                format!("{path} is outside the server's data roots"),
            ));
        }
        Ok(resolved)
    }

    /// A message about the server's own files as a client is shown it: paths under a data
    /// root relative to it, uploaded files by their name (as [`Daemon::shown_path`] shows
    /// them), so that no client learns where the server keeps its files.
    pub(crate) fn without_server_folders(&self, message: &str) -> String {
        let uploads = self.config.uploads_dir();
        let folders = self
            .config
            .data_roots
            .iter()
            .chain(std::iter::once(&uploads))
            .flat_map(|folder| [folder.canonicalize().ok(), Some(folder.clone())])
            .flatten();
        folders.fold(message.to_string(), |message, folder| {
            message.replace(&format!("{}/", folder.display()), "")
        })
    }

    /// One dataset of the files of `ids`, in that order (a campaign uploaded file by file).
    pub fn compose_dataset(&self, ids: &[String], name: &str) -> Result<Dataset, DaemonError> {
        check_count("dataset_ids", ids.len())?;
        check_length("name", name, MAX_NAME_BYTES)?;
        let mut files = Vec::new();
        let mut seen = HashSet::new();
        for id in ids {
            let dataset = lookup("dataset_ids", "dataset", id, |id| self.state.dataset(id))?;
            dataset.check_local("composing")?;
            files.extend(
                dataset
                    .files()
                    .into_iter()
                    .filter(|file| seen.insert(file.sha256.clone())),
            );
        }
        check_count("dataset_ids", files.len())?;
        let name = if name.is_empty() {
            format!("{} files", files.len())
        } else {
            name.to_string()
        };
        self.add_dataset(name, files)
    }

    /// Where an upload is written while it arrives.
    pub fn upload_path(&self) -> PathBuf {
        self.config
            .uploads_dir()
            .join(format!("upload-{}.part", unique_suffix()))
    }

    /// The lower-case extension of an upload named `name` (`las` or `laz`), checked before
    /// any of its bytes are received.
    fn upload_extension(name: &str) -> Result<String, DaemonError> {
        check_length("header.name", name, MAX_NAME_BYTES)?;
        Path::new(name)
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase)
            .filter(|e| e == "las" || e == "laz")
            .ok_or_else(|| DaemonError::invalid("header.name", "must end in .las or .laz"))
    }

    /// Refuses, before any of its bytes arrive, an upload named `name` of `size_bytes` that
    /// is not LAS/LAZ by its name, exceeds the upload limit, or would take the uploaded
    /// datasets past the quota.
    pub fn check_upload(&self, name: &str, size_bytes: u64) -> Result<(), DaemonError> {
        Self::upload_extension(name)?;
        let limit = self.config.max_upload_bytes;
        if size_bytes > limit {
            return Err(DaemonError::ResourceExhausted(format!(
                "upload of {size_bytes} bytes exceeds the limit of {limit} bytes"
            )));
        }
        let Some(quota) = self.config.upload_quota_bytes else {
            return Ok(());
        };
        let used = self.state.uploaded_bytes(&self.config.uploads_dir())?;
        if used.saturating_add(size_bytes) > quota {
            return Err(DaemonError::ResourceExhausted(format!(
                "an upload of {size_bytes} bytes exceeds the quota: {used} of {quota} bytes \
                 are taken by uploaded datasets"
            )));
        }
        Ok(())
    }

    /// Takes a completely received upload at `temp` into the datasets.
    pub fn finish_upload(
        &self,
        temp: &Path,
        name: &str,
        sha256: String,
        size_bytes: u64,
    ) -> Result<Dataset, DaemonError> {
        let extension = Self::upload_extension(name)?;
        let id = dataset_id(&sha256);
        let path = self.config.uploads_dir().join(format!("{id}.{extension}"));
        std::fs::rename(temp, &path)?;
        let file = DatasetFile {
            name: name.to_string(),
            path,
            size_bytes,
            sha256,
        };
        self.add_dataset(name.to_string(), vec![file])
    }

    fn add_dataset(&self, name: String, files: Vec<DatasetFile>) -> Result<Dataset, DaemonError> {
        let sha256 = content_sha256(&files);
        let id = dataset_id(&sha256);
        if let Some(existing) = self.state.dataset(&id)? {
            return Ok(existing);
        }
        let Some(first) = files.first() else {
            return Err(DaemonError::invalid("path", "names no file"));
        };
        let dataset = Dataset {
            id,
            name,
            size_bytes: files.iter().map(|f| f.size_bytes).sum(),
            sha256,
            path: first.path.clone(),
            files: if files.len() > 1 { files } else { Vec::new() },
            created_unix_ms: now_unix_ms(),
            remote: None,
            tiles: Vec::new(),
        };
        self.state.put_dataset(&dataset)?;
        tracing::info!(
            dataset = %dataset.id,
            files = dataset.files().len(),
            path = %dataset.path.display(),
            "dataset added"
        );
        Ok(dataset)
    }

    pub fn dataset(&self, id: &str) -> Result<Dataset, DaemonError> {
        lookup("dataset_id", "dataset", id, |id| self.state.dataset(id))
    }

    pub fn list_datasets(&self, page_size: u32, token: &str) -> Result<Page<Dataset>, DaemonError> {
        Ok(self.state.list_datasets(page_size as usize, token)?)
    }

    /// Deletes a dataset, and those of its uploaded files, store and published store that no
    /// other dataset has. Refused while unfinished jobs use it.
    pub fn delete_dataset(&self, id: &str) -> Result<(), DaemonError> {
        check_id("dataset_id", id)?;
        let dataset = self.dataset(id)?;
        if self.state.dataset_in_use(id)? {
            return Err(DaemonError::FailedPrecondition(format!(
                "dataset {id} is used by unfinished jobs"
            )));
        }
        self.state.delete_dataset(id)?;
        let remaining = self.state.datasets()?;
        let still_used: HashSet<PathBuf> = remaining
            .iter()
            .flat_map(Dataset::files)
            .map(|file| file.path)
            .collect();
        if !remaining.iter().any(|d| d.sha256 == dataset.sha256) {
            self.stores.unpublish(&dataset.sha256);
            self.stores.remove(&dataset.sha256);
        }
        let uploads = self.config.uploads_dir();
        for file in dataset.files() {
            if file.path.starts_with(&uploads) && !still_used.contains(&file.path) {
                let _ = std::fs::remove_file(&file.path);
            }
        }
        Ok(())
    }
}

impl Daemon {
    /// The level-of-detail store of dataset `id` for a worker's frame (see
    /// [`DatasetStores::open`](crate::stores::DatasetStores::open)).
    pub fn open_dataset_store(
        &self,
        id: &str,
        levels_of_detail: bool,
    ) -> Result<StoreAnswer, DaemonError> {
        check_id("dataset_id", id)?;
        let dataset = self.store_dataset(id)?;
        self.stores.open(&dataset, levels_of_detail)
    }

    /// The preview sample of dataset `id`, which workers render while its store builds.
    pub fn preview_sample(&self, id: &str) -> Result<Arc<PreviewBytes>, DaemonError> {
        check_id("dataset_id", id)?;
        let dataset = self.store_dataset(id)?;
        self.stores.preview_sample(&dataset)
    }

    /// The opened store of dataset `id`, whose hierarchy and nodes workers fetch.
    pub fn ready_dataset_store(&self, id: &str) -> Result<Arc<ReadyStore>, DaemonError> {
        check_id("dataset_id", id)?;
        let dataset = self.store_dataset(id)?;
        self.stores.ready(&dataset)
    }

    /// Dataset `id`, or the part of one whose store a job reads first (`stores::camera_first`),
    /// for what workers ask of a store.
    pub fn store_dataset(&self, id: &str) -> Result<Dataset, DaemonError> {
        match self.stores.part_dataset(id) {
            Some(part) => Ok(part),
            None => self.dataset(id),
        }
    }
}

mod store_parts;
#[cfg(test)]
mod tests;
