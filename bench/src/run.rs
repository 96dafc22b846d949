//! The runner: selects the workloads a run asks for, builds their scenes one at a time,
//! measures each view, then the huge cloud and the ingest figures, and gathers the report.

use std::sync::Arc;

use glam::DVec3;
use pointfarm_render::camera::Camera;
use pointfarm_render::cloud::WorldBounds;
use pointfarm_render::gpu::GpuContext;
use pointfarm_render::raster::FrameSettings;

use crate::huge::HugeCloud;
use crate::ingest::{self, generated_workload};
use crate::report::{scaling_fits, AdapterReport, BenchReport, SkippedWorkload};
use crate::rounds::{measure, Methods};
use crate::workloads::{
    points_in_view, uniform_workload, SceneSpec, CUBOID_PLANES, HEADLINE_WORKLOAD, REAL_SCANS,
    UNIFORM_SERIES,
};
use crate::{BenchError, BenchOptions};

/// Runs every workload; `progress` receives one line per step.
pub fn run(
    gpu: Arc<GpuContext>,
    options: &BenchOptions,
    progress: &mut dyn FnMut(&str),
) -> Result<BenchReport, BenchError> {
    if options.rounds.frames == 0 {
        return Err(BenchError::NoFrames);
    }
    // A software adapter's timestamps under-report compute passes (docs/perf/gpu-timestamps.md),
    // so it is always timed by host clocks.
    let host_clocks = options.host_clocks || gpu.adapter_info.device_type == wgpu::DeviceType::Cpu;
    let mut methods = Methods::new(&gpu, options.modes.len(), host_clocks);
    // Refuse a bad image size before spending time on a 10M-point cloud.
    let unit_box = WorldBounds {
        min: DVec3::ZERO,
        max: DVec3::ONE,
    };
    let aspect = options.rounds.width as f64 / options.rounds.height.max(1) as f64;
    let probe = FrameSettings::new(
        options.rounds.width,
        options.rounds.height,
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
            let settings =
                FrameSettings::new(options.rounds.width, options.rounds.height, view.camera);
            let in_view = points_in_view(&scene.cloud, &settings);
            let result = measure(&mut methods, &resident, (view, in_view), &settings, options)?;
            progress(&result.summary_line());
            workloads.push(result);
        }
        tracing::debug!(scene = %scene.name, "scene done");
    }

    // The huge cloud last: rendered first, it slowed llvmpipe's PointList path on every later
    // workload of the process, which flattered every ratio; kept resident from the start, it
    // slowed others too (docs/perf/pointlist-baseline.md).
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
        rounds: options.rounds,
        speedup_vs_pointlist,
        scaling: scaling_fits(&workloads),
        workloads,
        ingest,
        skipped,
    })
}
