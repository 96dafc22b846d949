//! The benchmark harness behind `pointfarm bench`: workloads, and a runner that renders each
//! with every method on the same resident buffers, the same camera and the same image size.
//!
//! Methods: the fixed-function `PointList` baseline ([`PointListBaseline`]), the compute
//! rasterizer's basic mode ([`Renderer`]) and its other modes ([`ComputeMode`]: high quality,
//! the 32-bit path, fill with EDL or Pintus shading).
//! A frame's time is the GPU work that produces its image: every pass of the frame (clear,
//! point passes, resolve, shading). Upload, readback and other host-side stages are reported
//! per stage but left out of the frame time, since they do not depend on the method. Every
//! figure is the median over measured frames, after warm-up rounds. Each round renders frames
//! with every method in turn, so that slow drifts of the machine's speed reach every method
//! alike; each method's measured frame follows at least [`WARM_IN_A_ROW`] of its own
//! unmeasured frames ([`SETTLE_AFTER_BASELINE`] for the first compute method after the
//! baseline on a software adapter), as in a job's run of frames. Each compute method has a
//! renderer of its own, so that no method starts its frame from the state another left
//! (`Methods`).
//!
//! Series: uniform cubes of 1M to 30M points (frame time against points in view, with a
//! least-squares line per method) and the k-plane cuboid (against overdraw); `huge` adds a
//! 100M-point cube generated and uploaded chunk by chunk, with the host's peak memory.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use glam::{DVec3, Vec3};
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::Serialize;

mod ingest;

pub use ingest::{generated_workload, IngestResult};

use crate::cache::CacheError;
use crate::camera::{Camera, Projection};
use crate::cloud::{pack_rgba8, PointCloud};
use crate::gpu::GpuContext;
use crate::ingest::{load_point_cloud, IngestError};
use crate::raster::{
    AtomicsMode, FillSettings, FrameSettings, GpuPointCloud, PointListBaseline, Quality,
    RenderError, Renderer, Shading, Stage, StageTimings, BATCH_POINTS,
};

/// Points of the uniform cloud that the targets are stated for.
pub const UNIFORM_POINTS: usize = 10_000_000;
/// The uniform clouds of the scaling series (all in view); the headline cloud is one of them.
pub const UNIFORM_SERIES: [usize; 4] = [1_000_000, 3_000_000, UNIFORM_POINTS, 30_000_000];
/// Points of the opt-in huge workload unless the run names another count.
pub const HUGE_POINTS: usize = 100_000_000;
/// Plane counts of the overdraw cuboid.
pub const CUBOID_PLANES: [usize; 4] = [1, 4, 16, 64];
/// The real scans measured when present in the data directory.
pub const REAL_SCANS: [&str; 2] = ["lone-star.laz", "autzen_trim.laz"];
/// Name of the workload whose speed-up is the headline figure.
pub const HEADLINE_WORKLOAD: &str = "uniform-10m";

/// What to run.
#[derive(Debug, Clone)]
pub struct BenchOptions {
    pub width: u32,
    pub height: u32,
    /// Frames rendered and discarded before measuring, per method and workload.
    pub warmup_frames: usize,
    /// Frames measured per method and workload.
    pub frames: usize,
    /// Points per side of a cuboid plane.
    pub cuboid_side: usize,
    /// Where the real scans are looked for.
    pub data_dir: PathBuf,
    /// Time stages with host clocks even where the adapter has timestamp queries.
    pub host_clocks: bool,
    /// Compute modes measured besides the basic mode.
    pub modes: Vec<ComputeMode>,
    /// Only these workloads (all when empty); a name also selects its other views
    /// (`uniform-10m` selects `uniform-10m-corner` and `uniform-10m-partial`).
    pub only: Vec<String>,
    /// Also render a cube of this many points ([`HUGE_POINTS`] by default), generated and
    /// uploaded chunk by chunk, with its host memory peak.
    pub huge: Option<usize>,
    /// Points of the cube written as LAZ for the ingest figures (none: only the real scans).
    pub ingest_points: Option<usize>,
    /// Measured loads per file and way (decode on all cores, on one, from the cache).
    pub ingest_repeats: usize,
}

/// A mode of the compute rasterizer measured besides the basic mode, as a change to the
/// basic mode's settings.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ComputeMode {
    /// Schütz & Wimmer's high-quality mode with its default 1% depth band.
    HighQuality,
    /// The basic mode on the 32-bit atomics path (depth pass, then colour pass), the fallback
    /// for adapters without 64-bit atomics: the same image by another route.
    BasicAtomic32,
    /// The basic mode, then Pintus et al.'s visibility and filling (default kernel) and
    /// Eye-Dome Lighting (default strength and radius).
    FillEdl,
    /// The basic mode, then visibility, filling and Pintus et al.'s multi-level shading.
    FillPintus,
}

impl ComputeMode {
    pub const ALL: [ComputeMode; 4] = [
        ComputeMode::HighQuality,
        ComputeMode::BasicAtomic32,
        ComputeMode::FillEdl,
        ComputeMode::FillPintus,
    ];

    pub fn name(self) -> &'static str {
        match self {
            ComputeMode::HighQuality => "compute-hq",
            ComputeMode::BasicAtomic32 => "compute-basic-32",
            ComputeMode::FillEdl => "compute-fill-edl",
            ComputeMode::FillPintus => "compute-fill-pintus",
        }
    }

    /// The settings of this mode, from the basic mode's.
    pub fn settings(self, basic: &FrameSettings) -> FrameSettings {
        match self {
            ComputeMode::HighQuality => FrameSettings {
                quality: Quality::HIGH,
                ..*basic
            },
            ComputeMode::BasicAtomic32 => FrameSettings {
                atomics: AtomicsMode::Force32,
                ..*basic
            },
            ComputeMode::FillEdl => FrameSettings {
                fill: Some(FillSettings::default()),
                shading: Shading::EDL,
                ..*basic
            },
            ComputeMode::FillPintus => FrameSettings {
                fill: Some(FillSettings::default()),
                shading: Shading::PINTUS,
                ..*basic
            },
        }
    }
}

impl BenchOptions {
    /// The full run: 1024x1024-point cuboid planes (up to 64 Mi points), 1 + 15 rounds.
    pub fn full(width: u32, height: u32, data_dir: PathBuf) -> Self {
        Self {
            width,
            height,
            warmup_frames: 1,
            frames: 15,
            cuboid_side: 1024,
            data_dir,
            host_clocks: false,
            modes: ComputeMode::ALL.to_vec(),
            only: Vec::new(),
            huge: None,
            ingest_points: Some(UNIFORM_POINTS),
            ingest_repeats: 5,
        }
    }

    /// A few minutes on a 2-core software adapter: 512x512-point planes, 1 + 7 rounds.
    pub fn quick(width: u32, height: u32, data_dir: PathBuf) -> Self {
        Self {
            warmup_frames: 1,
            frames: 7,
            cuboid_side: 512,
            ingest_points: Some(2_000_000),
            ingest_repeats: 3,
            ..Self::full(width, height, data_dir)
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum BenchError {
    #[error(transparent)]
    Render(#[from] RenderError),
    #[error(transparent)]
    Ingest(#[from] IngestError),
    #[error("the benchmark needs at least one measured frame")]
    NoFrames,
    #[error("no workload matches --only {0}")]
    NothingSelected(String),
    #[error(transparent)]
    DatasetCache(#[from] CacheError),
    #[error("{0}")]
    CacheMismatch(String),
    #[error("benchmark scratch space: {0}")]
    Scratch(String),
}

/// The adapter the figures were measured on.
#[derive(Debug, Clone, Serialize)]
pub struct AdapterReport {
    pub name: String,
    pub device_type: String,
    pub backend: String,
    pub driver: String,
    pub driver_info: String,
    pub int64_atomics: bool,
    pub gpu_timestamps: bool,
}

impl AdapterReport {
    pub fn of(gpu: &GpuContext) -> Self {
        let info = &gpu.adapter_info;
        Self {
            name: info.name.clone(),
            device_type: format!("{:?}", info.device_type),
            backend: format!("{:?}", info.backend),
            driver: info.driver.clone(),
            driver_info: info.driver_info.clone(),
            int64_atomics: gpu.capabilities.int64_atomics,
            gpu_timestamps: gpu.capabilities.timestamps,
        }
    }
}

/// Median time of one stage over the measured frames.
#[derive(Debug, Clone, Serialize)]
pub struct StageMedian {
    pub stage: &'static str,
    pub ms: f64,
    /// "gpu" (timestamp queries) or "host" (wall clock).
    pub clock: &'static str,
}

/// One method on one workload.
#[derive(Debug, Clone, Serialize)]
pub struct MethodResult {
    /// `pointlist`, `compute-basic` (with the atomics path in `variant`) or another compute
    /// mode's name ([`ComputeMode::name`]).
    pub method: &'static str,
    pub variant: String,
    /// Median over frames of the time that produces the image: the host's culling and every
    /// GPU pass of the frame (rasterize, accumulate, resolve, shade), the passes on the GPU
    /// clock where the adapter has timestamps.
    pub frame_ms: f64,
    /// Median host wall-clock time of a whole frame as a caller sees it, readback included: a
    /// cross-check of `frame_ms` that does not trust the adapter's timestamps.
    pub wall_ms: f64,
    /// Points of the cloud (in view or not) divided by `frame_ms`.
    pub mpoints_per_s: f64,
    pub stages: Vec<StageMedian>,
}

/// One workload: a cloud, a camera, every method.
#[derive(Debug, Clone, Serialize)]
pub struct WorkloadResult {
    pub workload: String,
    pub description: String,
    pub points: usize,
    /// Points that project into the image (CPU count with the frame's camera).
    pub points_in_view: usize,
    pub pointlist: MethodResult,
    /// The basic mode.
    pub compute: MethodResult,
    /// PointList frame time over compute (basic mode) frame time.
    pub speedup_vs_pointlist: f64,
    /// The other compute modes, with their cost relative to the basic mode.
    pub modes: Vec<ModeResult>,
    /// Bytes of GPU buffers per point that hold the cloud.
    pub gpu_bytes_per_point: f64,
    /// The huge workload: the host's memory peak while the cloud was generated and uploaded.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub ingest_memory: Option<IngestMemory>,
    /// Of the pixels covered by either method, the fraction with the same colour in both:
    /// a check that both drew the same thing.
    pub image_agreement: f64,
    /// How the basic mode's last frame culled the cloud's batches.
    pub batches: BatchCounts,
}

/// Batches of a cloud in one frame of the basic mode: all of them, those the host listed as
/// possibly in view (a batch at the view's edge may count once per run of it listed), and
/// those the depth pass then skipped as hidden (occlusion culling).
#[derive(Debug, Clone, Copy, Serialize)]
pub struct BatchCounts {
    pub total: usize,
    pub listed: u32,
    /// Points of the listed entries (the culling's tightness against points in view).
    pub listed_points: u64,
    pub occluded: u32,
}

/// A compute mode other than basic on one workload.
#[derive(Debug, Clone, Serialize)]
pub struct ModeResult {
    #[serde(flatten)]
    pub result: MethodResult,
    /// Frame time over the basic mode's.
    pub cost_vs_basic: f64,
}

/// Host memory while a cloud is generated and uploaded, against the size of its GPU buffers.
#[derive(Debug, Clone, Serialize)]
pub struct IngestMemory {
    /// Peak resident set size of the process during ingest (`VmHWM`, reset before).
    pub peak_host_bytes: u64,
    /// Resident set size just before ingest started.
    pub before_host_bytes: u64,
    pub gpu_bytes: u64,
    /// What the ingest itself held at its peak, `peak_host_bytes - before_host_bytes`, over
    /// `gpu_bytes`. The huge cloud is ingested after the other workloads, whose memory the
    /// process may keep (on lavapipe the GPU data is host memory too, and counts in both).
    pub ingest_over_gpu: f64,
}

/// A least-squares line through frame times of one method against points in view.
#[derive(Debug, Clone, Serialize)]
pub struct ScalingFit {
    pub method: String,
    /// The workloads of the series, in order.
    pub workloads: Vec<String>,
    pub ns_per_point: f64,
    pub intercept_ms: f64,
    /// Coefficient of determination: 1 for perfectly linear growth.
    pub r_squared: f64,
}

#[derive(Debug, Clone, Serialize)]
pub struct SkippedWorkload {
    pub workload: String,
    pub reason: String,
}

/// Everything one run measured.
#[derive(Debug, Clone, Serialize)]
pub struct BenchReport {
    pub adapter: AdapterReport,
    /// Whether stages were timed by host clocks (asked for, or a software adapter).
    pub host_clocks: bool,
    pub width: u32,
    pub height: u32,
    pub warmup_frames: usize,
    pub frames: usize,
    /// Speed-up of the compute path over PointList on [`HEADLINE_WORKLOAD`].
    pub speedup_vs_pointlist: Option<f64>,
    pub workloads: Vec<WorkloadResult>,
    /// Frame time against points in view over the uniform series, per method.
    pub scaling: Vec<ScalingFit>,
    /// Loading datasets: LAZ decoding on all cores and on one, and dataset-cache hits.
    pub ingest: Vec<IngestResult>,
    pub skipped: Vec<SkippedWorkload>,
}

/// The scenes of a run, built one at a time.
enum SceneSpec {
    Uniform(usize),
    Cuboid(usize),
    RealScan(PathBuf),
}

/// Name of the uniform workload of `points` points: `uniform-10m`.
pub fn uniform_workload(points: usize) -> String {
    if points.is_multiple_of(1_000_000) {
        format!("uniform-{}m", points / 1_000_000)
    } else {
        format!("uniform-{points}")
    }
}

impl SceneSpec {
    fn name(&self) -> String {
        match self {
            SceneSpec::Uniform(points) => uniform_workload(*points),
            SceneSpec::Cuboid(planes) => format!("cuboid-k{planes}"),
            SceneSpec::RealScan(path) => path
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default(),
        }
    }

    /// The scene, or `None` for a real scan that is not there.
    fn build(&self, options: &BenchOptions) -> Result<Option<Scene>, BenchError> {
        let aspect = options.width as f64 / options.height as f64;
        Ok(Some(match self {
            SceneSpec::Uniform(points) => uniform_scene(*points, aspect, 1),
            SceneSpec::Cuboid(planes) => cuboid_scene(
                *planes,
                options.cuboid_side,
                options.width,
                options.height,
                2,
            ),
            SceneSpec::RealScan(path) => return real_scene(path, aspect),
        }))
    }
}

/// A cloud and the views of it that are measured.
struct Scene {
    name: String,
    cloud: PointCloud,
    views: Vec<View>,
}

struct View {
    workload: String,
    description: String,
    camera: Camera,
}

/// Runs every workload; `progress` receives one line per step.
pub fn run(
    gpu: Arc<GpuContext>,
    options: &BenchOptions,
    progress: &mut dyn FnMut(&str),
) -> Result<BenchReport, BenchError> {
    if options.frames == 0 {
        return Err(BenchError::NoFrames);
    }
    // A software adapter's timestamps under-report compute passes (lavapipe: BENCHMARKS.md),
    // so it is always timed by host clocks.
    let host_clocks = options.host_clocks || gpu.adapter_info.device_type == wgpu::DeviceType::Cpu;
    let mut methods = Methods::new(&gpu, options.modes.len(), host_clocks);
    // Refuse a bad image size before spending time on a 10M-point cloud.
    let unit_box = crate::cloud::WorldBounds {
        min: DVec3::ZERO,
        max: DVec3::ONE,
    };
    let aspect = options.width as f64 / options.height.max(1) as f64;
    let probe = FrameSettings::new(
        options.width,
        options.height,
        Camera::auto(&unit_box, aspect),
    );
    methods.compute[0].validate(&probe)?;
    methods.baseline.validate(&probe)?;
    let mut workloads = Vec::new();
    let mut skipped = Vec::new();
    // A name selects itself and the views named after it ("uniform-10m" and its "-partial").
    let selected = |name: &str| {
        options.only.is_empty()
            || options.only.iter().any(|o| {
                name == o
                    || name
                        .strip_prefix(o.as_str())
                        .is_some_and(|rest| rest.starts_with('-'))
            })
    };

    // Scenes are built one at a time so that only one large cloud is in memory.
    let mut specs: Vec<SceneSpec> = UNIFORM_SERIES.map(SceneSpec::Uniform).into();
    specs.extend(CUBOID_PLANES.map(SceneSpec::Cuboid));
    specs.extend(REAL_SCANS.map(|file| SceneSpec::RealScan(options.data_dir.join(file))));
    specs.retain(|spec| {
        let name = spec.name();
        // The partial views of the headline cloud select that cloud too.
        selected(&name)
            || (name == HEADLINE_WORKLOAD
                && ["corner", "partial"]
                    .iter()
                    .any(|view| selected(&format!("{HEADLINE_WORKLOAD}-{view}"))))
    });
    let huge_points = options.huge.filter(|&n| selected(&uniform_workload(n)));
    let mut ingest_files = Vec::new();
    for file in REAL_SCANS
        .iter()
        .filter(|f| selected(&format!("ingest-{f}")))
    {
        let path = options.data_dir.join(file);
        if path.is_file() {
            ingest_files.push(path);
        } else {
            skipped.push(SkippedWorkload {
                workload: format!("ingest-{file}"),
                reason: format!("{file} not found in {}", options.data_dir.display()),
            });
        }
    }
    let ingest_points = options
        .ingest_points
        .filter(|&n| selected(&generated_workload(n)));
    if specs.is_empty()
        && huge_points.is_none()
        && ingest_files.is_empty()
        && ingest_points.is_none()
    {
        return Err(BenchError::NothingSelected(options.only.join(",")));
    }

    for spec in specs {
        let name = spec.name();
        progress(&format!("{name}: preparing"));
        let Some(scene) = spec.build(options)? else {
            let reason = format!("{name} not found in {}", options.data_dir.display());
            progress(&format!("{name}: skipped ({reason})"));
            skipped.push(SkippedWorkload {
                workload: name,
                reason,
            });
            continue;
        };
        let resident = methods.compute[0].upload(&scene.cloud)?;
        for view in scene.views.iter().filter(|v| selected(&v.workload)) {
            progress(&format!(
                "{}: {} points, measuring",
                view.workload,
                scene.cloud.len()
            ));
            let settings = FrameSettings::new(options.width, options.height, view.camera);
            let in_view = points_in_view(&scene.cloud, &settings);
            let result = measure(&mut methods, &resident, (view, in_view), &settings, options)?;
            progress(&summary_line(&result));
            workloads.push(result);
        }
        tracing::debug!(scene = %scene.name, "scene done");
    }

    // The huge cloud last: rendered first, it left llvmpipe's PointList path 35% slower on
    // every later workload of the process (the 10M cube's 705 ms became 963 ms), which
    // flattered every ratio; kept resident from the start, it slowed others too.
    if let Some(points) = huge_points {
        let huge = HugeCloud::ingest(&methods, options, points, progress)?;
        workloads.push(huge.measure(&mut methods, options, progress)?);
    }
    // Ingest uses no GPU; last, so that its files and caches leave the renders alone.
    let ingest = if ingest_files.is_empty() && ingest_points.is_none() {
        Vec::new()
    } else {
        ingest::measure_files(
            &ingest_files,
            ingest_points,
            options.ingest_repeats,
            progress,
        )?
    };

    let speedup_vs_pointlist = workloads
        .iter()
        .find(|w| w.workload == HEADLINE_WORKLOAD)
        .map(|w| w.speedup_vs_pointlist);
    Ok(BenchReport {
        adapter: AdapterReport::of(&gpu),
        host_clocks,
        width: options.width,
        height: options.height,
        warmup_frames: options.warmup_frames,
        frames: options.frames,
        speedup_vs_pointlist,
        scaling: scaling_fits(&workloads),
        workloads,
        ingest,
        skipped,
    })
}

fn summary_line(result: &WorkloadResult) -> String {
    let mut line = format!(
        "{}: pointlist {:.1} ms, compute {:.1} ms, speed-up {:.2}x",
        result.workload,
        result.pointlist.frame_ms,
        result.compute.frame_ms,
        result.speedup_vs_pointlist
    );
    for mode in &result.modes {
        line += &format!(
            ", {} {:.1} ms ({:.2}x basic)",
            mode.result.method, mode.result.frame_ms, mode.cost_vs_basic
        );
    }
    line
}

/// A cube of `points` (the run's is [`HUGE_POINTS`]), generated in Morton-ordered cells and
/// uploaded chunk by chunk: the host never holds the whole cloud. Its ingest's memory is the
/// peak above the process's size before it ([`IngestMemory`]).
struct HugeCloud {
    resident: GpuPointCloud,
    view: View,
    in_view: usize,
    settings: FrameSettings,
    memory: IngestMemory,
}

impl HugeCloud {
    fn ingest(
        methods: &Methods,
        options: &BenchOptions,
        points: usize,
        progress: &mut dyn FnMut(&str),
    ) -> Result<Self, BenchError> {
        let name = uniform_workload(points);
        progress(&format!("{name}: generating and uploading chunk by chunk"));
        let aspect = options.width as f64 / options.height as f64;
        let (origin, bounds) = cube_bounds();
        let camera = Camera::auto(&bounds, aspect);
        let settings = FrameSettings::new(options.width, options.height, camera);
        let transform = camera.transform(origin, options.width, options.height);
        let (w, h) = (options.width as f64, options.height as f64);

        let before_host_bytes = memory::resident_bytes();
        memory::reset_peak();
        let mut generator = CellCubeGenerator::new(points, 7);
        let mut in_view = 0usize;
        let resident = methods.compute[0].upload_chunks(origin, &mut |n| {
            let chunk = generator.next_chunk(n)?;
            in_view += chunk
                .0
                .iter()
                .filter(|p| {
                    transform
                        .project(p.as_dvec3())
                        .is_some_and(|(x, y, _)| x >= 0.0 && y >= 0.0 && x < w && y < h)
                })
                .count();
            Some(chunk)
        })?;
        let peak_host_bytes = memory::peak_resident_bytes();
        let gpu_bytes = resident.gpu_bytes();
        let view = View {
            workload: name,
            description: format!(
                "{points} uniform random points in a cube, all in view, generated and uploaded \
                 chunk by chunk"
            ),
            camera,
        };
        Ok(Self {
            resident,
            view,
            in_view,
            settings,
            memory: IngestMemory {
                peak_host_bytes,
                before_host_bytes,
                gpu_bytes,
                ingest_over_gpu: peak_host_bytes.saturating_sub(before_host_bytes) as f64
                    / gpu_bytes.max(1) as f64,
            },
        })
    }

    /// Renders it, over three rounds without warm-up rounds (each round's first frame of a
    /// method warms it).
    fn measure(
        self,
        methods: &mut Methods,
        options: &BenchOptions,
        progress: &mut dyn FnMut(&str),
    ) -> Result<WorkloadResult, BenchError> {
        progress(&format!("{}: measuring", self.view.workload));
        let huge_options = BenchOptions {
            warmup_frames: 0,
            frames: 3,
            ..options.clone()
        };
        let mut result = measure(
            methods,
            &self.resident,
            (&self.view, self.in_view),
            &self.settings,
            &huge_options,
        )?;
        result.ingest_memory = Some(self.memory);
        progress(&summary_line(&result));
        Ok(result)
    }
}

/// Warms up and measures every method on one view of a resident cloud.
/// The methods a workload is measured with: the `PointList` baseline, and one renderer per
/// compute method (basic first, then each mode). Each renderer keeps its own frame state (the
/// resolve's last footprint, the high-quality accumulator), as one job's frames would: with a
/// shared renderer every mode would start from the state another mode left.
struct Methods {
    baseline: PointListBaseline,
    compute: Vec<Renderer>,
    /// How long the first compute method renders unmeasured frames after the baseline's
    /// frame; `None`: as every other method ([`warm_in_a_row`]).
    settle_after_baseline: Option<Duration>,
}

impl Methods {
    fn new(gpu: &Arc<GpuContext>, modes: usize, host_clocks: bool) -> Self {
        let mut baseline = PointListBaseline::new(gpu.clone());
        let mut compute: Vec<Renderer> = (0..=modes).map(|_| Renderer::new(gpu.clone())).collect();
        if host_clocks {
            baseline.use_host_clocks();
            compute.iter_mut().for_each(Renderer::use_host_clocks);
        }
        Self {
            baseline,
            compute,
            settle_after_baseline: settle_after_baseline(gpu.adapter_info.device_type),
        }
    }
}

/// Before its measured frame in a round, a method renders unmeasured frames of its own until
/// they took at least this long (one at least, [`MAX_WARM_FRAMES`] at most). A measured frame
/// then starts from the state its own method left, as in a job's run of frames, not from the
/// caches another method left. A time, not a count: short frames need several. A frame of
/// 50 ms or more gets one unmeasured frame.
pub const WARM_IN_A_ROW: Duration = Duration::from_millis(50);

/// At most this many unmeasured frames before each measured one.
pub const MAX_WARM_FRAMES: usize = 8;

/// On a software adapter, the first compute method after the baseline's frame renders
/// unmeasured frames for this long, however many that takes. While lavapipe draws a
/// `PointList` frame (0.5 s to 13 s on 2 cores) its compute threads sleep, and for a while
/// after they wake the two of them wait on the CPUs' run queues: right after two baseline frames, the 10M cube's corner view
/// rasterized in 6.2-6.8 ms a frame, each compute thread waiting 12-21 ms over 8 frames,
/// against 4.5-4.8 ms and under 1 ms of wait in a run of compute frames alone. Rounds of 8
/// frames still slow in part after 200 ms of compute frames: 2 of 5; after 500 ms: 3 of 12;
/// after 1 s: 0 of 6 (BENCHMARKS.md, session 11). A job renders its frames back to back: the
/// bench measures that state.
pub const SETTLE_AFTER_BASELINE: Duration = Duration::from_secs(1);

/// [`SETTLE_AFTER_BASELINE`] on a software adapter, where the baseline's frame leaves the
/// compute threads waiting on the CPUs; `None` on a GPU, which has no such state to leave
/// (on an H200 it took most of a 308 s run).
pub fn settle_after_baseline(device_type: wgpu::DeviceType) -> Option<Duration> {
    (device_type == wgpu::DeviceType::Cpu).then_some(SETTLE_AFTER_BASELINE)
}

/// Renders unmeasured frames with `render` until [`WARM_IN_A_ROW`] has passed.
fn warm_in_a_row<E>(render: impl FnMut() -> Result<(), E>) -> Result<(), E> {
    warm_up(WARM_IN_A_ROW, MAX_WARM_FRAMES, render)
}

/// Renders frames with `render` until `least` has passed or `max_frames` were rendered (one
/// at least).
fn warm_up<E>(
    least: Duration,
    max_frames: usize,
    mut render: impl FnMut() -> Result<(), E>,
) -> Result<(), E> {
    let started = Instant::now();
    for _ in 0..max_frames.max(1) {
        render()?;
        if started.elapsed() >= least {
            break;
        }
    }
    Ok(())
}

fn measure(
    methods: &mut Methods,
    resident: &GpuPointCloud,
    (view, points_in_view): (&View, usize),
    settings: &FrameSettings,
    options: &BenchOptions,
) -> Result<WorkloadResult, BenchError> {
    let rounds = options.warmup_frames + options.frames;
    let points = resident.len();

    // Every round renders one frame with each method in turn, so that every method sees the
    // same machine: on a shared or throttled CPU speed drifts over seconds, and measuring the
    // methods one after another turned that drift into their ratios.
    let mut settings_of: Vec<FrameSettings> = vec![*settings];
    settings_of.extend(options.modes.iter().map(|mode| mode.settings(settings)));
    let mut pointlist_timings = Vec::with_capacity(options.frames);
    let mut pointlist_wall_ms = Vec::with_capacity(options.frames);
    let mut pointlist_image = None;
    let mut compute_timings = vec![Vec::with_capacity(options.frames); settings_of.len()];
    let mut compute_wall_ms = vec![Vec::with_capacity(options.frames); settings_of.len()];
    let mut compute_frames = vec![None; settings_of.len()];
    for round in 0..rounds {
        let measured = round >= options.warmup_frames;
        warm_in_a_row(|| methods.baseline.render(resident, settings).map(drop))?;
        let started = Instant::now();
        let frame = methods.baseline.render(resident, settings)?;
        if measured {
            pointlist_wall_ms.push(started.elapsed().as_secs_f64() * 1e3);
            pointlist_timings.push(frame.timings);
        }
        pointlist_image = Some(frame.image);
        for (method, (settings, renderer)) in
            settings_of.iter().zip(&mut methods.compute).enumerate()
        {
            let warm = || renderer.render(resident, settings).map(drop);
            match methods.settle_after_baseline {
                Some(settle) if method == 0 => warm_up(settle, usize::MAX, warm)?,
                _ => warm_in_a_row(warm)?,
            }
            let started = Instant::now();
            let frame = renderer.render(resident, settings)?;
            if measured {
                compute_wall_ms[method].push(started.elapsed().as_secs_f64() * 1e3);
                compute_timings[method].push(frame.timings.clone());
            }
            compute_frames[method] = Some(frame);
        }
    }
    let mut results = compute_timings
        .into_iter()
        .zip(compute_wall_ms)
        .zip(compute_frames)
        .map(|((timings, wall_ms), frame)| (timings, wall_ms, frame));
    let Some((compute_timings, compute_wall_ms, compute_frame)) = results.next() else {
        return Err(BenchError::NoFrames);
    };

    // The basic renderer's last frame: what its culling left and what occlusion then skipped.
    let batches = BatchCounts {
        total: resident.batch_count(),
        listed: methods.compute[0].listed_batches(),
        listed_points: methods.compute[0].listed_points(),
        occluded: methods.compute[0].occlusion_skipped()?.depth_pass,
    };
    let image_agreement = match (&pointlist_image, &compute_frame) {
        (Some(a), Some(b)) => image_agreement(a, &b.image, settings.background),
        _ => 0.0,
    };
    let pointlist = method_result(
        "pointlist",
        "render pipeline".into(),
        &pointlist_timings,
        pointlist_wall_ms,
        points,
    );
    let compute = method_result(
        "compute-basic",
        compute_frame
            .as_ref()
            .map_or_else(String::new, |f| format!("{:?}", f.atomics)),
        &compute_timings,
        compute_wall_ms,
        points,
    );
    let mut modes = Vec::new();
    for (mode, (timings, wall_ms, frame)) in options.modes.iter().zip(results) {
        let result = method_result(
            mode.name(),
            frame.map_or_else(String::new, |f| format!("{:?}", f.atomics)),
            &timings,
            wall_ms,
            points,
        );
        modes.push(ModeResult {
            cost_vs_basic: result.frame_ms / compute.frame_ms,
            result,
        });
    }
    Ok(WorkloadResult {
        workload: view.workload.clone(),
        description: view.description.clone(),
        points,
        points_in_view,
        speedup_vs_pointlist: pointlist.frame_ms / compute.frame_ms,
        pointlist,
        compute,
        modes,
        image_agreement,
        gpu_bytes_per_point: resident.gpu_bytes_per_point(),
        ingest_memory: None,
        batches,
    })
}

/// Stages left out of the frame time: transfers (the uniforms; the points, once) and what
/// follows the image. The host's culling counts: it is the compute method's own work.
fn is_frame_stage(stage: Stage) -> bool {
    !matches!(
        stage,
        Stage::Upload | Stage::Readback | Stage::Encode | Stage::Downsample
    )
}

/// Whether a workload belongs to the series of uniform cubes seen whole (the huge one
/// included), against which frame time is fitted and plotted.
pub fn in_uniform_series(workload: &WorkloadResult) -> bool {
    workload.ingest_memory.is_some()
        || UNIFORM_SERIES
            .iter()
            .any(|&n| workload.workload == uniform_workload(n))
}

/// Least-squares lines of frame time against points in view over the uniform series (all in
/// view), one per method.
fn scaling_fits(workloads: &[WorkloadResult]) -> Vec<ScalingFit> {
    let mut series: Vec<&WorkloadResult> =
        workloads.iter().filter(|w| in_uniform_series(w)).collect();
    series.sort_by_key(|w| w.points);
    if series.len() < 2 {
        return Vec::new();
    }
    let mut methods: Vec<(String, Vec<f64>)> = vec![
        (
            "pointlist".into(),
            series.iter().map(|w| w.pointlist.frame_ms).collect(),
        ),
        (
            "compute-basic".into(),
            series.iter().map(|w| w.compute.frame_ms).collect(),
        ),
    ];
    for (i, mode) in series[0].modes.iter().enumerate() {
        let times: Option<Vec<f64>> = series
            .iter()
            .map(|w| w.modes.get(i).map(|m| m.result.frame_ms))
            .collect();
        if let Some(times) = times {
            methods.push((mode.result.method.to_string(), times));
        }
    }
    let xs: Vec<f64> = series.iter().map(|w| w.points_in_view as f64).collect();
    methods
        .into_iter()
        .map(|(method, ys)| {
            let (slope, intercept, r_squared) = least_squares(&xs, &ys);
            ScalingFit {
                method,
                workloads: series.iter().map(|w| w.workload.clone()).collect(),
                ns_per_point: slope * 1e6,
                intercept_ms: intercept,
                r_squared,
            }
        })
        .collect()
}

/// Slope, intercept and coefficient of determination of the line through (xs, ys).
fn least_squares(xs: &[f64], ys: &[f64]) -> (f64, f64, f64) {
    let n = xs.len() as f64;
    let (mx, my) = (xs.iter().sum::<f64>() / n, ys.iter().sum::<f64>() / n);
    let sxy: f64 = xs.iter().zip(ys).map(|(x, y)| (x - mx) * (y - my)).sum();
    let sxx: f64 = xs.iter().map(|x| (x - mx).powi(2)).sum();
    let slope = if sxx > 0.0 { sxy / sxx } else { 0.0 };
    let intercept = my - slope * mx;
    let total: f64 = ys.iter().map(|y| (y - my).powi(2)).sum();
    let residual: f64 = xs
        .iter()
        .zip(ys)
        .map(|(x, y)| (y - (intercept + slope * x)).powi(2))
        .sum();
    let r_squared = if total > 0.0 {
        1.0 - residual / total
    } else {
        1.0
    };
    (slope, intercept, r_squared)
}

fn method_result(
    method: &'static str,
    variant: String,
    frames: &[StageTimings],
    wall_ms: Vec<f64>,
    points: usize,
) -> MethodResult {
    let frame_ms = median(
        frames
            .iter()
            .map(|t| {
                t.stages
                    .iter()
                    .filter(|s| is_frame_stage(s.stage))
                    .map(|s| s.ms)
                    .sum()
            })
            .collect(),
    );
    // Every stage that ran, in the order of the first frame.
    let mut stages = Vec::new();
    for timing in frames.first().map_or(&[][..], |t| &t.stages[..]) {
        if stages
            .iter()
            .any(|s: &StageMedian| s.stage == timing.stage.name())
        {
            continue;
        }
        let ms: Vec<f64> = frames.iter().filter_map(|t| t.get(timing.stage)).collect();
        stages.push(StageMedian {
            stage: timing.stage.name(),
            ms: median(ms),
            clock: match timing.clock {
                crate::raster::Clock::Gpu => "gpu",
                crate::raster::Clock::Host => "host",
            },
        });
    }
    MethodResult {
        method,
        variant,
        frame_ms,
        wall_ms: median(wall_ms),
        mpoints_per_s: points as f64 / (frame_ms * 1e3),
        stages,
    }
}

impl MethodResult {
    /// Wall-clock time of a frame that none of its stages accounts for. Large when the
    /// adapter's timestamps under-report a pass (seen on lavapipe); small otherwise, since a
    /// frame is little more than its stages.
    pub fn unaccounted_ms(&self) -> f64 {
        self.wall_ms - self.stages.iter().map(|s| s.ms).sum::<f64>()
    }
}

fn median(mut values: Vec<f64>) -> f64 {
    if values.is_empty() {
        return f64::NAN;
    }
    values.sort_by(f64::total_cmp);
    let mid = values.len() / 2;
    if values.len() % 2 == 1 {
        values[mid]
    } else {
        (values[mid - 1] + values[mid]) * 0.5
    }
}

/// Of the pixels that either image covers (differs from `background`), the fraction that are
/// equal in both.
pub fn image_agreement(a: &image::RgbaImage, b: &image::RgbaImage, background: [u8; 4]) -> f64 {
    let (mut covered, mut equal) = (0usize, 0usize);
    for (pa, pb) in a.pixels().zip(b.pixels()) {
        if pa.0 != background || pb.0 != background {
            covered += 1;
            equal += usize::from(pa == pb);
        }
    }
    if covered == 0 {
        1.0
    } else {
        equal as f64 / covered as f64
    }
}

fn points_in_view(cloud: &PointCloud, settings: &FrameSettings) -> usize {
    let t = settings
        .camera
        .transform(cloud.origin, settings.width, settings.height);
    let (w, h) = (settings.width as f64, settings.height as f64);
    cloud
        .positions
        .iter()
        .filter(|p| {
            t.project(p.as_dvec3())
                .is_some_and(|(x, y, _)| x >= 0.0 && y >= 0.0 && x < w && y < h)
        })
        .count()
}

/// Side of the generated uniform cube, in world units.
const CUBE_SIDE: f64 = 100.0;

/// `points` uniform random points in a cube, coloured by position; viewed whole by the
/// automatic camera of the cube's box (the same for every cloud of the series), and, for the
/// headline cloud, from above with ~10% of the points in view.
fn uniform_scene(points: usize, aspect: f64, seed: u64) -> Scene {
    uniform_scene_with(points, aspect, seed, points == UNIFORM_POINTS)
}

fn uniform_scene_with(points: usize, aspect: f64, seed: u64, with_partial: bool) -> Scene {
    let cloud = uniform_cube(points, seed);
    let (_, bounds) = cube_bounds();
    let centre = bounds.center();
    let name = uniform_workload(points);
    let mut views = vec![View {
        workload: name.clone(),
        description: format!("{points} uniform random points in a cube, all in view"),
        camera: Camera::auto(&bounds, aspect),
    }];
    if with_partial {
        // The automatic camera moved sideways, seeing a corner of the cube: points fall as
        // densely per pixel as in the full view, so this view measures the culling alone.
        views.push(View {
            workload: format!("{name}-corner"),
            description:
                "the same cloud and camera distance, panned to a corner, ~10% of it in view".into(),
            camera: panned_to_fraction(&cloud, views[0].camera, aspect, 0.1),
        });
        // Orthographic, straight down: the view rectangle covers 10% of the cube's top face,
        // so 10% of the points (at every depth) are in view and 90% are culled. They spread
        // over the whole image, ~0.5 per pixel: nearly every one passes the depth test.
        let view_height = CUBE_SIDE * (0.1 / aspect).sqrt();
        views.push(View {
            workload: format!("{name}-partial"),
            description: "the same cloud, orthographic from above, ~10% of it in view".into(),
            camera: Camera {
                position: centre + DVec3::Z * CUBE_SIDE,
                target: centre,
                up: DVec3::Y,
                projection: Projection::Orthographic {
                    height: view_height,
                },
                near: CUBE_SIDE * 0.25,
                far: CUBE_SIDE * 1.75,
            },
        });
    }
    Scene { name, views, cloud }
}

/// `camera` moved without turning, along the diagonal of its image, until about `fraction` of
/// the points of `cloud` are in view (bisection on a sample of the points).
fn panned_to_fraction(cloud: &PointCloud, camera: Camera, aspect: f64, fraction: f64) -> Camera {
    let sample: Vec<usize> = (0..cloud.len())
        .step_by(cloud.len().div_ceil(20_000))
        .collect();
    let sample = cloud.select(&sample);
    // Towards the image's lower right corner.
    let panned = |distance: f64| {
        let step = distance * std::f64::consts::FRAC_1_SQRT_2;
        camera.moved_sideways(step, -step)
    };
    let height = 1000;
    let width = (f64::from(height) * aspect).round() as u32;
    let seen = |distance: f64| {
        let settings = FrameSettings::new(width, height, panned(distance));
        points_in_view(&sample, &settings) as f64 / sample.len().max(1) as f64
    };
    // Far enough that nothing is in view: the camera's distance to the cloud's far side.
    let (mut near, mut far) = (0.0, (camera.target - camera.position).length() * 4.0);
    for _ in 0..40 {
        let middle = 0.5 * (near + far);
        if seen(middle) > fraction {
            near = middle;
        } else {
            far = middle;
        }
    }
    panned(0.5 * (near + far))
}

/// The generated cube: its centre (the clouds' origin) and its box, at survey-like coordinates.
fn cube_bounds() -> (DVec3, crate::cloud::WorldBounds) {
    let min = DVec3::new(515_000.0, 4_918_000.0, 2_000.0);
    let bounds = crate::cloud::WorldBounds {
        min,
        max: min + DVec3::splat(CUBE_SIDE),
    };
    (bounds.center(), bounds)
}

/// The colour of a point at `unit` (0..1 per axis) in the cube.
fn cube_color(unit: Vec3) -> u32 {
    let [r, g, b] = (unit * 255.0).as_uvec3().to_array().map(|c| c as u8);
    pack_rgba8(r, g, b)
}

/// Uniform random points in a `CUBE_SIDE` cube at survey-like coordinates, generated relative
/// to the cube's centre (no f64 copy of the cloud).
pub fn uniform_cube(points: usize, seed: u64) -> PointCloud {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let (origin, bounds) = cube_bounds();
    let mut positions = Vec::with_capacity(points);
    let mut colors = Vec::with_capacity(points);
    for _ in 0..points {
        let unit = Vec3::new(rng.random(), rng.random(), rng.random());
        positions.push((unit - 0.5) * CUBE_SIDE as f32);
        colors.push(cube_color(unit));
    }
    PointCloud {
        origin,
        positions,
        colors: colors,
        intensity: vec![0; points],
        classification: vec![0; points],
        return_number: vec![0; points],
        bounds,
        color_source: crate::cloud::ColorSource::Rgb16,
    }
}

/// The uniform cube generated cell by cell: the cube is split into 2^(3 levels) cells visited
/// in Morton order, each filled with its share of uniform random points, so that consecutive
/// points are close together without a sort and the cloud never exists whole on the host.
struct CellCubeGenerator {
    rng: ChaCha8Rng,
    levels: u32,
    next_cell: u64,
    cells: u64,
    points: usize,
}

impl CellCubeGenerator {
    fn new(points: usize, seed: u64) -> Self {
        // Cells of at most one batch each.
        let mut levels = 0;
        while (points as u64).div_ceil(1 << (3 * levels)) > BATCH_POINTS as u64 {
            levels += 1;
        }
        Self {
            rng: ChaCha8Rng::seed_from_u64(seed),
            levels,
            next_cell: 0,
            cells: 1 << (3 * levels),
            points,
        }
    }

    /// Points of cell `cell`: an even share, the first cells taking the remainder.
    fn cell_points(&self, cell: u64) -> usize {
        let base = self.points as u64 / self.cells;
        (base + u64::from(cell < self.points as u64 % self.cells)) as usize
    }

    /// Whole cells of at most `max_points` points (at least one cell), or `None` when done.
    fn next_chunk(&mut self, max_points: usize) -> Option<(Vec<Vec3>, Vec<u32>)> {
        if self.next_cell >= self.cells {
            return None;
        }
        let side = (1u32 << self.levels) as f32;
        let (mut positions, mut colors) = (Vec::new(), Vec::new());
        while self.next_cell < self.cells {
            let n = self.cell_points(self.next_cell);
            if !positions.is_empty() && positions.len() + n > max_points {
                break;
            }
            let corner = Vec3::from_array(demorton3(self.next_cell).map(|c| c as f32));
            for _ in 0..n {
                let jitter = Vec3::new(self.rng.random(), self.rng.random(), self.rng.random());
                let unit = (corner + jitter) / side;
                positions.push((unit - 0.5) * CUBE_SIDE as f32);
                colors.push(cube_color(unit));
            }
            self.next_cell += 1;
        }
        Some((positions, colors))
    }
}

/// The x, y, z cell coordinates interleaved in a Morton code (x in the lowest bit).
fn demorton3(code: u64) -> [u32; 3] {
    let mut xyz = [0u32; 3];
    for bit in 0..21 {
        for (axis, c) in xyz.iter_mut().enumerate() {
            *c |= (((code >> (3 * bit + axis)) & 1) as u32) << bit;
        }
    }
    xyz
}

/// The process's resident memory, from `/proc/self/status` (Linux; 0 elsewhere).
mod memory {
    fn status_kib(field: &str) -> u64 {
        std::fs::read_to_string("/proc/self/status")
            .ok()
            .and_then(|status| {
                status
                    .lines()
                    .find(|l| l.starts_with(field))
                    .and_then(|l| l.split_whitespace().nth(1))
                    .and_then(|kib| kib.parse().ok())
            })
            .unwrap_or(0)
    }

    pub fn resident_bytes() -> u64 {
        status_kib("VmRSS:") * 1024
    }

    /// The peak resident set size since the last [`reset_peak`] (or the start).
    pub fn peak_resident_bytes() -> u64 {
        status_kib("VmHWM:") * 1024
    }

    /// Resets the peak to the current size (Linux 4.0 and later; ignored where refused).
    pub fn reset_peak() {
        let _ = std::fs::write("/proc/self/clear_refs", "5");
    }
}

/// `planes` planes of `side` x `side` points, one unit apart in every direction, in shuffled
/// order; seen face-on by an orthographic camera at one point per pixel, so every covered
/// pixel is drawn `planes` times (the overdraw workload of Schütz et al.). The upload
/// Morton-orders the points, for both methods alike.
fn cuboid_scene(planes: usize, side: usize, width: u32, height: u32, seed: u64) -> Scene {
    let cloud = shuffled_cuboid(planes, side, seed);
    let centre = cloud.bounds.center();
    let camera = Camera {
        position: centre + DVec3::Z * (planes as f64 + 10.0),
        target: centre,
        up: DVec3::Y,
        // One world unit per pixel.
        projection: Projection::Orthographic {
            height: height as f64,
        },
        near: 1.0,
        far: 2.0 * planes as f64 + 20.0,
    };
    let name = format!("cuboid-k{planes}");
    Scene {
        views: vec![View {
            workload: name.clone(),
            description: format!(
                "{planes} planes of {side}x{side} points, face-on, {planes}x overdraw \
                 ({width}x{height} image)"
            ),
            camera,
        }],
        name,
        cloud,
    }
}

/// The cuboid's points: plane `k` at height `k`, each plane one colour.
pub fn shuffled_cuboid(planes: usize, side: usize, seed: u64) -> PointCloud {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let origin = DVec3::new(515_000.0, 4_918_000.0, 2_000.0);
    let mut order: Vec<usize> = (0..planes * side * side).collect();
    order.shuffle(&mut rng);
    let plane_colors: Vec<u32> = (0..planes)
        .map(|_| pack_rgba8(rng.random(), rng.random(), rng.random()))
        .collect();
    let (positions, colors) = order
        .into_iter()
        .map(|i| {
            let (plane, cell) = (i / (side * side), i % (side * side));
            let (x, y) = (cell % side, cell / side);
            let p = origin + DVec3::new(x as f64 + 0.5, y as f64 + 0.5, plane as f64);
            (p, plane_colors[plane])
        })
        .unzip::<_, _, Vec<DVec3>, Vec<u32>>();
    PointCloud::from_world_points(&positions, colors)
}

/// A real scan from the data directory, viewed by the automatic camera; `None` if absent.
fn real_scene(path: &Path, aspect: f64) -> Result<Option<Scene>, BenchError> {
    if !path.is_file() {
        return Ok(None);
    }
    let cloud = load_point_cloud(path)?;
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    Ok(Some(Scene {
        views: vec![View {
            workload: name.clone(),
            description: "real scan, automatic camera".into(),
            camera: Camera::auto(&cloud.bounds, aspect),
        }],
        name,
        cloud,
    }))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::gpu;

    #[test]
    fn least_squares_recovers_a_line() {
        let xs = [1e6, 3e6, 1e7, 3e7];
        let ys: Vec<f64> = xs.iter().map(|x| 2.0 + 5e-6 * x).collect();
        let (slope, intercept, r2) = least_squares(&xs, &ys);
        assert!((slope - 5e-6).abs() < 1e-12 && (intercept - 2.0).abs() < 1e-6);
        assert!((r2 - 1.0).abs() < 1e-9);
    }

    #[test]
    fn cell_generator_yields_every_point_once_in_compact_cells() {
        let mut generator = CellCubeGenerator::new(100_000, 3);
        let (mut total, mut chunks) = (0, 0);
        while let Some((positions, colors)) = generator.next_chunk(3 * BATCH_POINTS) {
            assert!(positions.len() <= 3 * BATCH_POINTS && positions.len() == colors.len());
            let half = CUBE_SIDE as f32 / 2.0;
            assert!(positions.iter().all(|p| p.abs().max_element() <= half));
            total += positions.len();
            chunks += 1;
        }
        assert_eq!(total, 100_000);
        assert!(chunks >= 100_000 / (3 * BATCH_POINTS));
        assert_eq!(demorton3(0b111_000), [2, 2, 2]);
        assert_eq!(demorton3(0b100), [0, 0, 1]);
    }

    #[test]
    fn frames_in_a_row_last_the_warm_up_time_within_their_bounds() {
        // A frame longer than the warm-up time is rendered once.
        let mut slow = 0;
        let result = warm_in_a_row(|| {
            slow += 1;
            std::thread::sleep(WARM_IN_A_ROW + Duration::from_millis(5));
            Ok::<(), ()>(())
        });
        assert_eq!(result, Ok(()));
        assert_eq!(slow, 1);
        // Instant frames stop at the cap.
        let mut instant = 0;
        let result = warm_in_a_row(|| {
            instant += 1;
            Ok::<(), ()>(())
        });
        assert_eq!(result, Ok(()));
        assert!((1..=MAX_WARM_FRAMES).contains(&instant));
        // The settling after the baseline counts time only.
        let mut settling = 0;
        let least = Duration::from_millis(30);
        let started = Instant::now();
        let result = warm_up(least, usize::MAX, || {
            settling += 1;
            std::thread::sleep(Duration::from_millis(1));
            Ok::<(), ()>(())
        });
        assert_eq!(result, Ok(()));
        assert!(started.elapsed() >= least);
        assert!(settling > MAX_WARM_FRAMES, "{settling} frames in {least:?}");
        // A failing frame stops the row with its error.
        let mut failing = 0;
        let result = warm_in_a_row(|| {
            failing += 1;
            Err("lost device")
        });
        assert_eq!((result, failing), (Err("lost device"), 1));
        // Only a software adapter settles after the baseline.
        assert_eq!(
            settle_after_baseline(wgpu::DeviceType::Cpu),
            Some(SETTLE_AFTER_BASELINE)
        );
        for gpu in [
            wgpu::DeviceType::DiscreteGpu,
            wgpu::DeviceType::IntegratedGpu,
        ] {
            assert_eq!(settle_after_baseline(gpu), None);
        }
    }

    #[test]
    fn median_of_odd_and_even_counts() {
        assert_eq!(median(vec![3.0, 1.0, 2.0]), 2.0);
        assert_eq!(median(vec![4.0, 1.0, 2.0, 3.0]), 2.5);
        assert!(median(vec![]).is_nan());
    }

    #[test]
    fn cuboid_has_every_grid_point_once() {
        let cloud = shuffled_cuboid(3, 4, 1);
        assert_eq!(cloud.len(), 48);
        let mut cells: Vec<(i64, i64, i64)> = cloud
            .positions
            .iter()
            .map(|p| {
                let w = cloud.origin + p.as_dvec3();
                (w.x.floor() as i64, w.y.floor() as i64, w.z.round() as i64)
            })
            .collect();
        cells.sort_unstable();
        cells.dedup();
        assert_eq!(cells.len(), 48);
    }

    #[test]
    fn cuboid_view_draws_each_pixel_once_per_plane() {
        let scene = cuboid_scene(4, 16, 64, 48, 3);
        let settings = FrameSettings::new(64, 48, scene.views[0].camera);
        // Every point is in view, on its own pixel of the 16x16 square.
        assert_eq!(points_in_view(&scene.cloud, &settings), 4 * 16 * 16);
    }

    #[test]
    fn partial_views_see_about_a_tenth_of_the_uniform_cloud() {
        let scene = uniform_scene_with(50_000, 16.0 / 9.0, 4, true);
        let full = FrameSettings::new(160, 90, scene.views[0].camera);
        assert_eq!(points_in_view(&scene.cloud, &full), 50_000);
        let names: Vec<&str> = scene.views.iter().map(|v| v.workload.as_str()).collect();
        assert_eq!(
            names,
            [
                "uniform-50000",
                "uniform-50000-corner",
                "uniform-50000-partial"
            ]
        );
        for view in &scene.views[1..] {
            let settings = FrameSettings::new(160, 90, view.camera);
            let fraction = points_in_view(&scene.cloud, &settings) as f64 / 50_000.0;
            assert!(
                (0.09..0.11).contains(&fraction),
                "{}: {fraction}",
                view.workload
            );
        }
        // The corner view keeps the full view's distance and direction: the same density of
        // points per pixel.
        let (full, corner) = (scene.views[0].camera, scene.views[1].camera);
        assert!((full.position - full.target).abs_diff_eq(corner.position - corner.target, 1e-9));
    }

    #[test]
    fn runner_measures_both_methods_on_a_small_workload() {
        let gpu = gpu();
        let scene = cuboid_scene(4, 32, 64, 48, 5);
        let options = BenchOptions {
            warmup_frames: 1,
            frames: 2,
            ..BenchOptions::quick(64, 48, PathBuf::new())
        };
        let mut methods = Methods::new(&gpu, options.modes.len(), false);
        let settings = FrameSettings::new(64, 48, scene.views[0].camera);
        let resident = methods.compute[0].upload(&scene.cloud).expect("upload");
        let in_view = points_in_view(&scene.cloud, &settings);
        let result = measure(
            &mut methods,
            &resident,
            (&scene.views[0], in_view),
            &settings,
            &options,
        )
        .expect("measure");
        assert_eq!(result.modes.len(), ComputeMode::ALL.len());
        for method in [&result.pointlist, &result.compute]
            .into_iter()
            .chain(result.modes.iter().map(|m| &m.result))
        {
            assert!(method.frame_ms > 0.0 && method.wall_ms > 0.0, "{method:?}");
        }
        let hq = &result.modes[0].result;
        assert_eq!(result.modes[1].result.variant, "Atomic32");
        assert!(hq.stages.iter().any(|s| s.stage == "accumulate"), "{hq:?}");
        assert!(result.gpu_bytes_per_point <= 12.0);
        // The front plane covers the same pixels with one colour in both methods.
        assert!(result.image_agreement > 0.99, "{}", result.image_agreement);
    }

    #[test]
    fn huge_workload_streams_many_chunks_and_reports_its_memory_peak() {
        let gpu = gpu();
        let options = BenchOptions {
            modes: vec![ComputeMode::HighQuality],
            ..BenchOptions::quick(96, 54, PathBuf::new())
        };
        let mut methods = Methods::new(&gpu, options.modes.len(), false);
        // Chunks of 8 batches, so that 300,000 points arrive in ten chunks.
        methods.compute[0].set_max_chunk_points(8 * BATCH_POINTS);
        let result = HugeCloud::ingest(&methods, &options, 300_000, &mut |_| {})
            .and_then(|huge| huge.measure(&mut methods, &options, &mut |_| {}))
            .expect("measure");
        assert_eq!(result.workload, "uniform-300000");
        assert_eq!(result.points, 300_000);
        assert!(result.points_in_view > 290_000, "{}", result.points_in_view);
        let memory = result.ingest_memory.expect("memory peak");
        assert!(memory.peak_host_bytes >= memory.before_host_bytes);
        assert!(memory.gpu_bytes as f64 >= 300_000.0 * 11.0);
        assert!(result.compute.frame_ms > 0.0 && result.modes[0].result.frame_ms > 0.0);
        assert!(result.image_agreement > 0.95, "{}", result.image_agreement);
    }
}
