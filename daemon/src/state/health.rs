//! Whether the daemon's disk takes writes: the first write refused (a full disk, a quota, a
//! failing device) is logged once and remembered until a probe write beside the database
//! succeeds again. While it is remembered no frames are leased and health is NOT_SERVING.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::{Mutex, MutexGuard};
use std::time::Instant;

use crate::error::disk_error_message;

/// Enough for sled's next log segment (512 KiB) and a frame or two: a disk with less free
/// would fail again at once.
const PROBE_BYTES: usize = 2 << 20;

/// What the disk refused, since when.
#[derive(Debug, Clone)]
struct Failure {
    since: Instant,
    /// Said to every caller that meets the failure.
    message: String,
    /// The state database met the error: sled stays failed until it is opened again.
    database: bool,
}

/// The disk's state as the state database knows it.
pub(super) struct DiskHealth {
    /// The probe file, beside the database (the frames live on the same data folder).
    probe_path: PathBuf,
    failure: Mutex<Option<Failure>>,
}

impl DiskHealth {
    pub(super) fn new(database: &Path) -> Self {
        Self {
            probe_path: database.with_extension("probe"),
            failure: Mutex::new(None),
        }
    }

    fn failure(&self) -> MutexGuard<'_, Option<Failure>> {
        // A plain value, consistent after any panic.
        self.failure.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Remembers that the disk refused a write (`database`: sled's own); logs only the first
    /// refusal of an outage. Returns what callers are told.
    pub(super) fn refused(&self, error: &std::io::Error, database: bool) -> String {
        let mut failure = self.failure();
        match failure.as_mut() {
            Some(known) => {
                known.database |= database;
                known.message.clone()
            }
            None => {
                let message = format!(
                    "{}: the daemon stores and leases no frames until space returns",
                    disk_error_message(error)
                );
                tracing::error!(
                    error = %error,
                    "{}; health is NOT_SERVING and no frames are leased meanwhile; the daemon \
                     probes the disk every second and resumes by itself",
                    disk_error_message(error)
                );
                *failure = Some(Failure {
                    since: Instant::now(),
                    message: message.clone(),
                    database,
                });
                message
            }
        }
    }

    /// Whether the disk takes a new record now: an error (what callers are told) during an
    /// outage, or when the free space under the database is below [`PROBE_BYTES`], which starts
    /// one. Checked before a record that must not be seen unless it is stored (a submitted
    /// job) is written: sled keeps a write in memory, visible to readers, even when flushing
    /// it fails.
    pub(super) fn check_room(&self) -> Result<(), String> {
        if let Some(message) = self.outage() {
            return Err(message);
        }
        match free_bytes(&self.probe_path) {
            Some(free) if free < PROBE_BYTES as u64 => Err(self.refused(
                &std::io::Error::from(std::io::ErrorKind::StorageFull),
                false,
            )),
            _ => Ok(()),
        }
    }

    /// What the disk refused, while the outage lasts.
    pub(super) fn outage(&self) -> Option<String> {
        self.failure().as_ref().map(|f| f.message.clone())
    }

    /// Whether sled met the outage (and must be opened again before it writes).
    pub(super) fn database_failed(&self) -> bool {
        self.failure().as_ref().is_some_and(|f| f.database)
    }

    /// Writes and syncs a probe file beside the database, then removes it: whether the disk
    /// takes writes again.
    pub(super) fn probe(&self) -> std::io::Result<()> {
        let written = (|| {
            let mut file = std::fs::File::create(&self.probe_path)?;
            file.write_all(&vec![0u8; PROBE_BYTES])?;
            file.sync_all()
        })();
        let _ = std::fs::remove_file(&self.probe_path);
        written
    }

    /// The outage is over; logs how long it lasted.
    pub(super) fn recovered(&self) {
        if let Some(failure) = self.failure().take() {
            tracing::info!(
                outage_s = failure.since.elapsed().as_secs(),
                reopened_database = failure.database,
                "the daemon's disk takes writes again: leasing and storing frames again"
            );
        }
    }
}

/// The bytes an unprivileged writer may still use on the filesystem of the folder holding
/// `beside`; None where that cannot be told.
#[cfg(unix)]
fn free_bytes(beside: &Path) -> Option<u64> {
    let folder = beside.parent()?;
    let stats = rustix::fs::statvfs(folder).ok()?;
    Some(stats.f_bavail.saturating_mul(stats.f_frsize))
}

#[cfg(not(unix))]
fn free_bytes(_: &Path) -> Option<u64> {
    None
}
