//! The worker's cache of processed datasets, in sled: a cloud that was decoded once (LAS/LAZ
//! parsing, recentring, color detection) loads again as plain columns, without decoding.
//!
//! Entries are keyed by the file's content hash and [`FORMAT_VERSION`], so a changed file or a
//! changed layout never returns stale points. Columns are stored in chunks of
//! [`CHUNK_POINTS`] points, 80 KB each: sled reads a value of many megabytes through a slow
//! path (docs/perf/dataset-cache.md). The cache holds at most `max_bytes`; the least recently
//! used entries are evicted to make room.

use std::path::{Path, PathBuf};
use std::time::Instant;

use glam::{DVec3, Vec3};
use serde::{Deserialize, Serialize};
use thiserror::Error;

use crate::cloud::{ColorSource, PointCloud, WorldBounds};
use crate::ingest::{load_dataset, IngestError};
use crate::sled_open::{is_lock_held, open_waiting};

/// Bump when the stored layout or the meaning of ingest's output changes.
pub const FORMAT_VERSION: u32 = 3;
const CHUNK_POINTS: usize = 1 << 12;
/// The chunk size of entries written before it was recorded in them.
const FIRST_CHUNK_POINTS: usize = 1 << 20;
/// Bytes per point in the cache: position, color, intensity, classification, return.
const BYTES_PER_POINT: u64 = 12 + 4 + 2 + 1 + 1;

#[derive(Debug, Error)]
pub enum CacheError {
    #[error("dataset cache: {0}")]
    Db(#[from] sled::Error),
    #[error("dataset cache {0} is locked: is another worker using it? ({1})")]
    Locked(String, String),
    #[error("dataset cache entry is unreadable: {0}")]
    Corrupt(String),
    #[error(transparent)]
    Ingest(#[from] IngestError),
}

/// Whether a load came from the cache.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CacheOutcome {
    Hit,
    /// Decoded from the file (and stored, if it fits).
    Miss,
}

#[derive(Serialize, Deserialize)]
struct EntryMeta {
    points: usize,
    #[serde(default = "first_chunk_points")]
    chunk_points: usize,
    origin: [f64; 3],
    bounds_min: [f64; 3],
    bounds_max: [f64; 3],
    color_source: String,
    bytes: u64,
    last_used_unix_ms: u128,
}

pub struct DatasetCache {
    entries: sled::Tree,
    chunks: sled::Tree,
    max_bytes: u64,
}

fn first_chunk_points() -> usize {
    FIRST_CHUNK_POINTS
}

fn now_ms() -> u128 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_millis())
        .unwrap_or(0)
}

fn chunk_key(key: &str, chunk: usize) -> Vec<u8> {
    let mut k = key.as_bytes().to_vec();
    k.push(b'/');
    k.extend_from_slice(&(chunk as u32).to_be_bytes());
    k
}

fn source_name(source: ColorSource) -> &'static str {
    match source {
        ColorSource::Rgb16 => "rgb16",
        ColorSource::Rgb8In16Bit => "rgb8in16",
        ColorSource::IntensityGrey => "intensity",
        ColorSource::Constant => "constant",
    }
}

fn source_from(name: &str) -> Option<ColorSource> {
    Some(match name {
        "rgb16" => ColorSource::Rgb16,
        "rgb8in16" => ColorSource::Rgb8In16Bit,
        "intensity" => ColorSource::IntensityGrey,
        "constant" => ColorSource::Constant,
        _ => return None,
    })
}

impl DatasetCache {
    /// Opens (or creates) the cache at `path`, waiting a while for a handle of this process
    /// that was just dropped to let go of it ([`crate::sled_open`]).
    pub fn open(path: &Path, max_bytes: u64) -> Result<Self, CacheError> {
        let db = match open_waiting(&sled::Config::new().path(path)) {
            Err(error) if is_lock_held(&error) => {
                return Err(CacheError::Locked(
                    path.display().to_string(),
                    error.to_string(),
                ))
            }
            result => result?,
        };
        Ok(Self {
            entries: db.open_tree("entries")?,
            chunks: db.open_tree("chunks")?,
            max_bytes,
        })
    }

    /// Whether the cache holds the points of the file with content hash `sha256` (so loading
    /// it will not read the file).
    pub fn contains(&self, sha256: &str) -> bool {
        let key = format!("{sha256}-v{FORMAT_VERSION}");
        self.entries.contains_key(key.as_bytes()).unwrap_or(false)
    }

    /// The cloud of the file with content hash `sha256` at `path`: from the cache, or decoded
    /// and then cached.
    pub fn load(
        &self,
        sha256: &str,
        files: &[PathBuf],
    ) -> Result<(PointCloud, CacheOutcome), CacheError> {
        let key = format!("{sha256}-v{FORMAT_VERSION}");
        let started = Instant::now();
        if let Some(cloud) = self.get(&key)? {
            tracing::info!(
                dataset = sha256,
                points = cloud.len(),
                ms = started.elapsed().as_millis() as u64,
                "dataset cache hit"
            );
            return Ok((cloud, CacheOutcome::Hit));
        }
        let cloud = load_dataset(files)?;
        tracing::info!(
            dataset = sha256,
            points = cloud.len(),
            ms = started.elapsed().as_millis() as u64,
            "dataset cache miss: decoded"
        );
        self.put(&key, &cloud)?;
        Ok((cloud, CacheOutcome::Miss))
    }

    fn get(&self, key: &str) -> Result<Option<PointCloud>, CacheError> {
        let Some(raw) = self.entries.get(key.as_bytes())? else {
            return Ok(None);
        };
        let mut meta: EntryMeta =
            serde_json::from_slice(&raw).map_err(|e| CacheError::Corrupt(e.to_string()))?;
        let n = meta.points;
        let mut cloud = PointCloud::with_capacity(
            DVec3::from_array(meta.origin),
            WorldBounds {
                min: DVec3::from_array(meta.bounds_min),
                max: DVec3::from_array(meta.bounds_max),
            },
            source_from(&meta.color_source)
                .ok_or_else(|| CacheError::Corrupt(meta.color_source.clone()))?,
            n,
        );
        let chunk_points = meta.chunk_points;
        if chunk_points == 0 {
            return Err(CacheError::Corrupt(format!("{key}: chunks of no points")));
        }
        for chunk in 0..n.div_ceil(chunk_points) {
            let bytes = self
                .chunks
                .get(chunk_key(key, chunk))?
                .ok_or_else(|| CacheError::Corrupt(format!("{key}: chunk {chunk} missing")))?;
            let count = (n - chunk * chunk_points).min(chunk_points);
            decode_chunk(&bytes, count, &mut cloud).ok_or_else(|| {
                CacheError::Corrupt(format!("{key}: chunk {chunk} has the wrong size"))
            })?;
        }
        meta.last_used_unix_ms = now_ms();
        if let Ok(raw) = serde_json::to_vec(&meta) {
            self.entries.insert(key.as_bytes(), raw)?;
        }
        Ok(Some(cloud))
    }

    fn put(&self, key: &str, cloud: &PointCloud) -> Result<(), CacheError> {
        let bytes = cloud.len() as u64 * BYTES_PER_POINT;
        if bytes > self.max_bytes {
            tracing::info!(
                key,
                bytes,
                max = self.max_bytes,
                "dataset too large for the cache"
            );
            return Ok(());
        }
        self.evict_until_free(bytes)?;
        for (chunk, start) in (0..cloud.len()).step_by(CHUNK_POINTS).enumerate() {
            let end = (start + CHUNK_POINTS).min(cloud.len());
            self.chunks
                .insert(chunk_key(key, chunk), encode_chunk(cloud, start..end))?;
        }
        let meta = EntryMeta {
            points: cloud.len(),
            chunk_points: CHUNK_POINTS,
            origin: cloud.origin.to_array(),
            bounds_min: cloud.bounds.min.to_array(),
            bounds_max: cloud.bounds.max.to_array(),
            color_source: source_name(cloud.color_source).into(),
            bytes,
            last_used_unix_ms: now_ms(),
        };
        let raw = serde_json::to_vec(&meta).map_err(|e| CacheError::Corrupt(e.to_string()))?;
        // The entry goes in last: a crash before it leaves only unreachable chunks.
        self.entries.insert(key.as_bytes(), raw)?;
        self.entries.flush()?;
        Ok(())
    }

    /// Removes least recently used entries until `needed` more bytes fit.
    fn evict_until_free(&self, needed: u64) -> Result<(), CacheError> {
        let mut entries: Vec<(String, EntryMeta)> = Vec::new();
        for item in self.entries.iter() {
            let (key, raw) = item?;
            if let Ok(meta) = serde_json::from_slice::<EntryMeta>(&raw) {
                entries.push((String::from_utf8_lossy(&key).into_owned(), meta));
            }
        }
        let mut used: u64 = entries.iter().map(|(_, m)| m.bytes).sum();
        entries.sort_by_key(|(_, m)| m.last_used_unix_ms);
        for (key, meta) in entries {
            if used.saturating_add(needed) <= self.max_bytes {
                break;
            }
            self.remove(&key, &meta)?;
            used -= meta.bytes;
            tracing::info!(key, "evicted from the dataset cache");
        }
        Ok(())
    }

    fn remove(&self, key: &str, meta: &EntryMeta) -> Result<(), CacheError> {
        self.entries.remove(key.as_bytes())?;
        for chunk in 0..meta.points.div_ceil(meta.chunk_points.max(1)) {
            self.chunks.remove(chunk_key(key, chunk))?;
        }
        Ok(())
    }

    /// Keys of the cached entries, for inspection.
    pub fn keys(&self) -> Vec<String> {
        self.entries
            .iter()
            .keys()
            .filter_map(Result::ok)
            .map(|k| String::from_utf8_lossy(&k).into_owned())
            .collect()
    }
}

/// Leads [`encode_cloud`]'s bytes; a change of their layout changes it.
const CLOUD_MAGIC: &[u8; 8] = b"PFCLOUD1";
/// The magic, the point count, the origin and the bounds (seven f64), the color source.
const CLOUD_HEADER_BYTES: usize = 8 + 8 + 9 * 8 + 1;

/// The length of [`encode_cloud`]'s bytes for a cloud of `points` points.
pub const fn encoded_cloud_bytes(points: u64) -> u64 {
    CLOUD_HEADER_BYTES as u64 + points * BYTES_PER_POINT
}

/// A whole cloud as bytes in the cache's column layout, after a header of its count, origin,
/// bounds and color decision: what a daemon sends a worker of a preview sample, decoded to
/// the bit by [`decode_cloud`].
pub fn encode_cloud(cloud: &PointCloud) -> Vec<u8> {
    let mut bytes = Vec::with_capacity(CLOUD_HEADER_BYTES + cloud.len() * BYTES_PER_POINT as usize);
    bytes.extend_from_slice(CLOUD_MAGIC);
    bytes.extend_from_slice(&(cloud.len() as u64).to_le_bytes());
    for v in [cloud.origin, cloud.bounds.min, cloud.bounds.max] {
        for c in v.to_array() {
            bytes.extend_from_slice(&c.to_le_bytes());
        }
    }
    let source = [
        ColorSource::Rgb16,
        ColorSource::Rgb8In16Bit,
        ColorSource::IntensityGrey,
        ColorSource::Constant,
    ]
    .iter()
    .position(|s| *s == cloud.color_source)
    .unwrap_or(3) as u8;
    bytes.push(source);
    bytes.extend_from_slice(&encode_chunk(cloud, 0..cloud.len()));
    bytes
}

/// The cloud [`encode_cloud`] wrote; `Corrupt` saying what is wrong with other bytes.
pub fn decode_cloud(bytes: &[u8]) -> Result<PointCloud, CacheError> {
    let corrupt = |what: &str| CacheError::Corrupt(format!("encoded cloud: {what}"));
    if bytes.len() < CLOUD_HEADER_BYTES || &bytes[..8] != CLOUD_MAGIC {
        return Err(corrupt("no header"));
    }
    let u64_at = |at: usize| {
        let mut b = [0; 8];
        b.copy_from_slice(&bytes[at..at + 8]);
        u64::from_le_bytes(b)
    };
    let f64_at = |at: usize| f64::from_bits(u64_at(at));
    let vec_at = |at: usize| DVec3::new(f64_at(at), f64_at(at + 8), f64_at(at + 16));
    let count = u64_at(8);
    let body = &bytes[CLOUD_HEADER_BYTES..];
    if count.checked_mul(BYTES_PER_POINT) != Some(body.len() as u64) {
        return Err(corrupt(&format!("{count} points in {} bytes", body.len())));
    }
    let color_source = match bytes[CLOUD_HEADER_BYTES - 1] {
        0 => ColorSource::Rgb16,
        1 => ColorSource::Rgb8In16Bit,
        2 => ColorSource::IntensityGrey,
        3 => ColorSource::Constant,
        other => return Err(corrupt(&format!("color source {other}"))),
    };
    let n = count as usize;
    let bounds = WorldBounds {
        min: vec_at(40),
        max: vec_at(64),
    };
    let mut cloud = PointCloud::with_capacity(vec_at(16), bounds, color_source, n);
    decode_chunk(body, n, &mut cloud).ok_or_else(|| corrupt("wrong size"))?;
    Ok(cloud)
}

fn encode_chunk(cloud: &PointCloud, range: std::ops::Range<usize>) -> Vec<u8> {
    let mut bytes = Vec::with_capacity(range.len() * BYTES_PER_POINT as usize);
    for p in &cloud.positions[range.clone()] {
        for c in p.to_array() {
            bytes.extend_from_slice(&c.to_le_bytes());
        }
    }
    for c in &cloud.colors[range.clone()] {
        bytes.extend_from_slice(&c.to_le_bytes());
    }
    for i in &cloud.intensity[range.clone()] {
        bytes.extend_from_slice(&i.to_le_bytes());
    }
    bytes.extend_from_slice(&cloud.classification[range.clone()]);
    bytes.extend_from_slice(&cloud.return_number[range]);
    bytes
}

fn decode_chunk(bytes: &[u8], count: usize, cloud: &mut PointCloud) -> Option<()> {
    if bytes.len() != count * BYTES_PER_POINT as usize {
        return None;
    }
    let (positions, rest) = bytes.split_at(count * 12);
    let (colors, rest) = rest.split_at(count * 4);
    let (intensity, rest) = rest.split_at(count * 2);
    let (classification, return_number) = rest.split_at(count);
    let f32_at = |b: &[u8]| f32::from_le_bytes([b[0], b[1], b[2], b[3]]);
    cloud.positions.extend(
        positions
            .chunks_exact(12)
            .map(|p| Vec3::new(f32_at(&p[0..4]), f32_at(&p[4..8]), f32_at(&p[8..12]))),
    );
    cloud.colors.extend(
        colors
            .chunks_exact(4)
            .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]])),
    );
    cloud.intensity.extend(
        intensity
            .chunks_exact(2)
            .map(|c| u16::from_le_bytes([c[0], c[1]])),
    );
    cloud.classification.extend_from_slice(classification);
    cloud.return_number.extend_from_slice(return_number);
    Some(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ingest::load_point_cloud;
    use crate::sample::sample_scene;

    /// Entries written before the chunk size was recorded (and made smaller) still load.
    #[test]
    fn an_entry_of_the_first_layout_still_loads() {
        let dir = tempfile::tempdir().expect("tempdir");
        let cloud = sample_scene(5_000, 2);
        // Too small for the entry: the first eviction removes it.
        let cache = DatasetCache::open(&dir.path().join("cache"), 10).expect("open");
        let key = "old";
        cache
            .chunks
            .insert(chunk_key(key, 0), encode_chunk(&cloud, 0..cloud.len()))
            .expect("chunk");
        let mut meta = serde_json::json!({
            "points": cloud.len(),
            "origin": cloud.origin.to_array(),
            "bounds_min": cloud.bounds.min.to_array(),
            "bounds_max": cloud.bounds.max.to_array(),
            "color_source": source_name(cloud.color_source),
            "bytes": cloud.len() as u64 * BYTES_PER_POINT,
            "last_used_unix_ms": 1,
        });
        assert!(meta.get("chunk_points").is_none());
        cache
            .entries
            .insert(key, serde_json::to_vec(&meta).expect("json"))
            .expect("entry");
        assert_eq!(cache.get(key).expect("get"), Some(cloud.clone()));

        // A chunk size of nothing is a corrupt entry, not a division by zero.
        meta["chunk_points"] = 0.into();
        cache
            .entries
            .insert(key, serde_json::to_vec(&meta).expect("json"))
            .expect("entry");
        assert!(matches!(cache.get(key), Err(CacheError::Corrupt(_))));
        cache
            .evict_until_free(1)
            .expect("eviction of the corrupt entry");
        assert!(cache.entries.get(key).expect("entries").is_none());
        assert!(cache.chunks.is_empty());
    }

    /// A second handle waits for the first to let go of the directory, and fails with a
    /// clear error while it is held.
    #[test]
    fn a_locked_cache_is_waited_for_and_then_named() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("cache");
        let first = DatasetCache::open(&path, u64::MAX).expect("open");
        let started = Instant::now();
        let error = DatasetCache::open(&path, u64::MAX).err().expect("locked");
        assert!(
            started.elapsed() >= crate::sled_open::LOCK_WAIT,
            "{:?}",
            started.elapsed()
        );
        assert!(matches!(error, CacheError::Locked(..)), "{error}");
        assert!(error.to_string().contains("another worker"), "{error}");
        drop(first);
        DatasetCache::open(&path, u64::MAX).expect("open once released");
    }

    /// An origin and bounds that serde_json's default float parsing reads back one ulp off
    /// (found by `pointfarm bench`'s ingest check on a generated UTM-like cube).
    #[test]
    fn an_encoded_cloud_decodes_to_the_bit() {
        let cloud = sample_scene(5_000, 4);
        let bytes = encode_cloud(&cloud);
        let back = decode_cloud(&bytes).expect("decodes");
        assert_eq!(back.origin, cloud.origin);
        assert_eq!(back.bounds, cloud.bounds);
        assert_eq!(back.color_source, cloud.color_source);
        assert_eq!(back.positions, cloud.positions);
        assert_eq!(back.colors, cloud.colors);
        assert_eq!(back.intensity, cloud.intensity);
        assert_eq!(back.classification, cloud.classification);
        assert_eq!(back.return_number, cloud.return_number);
        assert!(decode_cloud(&bytes[..bytes.len() - 1]).is_err());
        assert!(decode_cloud(b"PFCLOUD1").is_err());
    }

    #[test]
    fn origin_and_bounds_come_back_to_the_bit() {
        let dir = tempfile::tempdir().expect("tempdir");
        let mut cloud = sample_scene(100, 1);
        cloud.origin = DVec3::new(515050.00399999996, 4918049.996, 2049.9935);
        cloud.bounds.min = cloud.origin - DVec3::splat(0.30000000000000004);
        cloud.bounds.max = cloud.origin + DVec3::new(1.0 / 3.0, 1e-17, 123456.789);
        let cache = DatasetCache::open(&dir.path().join("cache"), u64::MAX).expect("open");
        cache.put("k", &cloud).expect("put");
        let back = cache.get("k").expect("get").expect("entry");
        let bits = |v: DVec3| v.to_array().map(f64::to_bits);
        assert_eq!(bits(back.origin), bits(cloud.origin));
        assert_eq!(bits(back.bounds.min), bits(cloud.bounds.min));
        assert_eq!(bits(back.bounds.max), bits(cloud.bounds.max));
    }

    #[test]
    fn a_cached_cloud_equals_the_decoded_one_and_the_cache_evicts_the_least_recent() {
        let dir = tempfile::tempdir().expect("tempdir");
        let files = crate::testing::write_scene_tiles(dir.path(), 3_000, 3);
        // Room for two of the three clouds.
        let cache = DatasetCache::open(&dir.path().join("cache"), 2 * 3_000 * BYTES_PER_POINT + 10)
            .expect("open");
        assert!(!cache.contains("aaa"));
        let (first, outcome) = cache
            .load("aaa", std::slice::from_ref(&files[0]))
            .expect("load");
        assert_eq!(outcome, CacheOutcome::Miss);
        assert!(cache.contains("aaa"));
        let (again, outcome) = cache
            .load("aaa", std::slice::from_ref(&files[0]))
            .expect("load");
        assert_eq!(outcome, CacheOutcome::Hit);
        assert_eq!(again, first, "the cache returns exactly the decoded cloud");
        assert_eq!(again, load_point_cloud(&files[0]).expect("decode"));

        cache
            .load("bbb", std::slice::from_ref(&files[1]))
            .expect("load");
        std::thread::sleep(std::time::Duration::from_millis(5));
        cache
            .load("aaa", std::slice::from_ref(&files[0]))
            .expect("touch aaa"); // bbb is now the least recent
        std::thread::sleep(std::time::Duration::from_millis(5));
        cache
            .load("ccc", std::slice::from_ref(&files[2]))
            .expect("load");
        let mut keys = cache.keys();
        keys.sort();
        assert_eq!(
            keys,
            vec![
                format!("aaa-v{FORMAT_VERSION}"),
                format!("ccc-v{FORMAT_VERSION}")
            ]
        );
        assert!(
            !cache.contains("bbb"),
            "an evicted cloud is no longer contained"
        );
    }
}
