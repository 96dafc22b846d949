//! The hostile-file corpus: LAS/LAZ files broken on purpose, from real scans and from clouds
//! written by `write_las`, and a runner that loads each in a child process and counts what
//! happened (clean errors, loads, panics, aborts, timeouts) and the peak memory.
//!
//! - `layout.rs`: where the mutated fields lie in a well-formed source;
//! - `sources.rs`: the real scans and the written sources;
//! - `mutations.rs`: the mutants of one source;
//! - `generate.rs`: the corpus on disk, reproducibly;
//! - `child.rs`: loading one file in the child and reporting;
//! - `runner.rs`: the children, their timeouts and memory;
//! - `summary.rs`: the counts and the worst files.

use std::io;
use std::path::{Path, PathBuf};

pub mod child;
pub mod generate;
pub mod layout;
pub mod mutations;
pub mod runner;
pub mod sources;
pub mod summary;

/// Why the corpus could not be generated or run (never a verdict on a corpus file).
#[derive(Debug, thiserror::Error)]
pub enum CorpusError {
    #[error("{}: {error}", path.display())]
    Io { path: PathBuf, error: io::Error },
    #[error("{0}")]
    Source(String),
    #[error(transparent)]
    Write(#[from] pointfarm_render::ingest::WriteLasError),
}

impl CorpusError {
    pub fn io(path: &Path, error: io::Error) -> Self {
        Self::Io {
            path: path.to_owned(),
            error,
        }
    }
}

/// Every file under `dir`, sorted, so runs list and count them in one order.
pub fn corpus_files(dir: &Path) -> Result<Vec<PathBuf>, CorpusError> {
    let mut files = Vec::new();
    let mut pending = vec![dir.to_owned()];
    while let Some(dir) = pending.pop() {
        for entry in std::fs::read_dir(&dir).map_err(|error| CorpusError::io(&dir, error))? {
            let path = entry.map_err(|error| CorpusError::io(&dir, error))?.path();
            if path.is_dir() {
                pending.push(path);
            } else if path
                .extension()
                .is_some_and(|extension| extension == "las" || extension == "laz")
            {
                files.push(path);
            }
        }
    }
    files.sort();
    Ok(files)
}
