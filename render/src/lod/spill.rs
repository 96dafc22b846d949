//! Spill files: a build's own folder (removed when the build ends, also on error), writers
//! that append points to many files through bounded buffers, and reading points back.

use std::fs::{File, OpenOptions};
use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

use super::error::LodError;
use super::memory::Reservation;
use super::point::{RawPoint, SPILL_RECORD_BYTES};

/// Records read per block when a spill file is streamed back.
const READ_BLOCK_POINTS: usize = 1 << 12;
/// What streaming a file back holds: a block of records and the block decoded. Callers
/// include it in their own reservation: a holder that reserved again could wait forever.
pub const READ_BLOCK_BYTES: u64 = (READ_BLOCK_POINTS * (SPILL_RECORD_BYTES + 40)) as u64;

/// The build's spill folder inside the caller's one; removed with everything in it on drop.
#[derive(Debug)]
pub struct SpillDir {
    path: PathBuf,
    written: AtomicU64,
}

impl SpillDir {
    pub fn create(parent: &Path) -> Result<Self, LodError> {
        static NEXT: AtomicU64 = AtomicU64::new(0);
        std::fs::create_dir_all(parent).map_err(|e| LodError::spill(parent, e))?;
        loop {
            let n = NEXT.fetch_add(1, Ordering::Relaxed);
            let path = parent.join(format!("pointfarm-lod-{}-{n}", std::process::id()));
            match std::fs::create_dir(&path) {
                Ok(()) => {
                    return Ok(Self {
                        path,
                        written: AtomicU64::new(0),
                    })
                }
                // Left by an earlier process with the same id: take the next name.
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => continue,
                Err(e) => return Err(LodError::spill(path, e)),
            }
        }
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    pub fn file(&self, name: &str) -> PathBuf {
        self.path.join(name)
    }

    /// Bytes written into spill files so far.
    pub fn written_bytes(&self) -> u64 {
        self.written.load(Ordering::Relaxed)
    }

    fn count_written(&self, bytes: usize) {
        self.written.fetch_add(bytes as u64, Ordering::Relaxed);
    }

    /// Writes `points` as one new file.
    pub fn write_file(&self, path: &Path, points: &[RawPoint]) -> Result<(), LodError> {
        let mut bytes = Vec::with_capacity(points.len() * SPILL_RECORD_BYTES);
        for p in points {
            p.write_to(&mut bytes);
        }
        std::fs::write(path, &bytes).map_err(|e| LodError::spill(path, e))?;
        self.count_written(bytes.len());
        Ok(())
    }
}

impl Drop for SpillDir {
    fn drop(&mut self) {
        if let Err(error) = std::fs::remove_dir_all(&self.path) {
            tracing::warn!(path = %self.path.display(), %error, "could not remove the spill folder");
        }
    }
}

/// Appends points to one of many files, holding at most `limit` bytes of records in memory:
/// when they are reached every buffer is appended to its file and freed.
pub struct SpillWriter<'a> {
    dir: &'a SpillDir,
    paths: Vec<PathBuf>,
    buffers: Vec<Vec<u8>>,
    buffered: usize,
    limit: usize,
    _reservation: Reservation<'a>,
}

impl<'a> SpillWriter<'a> {
    /// A writer to `paths` holding at most `limit` bytes of records; `reservation` covers
    /// twice that (the slack of growing vectors), taken by the caller with whatever else it
    /// holds at once.
    pub fn new(
        dir: &'a SpillDir,
        paths: Vec<PathBuf>,
        limit: usize,
        reservation: Reservation<'a>,
    ) -> Self {
        let limit = limit.max(SPILL_RECORD_BYTES);
        debug_assert!(reservation.bytes() >= 2 * limit as u64);
        Self {
            dir,
            buffers: vec![Vec::new(); paths.len()],
            paths,
            buffered: 0,
            limit,
            _reservation: reservation,
        }
    }

    pub fn push(&mut self, target: usize, point: &RawPoint) -> Result<(), LodError> {
        point.write_to(&mut self.buffers[target]);
        self.buffered += SPILL_RECORD_BYTES;
        if self.buffered + SPILL_RECORD_BYTES > self.limit {
            self.flush()?;
        }
        Ok(())
    }

    fn flush(&mut self) -> Result<(), LodError> {
        for (buffer, path) in self.buffers.iter_mut().zip(&self.paths) {
            if buffer.is_empty() {
                continue;
            }
            // Opened per flush rather than kept open: a build may spill to more files than
            // the process may hold open.
            let mut file = OpenOptions::new()
                .create(true)
                .append(true)
                .open(path)
                .map_err(|e| LodError::spill(path, e))?;
            file.write_all(buffer)
                .map_err(|e| LodError::spill(path, e))?;
            self.dir.count_written(buffer.len());
            *buffer = Vec::new();
        }
        self.buffered = 0;
        Ok(())
    }

    /// Writes what is left; every file now holds all its points.
    pub fn finish(mut self) -> Result<(), LodError> {
        self.flush()
    }
}

/// Streams the points of `path` in blocks of at most [`READ_BLOCK_POINTS`].
pub fn for_each_block(
    path: &Path,
    mut visit: impl FnMut(&[RawPoint]) -> Result<(), LodError>,
) -> Result<u64, LodError> {
    let mut reader = File::open(path).map_err(|e| LodError::spill(path, e))?;
    let mut bytes = vec![0; READ_BLOCK_POINTS * SPILL_RECORD_BYTES];
    let mut points = Vec::with_capacity(READ_BLOCK_POINTS);
    let mut total = 0;
    loop {
        let mut filled = 0;
        while filled < bytes.len() {
            let n = reader
                .read(&mut bytes[filled..])
                .map_err(|e| LodError::spill(path, e))?;
            if n == 0 {
                break;
            }
            filled += n;
        }
        if filled % SPILL_RECORD_BYTES != 0 {
            let error = std::io::Error::new(
                std::io::ErrorKind::UnexpectedEof,
                "the file ends inside a point record",
            );
            return Err(LodError::spill(path, error));
        }
        if filled == 0 {
            return Ok(total);
        }
        points.clear();
        points.extend(
            bytes[..filled]
                .chunks_exact(SPILL_RECORD_BYTES)
                .map(RawPoint::read_from),
        );
        total += points.len() as u64;
        visit(&points)?;
    }
}

/// Reads all points of `path`, which must hold exactly `expected`.
pub fn read_all(path: &Path, expected: u64) -> Result<Vec<RawPoint>, LodError> {
    let mut points = Vec::with_capacity(expected as usize);
    for_each_block(path, |block| {
        points.extend_from_slice(block);
        Ok(())
    })?;
    if points.len() as u64 != expected {
        let error = std::io::Error::new(
            std::io::ErrorKind::InvalidData,
            format!("holds {} points, {expected} were written", points.len()),
        );
        return Err(LodError::spill(path, error));
    }
    Ok(points)
}

/// Removes a spill file that has been consumed.
pub fn remove(path: &Path) -> Result<(), LodError> {
    std::fs::remove_file(path).map_err(|e| LodError::spill(path, e))
}
