//! `ObjectReader`: an object read from start to end as a file is, `Read + Seek` for the LAS and
//! LAZ readers, through ranged GETs of large blocks with one block read ahead, never the whole
//! object at once.
//!
//! Every block comes from the version the object was opened at (each GET is pinned, as every
//! `RemoteObject` read is), so a replaced object fails the read that meets it with
//! `ObjectChanged` naming the URL. A few blocks are kept, so that a reader's seek to the end
//! (a LAZ chunk table) and back to the points costs no second fetch of the first block.

use std::collections::VecDeque;
use std::io::{self, Read, Seek, SeekFrom};
use std::ops::Range;
use std::sync::Arc;
use std::thread::JoinHandle;

use super::client::RemoteClient;
use super::error::RemoteError;
use super::object::RemoteObject;
use super::url::ObjectUrl;

/// Bytes of one ranged GET of a stream: few requests per object, and a bounded buffer.
pub const STREAM_BLOCK_BYTES: u64 = 8 << 20;
/// Blocks a reader keeps besides the one read ahead: at most this many plus one blocks of an
/// object are in memory per reader.
const BLOCKS_KEPT: usize = 3;

/// What an [`ObjectReader`] reads its blocks from: an object opened by URL, or bytes in
/// memory in the unit tests.
pub trait BlockSource: Send + Sync + 'static {
    fn size(&self) -> u64;
    /// The bytes of `range`, which lies inside.
    fn fetch(&self, range: Range<u64>) -> Result<Vec<u8>, RemoteError>;
}

impl BlockSource for RemoteObject {
    fn size(&self) -> u64 {
        RemoteObject::size(self)
    }

    fn fetch(&self, range: Range<u64>) -> Result<Vec<u8>, RemoteError> {
        self.read_range(range)
    }
}

impl RemoteClient {
    /// Opens an object found by a listing, held to the version listed: an object replaced
    /// since is `ObjectChanged`, so that a dataset never mixes versions of its tiles.
    pub fn open_listed(
        &self,
        url: &ObjectUrl,
        listed_version: Option<&str>,
    ) -> Result<RemoteObject, RemoteError> {
        let object = self.open(url)?;
        match listed_version {
            Some(listed) if object.version() != Some(listed) => Err(RemoteError::ObjectChanged {
                url: url.to_string(),
                version: listed.to_owned(),
            }),
            _ => Ok(object),
        }
    }
}

/// A block fetched: its first byte's offset and its bytes.
struct Block {
    start: u64,
    bytes: Vec<u8>,
}

impl Block {
    fn holds(&self, position: u64) -> bool {
        self.start <= position && position < self.start + self.bytes.len() as u64
    }
}

/// A block being fetched on a thread of its own.
struct Ahead {
    range: Range<u64>,
    fetch: JoinHandle<Result<Vec<u8>, RemoteError>>,
}

/// An object read as a stream, in blocks of `block_bytes` with the next one fetched while the
/// current one is read.
pub struct ObjectReader<S: BlockSource = RemoteObject> {
    source: Arc<S>,
    block_bytes: u64,
    position: u64,
    /// The blocks kept, the most recently read first.
    kept: VecDeque<Block>,
    ahead: Option<Ahead>,
    read_ahead: bool,
}

impl<S: BlockSource> ObjectReader<S> {
    /// A stream over `source` in blocks of [`STREAM_BLOCK_BYTES`], read ahead.
    pub fn new(source: Arc<S>) -> Self {
        Self::with_blocks(source, STREAM_BLOCK_BYTES, true)
    }

    /// A stream in blocks of `block_bytes` (at least one), read ahead or not: a header's
    /// checks read a few small blocks and nothing after them.
    pub fn with_blocks(source: Arc<S>, block_bytes: u64, read_ahead: bool) -> Self {
        Self {
            source,
            block_bytes: block_bytes.max(1),
            position: 0,
            kept: VecDeque::new(),
            ahead: None,
            read_ahead,
        }
    }

    /// The block from `start` on, up to the end of the object.
    fn block_range(&self, start: u64) -> Range<u64> {
        start
            ..start
                .saturating_add(self.block_bytes)
                .min(self.source.size())
    }

    /// Makes the block holding the position the first kept, fetching it when no block holds
    /// it (taking the one read ahead first, whatever it holds, so none is fetched twice).
    fn hold_position(&mut self) -> Result<(), RemoteError> {
        let position = self.position;
        if let Some(index) = self.kept.iter().position(|block| block.holds(position)) {
            let block = self.kept.remove(index).expect("found just now");
            self.kept.push_front(block);
            return Ok(());
        }
        if let Some(ahead) = self.ahead.take() {
            let covers = ahead.range.contains(&position);
            let fetched = ahead.fetch.join().unwrap_or_else(|_| {
                Err(RemoteError::Runtime {
                    message: "the thread reading ahead panicked".to_owned(),
                })
            });
            match fetched {
                Ok(bytes) => self.keep(ahead.range.start, bytes),
                // A failure of bytes no longer wanted shows again when they are.
                Err(error) if covers => return Err(error),
                Err(_) => {}
            }
            if covers {
                return Ok(());
            }
        }
        let range = self.block_range(position);
        let bytes = self.source.fetch(range.clone())?;
        self.keep(range.start, bytes);
        Ok(())
    }

    fn keep(&mut self, start: u64, bytes: Vec<u8>) {
        self.kept.push_front(Block { start, bytes });
        self.kept.truncate(BLOCKS_KEPT);
    }

    /// Starts fetching the block after the first kept, unless it is kept or on its way, or
    /// the object ends there.
    fn read_next(&mut self) {
        let Some(end) = (self.kept.front()).map(|b| b.start + b.bytes.len() as u64) else {
            return;
        };
        let wanted = self.read_ahead
            && self.ahead.is_none()
            && end < self.source.size()
            && !self.kept.iter().any(|block| block.holds(end));
        if !wanted {
            return;
        }
        let range = self.block_range(end);
        let source = Arc::clone(&self.source);
        let fetched = range.clone();
        let spawned = std::thread::Builder::new()
            .name("object-read-ahead".into())
            .spawn(move || source.fetch(fetched));
        // Without a thread the block is fetched when it is read.
        if let Ok(fetch) = spawned {
            self.ahead = Some(Ahead { range, fetch });
        }
    }
}

impl<S: BlockSource> Read for ObjectReader<S> {
    fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
        if buf.is_empty() || self.position >= self.source.size() {
            return Ok(0);
        }
        self.hold_position().map_err(io::Error::other)?;
        let block = self.kept.front().expect("held just now");
        let within = (self.position - block.start) as usize;
        let n = buf.len().min(block.bytes.len() - within);
        buf[..n].copy_from_slice(&block.bytes[within..within + n]);
        self.position += n as u64;
        self.read_next();
        Ok(n)
    }
}

impl<S: BlockSource> Seek for ObjectReader<S> {
    fn seek(&mut self, to: SeekFrom) -> io::Result<u64> {
        let target = match to {
            SeekFrom::Start(offset) => Some(offset),
            SeekFrom::End(delta) => self.source.size().checked_add_signed(delta),
            SeekFrom::Current(delta) => self.position.checked_add_signed(delta),
        };
        self.position = target.ok_or_else(|| {
            io::Error::new(
                io::ErrorKind::InvalidInput,
                "a seek before the start of the object",
            )
        })?;
        Ok(self.position)
    }
}

#[cfg(test)]
mod tests {
    use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
    use std::sync::Mutex;

    use super::*;

    /// Bytes in memory that count their fetches and can be "replaced", as a server's object
    /// pinned to its version answers once it is.
    struct Bytes {
        bytes: Vec<u8>,
        fetches: Mutex<Vec<Range<u64>>>,
        fetched_bytes: AtomicU64,
        replaced: AtomicBool,
    }

    impl Bytes {
        fn new(len: usize) -> Arc<Self> {
            Arc::new(Self {
                bytes: (0..len).map(|i| (i * 7 % 251) as u8).collect(),
                fetches: Mutex::default(),
                fetched_bytes: AtomicU64::new(0),
                replaced: AtomicBool::new(false),
            })
        }

        fn fetches(&self) -> Vec<Range<u64>> {
            self.fetches.lock().expect("the fetches").clone()
        }
    }

    impl BlockSource for Bytes {
        fn size(&self) -> u64 {
            self.bytes.len() as u64
        }

        fn fetch(&self, range: Range<u64>) -> Result<Vec<u8>, RemoteError> {
            assert!(
                range.end <= self.size() && range.start < range.end,
                "{range:?}"
            );
            if self.replaced.load(Ordering::SeqCst) {
                return Err(RemoteError::ObjectChanged {
                    url: "s3://bucket/tile.laz".into(),
                    version: "\"abc\"".into(),
                });
            }
            self.fetches
                .lock()
                .expect("the fetches")
                .push(range.clone());
            self.fetched_bytes
                .fetch_add(range.end - range.start, Ordering::SeqCst);
            Ok(self.bytes[range.start as usize..range.end as usize].to_vec())
        }
    }

    #[test]
    fn a_stream_reads_every_byte_once_across_block_boundaries() {
        let source = Bytes::new(10_000);
        let mut reader = ObjectReader::with_blocks(Arc::clone(&source), 1_000, true);
        let mut read = Vec::new();
        // Odd-sized reads straddle every block boundary.
        let mut buf = [0u8; 333];
        loop {
            let n = reader.read(&mut buf).expect("read");
            if n == 0 {
                break;
            }
            read.extend_from_slice(&buf[..n]);
        }
        assert_eq!(read, source.bytes);
        assert_eq!(source.fetched_bytes.load(Ordering::SeqCst), 10_000);
        let mut fetches = source.fetches();
        fetches.sort_by_key(|range| range.start);
        let expected: Vec<Range<u64>> = (0..10).map(|k| k * 1_000..(k + 1) * 1_000).collect();
        assert_eq!(fetches, expected);
    }

    #[test]
    fn seeks_read_the_right_bytes_and_a_seek_back_costs_no_fetch() {
        let source = Bytes::new(5_500);
        let mut reader = ObjectReader::with_blocks(Arc::clone(&source), 1_000, false);
        let mut head = [0u8; 10];
        reader.read_exact(&mut head).expect("head");
        assert_eq!(head, source.bytes[..10]);
        // To the end (a chunk table), then back to the points.
        assert_eq!(reader.seek(SeekFrom::End(-100)).expect("seek"), 5_400);
        let mut tail = Vec::new();
        reader.read_to_end(&mut tail).expect("tail");
        assert_eq!(tail, source.bytes[5_400..]);
        assert_eq!(reader.seek(SeekFrom::Start(20)).expect("back"), 20);
        let mut again = [0u8; 50];
        reader.read_exact(&mut again).expect("again");
        assert_eq!(again, source.bytes[20..70]);
        assert_eq!(source.fetches(), [0..1_000, 5_400..5_500]);
        reader.seek(SeekFrom::Current(1_000)).expect("forward");
        reader.read_exact(&mut again).expect("forward read");
        assert_eq!(again, source.bytes[1_070..1_120]);
        assert!(reader.seek(SeekFrom::Current(-5_000)).is_err());
        // Past the end reads nothing.
        reader.seek(SeekFrom::Start(9_000)).expect("past the end");
        assert_eq!(reader.read(&mut again).expect("nothing"), 0);
    }

    #[test]
    fn a_replaced_object_fails_the_read_naming_it() {
        let source = Bytes::new(4_000);
        let mut reader = ObjectReader::with_blocks(Arc::clone(&source), 1_000, true);
        let mut buf = [0u8; 1_000];
        reader.read_exact(&mut buf).expect("first block");
        // Wait for the block read ahead, then replace: the third block fails.
        reader
            .read_exact(&mut buf)
            .expect("second block, read ahead");
        if let Some(ahead) = reader.ahead.take() {
            let bytes = ahead.fetch.join().expect("joined").expect("fetched");
            reader.keep(ahead.range.start, bytes);
        }
        source.replaced.store(true, Ordering::SeqCst);
        let error = reader.read_exact(&mut [0u8; 1_500]).expect_err("replaced");
        let text = error.to_string();
        assert!(
            text.contains("s3://bucket/tile.laz") && text.contains("changed"),
            "{text}"
        );
    }
}
