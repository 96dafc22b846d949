//! The build journal: what a build has finished, kept in its spill folder so that a build that
//! stopped (killed, power lost) resumes when it runs again on the same inputs and options.
//!
//! Three files. `inputs` names what the build reads and how (the source's fingerprint, the
//! options and what the build derived from them); a journal of other inputs is wiped, never
//! read. `counted` holds the counting pass's grid and statistics, rewritten as the pass reaches
//! each part of the source (a file) and once it ends. Both are written whole:
//! to a temporary file, synced, renamed, the folder synced. `units.log` lists every finished
//! unit in the order its output was written, each frame its length and checksum first; a torn
//! or damaged frame ends the log, is cut off and its unit (and any after it) is redone.
//!
//! Units commit in groups. Under the journal's queue lock a unit only writes its output where
//! the order matters (its payload region) and queues its frame with a sequence number; then one
//! unit at a time leads a flush, which takes every queued frame, syncs the units' outputs once,
//! appends the frames and syncs the log once, so a unit waits for one sync of each file shared
//! with every unit queued beside it instead of a chain of syncs. A frame is never durable before
//! the outputs it lists, and the log lists frames in the order of their payload regions.

use std::fs::{self, File, OpenOptions};
use std::io::{self, Read, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Mutex, MutexGuard};

use super::checksum::checksum64;
use super::error::LodError;
use super::hierarchy::{decode_listing, encode_listing, NodeInfo};
use super::key::NodeKey;
use super::stats::DatasetStats;

const INPUTS_FILE: &str = "inputs";
const COUNTED_FILE: &str = "counted";
const UNITS_FILE: &str = "units.log";
const FRAME_SEED: &[u8] = b"build journal frame";
const FILE_SEED: &[u8] = b"build journal file";
/// Bytes before a frame's body: its length (u32) and checksum (u64).
const FRAME_HEAD: usize = 12;

/// What kind of unit a frame records.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum UnitKind {
    /// A partition's octree, stored.
    Partition = 1,
    /// A partition split on disk into its children's files.
    Split = 2,
    /// A node above the partitions, with its children, stored.
    Parent = 3,
}

impl UnitKind {
    /// The unit's stage in the build's test hook (`pause.rs`).
    pub fn stage(self) -> &'static str {
        match self {
            UnitKind::Partition => "partition",
            UnitKind::Split => "split",
            UnitKind::Parent => "parent",
        }
    }
}

/// A subtree root left in a spill file for the level above: its points, sampling grid, and
/// the file's length and checksum.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct WaitingRoot {
    pub count: u64,
    pub sample_grid: u32,
    pub bytes: u64,
    pub checksum: u64,
}

/// One finished unit.
#[derive(Debug, Clone, PartialEq)]
pub struct UnitRecord {
    pub kind: UnitKind,
    pub key: NodeKey,
    /// The payload file's length once this unit's nodes were in it.
    pub payload_end: u64,
    /// The unit's subtree root, waiting for the level above (none for the root itself and a
    /// split).
    pub waiting: Option<WaitingRoot>,
    /// A split's points per child; zeros otherwise.
    pub children: [u64; 8],
    /// The nodes the unit stored, where their records lie.
    pub nodes: Vec<NodeInfo>,
}

/// The counting pass's result, or where it got to: its first `points_read` points counted.
#[derive(Debug, Clone, PartialEq)]
pub struct Counted {
    pub points_read: u64,
    pub level: u32,
    pub segment_points: u64,
    pub counts: Vec<u64>,
    pub stats: DatasetStats,
}

/// What an earlier run of the same build finished.
#[derive(Debug)]
pub struct Replay {
    pub counted: Counted,
    pub units: Vec<UnitRecord>,
}

pub struct BuildJournal {
    dir: PathBuf,
    /// The frames queued in order; its lock orders the units' outputs.
    queue: Mutex<Queue>,
    /// The open log, held by the unit leading a flush; `None` for a build that does not
    /// resume (its source has no fingerprint).
    log: Mutex<Flushed>,
    /// Whether `log` is open: read without its lock by units that sync their outputs.
    enabled: AtomicBool,
    committed: [AtomicU64; 3],
}

/// Frames recorded and not yet in the log.
#[derive(Default)]
struct Queue {
    frames: Vec<u8>,
    /// The sequence number of the last frame queued.
    last: u64,
}

/// The log and how far it is durable.
#[derive(Default)]
struct Flushed {
    file: Option<File>,
    /// The sequence number of the last frame synced in the log.
    durable: u64,
    /// Set once a flush failed: the frames it took are lost, so no later unit is durable.
    failed: bool,
}

/// The journal held while a unit's output is written and its frame queued: the payload file
/// grows in the order the log lists the units.
pub struct Commit<'j> {
    journal: &'j BuildJournal,
    queue: MutexGuard<'j, Queue>,
}

/// A unit's frame queued in the journal, durable once [`Queued::wait`] returns.
#[must_use = "a queued unit is durable only once it is waited for"]
pub struct Queued<'j> {
    journal: &'j BuildJournal,
    /// The frame's sequence number; `None` when the journal is off.
    sequence: Option<u64>,
}

impl BuildJournal {
    /// A journal that records nothing.
    pub fn disabled(dir: &Path) -> Self {
        Self {
            dir: dir.to_path_buf(),
            queue: Mutex::default(),
            log: Mutex::default(),
            enabled: AtomicBool::new(false),
            committed: Default::default(),
        }
    }

    /// The journal in `dir` for a build of `inputs`, with what an earlier run of the same
    /// build finished; a folder of other inputs, or without a finished counting pass, is
    /// emptied and the build starts over.
    pub fn open(dir: &Path, inputs: &str) -> Result<(Self, Option<Replay>), LodError> {
        let replay = match read_whole(&dir.join(INPUTS_FILE)) {
            Some(recorded) if recorded == inputs.as_bytes() => read_replay(dir)?,
            _ => None,
        };
        let journal = Self::disabled(dir);
        match replay {
            Some(replay) => {
                journal.lock_log().file = Some(open_log(dir)?);
                journal.enabled.store(true, Ordering::Relaxed);
                Ok((journal, Some(replay)))
            }
            None => {
                journal.start_over(inputs)?;
                Ok((journal, None))
            }
        }
    }

    /// Empties the folder and records `inputs`: nothing an earlier run wrote is used.
    pub fn start_over(&self, inputs: &str) -> Result<(), LodError> {
        let mut log = self.lock_log();
        *log = Flushed::default();
        *lock(&self.queue) = Queue::default();
        self.enabled.store(false, Ordering::Relaxed);
        match fs::remove_dir_all(&self.dir) {
            Ok(()) => {}
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
            Err(e) => return Err(LodError::spill(&self.dir, e)),
        }
        fs::create_dir_all(&self.dir).map_err(|e| LodError::spill(&self.dir, e))?;
        write_atomically(&self.dir, INPUTS_FILE, inputs.as_bytes())?;
        log.file = Some(open_log(&self.dir)?);
        self.enabled.store(true, Ordering::Relaxed);
        Ok(())
    }

    pub fn is_enabled(&self) -> bool {
        self.enabled.load(Ordering::Relaxed)
    }

    /// Records the counting pass's result, or where it got to; its bucket files must be
    /// synced first.
    pub fn record_counted(&self, counted: &Counted) -> Result<(), LodError> {
        if !self.is_enabled() {
            return Ok(());
        }
        let mut bytes = Vec::with_capacity(16 + counted.counts.len() * 8);
        bytes.extend_from_slice(&counted.points_read.to_le_bytes());
        bytes.extend_from_slice(&counted.level.to_le_bytes());
        bytes.extend_from_slice(&counted.segment_points.to_le_bytes());
        bytes.extend_from_slice(&(counted.counts.len() as u64).to_le_bytes());
        for count in &counted.counts {
            bytes.extend_from_slice(&count.to_le_bytes());
        }
        bytes.extend_from_slice(&encode_listing(&counted.stats, Vec::new()));
        write_atomically(&self.dir, COUNTED_FILE, &bytes)
    }

    /// Takes the journal for one unit's commit: the unit's ordered output is written while it
    /// is held.
    pub fn commit(&self) -> Commit<'_> {
        Commit {
            journal: self,
            queue: lock(&self.queue),
        }
    }

    /// Units of `kind` this run recorded.
    pub fn committed(&self, kind: UnitKind) -> u64 {
        self.committed[kind as usize - 1].load(Ordering::Relaxed)
    }

    fn lock_log(&self) -> MutexGuard<'_, Flushed> {
        lock(&self.log)
    }

    /// Returns once the log's synced frames reach `sequence`, leading a flush when they do
    /// not: every frame queued is taken, `sync_outputs` makes what they list durable, then
    /// they are appended to the log and synced.
    fn flush_to(
        &self,
        sequence: u64,
        sync_outputs: impl FnOnce() -> Result<(), LodError>,
    ) -> Result<(), LodError> {
        let mut log = self.lock_log();
        if log.durable >= sequence {
            return Ok(());
        }
        let path = self.dir.join(UNITS_FILE);
        if log.failed {
            let error = io::Error::other("an earlier write of the build journal failed");
            return Err(LodError::spill(path, error));
        }
        let (frames, last) = {
            let mut queue = lock(&self.queue);
            (std::mem::take(&mut queue.frames), queue.last)
        };
        log.failed = true;
        sync_outputs()?;
        let Some(file) = log.file.as_mut() else {
            let error = io::Error::other("the build journal is closed");
            return Err(LodError::spill(path, error));
        };
        file.write_all(&frames)
            .and_then(|()| file.sync_data())
            .map_err(|e| LodError::spill(path, e))?;
        log.failed = false;
        log.durable = last;
        Ok(())
    }
}

fn lock<T>(mutex: &Mutex<T>) -> MutexGuard<'_, T> {
    mutex
        .lock()
        .unwrap_or_else(|poisoned| poisoned.into_inner())
}

impl<'j> Commit<'j> {
    /// Queues `unit`'s frame after every frame queued before, and lets the next unit commit;
    /// what the unit lists must already be written, and its own files other than the payload
    /// synced.
    pub fn record(mut self, unit: &UnitRecord) -> Result<Queued<'j>, LodError> {
        let journal = self.journal;
        journal.committed[unit.kind as usize - 1].fetch_add(1, Ordering::Relaxed);
        if !journal.is_enabled() {
            return Ok(Queued {
                journal,
                sequence: None,
            });
        }
        let body = encode_unit(unit);
        let queue = &mut *self.queue;
        queue
            .frames
            .extend_from_slice(&(body.len() as u32).to_le_bytes());
        queue
            .frames
            .extend_from_slice(&checksum64(FRAME_SEED, &body).to_le_bytes());
        queue.frames.extend_from_slice(&body);
        queue.last += 1;
        Ok(Queued {
            journal,
            sequence: Some(queue.last),
        })
    }
}

impl Queued<'_> {
    /// Returns once the unit's frame is synced in the log. `sync_outputs` syncs the payload
    /// file, and is called only when this unit leads a flush; nothing is synced with the
    /// journal off.
    pub fn wait(self, sync_outputs: impl FnOnce() -> Result<(), LodError>) -> Result<(), LodError> {
        match self.sequence {
            Some(sequence) => self.journal.flush_to(sequence, sync_outputs),
            None => Ok(()),
        }
    }
}

fn open_log(dir: &Path) -> Result<File, LodError> {
    let path = dir.join(UNITS_FILE);
    let log = OpenOptions::new()
        .create(true)
        .append(true)
        .open(&path)
        .map_err(|e| LodError::spill(&path, e))?;
    sync_dir(dir)?;
    Ok(log)
}

/// Writes `name` in `dir` whole or not at all: a temporary file, synced, renamed over it, the
/// folder synced. The bytes are followed by their checksum.
pub fn write_atomically(dir: &Path, name: &str, bytes: &[u8]) -> Result<(), LodError> {
    let partial = dir.join(format!("{name}.partial"));
    let mut file = File::create(&partial).map_err(|e| LodError::spill(&partial, e))?;
    file.write_all(bytes)
        .and_then(|()| file.write_all(&checksum64(FILE_SEED, bytes).to_le_bytes()))
        .and_then(|()| file.sync_all())
        .map_err(|e| LodError::spill(&partial, e))?;
    let path = dir.join(name);
    fs::rename(&partial, &path).map_err(|e| LodError::spill(&path, e))?;
    sync_dir(dir)
}

/// The bytes of a file [`write_atomically`] wrote, or `None` when it is missing or damaged.
fn read_whole(path: &Path) -> Option<Vec<u8>> {
    let mut bytes = fs::read(path).ok()?;
    let at = bytes.len().checked_sub(8)?;
    let sum = u64::from_le_bytes(bytes[at..].try_into().ok()?);
    bytes.truncate(at);
    (checksum64(FILE_SEED, &bytes) == sum).then_some(bytes)
}

/// Syncs a folder, so that the files created, renamed or removed in it stay so.
pub fn sync_dir(dir: &Path) -> Result<(), LodError> {
    File::open(dir)
        .and_then(|d| d.sync_all())
        .map_err(|e| LodError::spill(dir, e))
}

/// The counting pass and the units an earlier run recorded; `None` without a counting pass.
/// A torn or damaged frame and everything after it are cut off the log.
fn read_replay(dir: &Path) -> Result<Option<Replay>, LodError> {
    let Some(counted) = read_whole(&dir.join(COUNTED_FILE)).and_then(|b| decode_counted(&b)) else {
        return Ok(None);
    };
    let path = dir.join(UNITS_FILE);
    let mut bytes = Vec::new();
    match File::open(&path) {
        Ok(mut file) => {
            file.read_to_end(&mut bytes)
                .map_err(|e| LodError::spill(&path, e))?;
        }
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
        Err(e) => return Err(LodError::spill(&path, e)),
    }
    let (units, valid) = decode_frames(&bytes);
    if valid < bytes.len() {
        tracing::warn!(
            path = %path.display(),
            kept = units.len(),
            cut_bytes = bytes.len() - valid,
            "the build journal ends in a torn or damaged frame: its unit is redone"
        );
        let file = OpenOptions::new()
            .write(true)
            .open(&path)
            .map_err(|e| LodError::spill(&path, e))?;
        file.set_len(valid as u64)
            .and_then(|()| file.sync_all())
            .map_err(|e| LodError::spill(&path, e))?;
    }
    Ok(Some(Replay { counted, units }))
}

/// The units of whole, checked frames, and the bytes they take.
fn decode_frames(bytes: &[u8]) -> (Vec<UnitRecord>, usize) {
    let mut units = Vec::new();
    let mut at = 0;
    while let Some(head) = bytes.get(at..at + FRAME_HEAD) {
        let len = u32::from_le_bytes([head[0], head[1], head[2], head[3]]) as usize;
        let sum = u64::from_le_bytes(head[4..12].try_into().unwrap_or_default());
        let Some(body) = bytes.get(at + FRAME_HEAD..at + FRAME_HEAD + len) else {
            break;
        };
        if checksum64(FRAME_SEED, body) != sum {
            break;
        }
        let Some(unit) = decode_unit(body) else {
            break;
        };
        units.push(unit);
        at += FRAME_HEAD + len;
    }
    (units, at)
}

fn decode_counted(bytes: &[u8]) -> Option<Counted> {
    let mut r = Fields { bytes, at: 0 };
    let points_read = r.u64()?;
    let level = r.u32()?;
    let segment_points = r.u64()?;
    let cells = usize::try_from(r.u64()?).ok()?;
    if cells != 1usize.checked_shl(3 * level)? {
        return None;
    }
    let counts = (0..cells).map(|_| r.u64()).collect::<Option<Vec<u64>>>()?;
    let (stats, _) = decode_listing(r.rest()).ok()?;
    Some(Counted {
        points_read,
        level,
        segment_points,
        counts,
        stats,
    })
}

fn encode_unit(unit: &UnitRecord) -> Vec<u8> {
    let mut out = Vec::with_capacity(128 + unit.nodes.len() * 64);
    out.push(unit.kind as u8);
    out.extend_from_slice(&unit.key.to_bytes());
    out.extend_from_slice(&unit.payload_end.to_le_bytes());
    match unit.waiting {
        Some(w) => {
            out.push(1);
            out.extend_from_slice(&w.count.to_le_bytes());
            out.extend_from_slice(&w.sample_grid.to_le_bytes());
            out.extend_from_slice(&w.bytes.to_le_bytes());
            out.extend_from_slice(&w.checksum.to_le_bytes());
        }
        None => out.push(0),
    }
    for count in unit.children {
        out.extend_from_slice(&count.to_le_bytes());
    }
    let stats = DatasetStats::new(false);
    out.extend_from_slice(&encode_listing(&stats, unit.nodes.clone()));
    out
}

fn decode_unit(body: &[u8]) -> Option<UnitRecord> {
    let mut r = Fields { bytes: body, at: 0 };
    let kind = match r.u8()? {
        1 => UnitKind::Partition,
        2 => UnitKind::Split,
        3 => UnitKind::Parent,
        _ => return None,
    };
    let key = NodeKey {
        level: r.u8()?,
        x: r.u32_be()?,
        y: r.u32_be()?,
        z: r.u32_be()?,
    };
    let payload_end = r.u64()?;
    let waiting = match r.u8()? {
        0 => None,
        1 => Some(WaitingRoot {
            count: r.u64()?,
            sample_grid: r.u32()?,
            bytes: r.u64()?,
            checksum: r.u64()?,
        }),
        _ => return None,
    };
    let mut children = [0u64; 8];
    for child in &mut children {
        *child = r.u64()?;
    }
    let (_, nodes) = decode_listing(r.rest()).ok()?;
    Some(UnitRecord {
        kind,
        key,
        payload_end,
        waiting,
        children,
        nodes,
    })
}

/// Reads fields off a checked body; `None` past its end.
struct Fields<'a> {
    bytes: &'a [u8],
    at: usize,
}

impl<'a> Fields<'a> {
    fn take<const N: usize>(&mut self) -> Option<[u8; N]> {
        let field = self.bytes.get(self.at..self.at + N)?.try_into().ok()?;
        self.at += N;
        Some(field)
    }
    fn u8(&mut self) -> Option<u8> {
        self.take::<1>().map(|b| b[0])
    }
    fn u32(&mut self) -> Option<u32> {
        self.take().map(u32::from_le_bytes)
    }
    fn u32_be(&mut self) -> Option<u32> {
        self.take().map(u32::from_be_bytes)
    }
    fn u64(&mut self) -> Option<u64> {
        self.take().map(u64::from_le_bytes)
    }
    fn rest(&self) -> &'a [u8] {
        &self.bytes[self.at..]
    }
}

#[cfg(test)]
#[path = "journal_tests.rs"]
mod tests;
