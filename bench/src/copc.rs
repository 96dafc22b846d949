//! `pointfarm bench --copc`: the first frame of a COPC file rendered node by node against
//! decoding the whole file, in a scratch folder removed afterwards:
//! 1. a generated terrain ([`GeneratedSource::terrain`]) built into a store and exported as
//!    one COPC file (the store is then removed: only the file is read from here on);
//! 2. **decoding**: every point of the file read as plain LAZ through [`DatasetSource`] on all
//!    cores, what a reader without the hierarchy pays before its first picture;
//! 3. **first frame**: the file opened ([`open_copc`]: header, hierarchy, the coarsest nodes
//!    for the color ranges) and one full view rendered at the default pixel error from empty
//!    node caches;
//! 4. **fidelity** ([`measure_fidelity`]): that pixel error against 0 in every mode.
//!
//! Before each of 2 and 3 the file's pages are dropped from the OS's page cache
//! (`posix_fadvise(DONTNEED)`, which needs no privilege for a file written and synced), so
//! both read it from the disk.

use std::fs::File;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

use pointfarm_render::copc::open_copc;
use pointfarm_render::cut::{CutOptions, CutRenderer, CutReport, DEFAULT_LOD_ERROR_PX};
use pointfarm_render::gpu::GpuContext;
use pointfarm_render::ingest::DatasetSource;
use pointfarm_render::lod::copc_export::{export_copc, ExportSettings};
use pointfarm_render::lod::{GeneratedSource, LodDataset};
use pointfarm_render::raster::{Frame, FrameSettings, Renderer};
use serde::Serialize;

use crate::campaign::points_read;
use crate::cuts::fidelity::measure_fidelity;
use crate::cuts::{build_and_open, full_view, FidelityResult};
use crate::scratch::{progress_log, scratch_dir};
use crate::BenchError;

/// Points of `--copc` given bare.
pub const COPC_POINTS: u64 = 100_000_000;
/// Points of `--copc` given bare with `--quick`.
pub const COPC_QUICK_POINTS: u64 = 10_000_000;

/// What to generate and measure.
#[derive(Debug, Clone)]
pub struct CopcOptions {
    pub points: u64,
    pub width: u32,
    pub height: u32,
    pub seed: u64,
    /// The pixel errors whose first frames are measured, each from empty caches; the
    /// fidelity is that of the first.
    pub lod_errors: Vec<f64>,
    /// The node caches' memory budget of the first frames and of the fidelity renders.
    pub memory_budget_bytes: u64,
    /// Where the scratch folder is made (the system's temporary folder by default).
    pub scratch_parent: Option<PathBuf>,
}

impl CopcOptions {
    /// The terrain of the cut benchmarks (same seed) within their memory budget.
    pub fn new(points: u64, width: u32, height: u32) -> Self {
        Self {
            points,
            width,
            height,
            seed: 11,
            lod_errors: vec![DEFAULT_LOD_ERROR_PX],
            memory_budget_bytes: crate::cuts::TURNTABLE_MEMORY_BUDGET,
            scratch_parent: None,
        }
    }
}

/// What `--copc` measured.
#[derive(Debug, Clone, Serialize)]
#[serde(rename_all = "camelCase")]
pub struct CopcResult {
    pub points: u64,
    pub width: u32,
    pub height: u32,
    pub store_build_s: f64,
    pub export_s: f64,
    pub file_bytes: u64,
    /// Nodes of the file's hierarchy, and its hierarchy pages.
    pub nodes: usize,
    pub pages: usize,
    /// Every point decoded as plain LAZ, on all cores.
    pub decode_s: f64,
    pub decode_mpoints_per_s: f64,
    /// Opening the file (header, hierarchy, the coarsest nodes for the color ranges), and
    /// the chunks that read for the color ranges.
    pub open_ms: f64,
    pub sample_bytes: u64,
    pub first_frames: Vec<FirstFrame>,
    pub fidelity: FidelityResult,
}

/// The first frame at one pixel error, from opening the file to the image.
#[derive(Debug, Clone, Serialize)]
#[serde(rename_all = "camelCase")]
pub struct FirstFrame {
    pub lod_error: f64,
    pub ms: f64,
    pub nodes: u64,
    pub points: u64,
    /// Bytes of chunks the frame read (the color ranges' besides).
    pub bytes_read: u64,
    /// Decoding the whole file over this first frame.
    pub speedup: f64,
}

/// Runs `--copc`, removing every file afterwards.
pub fn measure(
    gpu: &Arc<GpuContext>,
    options: &CopcOptions,
    progress: &mut dyn FnMut(&str),
) -> Result<CopcResult, BenchError> {
    let mut log = progress_log("copc", progress);
    let scratch = scratch_dir(options.scratch_parent.as_deref(), "copc")?;
    let dir = scratch.path();
    let path = dir.join("terrain.copc.laz");
    let (store_build_s, export_s) = write_copc(options, dir, &path, &mut log)?;
    let file_bytes = std::fs::metadata(&path)
        .map_err(|e| write_error(&path, e))?
        .len();

    drop_page_cache(&path)?;
    let started = Instant::now();
    let source = DatasetSource::open(std::slice::from_ref(&path))?;
    let decoded = points_read(&source)?;
    let decode_s = started.elapsed().as_secs_f64();
    log(format!(
        "copc: {decoded} points decoded whole in {decode_s:.2} s"
    ));

    let mut first_frames = Vec::with_capacity(options.lod_errors.len());
    let mut opened = None;
    for &lod_error in &options.lod_errors {
        drop_page_cache(&path)?;
        let started = Instant::now();
        let copc = open_copc(&path).map_err(|e| BenchError::Copc(e.to_string()))?;
        let open_ms = started.elapsed().as_secs_f64() * 1e3;
        let dataset = &copc.dataset;
        let (_, report, settings) = render_full_view(gpu, dataset, options, lod_error)?;
        let ms = started.elapsed().as_secs_f64() * 1e3;
        log(format!(
            "copc: first frame at {lod_error} px in {ms:.0} ms (open {open_ms:.0} ms), {} of {} points",
            report.counts.points_rendered,
            dataset.point_count()
        ));
        first_frames.push(FirstFrame {
            lod_error,
            ms,
            nodes: report.counts.nodes,
            points: report.counts.points_rendered,
            bytes_read: report.counts.bytes_read,
            speedup: decode_s * 1e3 / ms,
        });
        opened.get_or_insert((copc, open_ms, settings));
    }
    let Some((copc, open_ms, settings)) = opened else {
        return Err(BenchError::NoFrames);
    };
    let dataset = &copc.dataset;
    let fidelity = measure_fidelity(
        gpu,
        "copc-terrain",
        dataset,
        &settings,
        first_frames[0].lod_error,
        options.memory_budget_bytes,
    )?;
    Ok(CopcResult {
        points: dataset.point_count(),
        width: options.width,
        height: options.height,
        store_build_s,
        export_s,
        file_bytes,
        nodes: copc.nodes,
        pages: copc.pages,
        decode_s,
        decode_mpoints_per_s: decoded as f64 / decode_s / 1e6,
        open_ms,
        sample_bytes: copc.sample_bytes,
        first_frames,
        fidelity,
    })
}

/// Renders `dataset`'s full view at `lod_error` from empty node caches, within the options'
/// memory budget: the frame, what its cut drew, and the view.
pub(crate) fn render_full_view(
    gpu: &Arc<GpuContext>,
    dataset: &LodDataset,
    options: &CopcOptions,
    lod_error: f64,
) -> Result<(Frame, CutReport, FrameSettings), BenchError> {
    let settings = full_view(&dataset.bounds(), options.width, options.height);
    let mut renderer = Renderer::new(Arc::clone(gpu));
    let cut_options = CutOptions {
        lod_error,
        memory_budget_bytes: options.memory_budget_bytes,
        gpu_budget_bytes: None,
    };
    let mut cut = CutRenderer::new(&renderer, dataset, cut_options)?;
    let (frame, report) = cut.render_rgb(&mut renderer, dataset, &settings)?;
    Ok((frame, report, settings))
}

/// Builds the terrain's store in `dir` and exports it to `path`, then removes the store;
/// returns the build's and the export's seconds.
pub(crate) fn write_copc(
    options: &CopcOptions,
    dir: &Path,
    path: &Path,
    log: &mut dyn FnMut(String),
) -> Result<(f64, f64), BenchError> {
    let source = GeneratedSource::terrain(options.points, options.seed);
    let store_dir = dir.join("store");
    let store = build_and_open("terrain", &source, &store_dir)?;
    log(format!(
        "copc: {} points built in {:.1} s, {} nodes",
        store.build.points, store.build.build_s, store.build.nodes
    ));
    let hierarchy = store.dataset.hierarchy();
    let started = Instant::now();
    export_copc(
        hierarchy,
        &**store.dataset.records(),
        &ExportSettings::fixed(&hierarchy.cube),
        path,
        &mut |_| {},
    )
    .map_err(|e| BenchError::Copc(e.to_string()))?;
    let export_s = started.elapsed().as_secs_f64();
    log(format!("copc: exported in {export_s:.1} s"));
    let build_s = store.build.build_s;
    drop(store);
    let _ = std::fs::remove_dir_all(&store_dir);
    Ok((build_s, export_s))
}

/// Drops `path`'s pages from the OS's page cache, so that the next read comes from the disk.
pub(crate) fn drop_page_cache(path: &Path) -> Result<(), BenchError> {
    let file = File::open(path).map_err(|e| write_error(path, e))?;
    rustix::fs::fadvise(&file, 0, None, rustix::fs::Advice::DontNeed)
        .map_err(|e| write_error(path, e.into()))
}

pub(crate) fn write_error(path: &Path, source: std::io::Error) -> BenchError {
    BenchError::Write {
        path: path.to_path_buf(),
        source,
    }
}

/// The result as markdown tables.
pub fn markdown(r: &CopcResult) -> String {
    let mut md = format!(
        "{} points of terrain, one COPC file of {:.1} MiB and {} nodes ({} hierarchy pages); \
         decoded whole as LAZ in {:.2} s ({:.2} M points/s); opened in {:.0} ms, reading \
         {:.1} MiB of coarse nodes for the color ranges.\n\n\
         | pixel error | first frame ({}x{}, cold) | decoding whole / first frame | nodes | points drawn | chunks read |\n\
         |---:|---:|---:|---:|---:|---:|\n",
        r.points,
        mib(r.file_bytes),
        r.nodes,
        r.pages,
        r.decode_s,
        r.decode_mpoints_per_s,
        r.open_ms,
        mib(r.sample_bytes),
        r.width,
        r.height,
    );
    for f in &r.first_frames {
        md.push_str(&format!(
            "| {} px | {:.2} s | {:.1}x | {} | {} ({:.1}%) | {:.1} MiB |\n",
            f.lod_error,
            f.ms / 1e3,
            f.speedup,
            f.nodes,
            f.points,
            f.points as f64 / r.points.max(1) as f64 * 100.0,
            mib(f.bytes_read),
        ));
    }
    let fidelity: Vec<String> = r
        .fidelity
        .modes
        .iter()
        .map(|m| format!("{} {:.2}%", m.mode, m.close_share * 100.0))
        .collect();
    md.push_str(&format!(
        "\nFidelity at {} px against 0: {}.\n",
        r.fidelity.lod_error,
        fidelity.join(", ")
    ));
    md
}

pub(crate) fn mib(bytes: u64) -> f64 {
    bytes as f64 / (1u64 << 20) as f64
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cuts::fidelity::{mode_name, FIDELITY_MODES};
    use pointfarm_render::testing::gpu;

    #[test]
    fn a_small_copc_file_is_measured_and_cleaned_up() {
        let parent = tempfile::tempdir().expect("tempdir");
        let options = CopcOptions {
            points: 300_000,
            width: 160,
            height: 90,
            seed: 7,
            lod_errors: vec![DEFAULT_LOD_ERROR_PX, 4.0],
            memory_budget_bytes: 256 << 20,
            scratch_parent: Some(parent.path().to_path_buf()),
        };
        let result = measure(&gpu(), &options, &mut |_| {}).expect("measured");
        assert_eq!(result.points, 300_000);
        assert!(result.nodes > 1, "{result:?}");
        let [fine, coarse] = &result.first_frames[..] else {
            panic!("a first frame per pixel error: {result:?}");
        };
        assert!(
            fine.points > 0 && fine.points <= result.points,
            "{result:?}"
        );
        assert!(
            coarse.points < fine.points && coarse.bytes_read < fine.bytes_read,
            "a coarser error reads and draws less: {result:?}"
        );
        assert!(result.decode_s > 0.0 && fine.ms > 0.0);
        for mode in FIDELITY_MODES {
            let name = mode_name(mode);
            assert!(
                result.fidelity.modes.iter().any(|m| m.mode == name),
                "{name} measured: {result:?}"
            );
        }
        assert!(markdown(&result).contains("300000 points"));
        let left: Vec<_> = std::fs::read_dir(parent.path()).expect("list").collect();
        assert!(left.is_empty(), "the scratch folder is removed: {left:?}");
    }
}
