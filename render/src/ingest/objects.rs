//! A dataset's files as objects by URL: each tile's header, records and chunk table checked
//! as a file's are, through small ranged blocks, and its points then streamed from start to
//! end through an [`ObjectReader`] (large blocks, one read ahead), never copied whole to disk
//! or memory. Every read of a tile is pinned to the version it was opened at.

use std::io::BufReader;
use std::path::PathBuf;
use std::sync::Arc;

use rayon::prelude::*;

use super::files::{open_dataset_file, Symlinks};
use super::preparse::ChunkChecks;
use super::ranged::check_stream;
use super::raw_file::ReadSeek;
use super::read::DatasetFile;
use super::{DatasetSource, IngestError};
use crate::remote::{ObjectReader, RemoteObject};

/// Blocks a tile's checks read: a header and its records take one or two, a chunk table one,
/// a layered chunk's layer table one each.
const CHECK_BLOCK_BYTES: u64 = 16 * 1024;

/// What a file's points are read through: a buffered file here, or a stream of the object.
pub(super) type FileBytes = Box<dyn ReadSeek + Send + Sync>;

impl DatasetFile {
    /// The file's bytes from their start: the file here (symbolic links followed), or the
    /// object streamed.
    pub(super) fn open_bytes(&self) -> Result<FileBytes, IngestError> {
        if let Some(object) = &self.object {
            return Ok(Box::new(ObjectReader::new(Arc::clone(object))));
        }
        let file =
            open_dataset_file(&self.path, Symlinks::Follow).map_err(|error| IngestError::Io {
                path: self.path.clone(),
                error,
            })?;
        Ok(Box::new(BufReader::new(file)))
    }

    /// An object checked as a file is (its chunks' layer tables too, read by range), named by
    /// its URL.
    pub(super) fn check_object(object: RemoteObject) -> Result<Self, IngestError> {
        let name = PathBuf::from(object.url().to_string());
        let size = object.size();
        let object = Arc::new(object);
        let mut stream = ObjectReader::with_blocks(Arc::clone(&object), CHECK_BLOCK_BYTES, false);
        let (mut file, _) = check_stream(&name, &mut stream, size, ChunkChecks::Layers)?;
        file.object = Some(object);
        Ok(file)
    }
}

impl DatasetSource {
    /// The LAS/LAZ objects of a dataset, each checked as a file is (in parallel on the
    /// caller's pool: each check waits on round trips), as a source whose build streams them
    /// one after another.
    pub fn open_objects(objects: Vec<RemoteObject>) -> Result<Self, IngestError> {
        let files = objects
            .into_par_iter()
            .map(DatasetFile::check_object)
            .collect::<Result<Vec<_>, _>>()?;
        Self::of_files(files)
    }
}

/// A fingerprint of `files` read by URL: each object's URL, size and version, so that a build
/// resumes only over the same versions.
pub(super) fn objects_fingerprint(files: &[DatasetFile]) -> Option<String> {
    let mut text = String::new();
    for file in files {
        let object = file.object.as_ref()?;
        text.push_str(&format!(
            "{} {} bytes version {}; ",
            object.url(),
            object.size(),
            object.version()?
        ));
    }
    Some(text)
}
