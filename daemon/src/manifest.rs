//! The state database's manifest: a small file beside it that records how many jobs and
//! datasets the database holds. sled recovers a truncated or bit-flipped log to an earlier,
//! consistent state without a word; the manifest is how the daemon tells that such a state
//! lost records. It is written after each record is added (so it never counts one the
//! database lacks) and before one is deleted.

use std::path::{Path, PathBuf};
use std::sync::Mutex;

use serde::{Deserialize, Serialize};

use crate::error::StateError;

/// What the manifest records.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Counts {
    pub jobs: u64,
    pub datasets: u64,
}

/// The manifest file and the counts it holds.
pub struct Manifest {
    path: PathBuf,
    counts: Mutex<Counts>,
}

impl Manifest {
    /// The manifest of the database at `database` (`state.sled` has `state.manifest.json`).
    pub fn beside(database: &Path) -> PathBuf {
        database.with_extension("manifest.json")
    }

    /// The counts recorded at `path`; None where there is no manifest yet (a new database,
    /// or one written before manifests existed).
    pub fn read(path: &Path) -> Result<Option<Counts>, StateError> {
        match std::fs::read(path) {
            Ok(bytes) => Ok(Some(serde_json::from_slice(&bytes).map_err(|e| {
                StateError::Damaged(format!(
                    "the manifest {} is unreadable: {e}",
                    path.display()
                ))
            })?)),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
            Err(e) => Err(StateError::Io(e)),
        }
    }

    /// Starts the manifest at `path` from `counts` (what the database holds now).
    pub fn create(path: PathBuf, counts: Counts) -> Result<Self, StateError> {
        let manifest = Self {
            path,
            counts: Mutex::new(counts),
        };
        manifest.write(counts)?;
        Ok(manifest)
    }

    /// Applies `change` to the counts and writes them.
    pub fn update(&self, change: impl FnOnce(&mut Counts)) -> Result<(), StateError> {
        let mut counts = self
            .counts
            .lock()
            .map_err(|_| StateError::Damaged("the manifest's lock is poisoned".into()))?;
        change(&mut counts);
        self.write(*counts)
    }

    /// Replaces the file whole: a crash leaves the old counts or the new, never half of them.
    fn write(&self, counts: Counts) -> Result<(), StateError> {
        let partial = self.path.with_extension("json.part");
        let written = std::fs::write(&partial, serde_json::to_vec(&counts)?)
            .and_then(|()| std::fs::rename(&partial, &self.path));
        if written.is_err() {
            // A full disk must not keep the half-written file.
            let _ = std::fs::remove_file(&partial);
        }
        Ok(written?)
    }
}
