//! Spill files: a build's own folder (removed when the build ends, also on error), writers
//! that append points to many files through bounded buffers, and reading points back.

use std::fs::{File, OpenOptions};
use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::Duration;

use super::attributes::AttributeRows;
use super::checksum::checksum64;
use super::error::LodError;
use super::memory::Reservation;
use super::point::{RawPoint, RecordLayout, MAX_RECORD_BYTES};
use super::thread_cpu::thread_cpu;

/// The most threads that append one set of buffers to their files at once: appends to
/// distinct files run side by side in the kernel, where one thread copying every byte a pass
/// writes bounds the pass however many cores decode (docs/perf/lod-build-decode-bound.md).
const MAX_WRITING_THREADS: usize = 8;

/// Records read per block when a spill file is streamed back.
const READ_BLOCK_POINTS: usize = 1 << 12;

/// What streaming a file of `layout` back holds: a block of records and the block decoded.
/// Callers include it in their own reservation: a holder that reserved again could wait
/// forever.
pub fn read_block_bytes(layout: RecordLayout) -> u64 {
    (READ_BLOCK_POINTS * (layout.record_bytes().max(MAX_RECORD_BYTES) + 48)) as u64
}

/// The build's spill folder inside the caller's one, and the layout of every record in it;
/// removed with everything in it on drop, unless it is kept for a build to resume.
#[derive(Debug)]
pub struct SpillDir {
    path: PathBuf,
    layout: RecordLayout,
    written: AtomicU64,
    kept: AtomicBool,
}

impl SpillDir {
    pub fn create(parent: &Path, layout: RecordLayout) -> Result<Self, LodError> {
        static NEXT: AtomicU64 = AtomicU64::new(0);
        std::fs::create_dir_all(parent).map_err(|e| LodError::spill(parent, e))?;
        loop {
            let n = NEXT.fetch_add(1, Ordering::Relaxed);
            let path = parent.join(format!("pointfarm-lod-{}-{n}", std::process::id()));
            match std::fs::create_dir(&path) {
                Ok(()) => return Ok(Self::at(path, layout, false)),
                // Left by an earlier process with the same id: take the next name.
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => continue,
                Err(e) => return Err(LodError::spill(path, e)),
            }
        }
    }

    /// The folder `path`, made by the caller, kept on drop while `kept` (a build that can
    /// resume keeps it until it has finished).
    pub fn at(path: PathBuf, layout: RecordLayout, kept: bool) -> Self {
        Self {
            path,
            layout,
            written: AtomicU64::new(0),
            kept: AtomicBool::new(kept),
        }
    }

    /// Removes the folder on drop after all: the build is finished.
    pub fn release(&self) {
        self.kept.store(false, Ordering::Relaxed);
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    pub fn layout(&self) -> RecordLayout {
        self.layout
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

    /// Writes `points`, with their attribute `rows`, as one new file, synced first when
    /// `synced`; returns its length and checksum ([`file_checksum`]).
    pub fn write_file(
        &self,
        path: &Path,
        points: &[RawPoint],
        rows: &AttributeRows,
        synced: bool,
    ) -> Result<(u64, u64), LodError> {
        let mut bytes = Vec::with_capacity(points.len() * self.layout.record_bytes());
        for p in points {
            self.layout.append(p, rows.of(p), &mut bytes)?;
        }
        let mut file = File::create(path).map_err(|e| LodError::spill(path, e))?;
        file.write_all(&bytes)
            .and_then(|()| if synced { file.sync_data() } else { Ok(()) })
            .map_err(|e| LodError::spill(path, e))?;
        self.count_written(bytes.len());
        Ok((bytes.len() as u64, checksum64(FILE_SEED, &bytes)))
    }
}

const FILE_SEED: &[u8] = b"spill file";

/// The length and checksum of a spill file's bytes, as [`SpillDir::write_file`] returned them.
pub fn file_checksum(path: &Path) -> Result<(u64, u64), LodError> {
    let bytes = std::fs::read(path).map_err(|e| LodError::spill(path, e))?;
    Ok((bytes.len() as u64, checksum64(FILE_SEED, &bytes)))
}

/// Syncs the files `paths` (those a writer appended to), for a journal to list them.
pub fn sync_files(paths: &[PathBuf]) -> Result<(), LodError> {
    for path in paths {
        File::open(path)
            .and_then(|file| file.sync_data())
            .map_err(|e| LodError::spill(path, e))?;
    }
    Ok(())
}

impl Drop for SpillDir {
    fn drop(&mut self) {
        if self.kept.load(Ordering::Relaxed) {
            return;
        }
        if let Err(error) = std::fs::remove_dir_all(&self.path) {
            tracing::warn!(path = %self.path.display(), %error, "could not remove the spill folder");
        }
    }
}

/// Appends points to one of many files, holding at most `limit` bytes of records in memory:
/// when half of them are buffered, the buffers go to a thread of their own that appends each
/// to its file while the next half fills, so reading the source and writing spill overlap.
///
/// Where the caller reserved more than twice `limit`, the written buffers come back and are
/// filled again, up to half of that excess in capacity: a buffer grown afresh each set costs
/// its copies while it doubles and the pages it first touches.
pub struct SpillWriter<'a> {
    dir: &'a SpillDir,
    paths: Arc<dyn Fn(usize) -> PathBuf + Send + Sync>,
    buffers: Vec<Vec<u8>>,
    /// The targets whose buffers hold records, in the order they were first written: a set
    /// is handed over by these alone, whatever the number of targets.
    filled: Vec<usize>,
    buffered: usize,
    record_bytes: usize,
    /// Bytes of records a set of buffers takes before it is handed to the writing thread.
    set_limit: usize,
    /// The set being appended to its files; its thread returns the CPU time it took.
    writing: Option<JoinHandle<Result<Written, LodError>>>,
    /// Written buffers, emptied, waiting to be filled again.
    spare: Vec<Vec<u8>>,
    /// Capacity of the buffers this holds: the spare ones and those being filled.
    held: usize,
    /// The most capacity a written buffer may come back into: the spare ones and those being
    /// filled stay within it, beside what they grow by in a set.
    reuse_limit: usize,
    /// CPU time of each set's busiest writing thread, summed over the sets that ended.
    writing_cpu: Duration,
    /// Threads that append a set: as many as the pool the writer was made on has, within
    /// [`MAX_WRITING_THREADS`].
    writing_threads: usize,
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
        let targets = paths.len();
        Self::named(
            dir,
            targets,
            move |target| paths[target].clone(),
            limit,
            reservation,
        )
    }

    /// A writer to `targets` files, file `target` at `path(target)` (made when it is first
    /// written to), holding at most `limit` bytes of records, as [`Self::new`].
    pub fn named(
        dir: &'a SpillDir,
        targets: usize,
        path: impl Fn(usize) -> PathBuf + Send + Sync + 'static,
        limit: usize,
        reservation: Reservation<'a>,
    ) -> Self {
        let record_bytes = dir.layout().record_bytes();
        let limit = limit.max(record_bytes);
        debug_assert!(reservation.bytes() >= 2 * limit as u64);
        let set_limit = (limit / 2).max(record_bytes);
        // Each of the two sets holds at most what comes back and what a set grows by.
        let reuse_limit = (reservation.bytes() as usize).saturating_sub(2 * limit) / 2;
        Self {
            dir,
            buffers: vec![Vec::new(); targets],
            paths: Arc::new(path),
            filled: Vec::new(),
            buffered: 0,
            record_bytes,
            set_limit,
            writing: None,
            spare: Vec::new(),
            held: 0,
            reuse_limit,
            writing_cpu: Duration::ZERO,
            writing_threads: rayon::current_num_threads().clamp(1, MAX_WRITING_THREADS),
            _reservation: reservation,
        }
    }

    /// Appends one record, in the spill folder's layout, to file `target`.
    pub fn push_record(&mut self, target: usize, record: &[u8]) -> Result<(), LodError> {
        debug_assert_eq!(record.len(), self.record_bytes);
        let buffer = &mut self.buffers[target];
        if buffer.is_empty() {
            self.filled.push(target);
            if buffer.capacity() == 0 {
                // A spare buffer's capacity is counted in `held` already.
                *buffer = self.spare.pop().unwrap_or_default();
            }
        }
        let before = buffer.capacity();
        buffer.extend_from_slice(record);
        self.held += buffer.capacity() - before;
        self.pushed()
    }

    fn pushed(&mut self) -> Result<(), LodError> {
        self.buffered += self.record_bytes;
        if self.buffered + self.record_bytes > self.set_limit {
            self.flush()?;
        }
        Ok(())
    }

    /// Hands the buffers to the writing thread once it is done with the previous set.
    fn flush(&mut self) -> Result<(), LodError> {
        self.wait()?;
        if self.buffered == 0 {
            return Ok(());
        }
        let buffers: Vec<(usize, Vec<u8>)> = self
            .filled
            .drain(..)
            .map(|target| (target, std::mem::take(&mut self.buffers[target])))
            .collect();
        self.held -= buffers.iter().map(|(_, b)| b.capacity()).sum::<usize>();
        self.dir.count_written(self.buffered);
        self.buffered = 0;
        let paths = Arc::clone(&self.paths);
        let threads = self.writing_threads;
        let thread = std::thread::Builder::new()
            .name("spill-writer".into())
            .spawn(move || append_all(paths.as_ref(), buffers, threads))
            .map_err(|e| LodError::spill(self.dir.path(), e))?;
        self.writing = Some(thread);
        Ok(())
    }

    /// Waits for the set being written, if any, and returns its error.
    fn wait(&mut self) -> Result<(), LodError> {
        match self.writing.take().map(JoinHandle::join) {
            None => Ok(()),
            Some(Ok(written)) => {
                let written = written?;
                self.writing_cpu += written.cpu;
                for mut buffer in written.buffers {
                    if self.held + buffer.capacity() > self.reuse_limit {
                        continue;
                    }
                    buffer.clear();
                    self.held += buffer.capacity();
                    self.spare.push(buffer);
                }
                Ok(())
            }
            Some(Err(_)) => Err(LodError::spill(
                self.dir.path(),
                std::io::Error::other("the spill writing thread panicked"),
            )),
        }
    }

    /// Writes every record pushed so far to its file and waits until it is written.
    pub fn settle(&mut self) -> Result<(), LodError> {
        self.flush()?;
        self.wait()
    }

    /// Writes what is left; every file now holds all its points. Returns the CPU time of the
    /// writing's critical path: each set's busiest thread, summed over the sets.
    pub fn finish(mut self) -> Result<Duration, LodError> {
        self.flush()?;
        self.wait()?;
        Ok(self.writing_cpu)
    }
}

impl Drop for SpillWriter<'_> {
    /// A writer dropped on an error still waits for its thread, which writes into the folder
    /// its owner is about to remove.
    fn drop(&mut self) {
        let _ = self.wait();
    }
}

/// A set appended to its files: the CPU time of its busiest thread, and its buffers, to be
/// filled again.
struct Written {
    cpu: Duration,
    buffers: Vec<Vec<u8>>,
}

/// Appends each non-empty buffer of a set (one at most a target) to its file, on up to
/// `threads` threads taking the largest buffers first; returns the CPU time of the set's
/// busiest thread, which the next set waits for, and the buffers.
fn append_all(
    paths: &(dyn Fn(usize) -> PathBuf + Send + Sync),
    buffers: Vec<(usize, Vec<u8>)>,
    threads: usize,
) -> Result<Written, LodError> {
    let mut buffers = buffers;
    let cpu = append_each(paths, &mut buffers, threads)?;
    Ok(Written {
        cpu,
        buffers: buffers.into_iter().map(|(_, buffer)| buffer).collect(),
    })
}

fn append_each(
    paths: &(dyn Fn(usize) -> PathBuf + Send + Sync),
    buffers: &mut Vec<(usize, Vec<u8>)>,
    threads: usize,
) -> Result<Duration, LodError> {
    buffers.retain(|(_, buffer)| !buffer.is_empty());
    buffers.sort_by_key(|(_, buffer)| std::cmp::Reverse(buffer.len()));
    let next = AtomicUsize::new(0);
    let failed = AtomicBool::new(false);
    let work = || -> Result<Duration, LodError> {
        while !failed.load(Ordering::Relaxed) {
            let Some((target, buffer)) = buffers.get(next.fetch_add(1, Ordering::Relaxed)) else {
                break;
            };
            append(&paths(*target), buffer)
                .inspect_err(|_| failed.store(true, Ordering::Relaxed))?;
        }
        Ok(thread_cpu().unwrap_or_default())
    };
    std::thread::scope(|scope| {
        // A helper that cannot be started leaves its share to the others.
        let helpers: Vec<_> = (1..threads.min(buffers.len()))
            .filter_map(|_| {
                std::thread::Builder::new()
                    .name("spill-writer".into())
                    .spawn_scoped(scope, work)
                    .ok()
            })
            .collect();
        let mut busiest = work()?;
        for helper in helpers {
            let cpu = helper.join().unwrap_or_else(|_| {
                Err(LodError::Source(
                    "a thread appending spill files panicked".into(),
                ))
            })?;
            busiest = busiest.max(cpu);
        }
        Ok(busiest)
    })
}

/// Appends `buffer` to the file at `path`, made if it is not there.
fn append(path: &Path, buffer: &[u8]) -> Result<(), LodError> {
    // Opened per set rather than kept open: a build may spill to more files than the process
    // may hold open.
    let mut file = OpenOptions::new()
        .create(true)
        .append(true)
        .open(path)
        .map_err(|e| LodError::spill(path, e))?;
    file.write_all(buffer).map_err(|e| LodError::spill(path, e))
}

/// Streams the points of `path`, records in `layout`, in blocks of at most
/// [`READ_BLOCK_POINTS`]: each block's points with their records.
pub fn for_each_block(
    path: &Path,
    layout: RecordLayout,
    mut visit: impl FnMut(&[RawPoint], &[u8]) -> Result<(), LodError>,
) -> Result<u64, LodError> {
    let mut reader = File::open(path).map_err(|e| LodError::spill(path, e))?;
    let record_bytes = layout.record_bytes();
    let mut bytes = vec![0; READ_BLOCK_POINTS * record_bytes];
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
        if filled % record_bytes != 0 {
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
                .chunks_exact(record_bytes)
                .map(|record| layout.read(record)),
        );
        total += points.len() as u64;
        visit(&points, &bytes[..filled])?;
    }
}

/// Reads all points of the files `paths`, in order, records in `layout`, their attribute
/// rows appended to `rows` (each point's `row` its index there); together they must hold
/// exactly `expected`.
pub fn read_all(
    paths: &[PathBuf],
    layout: RecordLayout,
    expected: u64,
    rows: &mut AttributeRows,
) -> Result<Vec<RawPoint>, LodError> {
    let mut points = Vec::new();
    read_all_into(paths, layout, expected, rows, &mut points)?;
    Ok(points)
}

/// [`read_all`] into the caller's `points`, emptied first, so that a buffer is reused from
/// one partition to the next.
pub fn read_all_into(
    paths: &[PathBuf],
    layout: RecordLayout,
    expected: u64,
    rows: &mut AttributeRows,
    points: &mut Vec<RawPoint>,
) -> Result<(), LodError> {
    points.clear();
    points.reserve_exact(expected as usize);
    rows.reserve(expected as usize);
    let record_bytes = layout.record_bytes();
    for path in paths {
        for_each_block(path, layout, |block, records| {
            if (points.len() + block.len()) as u64 > expected {
                let error = std::io::Error::new(
                    std::io::ErrorKind::InvalidData,
                    format!("holds more than the {expected} points written"),
                );
                return Err(LodError::spill(path, error));
            }
            for (p, record) in block.iter().zip(records.chunks_exact(record_bytes)) {
                let row = rows.push(layout.row(record));
                points.push(RawPoint { row, ..*p });
            }
            Ok(())
        })?;
    }
    if points.len() as u64 != expected {
        let error = std::io::Error::new(
            std::io::ErrorKind::InvalidData,
            format!("hold {} points, {expected} were written", points.len()),
        );
        let path = paths.last().map_or(Path::new(""), PathBuf::as_path);
        return Err(LodError::spill(path, error));
    }
    Ok(())
}

/// Removes a spill file that has been consumed.
pub fn remove(path: &Path) -> Result<(), LodError> {
    std::fs::remove_file(path).map_err(|e| LodError::spill(path, e))
}
