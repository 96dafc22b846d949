//! Where a daemon reads its datasets' files from, and how it names them to clients: a file
//! is opened without blocking and read only where it lies inside a data root or the uploads
//! folder (a link swapped in since registration is not followed out), and shown by its path
//! under its data root, or its name.

use std::path::{Path, PathBuf};

use pointfarm_render::ingest::{open_dataset_file, Symlinks};

use crate::error::DaemonError;
use crate::model::Dataset;

/// The folders a dataset's files are read from: the data roots and the uploads folder.
#[derive(Debug, Clone)]
pub struct DatasetFolders {
    data_roots: Vec<PathBuf>,
    uploads: PathBuf,
}

impl DatasetFolders {
    pub fn new(data_roots: Vec<PathBuf>, uploads: PathBuf) -> Self {
        Self {
            data_roots,
            uploads,
        }
    }

    fn folders(&self) -> impl Iterator<Item = &PathBuf> {
        self.data_roots.iter().chain(std::iter::once(&self.uploads))
    }

    /// How a client is shown the server's file `path`: its path under the data root it lies
    /// in, else (an uploaded file) its name.
    pub fn shown(&self, path: &Path) -> String {
        self.data_roots
            .iter()
            .filter_map(|root| root.canonicalize().ok())
            .find_map(|root| {
                path.strip_prefix(root)
                    .ok()
                    .map(|under| under.display().to_string())
            })
            .unwrap_or_else(|| file_name(path))
    }

    /// Opens a dataset's stored file to read it ([`open_dataset_file`]: a regular file only,
    /// never blocking on a special one), refusing it unless the file opened lies inside one
    /// of the folders: a link put in place of the file or a folder since registration is
    /// followed only as far as the roots. (Links inside the roots stay readable, as records
    /// registered through them store the link's path.)
    pub fn open(&self, path: &Path) -> std::io::Result<std::fs::File> {
        let file = open_dataset_file(path, Symlinks::Follow)?;
        let opened = opened_path(&file).or_else(|_| path.canonicalize())?;
        let allowed = self
            .folders()
            .filter_map(|folder| folder.canonicalize().ok())
            .any(|folder| opened.starts_with(folder));
        if !allowed {
            tracing::warn!(
                path = %path.display(),
                opened = %opened.display(),
                "refused to read a dataset's file: it now lies outside the data roots"
            );
            return Err(std::io::Error::new(
                std::io::ErrorKind::PermissionDenied,
                "now lies outside the server's data roots",
            ));
        }
        Ok(file)
    }

    /// Refuses `dataset` unless every file of it still opens as [`DatasetFolders::open`]
    /// opens it: checked before the render crate's readers (which follow links, as the CLI's
    /// must) read the files for a store or a preview. The error names the file as a client
    /// sees it.
    pub fn check(&self, dataset: &Dataset) -> Result<(), DaemonError> {
        dataset.check_local("reading the files of")?;
        for file in dataset.files() {
            self.open(&file.path).map_err(|error| {
                tracing::warn!(path = %file.path.display(), %error, "a dataset's file cannot be read");
                DaemonError::FailedPrecondition(format!(
                    "dataset {}, file {}: {error}",
                    dataset.id,
                    self.shown(&file.path)
                ))
            })?;
        }
        Ok(())
    }
}

/// The last component of `path`: how a dataset's file is named, and an uploaded one shown.
pub(crate) fn file_name(path: &Path) -> String {
    path.file_name()
        .map(|name| name.to_string_lossy().into_owned())
        .unwrap_or_default()
}

/// Where the opened `file` lies, as the kernel knows it (no race with a path changed since).
#[cfg(target_os = "linux")]
fn opened_path(file: &std::fs::File) -> std::io::Result<PathBuf> {
    use std::os::fd::AsRawFd;
    std::fs::read_link(format!("/proc/self/fd/{}", file.as_raw_fd()))
}

#[cfg(not(target_os = "linux"))]
fn opened_path(_: &std::fs::File) -> std::io::Result<PathBuf> {
    Err(std::io::ErrorKind::Unsupported.into())
}
