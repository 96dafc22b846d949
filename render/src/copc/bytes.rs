//! Where a COPC file's bytes come from: a file here, or an object by URL ([`RemoteObject`]),
//! read by byte ranges through one face, so that the header, the hierarchy pages, the node
//! grids and the chunks are read, and checked, by the same code either way.
//!
//! A file is read with positioned reads, many at once; an object with ranged requests, near
//! ranges coalesced into one and the requests in parallel, every one pinned to the version
//! opened. The small reads of the header and its records go through a [`RangeReader`], which
//! fetches an object in blocks so that they cost a few requests, not one each. An object's
//! chunks read while it is opened (the color sample's coarsest nodes) are kept, because the
//! framing sample and the first frames draw the same nodes (docs/perf/remote-copc-reads.md).
//!
//! A [`RangeCache`] given with an object (a worker's disk cache) serves the ranges it holds
//! of the object's version and keeps those fetched, so that the same ranges read by a later
//! opening of the same version cost no request; an object without a version, or with only a
//! weak ETag, is not cached.
//!
//! It is also the ranged face of plain LAS/LAZ files by URL ([`RangedBytes`]): the pre-parse,
//! the header and a preview's sampled records of a tile read through it as a file's are.

use std::collections::HashMap;
use std::fs::File;
use std::io::{self, Read, Seek, SeekFrom};
use std::ops::Range;
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};

use super::error::CopcError;
use crate::ingest::{open_dataset_file, IngestError, RangedBytes, ReadSeek, Symlinks};
use crate::lod::read_concurrently;
use crate::remote::{RemoteError, RemoteObject};

/// Bytes an object is fetched in by a [`RangeReader`]: a LAS header and its VLRs fit one
/// block, a chunk table or the EVLRs' headers another.
const BLOCK_BYTES: u64 = 16 * 1024;
/// Blocks a [`RangeReader`] keeps.
const BLOCKS_KEPT: usize = 8;

/// Ranges of objects kept across openings, by their caller: keyed by the object's URL, its
/// version and the range, so that a replaced object never reads another version's bytes.
pub trait RangeCache: Send + Sync {
    /// The bytes of `range`, when they are kept and intact.
    fn get(&self, url: &str, version: &str, range: &Range<u64>) -> Option<Vec<u8>>;
    /// Keeps the bytes just fetched for `range`.
    fn put(&self, url: &str, version: &str, range: &Range<u64>, bytes: &[u8]);
}

/// A COPC file's bytes, read by range.
pub(crate) struct CopcBytes {
    /// What errors name it by: the file's path, or the object's URL (which never holds
    /// credentials).
    name: PathBuf,
    size: u64,
    origin: Origin,
    /// Whether an object's ranges read now are kept ([`CopcBytes::keep_reads`]).
    keeping: AtomicBool,
    /// An object's ranges read while `keeping`, served again without a request: at most the
    /// bytes of the chunks read while opening it.
    kept: Mutex<HashMap<Range<u64>, Vec<u8>>>,
    /// Where an object's ranges are looked up before they are fetched, and kept after.
    cache: Option<Arc<dyn RangeCache>>,
}

enum Origin {
    File(File),
    Remote(Box<RemoteObject>),
}

impl CopcBytes {
    /// The file at `path`, opened as every dataset file is (symbolic links followed).
    pub fn file(path: &Path) -> Result<Self, CopcError> {
        let file = open_dataset_file(path, Symlinks::Follow).map_err(|e| CopcError::io(path, e))?;
        let size = file.metadata().map_err(|e| CopcError::io(path, e))?.len();
        Ok(Self {
            name: path.to_owned(),
            size,
            origin: Origin::File(file),
            keeping: AtomicBool::new(false),
            kept: Mutex::default(),
            cache: None,
        })
    }

    /// An object opened by URL, at the size and version its HEAD reported.
    pub fn remote(object: RemoteObject) -> Self {
        Self {
            name: PathBuf::from(object.url().to_string()),
            size: object.size(),
            origin: Origin::Remote(Box::new(object)),
            keeping: AtomicBool::new(false),
            kept: Mutex::default(),
            cache: None,
        }
    }

    /// The object's ranges looked up in `cache` before they are fetched, and kept there after.
    pub fn with_cache(mut self, cache: Arc<dyn RangeCache>) -> Self {
        self.cache = Some(cache);
        self
    }

    /// From now on (`true`) or no longer, an object's ranges that [`CopcBytes::read_many`]
    /// fetches are kept and served again without a request; a file's page cache does that for
    /// it already. Opening keeps the color sample's chunks, which the framing sample and the
    /// first frames read again.
    pub fn keep_reads(&self, keep: bool) {
        if matches!(self.origin, Origin::Remote(_)) {
            self.keeping.store(keep, Ordering::Relaxed);
        }
    }

    /// The path or URL that errors name.
    pub fn name(&self) -> &Path {
        &self.name
    }

    /// Bytes in the file or object.
    pub fn size(&self) -> u64 {
        self.size
    }

    /// `len` bytes at `offset`, allocated only once they are known to lie inside.
    pub fn read_at(&self, offset: u64, len: u64) -> Result<Vec<u8>, CopcError> {
        let range = self.checked(offset, len)?;
        match &self.origin {
            Origin::File(file) => {
                let mut bytes = vec![0u8; (range.end - range.start) as usize];
                file.read_exact_at(&mut bytes, range.start)
                    .map_err(|e| CopcError::io(&self.name, e))?;
                Ok(bytes)
            }
            Origin::Remote(object) => {
                if let Some(bytes) = self.cached(object, &range) {
                    return Ok(bytes);
                }
                let bytes = object.read_range(range.clone())?;
                self.keep_cached(object, &range, &bytes);
                Ok(bytes)
            }
        }
    }

    /// The bytes of `range` from the cache given, when it holds them for the object's version.
    fn cached(&self, object: &RemoteObject, range: &Range<u64>) -> Option<Vec<u8>> {
        let (cache, version) = (self.cache.as_ref()?, cache_version(object)?);
        let bytes = cache.get(&object.url().to_string(), version, range)?;
        (bytes.len() as u64 == range.end - range.start).then_some(bytes)
    }

    fn keep_cached(&self, object: &RemoteObject, range: &Range<u64>, bytes: &[u8]) {
        if let (Some(cache), Some(version)) = (&self.cache, cache_version(object)) {
            cache.put(&object.url().to_string(), version, range, bytes);
        }
    }

    /// The bytes of every range, in the order asked: a file's read concurrently, an object's
    /// near ones fetched as one request and the requests in parallel.
    pub fn read_many(&self, ranges: &[Range<u64>]) -> Result<Vec<Vec<u8>>, CopcError> {
        for range in ranges {
            // A reversed range is no range inside: its length would wrap.
            let len = range.end.checked_sub(range.start).unwrap_or(u64::MAX);
            self.checked(range.start, len)?;
        }
        match &self.origin {
            Origin::File(_) => read_concurrently(ranges, |range| {
                self.read_at(range.start, range.end - range.start)
            }),
            Origin::Remote(object) => {
                let kept = || self.kept.lock().unwrap_or_else(|e| e.into_inner());
                let mut found: Vec<Option<Vec<u8>>> = {
                    let kept = kept();
                    ranges
                        .iter()
                        .map(|range| kept.get(range).cloned())
                        .collect()
                };
                for (range, found) in ranges.iter().zip(&mut found) {
                    if found.is_none() {
                        *found = self.cached(object, range);
                    }
                }
                let missing: Vec<Range<u64>> = (ranges.iter().zip(&found))
                    .filter(|(_, found)| found.is_none())
                    .map(|(range, _)| range.clone())
                    .collect();
                let fetched = fetch_in_batches(object, &missing)?;
                for (range, bytes) in missing.iter().zip(&fetched) {
                    self.keep_cached(object, range, bytes);
                }
                let mut fetched = fetched.into_iter();
                let keeping = self.keeping.load(Ordering::Relaxed);
                let mut kept = kept();
                let mut read = Vec::with_capacity(ranges.len());
                for (range, found) in ranges.iter().zip(found) {
                    let bytes = match found {
                        Some(bytes) => bytes,
                        None => fetched.next().ok_or_else(|| {
                            CopcError::io(&self.name, io::Error::other("a range went unanswered"))
                        })?,
                    };
                    if keeping && !kept.contains_key(range) {
                        kept.insert(range.clone(), bytes.clone());
                    }
                    read.push(bytes);
                }
                Ok(read)
            }
        }
    }

    /// A reader of small pieces from the start, for the header's checks.
    pub fn reader(&self) -> RangeReader<'_> {
        RangeReader {
            bytes: self,
            position: 0,
            blocks: Vec::new(),
            failed: None,
        }
    }

    /// `offset..offset + len`, when it lies inside.
    fn checked(&self, offset: u64, len: u64) -> Result<Range<u64>, CopcError> {
        match offset.checked_add(len) {
            Some(end) if end <= self.size => Ok(offset..end),
            _ => Err(CopcError::io(
                &self.name,
                io::Error::new(
                    io::ErrorKind::UnexpectedEof,
                    format!(
                        "{len} bytes at offset {offset} lie past the end of its {} bytes",
                        self.size
                    ),
                ),
            )),
        }
    }
}

impl RangedBytes for CopcBytes {
    type Error = CopcError;

    fn name(&self) -> &Path {
        &self.name
    }

    fn read_stream<T>(
        &self,
        read: impl FnOnce(&mut dyn ReadSeek, u64) -> Result<T, IngestError>,
    ) -> Result<T, CopcError> {
        let mut reader = self.reader();
        read(&mut reader, self.size).map_err(|error| reader.error(error.into()))
    }

    fn read_sparse(&self, ranges: &[Range<u64>]) -> Result<Vec<Vec<u8>>, CopcError> {
        match &self.origin {
            Origin::File(_) => self.read_many(ranges),
            Origin::Remote(object) => {
                for range in ranges {
                    let len = range.end.checked_sub(range.start).unwrap_or(u64::MAX);
                    self.checked(range.start, len)?;
                }
                Ok(object.read_sparse(ranges)?)
            }
        }
    }
}

/// The version an object's ranges are cached by: none for a weak ETag, which a server may keep
/// for other bytes it deems equivalent.
fn cache_version(object: &RemoteObject) -> Option<&str> {
    object
        .version()
        .filter(|version| !version.starts_with("W/"))
}

/// The bytes of `ranges` of `object`, within the client's bound on one read, batch by batch.
fn fetch_in_batches(
    object: &RemoteObject,
    ranges: &[Range<u64>],
) -> Result<Vec<Vec<u8>>, CopcError> {
    let limit = object.settings().max_read_bytes.max(1);
    let mut read = Vec::with_capacity(ranges.len());
    let mut batch_start = 0;
    let mut batch_bytes = 0u64;
    for (i, range) in ranges.iter().enumerate() {
        let len = range.end - range.start;
        if i > batch_start && batch_bytes + len > limit {
            read.extend(object.read_ranges(&ranges[batch_start..i])?);
            (batch_start, batch_bytes) = (i, 0);
        }
        batch_bytes += len;
    }
    if batch_start < ranges.len() {
        read.extend(object.read_ranges(&ranges[batch_start..])?);
    }
    Ok(read)
}

/// [`CopcBytes`] read as a stream with a position, for the checks every LAS/LAZ file passes
/// (`ingest::check_file`) and the header's small reads: a file's bytes are read where they
/// lie, an object's a block at a time, the last few blocks kept.
pub(crate) struct RangeReader<'a> {
    bytes: &'a CopcBytes,
    position: u64,
    /// Blocks fetched, by their index, the oldest first.
    blocks: Vec<(u64, Vec<u8>)>,
    /// What failed a read of an object, which the stream could only report as an I/O error.
    failed: Option<RemoteError>,
}

impl RangeReader<'_> {
    /// The path or URL that errors name.
    pub fn name(&self) -> PathBuf {
        self.bytes.name.clone()
    }

    pub fn size(&self) -> u64 {
        self.bytes.size()
    }

    /// `len` bytes at `offset`: from the kept blocks where they are small.
    pub fn read_at(&mut self, offset: u64, len: u64) -> Result<Vec<u8>, CopcError> {
        if matches!(self.bytes.origin, Origin::File(_)) || len >= BLOCK_BYTES {
            return self.bytes.read_at(offset, len);
        }
        let range = self.bytes.checked(offset, len)?;
        let mut out = Vec::with_capacity(len as usize);
        let mut at = range.start;
        while at < range.end {
            let piece = self.in_blocks(at, range.end)?;
            at += piece.len() as u64;
            out.extend_from_slice(piece);
        }
        Ok(out)
    }

    /// The error a failed read of the stream stands for: the object's, where one failed
    /// (it names the URL), else `error`.
    pub fn error(&mut self, error: CopcError) -> CopcError {
        self.failed.take().map_or(error, CopcError::Remote)
    }

    /// The bytes from `at` up to `end` or the end of its block, whichever comes first.
    fn in_blocks(&mut self, at: u64, end: u64) -> Result<&[u8], CopcError> {
        let index = at / BLOCK_BYTES;
        let kept = match self.blocks.iter().position(|(i, _)| *i == index) {
            Some(kept) => kept,
            None => {
                let start = index * BLOCK_BYTES;
                let len = BLOCK_BYTES.min(self.bytes.size - start);
                let block = self.bytes.read_at(start, len)?;
                if self.blocks.len() == BLOCKS_KEPT {
                    self.blocks.remove(0);
                }
                self.blocks.push((index, block));
                self.blocks.len() - 1
            }
        };
        let block = &self.blocks[kept].1;
        let from = (at - index * BLOCK_BYTES) as usize;
        let to = (end - index * BLOCK_BYTES).min(block.len() as u64) as usize;
        Ok(&block[from..to])
    }
}

impl Read for RangeReader<'_> {
    fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
        let size = self.bytes.size;
        if buf.is_empty() || self.position >= size {
            return Ok(0);
        }
        let n = match &self.bytes.origin {
            Origin::File(file) => file.read_at(buf, self.position)?,
            Origin::Remote(_) => {
                let end = size.min(self.position + buf.len() as u64);
                match self.in_blocks(self.position, end) {
                    Ok(piece) => {
                        buf[..piece.len()].copy_from_slice(piece);
                        piece.len()
                    }
                    Err(CopcError::Remote(error)) => {
                        self.failed = Some(error);
                        return Err(io::Error::other("the object could not be read"));
                    }
                    Err(other) => return Err(io::Error::other(other.to_string())),
                }
            }
        };
        self.position += n as u64;
        Ok(n)
    }
}

impl Seek for RangeReader<'_> {
    fn seek(&mut self, to: SeekFrom) -> io::Result<u64> {
        let position = match to {
            SeekFrom::Start(at) => Some(at),
            SeekFrom::End(delta) => self.bytes.size.checked_add_signed(delta),
            SeekFrom::Current(delta) => self.position.checked_add_signed(delta),
        };
        self.position = position.ok_or_else(|| {
            io::Error::new(io::ErrorKind::InvalidInput, "a seek before the start")
        })?;
        Ok(self.position)
    }
}

#[cfg(test)]
mod tests {
    use std::io::{Read, Seek, SeekFrom};

    use super::super::tests::copc_file;
    use super::*;

    #[test]
    fn ranges_read_as_the_file_holds_them_and_none_past_its_end() {
        let path = copc_file("simple_with_page.copc.laz");
        let whole = std::fs::read(&path).expect("file");
        let bytes = CopcBytes::file(&path).expect("opens");
        assert_eq!(bytes.size(), whole.len() as u64);
        assert_eq!(bytes.read_at(100, 50).expect("inside"), whole[100..150]);
        let many = bytes
            .read_many(&[2000..2100, 0..4, 30_000..30_001])
            .expect("inside");
        assert_eq!(
            many,
            [&whole[2000..2100], &whole[..4], &whole[30_000..30_001]]
        );
        let size = bytes.size();
        for refused in [
            bytes.read_at(size - 1, 2),
            bytes.read_at(u64::MAX, 2),
            bytes.read_many(&[0..4, size..size + 1]).map(|_| Vec::new()),
            // A reversed range, as a forged entry could give.
            bytes
                .read_many(&[0..4, Range { start: 10, end: 4 }])
                .map(|_| Vec::new()),
        ] {
            let error = refused.expect_err("outside");
            assert!(error.to_string().contains("past the end"), "{error}");
        }
    }

    #[test]
    fn the_reader_seeks_and_reads_as_the_file_does() {
        let path = copc_file("simple.copc.laz");
        let whole = std::fs::read(&path).expect("file");
        let bytes = CopcBytes::file(&path).expect("opens");
        let mut reader = bytes.reader();
        let mut head = [0u8; 10];
        reader.read_exact(&mut head).expect("head");
        assert_eq!(head, whole[..10]);
        let end = reader.seek(SeekFrom::End(-5)).expect("seek");
        assert_eq!(end, whole.len() as u64 - 5);
        let mut tail = Vec::new();
        reader.read_to_end(&mut tail).expect("tail");
        assert_eq!(tail, whole[whole.len() - 5..]);
        assert!(reader
            .seek(SeekFrom::Current(-(whole.len() as i64) - 1))
            .is_err());
        assert_eq!(
            reader.read_at(375, 54).expect("a VLR header"),
            whole[375..429]
        );
    }
}
