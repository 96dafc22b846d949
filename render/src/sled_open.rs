//! Opening a sled database that a handle of this process has just dropped.
//!
//! sled locks its directory, and a dropped handle's flusher thread lets go of the lock a
//! little after the drop, so an open right after a drop (a store built, then opened again;
//! a cache reopened) can find the lock held by nobody that still needs it. Every open of a
//! database this crate owns goes through [`open_waiting`], which waits up to [`LOCK_WAIT`]
//! for the lock before failing: past that, another process most likely uses the directory.

use std::time::{Duration, Instant};

/// How long an open waits for sled's lock on the directory.
pub const LOCK_WAIT: Duration = Duration::from_secs(2);

/// Whether `error` is sled's refusal of a directory whose lock another handle holds.
pub fn is_lock_held(error: &sled::Error) -> bool {
    matches!(error, sled::Error::Io(io) if io.to_string().contains("could not acquire lock"))
}

/// Opens `config`'s database, waiting up to [`LOCK_WAIT`] while its lock is held; the last
/// error when the wait runs out (see [`is_lock_held`]).
pub fn open_waiting(config: &sled::Config) -> sled::Result<sled::Db> {
    let started = Instant::now();
    loop {
        match config.open() {
            Err(error) if is_lock_held(&error) && started.elapsed() < LOCK_WAIT => {
                std::thread::sleep(Duration::from_millis(10));
            }
            result => return result,
        }
    }
}
