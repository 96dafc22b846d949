//! The measurement rounds: the methods a workload is measured with, how each is warmed before
//! its measured frame, and the rounds that render one frame with every method in turn.

use std::sync::Arc;
use std::time::{Duration, Instant};

use pointfarm_render::gpu::GpuContext;
use pointfarm_render::raster::{
    Clock, FrameSettings, GpuPointCloud, PointListBaseline, Renderer, Stage, StageTimings,
};

use crate::report::{BatchCounts, MethodResult, ModeResult, StageMedian, WorkloadResult};
use crate::stats::median;
use crate::workloads::View;
use crate::{BenchError, BenchOptions};

/// The methods a workload is measured with: the `PointList` baseline, and one renderer per
/// compute method (basic first, then each mode). Each renderer keeps its own frame state (the
/// resolve's last footprint, the high-quality accumulator), as one job's frames would: with a
/// shared renderer every mode would start from the state another mode left.
pub(crate) struct Methods {
    pub(crate) baseline: PointListBaseline,
    pub(crate) compute: Vec<Renderer>,
    /// How long the first compute method renders unmeasured frames after the baseline's
    /// frame; `None`: as every other method ([`warm_in_a_row`]).
    settle_after_baseline: Option<Duration>,
}

impl Methods {
    pub(crate) fn new(gpu: &Arc<GpuContext>, modes: usize, host_clocks: bool) -> Self {
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
/// `PointList` frame its compute threads sleep, and for a while after they wake they wait on
/// the CPUs' run queues, which slows the next compute frames; a second of compute frames
/// leaves that state behind (docs/perf/lavapipe-settle.md). A job renders its frames back to
/// back: the bench measures that state.
pub const SETTLE_AFTER_BASELINE: Duration = Duration::from_secs(1);

/// [`SETTLE_AFTER_BASELINE`] on a software adapter, where the baseline's frame leaves the
/// compute threads waiting on the CPUs; `None` on a GPU, which has no such state to leave
/// and where the settling would take most of a run (docs/perf/lavapipe-settle.md).
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

/// Warms up and measures every method on one view of a resident cloud.
pub(crate) fn measure(
    methods: &mut Methods,
    resident: &GpuPointCloud,
    (view, points_in_view): (&View, usize),
    settings: &FrameSettings,
    options: &BenchOptions,
) -> Result<WorkloadResult, BenchError> {
    let rounds = options.rounds.warmup_frames + options.rounds.frames;
    let points = resident.len();

    // Every round renders one frame with each method in turn, so that every method sees the
    // same machine: on a shared or throttled CPU speed drifts over seconds, and measuring the
    // methods one after another turned that drift into their ratios.
    let mut settings_of: Vec<FrameSettings> = vec![*settings];
    settings_of.extend(options.modes.iter().map(|mode| mode.settings(settings)));
    let mut pointlist_timings = Vec::with_capacity(options.rounds.frames);
    let mut pointlist_wall_ms = Vec::with_capacity(options.rounds.frames);
    let mut pointlist_image = None;
    let mut compute_timings = vec![Vec::with_capacity(options.rounds.frames); settings_of.len()];
    let mut compute_wall_ms = vec![Vec::with_capacity(options.rounds.frames); settings_of.len()];
    let mut compute_frames = vec![None; settings_of.len()];
    for round in 0..rounds {
        let measured = round >= options.rounds.warmup_frames;
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
                Clock::Gpu => "gpu",
                Clock::Host => "host",
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

#[cfg(test)]
mod tests {
    use std::path::PathBuf;

    use super::*;
    use crate::workloads::{cuboid_scene, points_in_view};
    use crate::ComputeMode;
    use pointfarm_render::testing::gpu;

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
    fn runner_measures_both_methods_on_a_small_workload() {
        let gpu = gpu();
        let scene = cuboid_scene(4, 32, 64, 48, 5);
        let mut options = BenchOptions::quick(64, 48, PathBuf::new());
        options.rounds.warmup_frames = 1;
        options.rounds.frames = 2;
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
        // The front plane covers the same pixels with one color in both methods.
        assert!(result.image_agreement > 0.99, "{}", result.image_agreement);
    }
}
