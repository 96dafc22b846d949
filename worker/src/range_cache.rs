//! The worker's on-disk cache of ranges of objects read by URL (header blocks, hierarchy pages,
//! node chunks), so that a dataset leased again is read from disk rather than fetched again.
//!
//! An entry is keyed by the object's URL, its version (ETag or version id) and the range, so an
//! object replaced and registered again at its new version never reads an old entry. An entry
//! is written to a temporary file and renamed into place, and carries its length and SHA-256,
//! both checked before its bytes are trusted: a damaged or cut entry is removed and its range
//! fetched again. The entries together stay within a budget, the least recently used evicted
//! first. The cache's own failures (a full disk, a removed folder) never fail a frame: the
//! range is fetched as if it were not cached.

use std::collections::HashMap;
use std::fs;
use std::io::{self, Write};
use std::ops::Range;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Mutex;
use std::time::SystemTime;

use pointfarm_render::copc::RangeCache;
use sha2::{Digest, Sha256};

/// The default bound of the cache's entries together: `worker --url-cache`.
pub const DEFAULT_URL_CACHE_BYTES: u64 = 2 << 30;

/// What an entry file starts with, before its length and SHA-256.
const MAGIC: &[u8; 8] = b"PFRANGE1";
/// The magic, the payload's length (u64, little-endian) and its SHA-256.
const HEADER_BYTES: u64 = 8 + 8 + 32;
/// The ending of an entry's file while it is written.
const PARTIAL: &str = ".partial";

/// Ranges of objects on disk, keyed by URL, version and range, within a byte budget.
#[derive(Debug)]
pub struct DiskRangeCache {
    dir: PathBuf,
    budget: u64,
    index: Mutex<Index>,
    /// Payload bytes served from the cache, and entries found damaged and dropped.
    served_bytes: AtomicU64,
    dropped: AtomicU64,
    /// Names temporary files apart when ranges are written at once.
    writes: AtomicU64,
}

/// The entries on disk, by file name, and when each was last used.
#[derive(Debug, Default)]
struct Index {
    entries: HashMap<String, Entry>,
    total: u64,
    clock: u64,
}

#[derive(Debug, Clone, Copy)]
struct Entry {
    /// The file's size, header included: what the budget counts.
    size: u64,
    used: u64,
}

impl Index {
    fn insert(&mut self, name: String, size: u64) {
        self.clock += 1;
        let entry = Entry {
            size,
            used: self.clock,
        };
        if let Some(old) = self.entries.insert(name, entry) {
            self.total -= old.size;
        }
        self.total += size;
    }

    fn remove(&mut self, name: &str) -> Option<Entry> {
        let entry = self.entries.remove(name)?;
        self.total -= entry.size;
        Some(entry)
    }

    /// The least recently used entries to remove for the total to fit `budget`.
    fn evict_to(&mut self, budget: u64) -> Vec<String> {
        let mut evicted = Vec::new();
        if self.total <= budget {
            return evicted;
        }
        let mut by_use: Vec<(u64, String)> = (self.entries.iter())
            .map(|(name, entry)| (entry.used, name.clone()))
            .collect();
        by_use.sort_unstable();
        for (_, name) in by_use {
            if self.total <= budget {
                break;
            }
            self.remove(&name);
            evicted.push(name);
        }
        evicted
    }
}

impl DiskRangeCache {
    /// The cache in `dir` (created if missing), its entries from earlier runs kept, the most
    /// recently written last to be evicted, and partial writes removed.
    pub fn open(dir: &Path, budget: u64) -> io::Result<Self> {
        fs::create_dir_all(dir)?;
        let mut found: Vec<(SystemTime, String, u64)> = Vec::new();
        for item in fs::read_dir(dir)? {
            let item = item?;
            let name = item.file_name().to_string_lossy().into_owned();
            let metadata = item.metadata()?;
            if !metadata.is_file() {
                continue;
            }
            if name.ends_with(PARTIAL) || !is_entry_name(&name) {
                let _ = fs::remove_file(item.path());
                continue;
            }
            let modified = metadata.modified().unwrap_or(SystemTime::UNIX_EPOCH);
            found.push((modified, name, metadata.len()));
        }
        found.sort();
        let mut index = Index::default();
        for (_, name, size) in found {
            index.insert(name, size);
        }
        let cache = Self {
            dir: dir.to_owned(),
            budget,
            index: Mutex::new(Index::default()),
            served_bytes: AtomicU64::new(0),
            dropped: AtomicU64::new(0),
            writes: AtomicU64::new(0),
        };
        let evicted = index.evict_to(budget);
        *cache.lock() = index;
        cache.remove_files(&evicted);
        Ok(cache)
    }

    /// The folder it keeps its entries in.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// The bytes its entries' files take together.
    pub fn bytes(&self) -> u64 {
        self.lock().total
    }

    /// Payload bytes served from the cache since it was opened.
    pub fn served_bytes(&self) -> u64 {
        self.served_bytes.load(Ordering::Relaxed)
    }

    /// Entries found damaged (cut, rewritten, of another length) and dropped.
    pub fn dropped(&self) -> u64 {
        self.dropped.load(Ordering::Relaxed)
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Index> {
        self.index.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn remove_files(&self, names: &[String]) {
        for name in names {
            let _ = fs::remove_file(self.dir.join(name));
        }
    }

    /// Drops a damaged entry, so that its range is fetched and written again.
    fn drop_damaged(&self, name: &str, why: &str) {
        self.lock().remove(name);
        let _ = fs::remove_file(self.dir.join(name));
        self.dropped.fetch_add(1, Ordering::Relaxed);
        tracing::warn!(entry = name, why, "a damaged range cache entry was dropped");
    }

    /// The payload of entry `name`, when its file holds `len` bytes whose SHA-256 it records.
    fn read_entry(&self, name: &str, len: u64) -> Option<Vec<u8>> {
        let path = self.dir.join(name);
        // Evicted meanwhile by another read: a miss, not damage.
        let size = fs::metadata(&path).ok()?.len();
        if size != HEADER_BYTES + len {
            self.drop_damaged(name, "its size is not its range's");
            return None;
        }
        let file = fs::read(&path).ok()?;
        if file.len() as u64 != HEADER_BYTES + len {
            self.drop_damaged(name, "it changed while it was read");
            return None;
        }
        let (header, payload) = file.split_at(HEADER_BYTES as usize);
        let recorded_len = u64::from_le_bytes(header[8..16].try_into().ok()?);
        if &header[..8] != MAGIC || recorded_len != len || payload.len() as u64 != len {
            self.drop_damaged(name, "its header is not a range's");
            return None;
        }
        if Sha256::digest(payload).as_slice() != &header[16..] {
            self.drop_damaged(name, "its SHA-256 does not match");
            return None;
        }
        Some(payload.to_vec())
    }

    /// Writes entry `name` atomically: a partial file, renamed once whole.
    fn write_entry(&self, name: &str, bytes: &[u8]) -> io::Result<()> {
        let write = self.writes.fetch_add(1, Ordering::Relaxed);
        let partial = (self.dir).join(format!("{name}.{}.{write}{PARTIAL}", std::process::id()));
        let result = (|| {
            let mut file = fs::File::create(&partial)?;
            file.write_all(MAGIC)?;
            file.write_all(&(bytes.len() as u64).to_le_bytes())?;
            file.write_all(&Sha256::digest(bytes))?;
            file.write_all(bytes)?;
            drop(file);
            fs::rename(&partial, self.dir.join(name))
        })();
        if result.is_err() {
            let _ = fs::remove_file(&partial);
        }
        result
    }
}

impl RangeCache for DiskRangeCache {
    fn get(&self, url: &str, version: &str, range: &Range<u64>) -> Option<Vec<u8>> {
        let len = range.end.checked_sub(range.start)?;
        let name = entry_name(url, version, range);
        {
            let mut index = self.lock();
            index.clock += 1;
            let clock = index.clock;
            index.entries.get_mut(&name)?.used = clock;
        }
        let payload = self.read_entry(&name, len)?;
        self.served_bytes.fetch_add(len, Ordering::Relaxed);
        Some(payload)
    }

    fn put(&self, url: &str, version: &str, range: &Range<u64>, bytes: &[u8]) {
        let size = HEADER_BYTES + bytes.len() as u64;
        if range.end.checked_sub(range.start) != Some(bytes.len() as u64) || size > self.budget {
            return;
        }
        let name = entry_name(url, version, range);
        if let Err(error) = self.write_entry(&name, bytes) {
            tracing::warn!(dir = %self.dir.display(), %error, "a range could not be cached");
            return;
        }
        let evicted = {
            let mut index = self.lock();
            index.insert(name, size);
            index.evict_to(self.budget)
        };
        self.remove_files(&evicted);
    }
}

/// An entry's file name: the SHA-256 of its URL, version and range, in hex.
fn entry_name(url: &str, version: &str, range: &Range<u64>) -> String {
    let mut key = Sha256::new();
    for part in [url.as_bytes(), version.as_bytes()] {
        key.update((part.len() as u64).to_le_bytes());
        key.update(part);
    }
    key.update(range.start.to_le_bytes());
    key.update(range.end.to_le_bytes());
    key.finalize().iter().map(|b| format!("{b:02x}")).collect()
}

fn is_entry_name(name: &str) -> bool {
    name.len() == 64 && name.bytes().all(|b| b.is_ascii_hexdigit())
}

#[cfg(test)]
mod tests {
    use super::*;

    const URL: &str = "https://data.example/a.copc.laz";

    fn payload(len: usize, seed: u8) -> Vec<u8> {
        (0..len)
            .map(|i| (i as u8).wrapping_mul(31) ^ seed)
            .collect()
    }

    fn entry_files(dir: &Path) -> Vec<PathBuf> {
        fs::read_dir(dir)
            .expect("dir")
            .map(|e| e.expect("entry").path())
            .collect()
    }

    #[test]
    fn a_range_is_served_only_for_its_url_version_and_range() {
        let dir = tempfile::tempdir().expect("dir");
        let cache = DiskRangeCache::open(dir.path(), 1 << 20).expect("opens");
        let bytes = payload(1000, 7);
        cache.put(URL, "\"v1\"", &(100..1100), &bytes);
        assert_eq!(cache.get(URL, "\"v1\"", &(100..1100)), Some(bytes.clone()));
        assert_eq!(cache.served_bytes(), 1000);
        assert_eq!(cache.get(URL, "\"v2\"", &(100..1100)), None);
        assert_eq!(cache.get(URL, "\"v1\"", &(100..1099)), None);
        assert_eq!(
            cache.get("https://data.example/b.copc.laz", "\"v1\"", &(100..1100)),
            None
        );
        // A length that is not the range's is never kept.
        cache.put(URL, "\"v1\"", &(0..10), &bytes);
        assert_eq!(cache.get(URL, "\"v1\"", &(0..10)), None);
        // Kept across a restart.
        drop(cache);
        let cache = DiskRangeCache::open(dir.path(), 1 << 20).expect("opens again");
        assert_eq!(cache.get(URL, "\"v1\"", &(100..1100)), Some(bytes));
        assert_eq!(cache.bytes(), 1000 + HEADER_BYTES);
    }

    #[test]
    fn a_damaged_entry_is_dropped_and_written_again() {
        let dir = tempfile::tempdir().expect("dir");
        let cache = DiskRangeCache::open(dir.path(), 1 << 20).expect("opens");
        let bytes = payload(4096, 3);
        let range = 0..4096;
        for damage in [
            |file: &mut Vec<u8>| file[HEADER_BYTES as usize + 17] ^= 1,
            |file: &mut Vec<u8>| file.truncate(file.len() - 1),
            |file: &mut Vec<u8>| file[0] = b'X',
            |file: &mut Vec<u8>| file[9] ^= 1,
        ] {
            cache.put(URL, "e", &range, &bytes);
            let [path] = entry_files(dir.path()).try_into().expect("one entry");
            let mut file = fs::read(&path).expect("entry");
            damage(&mut file);
            fs::write(&path, file).expect("damaged");
            assert_eq!(cache.get(URL, "e", &range), None);
            assert!(!path.exists(), "the damaged entry is removed");
            assert_eq!(cache.bytes(), 0);
        }
        assert_eq!(cache.dropped(), 4);
        cache.put(URL, "e", &range, &bytes);
        assert_eq!(cache.get(URL, "e", &range), Some(bytes));
    }

    #[test]
    fn the_budget_bounds_the_folder_the_least_recently_used_evicted() {
        let dir = tempfile::tempdir().expect("dir");
        let entry = 1000 + HEADER_BYTES;
        let cache = DiskRangeCache::open(dir.path(), 3 * entry).expect("opens");
        let ranges: Vec<Range<u64>> = (0..5).map(|i| i * 1000..(i + 1) * 1000).collect();
        for (i, range) in ranges.iter().take(3).enumerate() {
            cache.put(URL, "v", range, &payload(1000, i as u8));
        }
        // The first is used again, so the second is the least recently used.
        assert!(cache.get(URL, "v", &ranges[0]).is_some());
        cache.put(URL, "v", &ranges[3], &payload(1000, 3));
        assert!(cache.get(URL, "v", &ranges[1]).is_none());
        assert!(cache.get(URL, "v", &ranges[0]).is_some());
        cache.put(URL, "v", &ranges[4], &payload(1000, 4));
        let on_disk: u64 = entry_files(dir.path())
            .iter()
            .map(|p| fs::metadata(p).expect("entry").len())
            .sum();
        assert_eq!(on_disk, cache.bytes());
        assert!(on_disk <= 3 * entry, "{on_disk} bytes");
        // A range larger than the whole budget is not kept.
        cache.put(URL, "v", &(0..4000), &payload(4000, 9));
        assert!(cache.get(URL, "v", &(0..4000)).is_none());
        // A smaller budget at the next start evicts down to it, and partial writes are removed.
        fs::write(dir.path().join(format!("{}{PARTIAL}", "ab")), b"cut").expect("partial");
        drop(cache);
        let cache = DiskRangeCache::open(dir.path(), entry).expect("opens smaller");
        assert_eq!(cache.bytes(), entry);
        assert_eq!(entry_files(dir.path()).len(), 1);
    }
}
