//! The campaign-scale ingest of `pointfarm bench --campaign`: what building the
//! level-of-detail store of a campaign of many files costs, from LAZ and from LAS. No GPU.
//!
//! In one run, in a scratch folder removed afterwards:
//! 1. a generated terrain ([`GeneratedSource::terrain`](pointfarm_render::lod::GeneratedSource))
//!    split on a grid into `files` tiles, written streaming as LAZ, and as LAS beside it when
//!    the disk holds both ([`tiles`]);
//! 2. every point of each kind read through [`DatasetSource`] without building: the LAZ
//!    figure is decoding on all cores, the bound of a build that reads its source twice;
//! 3. the store built from each kind with [`build_lod`] into a fresh store, measuring the wall
//!    time, the builder's stages, the process's peak resident memory (`VmHWM`, reset before
//!    the build), the builder's own tracked peak, the store's bytes on disk per point and
//!    its digest (`lod::digest`), the same for two binaries that stored the same nodes.
//!
//! The files are in the OS's page cache when they are read (just written, unless the
//! campaign outgrows the memory): the figures are the decoder's and the builder's, not the
//! disk's.

pub mod cpu;
mod flags;
pub mod serial;
mod serve_flags;
pub mod store_points;
mod tiles;

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

use pointfarm_render::cut::LodDataset;
use pointfarm_render::gpu::GpuContext;

use pointfarm_render::ingest::DatasetSource;
use pointfarm_render::lod::digest::store_digest;
use pointfarm_render::lod::disk::{build_disk_bytes, MAX_SPILL_RECORD_BYTES};
use pointfarm_render::lod::PointSource;
use pointfarm_render::lod::{build_lod, BuildTimings, LodBuildOptions};
use serde::Serialize;

use crate::cuts::{render_turntable, TurntableOptions, TurntableResult};
use crate::scratch::{load_average, progress_log, scratch_dir};
use crate::store::create_store;
use crate::{memory, BenchError};
pub use flags::{CampaignFlags, ScratchCampaign};
pub use serial::SerialThreads;
pub use serve_flags::ServeCampaignFlags;
pub use tiles::{grid, write_campaign, CampaignFiles, LAS_RECORD_BYTES, MIN_POINTS_PER_FILE};

/// Points of `--campaign` given bare.
pub const CAMPAIGN_POINTS: u64 = 20_000_000;
/// Points of `--campaign` given bare with `--quick`.
pub const CAMPAIGN_QUICK_POINTS: u64 = 4_000_000;
/// Files of a campaign unless `--campaign-files` says otherwise.
pub const CAMPAIGN_FILES: usize = 20;
/// Disk a point's LAZ file is expected to take (15.4 B for the terrain, whose points are in
/// random order within a tile); its build's peak is [`build_disk_bytes`]'s.
const LAZ_BYTES_PER_POINT: u64 = 16;
/// Disk left free by the benchmark, beyond what it expects to write.
const DISK_MARGIN_BYTES: u64 = 4 << 30;

/// What to generate and build.
#[derive(Debug, Clone)]
pub struct CampaignOptions {
    pub points: u64,
    pub files: usize,
    pub seed: u64,
    /// Also write and build from LAS, when the disk holds it.
    pub las: bool,
    /// Where the scratch folder is made (the system's temporary folder by default).
    pub scratch_parent: Option<PathBuf>,
    /// After the LAZ build, render a turntable of its store (needs the GPU of
    /// [`measure_with_frames`]).
    pub turntable: Option<TurntableOptions>,
}

impl CampaignOptions {
    pub fn new(points: u64, files: usize) -> Self {
        Self {
            points,
            files,
            seed: 11,
            las: true,
            scratch_parent: None,
            turntable: None,
        }
    }
}

/// Reading every point of one kind of files through [`DatasetSource`], building nothing.
#[derive(Debug, Clone, Serialize)]
pub struct DecodeResult {
    /// `laz` or `las`.
    pub input: &'static str,
    pub points: u64,
    pub file_bytes: u64,
    pub file_bytes_per_point: f64,
    pub read_s: f64,
    pub mpoints_per_s: f64,
    /// CPU seconds of the process while it read, all threads.
    pub cpu_s: f64,
}

/// The builder's stages, in seconds ([`BuildTimings`]).
#[derive(Debug, Clone, Copy, Serialize)]
pub struct BuildStages {
    pub counting_s: f64,
    pub partitions_s: f64,
    pub upper_levels_s: f64,
    pub total_s: f64,
}

impl From<BuildTimings> for BuildStages {
    fn from(t: BuildTimings) -> Self {
        Self {
            counting_s: t.counting.as_secs_f64(),
            partitions_s: t.partitions.as_secs_f64(),
            upper_levels_s: t.upper_levels.as_secs_f64(),
            total_s: t.total.as_secs_f64(),
        }
    }
}

/// One build of the store from one kind of files.
#[derive(Debug, Clone, Serialize)]
pub struct BuildResult {
    /// `laz` or `las`.
    pub input: &'static str,
    /// Points the files' headers declare.
    pub points: u64,
    /// Points the built hierarchy holds (the builder fails unless it stored each point once).
    pub stored_points: u64,
    /// Rayon threads of the build.
    pub threads: usize,
    /// Wall time of `build_lod`.
    pub build_s: f64,
    pub mpoints_per_s: f64,
    pub stages: BuildStages,
    /// The counting pass's own threads' CPU and the ceiling the largest sets.
    pub counting_threads: SerialThreads,
    /// The build's rate over the rate of reading the same files ([`DecodeResult`]).
    pub over_decode: f64,
    /// The read time over the build time: the share of the build that its one reading of the
    /// source takes at the decode-only rate.
    pub reads_share: f64,
    /// CPU seconds of the process during the build, all threads.
    pub cpu_s: f64,
    /// The read's CPU seconds over the build's: on a busy host, where wall times stretch
    /// with the other work, what the build adds to decoding.
    pub cpu_over_decode: f64,
    /// The process's resident memory just before the build.
    pub before_rss_bytes: u64,
    /// The process's peak resident memory during the build (`VmHWM`, reset before it unless
    /// [`CampaignResult::peak_reset`] is false).
    pub peak_rss_bytes: u64,
    /// The most bytes the builder's tracked buffers held, and their budget.
    pub builder_peak_bytes: u64,
    pub memory_budget_bytes: u64,
    pub partitions: usize,
    pub nodes: usize,
    pub spilled_bytes: u64,
    /// Bytes of a point's spill record (26 on one LAS grid, 38 in f64).
    pub spill_record_bytes: usize,
    /// Bytes of node records written.
    pub stored_bytes: u64,
    /// Bytes the store's folder (sled's hierarchy and the node payload file) takes on disk
    /// once closed.
    pub store_disk_bytes: u64,
    pub store_disk_bytes_per_point: f64,
    /// The digest of the stored nodes, in hex (`lod::digest`): the same for two binaries
    /// exactly when they stored the same bytes.
    pub store_digest: String,
}

/// Everything one campaign run measured.
#[derive(Debug, Clone, Serialize)]
pub struct CampaignResult {
    /// Points generated and written, each to one file of each kind.
    pub points: u64,
    pub files: usize,
    /// Rows and columns of the tiles.
    pub grid: [usize; 2],
    /// Threads of rayon's pool (the LAZ decoder's and the builder's).
    pub threads: usize,
    /// Generating and writing the files (LAZ, and LAS when written).
    pub write_s: f64,
    pub decode: Vec<DecodeResult>,
    pub builds: Vec<BuildResult>,
    /// Why no LAS was written, when it was not.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub las_skipped: Option<String>,
    /// Whether the peak resident memory could be reset before each build; when not, each
    /// peak is the process's since its start.
    pub peak_reset: bool,
    /// The turntable of the LAZ build's store, when asked for.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub turntable: Option<TurntableResult>,
    /// The machine's 1-minute load average when the run started and when it ended (Linux):
    /// above the cores, other work shared them and the rates are lower bounds.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub load_average: Option<[f64; 2]>,
}

impl CampaignResult {
    pub fn decode_of(&self, input: &str) -> Option<&DecodeResult> {
        self.decode.iter().find(|d| d.input == input)
    }

    pub fn build_of(&self, input: &str) -> Option<&BuildResult> {
        self.builds.iter().find(|b| b.input == input)
    }
}

/// Bytes the files under `path` take on disk (allocated blocks where the OS says).
fn disk_bytes(path: &Path) -> u64 {
    let Ok(entries) = std::fs::read_dir(path) else {
        return 0;
    };
    entries
        .flatten()
        .map(|entry| match entry.metadata() {
            Ok(meta) if meta.is_dir() => disk_bytes(&entry.path()),
            Ok(meta) => allocated(&meta),
            Err(_) => 0,
        })
        .sum()
}

#[cfg(unix)]
fn allocated(meta: &std::fs::Metadata) -> u64 {
    std::os::unix::fs::MetadataExt::blocks(meta) * 512
}

#[cfg(not(unix))]
fn allocated(meta: &std::fs::Metadata) -> u64 {
    meta.len()
}

fn file_bytes(paths: &[PathBuf]) -> u64 {
    paths
        .iter()
        .filter_map(|p| std::fs::metadata(p).ok())
        .map(|m| m.len())
        .sum()
}

/// Bytes free to this user on the file system of `path`.
fn free_disk_bytes(path: &Path) -> Option<u64> {
    let stat = rustix::fs::statvfs(path).ok()?;
    Some(stat.f_bavail.saturating_mul(stat.f_frsize))
}

fn gib(bytes: u64) -> f64 {
    bytes as f64 / (1u64 << 30) as f64
}

/// Whether LAS fits beside the rest: `Err` says why not. A run that does not fit even
/// without LAS fails before it writes anything.
fn plan_disk(options: &CampaignOptions, dir: &Path) -> Result<Result<(), String>, BenchError> {
    let Some(free) = free_disk_bytes(dir) else {
        return Ok(if options.las {
            Ok(())
        } else {
            Err("not asked for".into())
        });
    };
    let needed = options.points.saturating_mul(LAZ_BYTES_PER_POINT)
        + build_disk_bytes(options.points, true, MAX_SPILL_RECORD_BYTES)
        + DISK_MARGIN_BYTES;
    if needed > free {
        return Err(BenchError::Scratch(format!(
            "{}: {} points need about {:.1} GiB of disk (LAZ, the build's spill and store, a \
             margin), {:.1} GiB are free",
            dir.display(),
            options.points,
            gib(needed),
            gib(free)
        )));
    }
    let las = options.points.saturating_mul(LAS_RECORD_BYTES);
    Ok(if !options.las {
        Err("not asked for".into())
    } else if needed + las > free {
        Err(format!(
            "the LAS files would take {:.1} GiB ({LAS_RECORD_BYTES} B a point), {:.1} GiB \
             beyond the {:.1} GiB that LAZ, the builds and a margin need of the {:.1} GiB free",
            gib(las),
            gib(needed + las - free),
            gib(needed),
            gib(free)
        ))
    } else {
        Ok(())
    })
}

/// Generates the campaign, measures reading and building it, and removes every file.
pub fn measure(
    options: &CampaignOptions,
    progress: &mut dyn FnMut(&str),
) -> Result<CampaignResult, BenchError> {
    measure_with_frames(options, None, progress)
}

/// [`measure`], and with a GPU the turntable of [`CampaignOptions::turntable`].
pub fn measure_with_frames(
    options: &CampaignOptions,
    gpu: Option<&Arc<GpuContext>>,
    progress: &mut dyn FnMut(&str),
) -> Result<CampaignResult, BenchError> {
    let mut log = progress_log("campaign", progress);
    let scratch = scratch_dir(options.scratch_parent.as_deref(), "campaign")?;
    let dir = scratch.path();
    let load_before = load_average();
    let las_plan = plan_disk(options, dir)?;
    let (rows, cols) = grid(options.files);
    let kinds = if las_plan.is_ok() {
        "LAZ and LAS"
    } else {
        "LAZ"
    };
    log(format!(
        "campaign: writing {} points of terrain as {} tiles ({rows}x{cols}), {kinds}, in {}",
        options.points,
        options.files,
        dir.display()
    ));
    if let Err(reason) = &las_plan {
        log(format!("campaign: no LAS: {reason}"));
    }
    let writing = Instant::now();
    let files = tiles::write_campaign(
        dir,
        options.points,
        options.files,
        options.seed,
        las_plan.is_ok(),
    )?;
    let write_s = writing.elapsed().as_secs_f64();
    log(format!(
        "campaign: written in {write_s:.1} s ({:.0} MB of LAZ, {:.0} MB of LAS)",
        file_bytes(&files.laz) as f64 / 1e6,
        file_bytes(&files.las) as f64 / 1e6
    ));

    let mut inputs = vec![("laz", &files.laz)];
    if !files.las.is_empty() {
        inputs.push(("las", &files.las));
    }
    let mut decode = Vec::new();
    let mut builds = Vec::new();
    let mut peak_reset = true;
    let mut turntable = None;
    for (input, paths) in inputs {
        let source = DatasetSource::open(paths)?;
        let read = read_all(input, &source, paths)?;
        log(format!(
            "campaign: {input}: read {} points in {:.2} s, {:.2} M points/s, CPU {:.2} s",
            read.points, read.read_s, read.mpoints_per_s, read.cpu_s
        ));
        let build_dir = dir.join(format!("build-{input}"));
        let (build, reset) = build(input, &source, &build_dir, &read)?;
        peak_reset &= reset;
        log(format!(
            "campaign: {input}: built in {:.1} s, {:.2} M points/s ({:.0}% of reading's rate; \
             counting {:.1} s, partitions {:.1} s, upper levels {:.1} s), peak \
             RSS {:.0} MiB, store {:.1} B/point, digest {}; CPU {:.2} s, reading's {:.0}% of it",
            build.build_s,
            build.mpoints_per_s,
            build.over_decode * 100.0,
            build.stages.counting_s,
            build.stages.partitions_s,
            build.stages.upper_levels_s,
            build.peak_rss_bytes as f64 / (1u64 << 20) as f64,
            build.store_disk_bytes_per_point,
            build.store_digest,
            build.cpu_s,
            build.cpu_over_decode * 100.0
        ));
        log(format!(
            "campaign: {input}: {}",
            build.counting_threads.line()
        ));
        if let (Some(frames), Some(gpu), "laz") = (&options.turntable, gpu, input) {
            let store = create_store(&build_dir.join("store"))?;
            let dataset = LodDataset::open(store.store.clone(), source.bounds())?;
            let result = render_turntable(gpu, &dataset, frames, &mut |l| {
                log(format!("campaign: {l}"))
            })?;
            log(format!(
                "campaign: turntable: first frame {:.2} s, following median {:.2} s, peak RSS \
                 {} MiB",
                result.first_ms / 1e3,
                result.following_median_ms / 1e3,
                result.peak_rss_bytes >> 20
            ));
            turntable = Some(result);
        }
        let _ = std::fs::remove_dir_all(&build_dir);
        decode.push(read);
        builds.push(build);
    }
    if !peak_reset {
        log(
            "campaign: the peak resident memory could not be reset: each peak is the \
             process's since its start"
                .into(),
        );
    }
    drop(scratch);
    Ok(CampaignResult {
        points: files.points,
        files: options.files,
        grid: [rows, cols],
        threads: rayon::current_num_threads(),
        write_s,
        decode,
        builds,
        las_skipped: las_plan.err(),
        peak_reset,
        turntable,
        load_average: load_before.zip(load_average()).map(|(a, b)| [a, b]),
    })
}

/// The points of `source`, each read once and counted: what a decode measurement times.
pub(crate) fn points_read(source: &DatasetSource) -> Result<u64, BenchError> {
    let mut points = 0u64;
    source.for_each_batch(&mut |batch| {
        points += batch.len() as u64;
        Ok(())
    })?;
    Ok(points)
}

/// Reads every point of `source` once, building nothing.
fn read_all(
    input: &'static str,
    source: &DatasetSource,
    paths: &[PathBuf],
) -> Result<DecodeResult, BenchError> {
    let cpu_before = cpu::process_cpu_s();
    let started = Instant::now();
    let points = points_read(source)?;
    let read_s = started.elapsed().as_secs_f64();
    let cpu_s = cpu::process_cpu_s() - cpu_before;
    let bytes = file_bytes(paths);
    Ok(DecodeResult {
        input,
        points,
        file_bytes: bytes,
        file_bytes_per_point: bytes as f64 / points.max(1) as f64,
        read_s,
        mpoints_per_s: points as f64 / read_s / 1e6,
        cpu_s,
    })
}

/// Builds the store of `source` into a fresh store in `dir`; with whether the memory peak was
/// reset before it.
fn build(
    input: &'static str,
    source: &DatasetSource,
    dir: &Path,
    read: &DecodeResult,
) -> Result<(BuildResult, bool), BenchError> {
    let store_dir = dir.join("store");
    let bench_store = create_store(&store_dir)?;
    let options = LodBuildOptions::new(dir.join("spill"));
    let _measuring = memory::measuring();
    let before_rss_bytes = memory::resident_bytes();
    let reset = memory::reset_peak();
    let cpu_before = cpu::process_cpu_s();
    let started = Instant::now();
    let report = build_lod(source, &bench_store.store, &options)?;
    let build_s = started.elapsed().as_secs_f64();
    let cpu_s = cpu::process_cpu_s() - cpu_before;
    let peak_rss_bytes = memory::peak_resident_bytes();
    let stored_points = bench_store.store.read_hierarchy()?.point_count;
    let store_digest = format!("{:016x}", store_digest(&bench_store.store)?);
    drop(bench_store);
    let store_disk_bytes = disk_bytes(&store_dir);
    let points = source.point_count();
    let mpoints_per_s = points as f64 / build_s / 1e6;
    Ok((
        BuildResult {
            input,
            points,
            stored_points,
            threads: options.threads.unwrap_or_else(rayon::current_num_threads),
            build_s,
            mpoints_per_s,
            stages: report.timings.into(),
            counting_threads: SerialThreads::of(&report.timings.counting_threads, points),
            over_decode: mpoints_per_s / read.mpoints_per_s,
            reads_share: read.read_s / build_s,
            cpu_s,
            cpu_over_decode: read.cpu_s / cpu_s.max(0.01),
            before_rss_bytes,
            peak_rss_bytes,
            builder_peak_bytes: report.peak_memory_bytes,
            memory_budget_bytes: report.memory_budget_bytes,
            partitions: report.partitions,
            nodes: report.hierarchy.nodes().len(),
            spilled_bytes: report.spilled_bytes,
            spill_record_bytes: report.spill_record_bytes,
            stored_bytes: report.stored_bytes,
            store_disk_bytes,
            store_disk_bytes_per_point: store_disk_bytes as f64 / points.max(1) as f64,
            store_digest,
        },
        reset,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A campaign of `points` in `files` with its scratch folder in a fresh folder.
    fn scratched(points: u64, files: usize) -> (tempfile::TempDir, CampaignOptions) {
        let parent = tempfile::tempdir().expect("tempdir");
        let options = CampaignOptions {
            scratch_parent: Some(parent.path().to_path_buf()),
            ..CampaignOptions::new(points, files)
        };
        (parent, options)
    }

    #[test]
    fn a_small_campaign_is_read_and_built_from_laz_and_las_and_cleaned_up() {
        let (parent, options) = scratched(200_000, 4);
        let mut lines = Vec::new();
        let result = measure(&options, &mut |l| lines.push(l.to_string())).expect("measured");
        assert_eq!(
            (result.points, result.files, result.grid),
            (200_000, 4, [2, 2])
        );
        assert!(result.threads >= 1 && result.write_s > 0.0);
        assert!(result.las_skipped.is_none(), "{:?}", result.las_skipped);
        assert_eq!(result.decode.len(), 2);
        assert_eq!(result.builds.len(), 2);
        for read in &result.decode {
            assert_eq!(read.points, 200_000, "{read:?}");
            assert!(read.mpoints_per_s > 0.0 && read.file_bytes > 0, "{read:?}");
        }
        let las = result.decode_of("las").expect("las read");
        assert!(las.file_bytes >= 200_000 * LAS_RECORD_BYTES, "{las:?}");
        assert!(result.decode_of("laz").expect("laz").file_bytes < las.file_bytes);
        for build in &result.builds {
            assert_eq!((build.points, build.stored_points), (200_000, 200_000));
            assert!(
                build.mpoints_per_s > 0.0 && build.over_decode > 0.0,
                "{build:?}"
            );
            let s = build.stages;
            assert!(s.total_s >= s.counting_s + s.partitions_s, "{s:?}");
            assert!(build.build_s >= s.total_s);
            assert!(build.nodes >= 1 && build.partitions >= 1);
            assert!(build.store_disk_bytes_per_point > 0.0, "{build:?}");
            assert!(build.peak_rss_bytes > 0 && build.builder_peak_bytes > 0);
            assert!(build.builder_peak_bytes <= build.memory_budget_bytes);
            // Every thread of the counting pass measured, the source's reader included.
            let t = &build.counting_threads;
            let each = [
                t.walker_cpu_s,
                t.scatterer_cpu_s,
                t.spill_writer_cpu_s,
                t.checkpoint_recorder_cpu_s,
                t.source_reader_cpu_s,
            ];
            assert!(each.iter().all(|&s| s > 0.0), "{t:?}");
            assert!(t.ceiling_mpoints_per_s > 0.0, "{t:?}");
        }
        // The same points from either kind of file: the same store.
        let digests: Vec<&str> = result
            .builds
            .iter()
            .map(|b| b.store_digest.as_str())
            .collect();
        assert_eq!((digests[0].len(), digests[0]), (16, digests[1]));
        assert!(lines.iter().any(|l| l.contains("built in")), "{lines:?}");
        let md = crate::markdown::campaign_tables(&result);
        assert!(md.contains("| LAZ |") && md.contains("| LAS |"), "{md}");
        println!("{md}");
        let json = crate::json::written_in(parent.path(), &result, crate::json::write_campaign);
        assert_eq!(json["campaign"]["points"], 200_000);
        assert_eq!(json["campaign"]["builds"][1]["input"], "las");
        let ceiling = &json["campaign"]["builds"][0]["countingThreads"]["ceilingMpointsPerS"];
        assert!(ceiling.as_f64().is_some_and(|c| c > 0.0), "{ceiling}");
        assert!(json["machine"]["cores"].as_u64().is_some_and(|c| c >= 1));
        // The scratch folder is gone.
        let left: Vec<_> = std::fs::read_dir(parent.path()).expect("dir").collect();
        assert!(left.is_empty(), "{left:?}");
    }

    #[test]
    fn too_few_points_for_the_files_is_an_error_before_anything_is_written() {
        let (parent, options) = scratched(500, 4);
        let error = measure(&options, &mut |_| {}).expect_err("too small");
        assert!(error.to_string().contains("1000 points a file"), "{error}");
        assert_eq!(std::fs::read_dir(parent.path()).expect("dir").count(), 0);
    }
}
