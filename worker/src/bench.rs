//! The benchmark harness behind `pointfarm bench`: workloads, and a runner that renders each
//! with every method on the same resident buffers, the same camera and the same image size.
//!
//! Methods: the fixed-function `PointList` baseline ([`PointListBaseline`]) and the compute
//! rasterizer's basic mode ([`Renderer`]). A frame's time is the GPU work that produces its
//! image: the point pass with its clear, plus the resolve for the compute path. Readback and
//! host-side stages are reported per stage but left out of the frame time, since they do not
//! depend on the method. Every figure is the median over measured frames, after warm-up frames.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

use glam::DVec3;
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::Serialize;

use crate::camera::{Camera, Projection};
use crate::cloud::{pack_rgba8, PointCloud};
use crate::gpu::GpuContext;
use crate::ingest::{load_point_cloud, IngestError};
use crate::raster::{
    FrameSettings, GpuPointCloud, PointListBaseline, RenderError, Renderer, Stage, StageTimings,
};

/// Points of the uniform cloud that the targets are stated for.
pub const UNIFORM_POINTS: usize = 10_000_000;
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
}

impl BenchOptions {
    /// The full run: 1024x1024-point cuboid planes (up to 64 Mi points), 3 + 15 frames.
    pub fn full(width: u32, height: u32, data_dir: PathBuf) -> Self {
        Self {
            width,
            height,
            warmup_frames: 3,
            frames: 15,
            cuboid_side: 1024,
            data_dir,
            host_clocks: false,
        }
    }

    /// About two minutes on a 2-core software adapter: 512x512-point planes, 2 + 9 frames.
    pub fn quick(width: u32, height: u32, data_dir: PathBuf) -> Self {
        Self {
            warmup_frames: 2,
            frames: 9,
            cuboid_side: 512,
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
    /// `pointlist` or `compute-basic` (with the atomics path in `variant`).
    pub method: &'static str,
    pub variant: String,
    /// Median over frames of the time that produces the image: the stages rasterize (with
    /// the clear) and resolve, on the GPU clock where the adapter has timestamps.
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
    pub compute: MethodResult,
    /// PointList frame time over compute frame time.
    pub speedup_vs_pointlist: f64,
    /// Of the pixels covered by either method, the fraction with the same colour in both:
    /// a check that both drew the same thing.
    pub image_agreement: f64,
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
    /// Whether stages were timed by host clocks although the adapter has timestamps.
    pub host_clocks: bool,
    pub width: u32,
    pub height: u32,
    pub warmup_frames: usize,
    pub frames: usize,
    /// Speed-up of the compute path over PointList on [`HEADLINE_WORKLOAD`].
    pub speedup_vs_pointlist: Option<f64>,
    pub workloads: Vec<WorkloadResult>,
    pub skipped: Vec<SkippedWorkload>,
}

/// The scenes of a run, built one at a time.
enum SceneSpec {
    Uniform,
    Cuboid(usize),
    RealScan(PathBuf),
}

impl SceneSpec {
    fn name(&self) -> String {
        match self {
            SceneSpec::Uniform => HEADLINE_WORKLOAD.into(),
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
            SceneSpec::Uniform => uniform_scene(UNIFORM_POINTS, aspect, 1),
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
    let mut renderer = Renderer::new(gpu.clone());
    let mut baseline = PointListBaseline::new(gpu.clone());
    if options.host_clocks {
        renderer.use_host_clocks();
        baseline.use_host_clocks();
    }
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
    renderer.validate(&probe)?;
    baseline.validate(&probe)?;
    let mut workloads = Vec::new();
    let mut skipped = Vec::new();

    // Scenes are built one at a time so that only one large cloud is in memory.
    let mut specs = vec![SceneSpec::Uniform];
    specs.extend(CUBOID_PLANES.map(SceneSpec::Cuboid));
    specs.extend(REAL_SCANS.map(|file| SceneSpec::RealScan(options.data_dir.join(file))));

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
        let resident = renderer.upload(&scene.cloud)?;
        for view in &scene.views {
            progress(&format!(
                "{}: {} points, measuring",
                view.workload,
                scene.cloud.len()
            ));
            let settings = FrameSettings::new(options.width, options.height, view.camera);
            let result = measure(
                &mut renderer,
                &mut baseline,
                &scene.cloud,
                &resident,
                view,
                &settings,
                options,
            )?;
            progress(&format!(
                "{}: pointlist {:.1} ms, compute {:.1} ms, speed-up {:.2}x",
                result.workload,
                result.pointlist.frame_ms,
                result.compute.frame_ms,
                result.speedup_vs_pointlist
            ));
            workloads.push(result);
        }
        tracing::debug!(scene = %scene.name, "scene done");
    }

    let speedup_vs_pointlist = workloads
        .iter()
        .find(|w| w.workload == HEADLINE_WORKLOAD)
        .map(|w| w.speedup_vs_pointlist);
    Ok(BenchReport {
        adapter: AdapterReport::of(&gpu),
        host_clocks: options.host_clocks,
        width: options.width,
        height: options.height,
        warmup_frames: options.warmup_frames,
        frames: options.frames,
        speedup_vs_pointlist,
        workloads,
        skipped,
    })
}

/// Warms up and measures both methods on one view.
fn measure(
    renderer: &mut Renderer,
    baseline: &mut PointListBaseline,
    cloud: &PointCloud,
    resident: &GpuPointCloud,
    view: &View,
    settings: &FrameSettings,
    options: &BenchOptions,
) -> Result<WorkloadResult, BenchError> {
    let rounds = options.warmup_frames + options.frames;

    let mut pointlist_timings = Vec::with_capacity(options.frames);
    let mut pointlist_wall_ms = Vec::with_capacity(options.frames);
    let mut pointlist_image = None;
    for round in 0..rounds {
        let started = Instant::now();
        let frame = baseline.render(resident, settings)?;
        if round >= options.warmup_frames {
            pointlist_wall_ms.push(started.elapsed().as_secs_f64() * 1e3);
            pointlist_timings.push(frame.timings);
        }
        pointlist_image = Some(frame.image);
    }

    let mut compute_timings = Vec::with_capacity(options.frames);
    let mut compute_wall_ms = Vec::with_capacity(options.frames);
    let mut compute_image = None;
    let mut path = None;
    for round in 0..rounds {
        let started = Instant::now();
        let frame = renderer.render(resident, settings)?;
        if round >= options.warmup_frames {
            compute_wall_ms.push(started.elapsed().as_secs_f64() * 1e3);
            compute_timings.push(frame.timings);
        }
        compute_image = Some(frame.image);
        path = Some(frame.atomics);
    }

    let image_agreement = match (&pointlist_image, &compute_image) {
        (Some(a), Some(b)) => image_agreement(a, b, settings.background),
        _ => 0.0,
    };
    let points = cloud.len();
    let pointlist = method_result(
        "pointlist",
        "render pipeline".into(),
        &pointlist_timings,
        pointlist_wall_ms,
        points,
    );
    let compute = method_result(
        "compute-basic",
        path.map_or_else(String::new, |p| format!("{p:?}")),
        &compute_timings,
        compute_wall_ms,
        points,
    );
    Ok(WorkloadResult {
        workload: view.workload.clone(),
        description: view.description.clone(),
        points,
        points_in_view: points_in_view(cloud, settings),
        speedup_vs_pointlist: pointlist.frame_ms / compute.frame_ms,
        pointlist,
        compute,
        image_agreement,
    })
}

/// Stages whose sum is the time to produce the image on the GPU.
const FRAME_STAGES: [Stage; 2] = [Stage::Rasterize, Stage::Resolve];

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
            .map(|t| FRAME_STAGES.iter().filter_map(|&s| t.get(s)).sum())
            .collect(),
    );
    let mut stages = Vec::new();
    for stage in [
        Stage::Upload,
        Stage::Rasterize,
        Stage::Resolve,
        Stage::Readback,
    ] {
        let ms: Vec<f64> = frames.iter().filter_map(|t| t.get(stage)).collect();
        let clock = frames
            .iter()
            .flat_map(|t| &t.stages)
            .find(|t| t.stage == stage)
            .map(|t| t.clock);
        if let Some(clock) = clock {
            stages.push(StageMedian {
                stage: stage.name(),
                ms: median(ms),
                clock: match clock {
                    crate::raster::Clock::Gpu => "gpu",
                    crate::raster::Clock::Host => "host",
                },
            });
        }
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
/// automatic camera, and from above with ~10% of the points in view.
fn uniform_scene(points: usize, aspect: f64, seed: u64) -> Scene {
    let cloud = uniform_cube(points, seed);
    let bounds = cloud.bounds;
    let centre = bounds.center();
    // Orthographic, straight down: the view rectangle covers 10% of the cube's top face, so
    // 10% of the points (at every depth) are in view and 90% are culled.
    let view_height = CUBE_SIDE * (0.1 / aspect).sqrt();
    let top = centre + DVec3::Z * CUBE_SIDE;
    let partial = Camera {
        position: top,
        target: centre,
        up: DVec3::Y,
        projection: Projection::Orthographic {
            height: view_height,
        },
        near: CUBE_SIDE * 0.25,
        far: CUBE_SIDE * 1.75,
    };
    Scene {
        name: HEADLINE_WORKLOAD.into(),
        views: vec![
            View {
                workload: HEADLINE_WORKLOAD.into(),
                description: format!("{points} uniform random points in a cube, all in view"),
                camera: Camera::auto(&bounds, aspect),
            },
            View {
                workload: "uniform-10m-partial".into(),
                description: "the same cloud, orthographic from above, ~10% of it in view".into(),
                camera: partial,
            },
        ],
        cloud,
    }
}

/// Uniform random points in a `CUBE_SIDE` cube at survey-like coordinates.
pub fn uniform_cube(points: usize, seed: u64) -> PointCloud {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let origin = DVec3::new(515_000.0, 4_918_000.0, 2_000.0);
    let mut positions = Vec::with_capacity(points);
    let mut colours = Vec::with_capacity(points);
    for _ in 0..points {
        let unit = DVec3::new(rng.random(), rng.random(), rng.random());
        positions.push(origin + unit * CUBE_SIDE);
        let [r, g, b] = (unit * 255.0).as_uvec3().to_array().map(|c| c as u8);
        colours.push(pack_rgba8(r, g, b));
    }
    PointCloud::from_world_points(&positions, colours)
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
    let plane_colours: Vec<u32> = (0..planes)
        .map(|_| pack_rgba8(rng.random(), rng.random(), rng.random()))
        .collect();
    let (positions, colours) = order
        .into_iter()
        .map(|i| {
            let (plane, cell) = (i / (side * side), i % (side * side));
            let (x, y) = (cell % side, cell / side);
            let p = origin + DVec3::new(x as f64 + 0.5, y as f64 + 0.5, plane as f64);
            (p, plane_colours[plane])
        })
        .unzip::<_, _, Vec<DVec3>, Vec<u32>>();
    PointCloud::from_world_points(&positions, colours)
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
    fn partial_view_sees_about_a_tenth_of_the_uniform_cloud() {
        let scene = uniform_scene(50_000, 16.0 / 9.0, 4);
        let settings = FrameSettings::new(160, 90, scene.views[1].camera);
        let fraction = points_in_view(&scene.cloud, &settings) as f64 / 50_000.0;
        assert!((0.09..0.11).contains(&fraction), "{fraction}");
    }

    #[test]
    fn runner_measures_both_methods_on_a_small_workload() {
        let gpu = gpu();
        let mut renderer = Renderer::new(gpu.clone());
        let mut baseline = PointListBaseline::new(gpu);
        let scene = cuboid_scene(4, 32, 64, 48, 5);
        let options = BenchOptions {
            warmup_frames: 1,
            frames: 2,
            ..BenchOptions::quick(64, 48, PathBuf::new())
        };
        let settings = FrameSettings::new(64, 48, scene.views[0].camera);
        let resident = renderer.upload(&scene.cloud).expect("upload");
        let result = measure(
            &mut renderer,
            &mut baseline,
            &scene.cloud,
            &resident,
            &scene.views[0],
            &settings,
            &options,
        )
        .expect("measure");
        for method in [&result.pointlist, &result.compute] {
            assert!(method.frame_ms > 0.0 && method.wall_ms > 0.0, "{method:?}");
        }
        // The front plane covers the same pixels with one colour in both methods.
        assert!(result.image_agreement > 0.99, "{}", result.image_agreement);
    }
}
