//! What a run measured, as serialised to the JSON file: the adapter, per workload every
//! method's medians, the scaling fits, the ingest figures and what was skipped.

use pointfarm_render::gpu::GpuContext;
use serde::Serialize;

use crate::ingest::IngestResult;
use crate::options::FrameRounds;
use crate::stats::least_squares;
use crate::workloads::{uniform_workload, UNIFORM_SERIES};

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
    /// mode's name ([`ComputeMode::name`](crate::ComputeMode::name)).
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
    /// Of the pixels covered by either method, the fraction with the same color in both:
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
    #[serde(flatten)]
    pub rounds: FrameRounds,
    /// Speed-up of the compute path over PointList on
    /// [`HEADLINE_WORKLOAD`](crate::HEADLINE_WORKLOAD).
    pub speedup_vs_pointlist: Option<f64>,
    pub workloads: Vec<WorkloadResult>,
    /// Frame time against points in view over the uniform series, per method.
    pub scaling: Vec<ScalingFit>,
    /// Loading datasets: LAZ decoding on all cores and on one, and dataset-cache hits.
    pub ingest: Vec<IngestResult>,
    pub skipped: Vec<SkippedWorkload>,
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
pub(crate) fn scaling_fits(workloads: &[WorkloadResult]) -> Vec<ScalingFit> {
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

impl WorkloadResult {
    /// One progress line of the workload's figures.
    pub fn summary_line(&self) -> String {
        let mut line = format!(
            "{}: pointlist {:.1} ms, compute {:.1} ms, speed-up {:.2}x",
            self.workload,
            self.pointlist.frame_ms,
            self.compute.frame_ms,
            self.speedup_vs_pointlist
        );
        for mode in &self.modes {
            line += &format!(
                ", {} {:.1} ms ({:.2}x basic)",
                mode.result.method, mode.result.frame_ms, mode.cost_vs_basic
            );
        }
        line
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

impl BenchReport {
    /// A warning when frames' wall-clock time exceeds their stages by much, which means the
    /// GPU timestamps missed work (lavapipe under-reports the resolve pass); `None` when the
    /// stages were timed by host clocks or account for the frames.
    pub fn timestamp_warning(&self) -> Option<String> {
        if self.host_clocks {
            return None;
        }
        let suspect: Vec<String> = self
            .workloads
            .iter()
            .flat_map(|w| {
                [(&w.workload, &w.pointlist), (&w.workload, &w.compute)]
                    .into_iter()
                    .chain(w.modes.iter().map(move |m| (&w.workload, &m.result)))
            })
            .filter(|(_, m)| m.unaccounted_ms() > 2.0_f64.max(0.2 * m.wall_ms))
            .map(|(workload, m)| {
                format!(
                    "{workload} {}: {:.1} of {:.1} ms",
                    m.method,
                    m.unaccounted_ms(),
                    m.wall_ms
                )
            })
            .collect();
        (!suspect.is_empty()).then(|| {
            format!(
                "wall-clock time that no stage accounts for ({}); this adapter's GPU timestamps \
                 may under-report; rerun with --host-clocks",
                suspect.join(", ")
            )
        })
    }
}
