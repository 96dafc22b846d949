//! The ingest half of `pointfarm bench`: what loading a dataset costs a worker before its first
//! frame, and what the dataset cache saves the next job.
//!
//! For each LAZ file (the real scans, and a generated cube written as LAZ so that the figures
//! do not rest on small files alone), in one run:
//! - decoding on all cores: [`load_point_cloud`], whose LAZ decoder runs on rayon's pool,
//!   against the same call inside a pool of one thread;
//! - a dataset-cache hit: the cloud stored in a sled cache on disk, the cache closed and opened
//!   again (as after a worker's restart), then loaded. The loaded cloud must equal the decoded
//!   one, or the run fails.
//!
//! Every figure is a median over repeated loads after an unmeasured first one, which leaves the
//! files in the OS's page cache: both sides read from memory, so the ratio is the work saved,
//! not the disk's speed.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Instant;

use pointfarm_render::cache::{CacheOutcome, DatasetCache};
use pointfarm_render::ingest::{load_point_cloud, write_las, LasWriteOptions};
use serde::Serialize;

use crate::clouds::uniform_cube;
use crate::stats::median;
use crate::workloads::uniform_workload;
use crate::BenchError;

/// What one file's loads cost.
#[derive(Debug, Clone, Serialize)]
pub struct IngestResult {
    /// `ingest-` and the file's name.
    pub workload: String,
    pub points: usize,
    pub file_bytes: u64,
    /// Threads of rayon's pool, which decodes LAZ.
    pub threads: usize,
    /// Decoding the file on all cores.
    pub decode_ms: f64,
    pub decode_mpoints_per_s: f64,
    /// Decoding it in a pool of one thread.
    pub decode_one_thread_ms: f64,
    /// `decode_one_thread_ms / decode_ms`: at most `threads`.
    pub parallel_speedup: f64,
    /// Opening the cache's sled database.
    pub cache_open_ms: f64,
    /// Loading the cloud from the cache just opened.
    pub cache_hit_ms: f64,
    /// `decode_ms / cache_hit_ms`.
    pub cache_speedup: f64,
}

/// A scratch directory removed when dropped, also when a measurement fails.
struct ScratchDir(PathBuf);

impl ScratchDir {
    fn new() -> Result<Self, BenchError> {
        static NEXT: AtomicU64 = AtomicU64::new(0);
        let path = std::env::temp_dir().join(format!(
            "pointfarm-bench-ingest-{}-{}",
            std::process::id(),
            NEXT.fetch_add(1, Ordering::Relaxed)
        ));
        std::fs::create_dir_all(&path).map_err(|e| scratch_error(&path, e))?;
        Ok(Self(path))
    }
}

impl Drop for ScratchDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

fn scratch_error(path: &Path, error: impl std::fmt::Display) -> BenchError {
    BenchError::Scratch(format!("{}: {error}", path.display()))
}

/// The generated file's name for `points` points.
pub fn generated_workload(points: usize) -> String {
    format!("ingest-{}.laz", uniform_workload(points))
}

/// Writes the uniform cube of `points` points as LAZ into a scratch directory (millimetre
/// coordinates, 16-bit color), measures it with the real `files`, and removes it.
pub fn measure_files(
    files: &[PathBuf],
    generated_points: Option<usize>,
    repeats: usize,
    progress: &mut dyn FnMut(&str),
) -> Result<Vec<IngestResult>, BenchError> {
    let scratch = ScratchDir::new()?;
    let mut paths: Vec<(String, PathBuf)> = files
        .iter()
        .map(|path| {
            let name = path.file_name().map_or_else(
                || path.display().to_string(),
                |n| n.to_string_lossy().into_owned(),
            );
            (format!("ingest-{name}"), path.clone())
        })
        .collect();
    if let Some(points) = generated_points {
        let workload = generated_workload(points);
        progress(&format!("{workload}: writing {points} points as LAZ"));
        let path = scratch.0.join(workload.trim_start_matches("ingest-"));
        write_las(&path, &uniform_cube(points, 7), &LasWriteOptions::default())
            .map_err(|e| scratch_error(&path, e))?;
        paths.push((workload, path));
    }
    let mut results = Vec::new();
    for (index, (workload, path)) in paths.iter().enumerate() {
        progress(&format!("{workload}: measuring"));
        let cache_dir = scratch.0.join(format!("cache-{index}"));
        let result = measure_file(workload, path, &cache_dir, repeats)?;
        progress(&format!(
            "{workload}: decode {:.1} ms on {} threads ({:.2}x one thread), cache hit {:.2} ms \
             ({:.0}x faster than decoding)",
            result.decode_ms,
            result.threads,
            result.parallel_speedup,
            result.cache_hit_ms,
            result.cache_speedup
        ));
        results.push(result);
    }
    Ok(results)
}

fn measure_file(
    workload: &str,
    path: &Path,
    cache_dir: &Path,
    repeats: usize,
) -> Result<IngestResult, BenchError> {
    let repeats = repeats.max(1);
    let file_bytes = std::fs::metadata(path)
        .map_err(|e| scratch_error(path, e))?
        .len();
    // The first load is unmeasured: it brings the file into the page cache.
    let decoded = load_point_cloud(path)?;
    let threads = rayon::current_num_threads();
    let one_thread = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .map_err(|e| BenchError::Scratch(format!("a one-thread pool: {e}")))?;
    let mut decode = Vec::with_capacity(repeats);
    let mut decode_one = Vec::with_capacity(repeats);
    // Alternating, so that a slow spell of the machine reaches both alike.
    for _ in 0..repeats {
        decode.push(time_ms(|| load_point_cloud(path))?.0);
        decode_one.push(time_ms(|| one_thread.install(|| load_point_cloud(path)))?.0);
    }

    let key = "bench";
    let max_bytes = u64::MAX;
    {
        let cache = DatasetCache::open(cache_dir, max_bytes)?;
        let (_, outcome) = cache.load(key, std::slice::from_ref(&path.to_path_buf()))?;
        if outcome != CacheOutcome::Miss {
            return Err(BenchError::CacheMismatch(format!(
                "{workload}: a new cache already held the cloud"
            )));
        }
    }
    let mut open = Vec::with_capacity(repeats);
    let mut hit = Vec::with_capacity(repeats);
    // The first hit after the store is unmeasured, like the first decode.
    for round in 0..=repeats {
        let (open_ms, cache) = time_ms(|| DatasetCache::open(cache_dir, max_bytes))?;
        let (hit_ms, (cloud, outcome)) =
            time_ms(|| cache.load(key, std::slice::from_ref(&path.to_path_buf())))?;
        if outcome != CacheOutcome::Hit || cloud != decoded {
            return Err(BenchError::CacheMismatch(format!(
                "{workload}: the cache did not give back the decoded cloud ({outcome:?})"
            )));
        }
        if round > 0 {
            open.push(open_ms);
            hit.push(hit_ms);
        }
    }
    let decode_ms = median(decode);
    let decode_one_thread_ms = median(decode_one);
    let cache_hit_ms = median(hit);
    Ok(IngestResult {
        workload: workload.to_string(),
        points: decoded.len(),
        file_bytes,
        threads,
        decode_ms,
        decode_mpoints_per_s: decoded.len() as f64 / decode_ms / 1e3,
        decode_one_thread_ms,
        parallel_speedup: decode_one_thread_ms / decode_ms,
        cache_open_ms: median(open),
        cache_hit_ms,
        cache_speedup: decode_ms / cache_hit_ms,
    })
}

/// Runs `f` and returns its wall time in milliseconds with its value.
fn time_ms<T, E>(f: impl FnOnce() -> Result<T, E>) -> Result<(f64, T), BenchError>
where
    BenchError: From<E>,
{
    let started = Instant::now();
    let value = f()?;
    Ok((started.elapsed().as_secs_f64() * 1e3, value))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_generated_laz_file_is_decoded_and_given_back_by_the_cache() {
        let mut lines = Vec::new();
        let results = measure_files(&[], Some(20_000), 1, &mut |l| lines.push(l.to_string()))
            .expect("measured");
        assert_eq!(results.len(), 1);
        let r = &results[0];
        assert_eq!(r.workload, "ingest-uniform-20000.laz");
        assert_eq!(r.points, 20_000);
        assert!(r.file_bytes > 0 && r.threads >= 1);
        for ms in [
            r.decode_ms,
            r.decode_one_thread_ms,
            r.cache_open_ms,
            r.cache_hit_ms,
        ] {
            assert!(ms > 0.0 && ms.is_finite(), "{r:?}");
        }
        assert!((r.parallel_speedup - r.decode_one_thread_ms / r.decode_ms).abs() < 1e-9);
        assert!((r.cache_speedup - r.decode_ms / r.cache_hit_ms).abs() < 1e-9);
        assert!(lines.iter().any(|l| l.contains("cache hit")), "{lines:?}");
    }

    #[test]
    fn a_real_scan_comes_back_from_the_cache_unchanged() {
        let Some(autzen) = pointfarm_render::testing::shared_data("autzen_trim.laz") else {
            return;
        };
        // `measure_file` fails unless the cache's cloud equals the decoded one, bit for bit.
        let results = measure_files(&[autzen], None, 1, &mut |_| {}).expect("measured");
        assert_eq!(results[0].workload, "ingest-autzen_trim.laz");
        assert_eq!(results[0].points, 110_000);
    }

    #[test]
    fn a_corrupt_file_is_an_ingest_error_and_the_scratch_space_is_removed() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("cut.laz");
        write_las(&path, &uniform_cube(5_000, 3), &LasWriteOptions::default()).expect("written");
        let bytes = std::fs::read(&path).expect("read");
        std::fs::write(&path, &bytes[..bytes.len() / 2]).expect("cut");
        let error = measure_files(&[path], None, 1, &mut |_| {}).expect_err("corrupt");
        assert!(matches!(error, BenchError::Ingest(_)), "{error}");

        let scratch = ScratchDir::new().expect("scratch");
        let kept = scratch.0.clone();
        assert!(kept.is_dir());
        drop(scratch);
        assert!(!kept.exists());
    }
}
