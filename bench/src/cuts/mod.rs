//! The figures of rendering level-of-detail stores cut by cut (`pointfarm bench --cuts`, and
//! the turntable of `--campaign --cut-frames`), in a scratch folder removed afterwards:
//! 1. **scaling**: the full view of two terrains of one density ([`GeneratedSource::terrain`],
//!    10 points a square metre), a small and a large one, at one image size and the default
//!    pixel error, warm caches: frame time follows pixels, not points;
//! 2. **turntables**: of the large terrain from a cold cache within a small memory budget
//!    ([`OUT_OF_CORE_BUDGET`]), and within the cuts' budget, with the process's peak resident
//!    memory;
//! 3. **fidelity** ([`fidelity`]): the default pixel error against 0 on the real scans, the
//!    small terrain and the uniform cube, per compute mode;
//! 4. **resident against cut**: the uniform cube rendered resident (uploaded whole) and as a
//!    warm cut at the default error and at 0, in one run.
//!
//! Stores are built straight from the generators ([`build_lod`] on every core, no files), or
//! from the real scans' files. Frame times are wall times of one render call (the image read
//! back), the median of [`WARM_FRAMES`] after one unmeasured frame.

pub mod fidelity;
pub mod markdown;
pub mod turntable;

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

use pointfarm_render::camera::Camera;
use pointfarm_render::cloud::{pack_rgba8, ColorSource, PointCloud, WorldBounds};
use pointfarm_render::cut::{CutOptions, CutRenderer, LodDataset, DEFAULT_LOD_ERROR_PX};
use pointfarm_render::gpu::GpuContext;
use pointfarm_render::ingest::DatasetSource;
use pointfarm_render::lod::{build_lod, GeneratedSource, LodBuildOptions, PointSource};
use pointfarm_render::raster::{FrameSettings, Renderer};
use serde::Serialize;

use crate::scratch::{progress_log, scratch_dir};
use crate::stats::median;
use crate::store::{create_store, BenchStore};
use crate::{BenchError, REAL_SCANS};
pub use fidelity::{FidelityResult, FIDELITY_TOLERANCE};
pub use turntable::{
    render_turntable, TurntableOptions, TurntableResult, TURNTABLE_FRAMES, TURNTABLE_MEMORY_BUDGET,
};

/// The memory budget of the out-of-core turntable.
pub const OUT_OF_CORE_BUDGET: u64 = 512 << 20;
/// Measured frames of a warm cache.
pub const WARM_FRAMES: usize = 5;

/// What `--cuts` measures.
#[derive(Debug, Clone)]
pub struct CutsOptions {
    pub width: u32,
    pub height: u32,
    /// Points of the small and the large terrain.
    pub small_points: u64,
    pub large_points: u64,
    /// Points of the uniform cube (fidelity, resident against cut).
    pub cube_points: u64,
    /// Frames of the out-of-core turntable (none: not rendered).
    pub out_of_core_frames: usize,
    /// Memory budget of every cut but the out-of-core turntable's.
    pub memory_budget_bytes: u64,
    /// Where the real scans are looked for.
    pub data_dir: PathBuf,
    pub scratch_parent: Option<PathBuf>,
    pub seed: u64,
}

impl CutsOptions {
    /// 10M and 100M points of terrain, a 10M cube, 12 frames out of core.
    pub fn full(width: u32, height: u32, data_dir: PathBuf) -> Self {
        Self {
            width,
            height,
            small_points: 10_000_000,
            large_points: 100_000_000,
            cube_points: 10_000_000,
            out_of_core_frames: TURNTABLE_FRAMES,
            memory_budget_bytes: TURNTABLE_MEMORY_BUDGET,
            data_dir,
            scratch_parent: None,
            seed: 11,
        }
    }

    /// 2M and 20M points of terrain, a 2M cube, 6 frames out of core.
    pub fn quick(width: u32, height: u32, data_dir: PathBuf) -> Self {
        Self {
            small_points: 2_000_000,
            large_points: 20_000_000,
            cube_points: 2_000_000,
            out_of_core_frames: 6,
            ..Self::full(width, height, data_dir)
        }
    }
}

/// 10000000 as `10m`, 200000 as `200k`.
fn short_count(points: u64) -> String {
    if points >= 1_000_000 && points.is_multiple_of(1_000_000) {
        format!("{}m", points / 1_000_000)
    } else if points >= 1_000 {
        format!("{}k", points / 1_000)
    } else {
        points.to_string()
    }
}

/// A store's build.
#[derive(Debug, Clone, Serialize)]
pub struct StoreBuild {
    pub name: String,
    pub points: u64,
    pub build_s: f64,
    pub nodes: usize,
}

/// The full view of one terrain at the default pixel error, warm.
#[derive(Debug, Clone, Serialize)]
pub struct ViewFigure {
    pub workload: String,
    pub points: u64,
    pub cut_nodes: u64,
    pub cut_points: u64,
    pub limited_by_budget: bool,
    /// The cold frame (first, empty caches), then the warm frames' median.
    pub cold_ms: f64,
    pub warm_ms: f64,
}

/// The uniform cube resident and as cuts, warm, in one run.
#[derive(Debug, Clone, Serialize)]
pub struct ResidentVsCut {
    pub points: u64,
    pub resident_ms: f64,
    pub cut_default: ViewFigure,
    pub cut_full: ViewFigure,
}

impl ResidentVsCut {
    /// The cut at the default error over resident.
    pub fn default_over_resident(&self) -> f64 {
        self.cut_default.warm_ms / self.resident_ms
    }
}

/// Everything `--cuts` measured.
#[derive(Debug, Clone, Serialize)]
pub struct CutsResult {
    pub width: u32,
    pub height: u32,
    pub lod_error: f64,
    pub memory_budget_bytes: u64,
    pub builds: Vec<StoreBuild>,
    /// The small and the large terrain's full views.
    pub scaling: [ViewFigure; 2],
    /// The large terrain's turntables from a cold cache: within [`OUT_OF_CORE_BUDGET`], and
    /// within the memory budget of the other cuts.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub out_of_core: Option<TurntableResult>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub turntable: Option<TurntableResult>,
    pub fidelity: Vec<FidelityResult>,
    pub resident_vs_cut: ResidentVsCut,
    /// The real scans not found.
    pub missing_scans: Vec<String>,
}

impl CutsResult {
    /// The large terrain's warm frame over the small one's.
    pub fn scaling_ratio(&self) -> f64 {
        self.scaling[1].warm_ms / self.scaling[0].warm_ms
    }
}

/// A built store, open for rendering; its folder lives as long as the scratch folder.
pub struct OpenStore {
    _store: BenchStore,
    pub dataset: LodDataset,
    pub build: StoreBuild,
}

/// Builds `source` into a fresh store in `dir` and opens it.
pub fn build_and_open(
    name: &str,
    source: &dyn PointSource,
    dir: &Path,
) -> Result<OpenStore, BenchError> {
    let store = create_store(&dir.join("store"))?;
    let started = Instant::now();
    let report = build_lod(
        source,
        &store.store,
        &LodBuildOptions::new(dir.join("spill")),
    )?;
    let build_s = started.elapsed().as_secs_f64();
    let _ = std::fs::remove_dir_all(dir.join("spill"));
    let dataset = LodDataset::open(store.store.clone(), source.bounds())?;
    Ok(OpenStore {
        _store: store,
        dataset,
        build: StoreBuild {
            name: name.to_string(),
            points: source.point_count(),
            build_s,
            nodes: report.hierarchy.nodes().len(),
        },
    })
}

/// The full view of `bounds` in the basic mode at `width` x `height`.
pub fn full_view(bounds: &WorldBounds, width: u32, height: u32) -> FrameSettings {
    let camera = Camera::auto(bounds, f64::from(width) / f64::from(height.max(1)));
    FrameSettings::new(width, height, camera)
}

/// One cold frame of a new cache, then the median of [`WARM_FRAMES`] after one unmeasured.
pub fn warm_view(
    gpu: &Arc<GpuContext>,
    workload: &str,
    dataset: &LodDataset,
    settings: &FrameSettings,
    options: CutOptions,
) -> Result<ViewFigure, BenchError> {
    let mut renderer = Renderer::new(Arc::clone(gpu));
    let mut cut = CutRenderer::new(&renderer, dataset, options)?;
    let mut frame = || -> Result<_, BenchError> {
        let started = Instant::now();
        let (_, report) = cut.render_rgb(&mut renderer, dataset, settings)?;
        Ok((started.elapsed().as_secs_f64() * 1e3, report))
    };
    let (cold_ms, report) = frame()?;
    frame()?;
    let mut warm = Vec::with_capacity(WARM_FRAMES);
    for _ in 0..WARM_FRAMES {
        warm.push(frame()?.0);
    }
    Ok(ViewFigure {
        workload: workload.to_string(),
        points: dataset.point_count(),
        cut_nodes: report.counts.nodes,
        cut_points: report.counts.points_rendered,
        limited_by_budget: report.counts.limited_by_budget,
        cold_ms,
        warm_ms: median(warm),
    })
}

/// The median wall time of a resident frame of `cloud`, as [`warm_view`] measures a cut.
fn resident_frame_ms(
    gpu: &Arc<GpuContext>,
    cloud: &PointCloud,
    settings: &FrameSettings,
) -> Result<f64, BenchError> {
    let mut renderer = Renderer::new(Arc::clone(gpu));
    let resident = renderer.upload(cloud)?;
    renderer.render(&resident, settings)?;
    let mut times = Vec::with_capacity(WARM_FRAMES);
    for _ in 0..WARM_FRAMES {
        let started = Instant::now();
        renderer.render(&resident, settings)?;
        times.push(started.elapsed().as_secs_f64() * 1e3);
    }
    Ok(median(times))
}

/// A generated source read whole into a cloud relative to its bounds' centre (the origin its
/// store renders at), colored from its 16-bit RGB as the cut colors it.
pub fn resident_cloud(source: &GeneratedSource) -> Result<PointCloud, BenchError> {
    let bounds = source.bounds();
    let origin = bounds.center();
    let n = source.point_count() as usize;
    let mut cloud = PointCloud {
        origin,
        positions: Vec::with_capacity(n),
        colors: Vec::with_capacity(n),
        intensity: Vec::with_capacity(n),
        classification: Vec::with_capacity(n),
        return_number: Vec::with_capacity(n),
        bounds,
        color_source: ColorSource::Rgb16,
    };
    source.for_each_batch(&mut |batch| {
        cloud
            .positions
            .extend(batch.positions.iter().map(|p| (*p - origin).as_vec3()));
        if let Some(rgb) = batch.rgb {
            cloud.colors.extend(rgb.iter().map(|c| {
                let [r, g, b] = c.map(|v| (v >> 8) as u8);
                pack_rgba8(r, g, b)
            }));
        }
        cloud.intensity.extend_from_slice(batch.intensity);
        cloud.classification.extend_from_slice(batch.classification);
        cloud.return_number.extend_from_slice(batch.return_number);
        Ok(())
    })?;
    Ok(cloud)
}

/// Runs every figure of `--cuts`, removing every file afterwards.
pub fn measure(
    gpu: &Arc<GpuContext>,
    options: &CutsOptions,
    progress: &mut dyn FnMut(&str),
) -> Result<CutsResult, BenchError> {
    let mut log = progress_log("cuts", progress);
    let scratch = scratch_dir(options.scratch_parent.as_deref(), "cuts")?;
    let dir = scratch.path();
    let (w, h) = (options.width, options.height);
    let cut_options = |lod_error| CutOptions {
        lod_error,
        memory_budget_bytes: options.memory_budget_bytes,
        gpu_budget_bytes: None,
    };
    let default_error = cut_options(DEFAULT_LOD_ERROR_PX);
    let mut builds = Vec::new();
    let mut built = |name: &str, source: &dyn PointSource, log: &mut dyn FnMut(String)| {
        let store = build_and_open(name, source, &dir.join(name))?;
        log(format!(
            "cuts: {name}: {} points built in {:.1} s, {} nodes",
            store.build.points, store.build.build_s, store.build.nodes
        ));
        builds.push(store.build.clone());
        Ok::<_, BenchError>(store)
    };

    // The large terrain first, so that the out-of-core turntable starts from a small process.
    let large_name = format!("terrain-{}", short_count(options.large_points));
    let large_source = GeneratedSource::terrain(options.large_points, options.seed);
    let large = built(&large_name, &large_source, &mut log)?;
    let mut turntable_within = |budget: u64, label: &str| {
        if options.out_of_core_frames == 0 {
            return Ok::<_, BenchError>(None);
        }
        let turntable = TurntableOptions {
            memory_budget_bytes: budget,
            width: w,
            height: h,
            ..TurntableOptions::new(options.out_of_core_frames)
        };
        let result = render_turntable(gpu, &large.dataset, &turntable, &mut |l| {
            log(format!("cuts: {label}: {l}"))
        })?;
        log(format!(
            "cuts: {label}: first frame {:.0} ms, following median {:.0} ms, peak RSS {} MiB",
            result.first_ms,
            result.following_median_ms,
            result.peak_rss_bytes >> 20
        ));
        Ok(Some(result))
    };
    let out_of_core = turntable_within(OUT_OF_CORE_BUDGET, "out of core")?;
    let turntable = turntable_within(options.memory_budget_bytes, "turntable")?;
    let large_view = warm_view(
        gpu,
        &large_name,
        &large.dataset,
        &full_view(&large.dataset.bounds(), w, h),
        default_error,
    )?;
    drop(large);
    let _ = std::fs::remove_dir_all(dir.join(&large_name));

    let small_name = format!("terrain-{}", short_count(options.small_points));
    let small = built(
        &small_name,
        &GeneratedSource::terrain(options.small_points, options.seed),
        &mut log,
    )?;
    let small_settings = full_view(&small.dataset.bounds(), w, h);
    let small_view = warm_view(
        gpu,
        &small_name,
        &small.dataset,
        &small_settings,
        default_error,
    )?;
    log(format!(
        "cuts: full views: {small_name} {:.0} ms ({} points), {large_name} {:.0} ms ({} points)",
        small_view.warm_ms, small_view.cut_points, large_view.warm_ms, large_view.cut_points
    ));
    let mut fidelity = Vec::new();
    let mut fidelity_of = |name: &str, dataset: &LodDataset, log: &mut dyn FnMut(String)| {
        let settings = full_view(&dataset.bounds(), w, h);
        let result = fidelity::measure_fidelity(
            gpu,
            name,
            dataset,
            &settings,
            DEFAULT_LOD_ERROR_PX,
            options.memory_budget_bytes,
        )?;
        log(format!(
            "cuts: fidelity of {name}: {}",
            result
                .modes
                .iter()
                .map(|m| format!(
                    "{} {:.2}% ({:.0} ms warm)",
                    m.mode,
                    m.close_share * 100.0,
                    m.cut_warm_ms
                ))
                .collect::<Vec<_>>()
                .join(", ")
        ));
        fidelity.push(result);
        Ok::<_, BenchError>(())
    };
    fidelity_of(&small_name, &small.dataset, &mut log)?;
    drop(small);

    let mut missing_scans = Vec::new();
    for scan in REAL_SCANS {
        let path = options.data_dir.join(scan);
        if !path.exists() {
            missing_scans.push(scan.to_string());
            continue;
        }
        let source = DatasetSource::open(&[path])?;
        let store = built(scan, &source, &mut log)?;
        fidelity_of(scan, &store.dataset, &mut log)?;
    }

    let cube_name = format!("uniform-{}", short_count(options.cube_points));
    let cube_source = GeneratedSource::cube(options.cube_points, options.seed);
    let cube = built(&cube_name, &cube_source, &mut log)?;
    fidelity_of(&cube_name, &cube.dataset, &mut log)?;
    let settings = full_view(&cube.dataset.bounds(), w, h);
    let cloud = resident_cloud(&cube_source)?;
    let resident_ms = resident_frame_ms(gpu, &cloud, &settings)?;
    drop(cloud);
    let cut_default = warm_view(gpu, &cube_name, &cube.dataset, &settings, default_error)?;
    let cut_full = warm_view(gpu, &cube_name, &cube.dataset, &settings, cut_options(0.0))?;
    log(format!(
        "cuts: {cube_name}: resident {resident_ms:.0} ms, cut at {DEFAULT_LOD_ERROR_PX} px {:.0} \
         ms, cut at 0 {:.0} ms",
        cut_default.warm_ms, cut_full.warm_ms
    ));
    drop(cube);
    drop(scratch);
    Ok(CutsResult {
        width: w,
        height: h,
        lod_error: DEFAULT_LOD_ERROR_PX,
        memory_budget_bytes: options.memory_budget_bytes,
        builds,
        scaling: [small_view, large_view],
        out_of_core,
        turntable,
        fidelity,
        resident_vs_cut: ResidentVsCut {
            points: options.cube_points,
            resident_ms,
            cut_default,
            cut_full,
        },
        missing_scans,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use pointfarm_render::testing::gpu;

    #[test]
    fn tiny_cuts_keep_their_invariants_and_leave_no_files() {
        let parent = tempfile::tempdir().expect("tempdir");
        let options = CutsOptions {
            small_points: 100_000,
            large_points: 300_000,
            cube_points: 100_000,
            out_of_core_frames: 3,
            data_dir: parent.path().join("no-scans"),
            scratch_parent: Some(parent.path().to_path_buf()),
            ..CutsOptions::quick(160, 120, PathBuf::new())
        };
        let mut lines = Vec::new();
        let r = measure(&gpu(), &options, &mut |l| lines.push(l.to_string())).expect("measured");
        assert_eq!(r.builds.len(), 3, "{:?}", r.builds);
        assert_eq!(r.missing_scans.len(), REAL_SCANS.len());
        let [small, large] = &r.scaling;
        assert_eq!((small.points, large.points), (100_000, 300_000));
        for v in [small, large, &r.resident_vs_cut.cut_default] {
            assert!(v.cut_nodes >= 1 && v.cut_points >= 1, "{v:?}");
            assert!(v.cut_points <= v.points, "{v:?}");
            assert!(v.warm_ms > 0.0 && v.cold_ms > 0.0, "{v:?}");
        }
        assert!(r.scaling_ratio() > 0.0);

        let t = r.out_of_core.as_ref().expect("out of core");
        assert_eq!(t.frames.len(), 3);
        assert_eq!(t.host_budget_bytes + t.gpu_budget_bytes, OUT_OF_CORE_BUDGET);
        let first = &t.frames[0].cut.counts;
        assert_eq!(first.gpu_hits, 0, "a cold cache: {first:?}");
        assert!(first.nodes_read >= 1 && first.bytes_read > 0, "{first:?}");
        for f in &t.frames {
            let c = &f.cut.counts;
            assert_eq!(c.gpu_hits + c.gpu_uploaded, c.nodes, "{c:?}");
            assert_eq!(c.host_hits + c.nodes_read, c.gpu_uploaded, "{c:?}");
            assert!(c.points_rendered <= c.points_total && c.points_total == 300_000);
            let names: Vec<_> = f.stages.iter().map(|s| s.stage).collect();
            assert_eq!(&names[..2], ["select", "load"], "{names:?}");
            assert!(f.wall_ms > 0.0);
        }
        assert_eq!(t.first_ms, t.frames[0].wall_ms);
        assert!(t.following_median_ms > 0.0 && t.following_max_ms >= t.following_median_ms);
        assert!(t.peak_rss_bytes > 0 && t.bytes_read() > 0);
        let within = r.turntable.as_ref().expect("turntable within the budget");
        assert_eq!(within.frames.len(), 3);
        assert_eq!(
            within.host_budget_bytes + within.gpu_budget_bytes,
            options.memory_budget_bytes
        );

        let names: Vec<_> = r.fidelity.iter().map(|f| f.workload.as_str()).collect();
        assert_eq!(names, ["terrain-100k", "uniform-100k"]);
        for f in &r.fidelity {
            assert_eq!(f.modes.len(), fidelity::FIDELITY_MODES.len() + 1);
            assert!(
                f.cut_points <= f.full_points && f.full_points <= f.points,
                "{f:?}"
            );
            for m in &f.modes {
                assert!(m.covered_pixels > 0, "{f:?}");
                assert!((0.0..=1.0).contains(&m.close_share), "{f:?}");
            }
        }
        let rc = &r.resident_vs_cut;
        assert!(rc.resident_ms > 0.0 && rc.default_over_resident() > 0.0);
        assert!(rc.cut_full.cut_points >= rc.cut_default.cut_points);

        let md = markdown::cuts_tables(&r);
        for needle in [
            "| terrain-300k |",
            "| uniform-100k |",
            "Out of core",
            "Within the memory budget",
            "| resident |",
        ] {
            assert!(md.contains(needle), "{needle}: {md}");
        }
        println!("{md}");
        let json = crate::json::written_in(parent.path(), &r, crate::json::write_cuts);
        assert_eq!(json["cuts"]["scaling"][1]["points"], 300_000);
        assert_eq!(
            json["cuts"]["outOfCore"]["frames"][0]["stages"][0]["stage"],
            "select"
        );
        let left: Vec<_> = std::fs::read_dir(parent.path()).expect("dir").collect();
        assert!(left.is_empty(), "{left:?}");
    }
}
