//! The huge workload: a cube of a hundred million points or more, generated cell by cell and
//! uploaded segment by segment, rendered like any other workload, with the host's memory peak
//! during its ingest.

use pointfarm_render::camera::Camera;
use pointfarm_render::raster::{FrameSettings, GpuPointCloud};

use crate::clouds::{cube_bounds, CellCubeGenerator};
use crate::memory;
use crate::report::{IngestMemory, WorkloadResult};
use crate::rounds::{measure, Methods};
use crate::workloads::{uniform_workload, View};
use crate::{BenchError, BenchOptions, FrameRounds};

/// A cube of `points` (the run's is [`HUGE_POINTS`](crate::HUGE_POINTS)), generated in
/// Morton-ordered cells and uploaded segment by segment: the host never holds the whole cloud. Its
/// ingest's memory is the peak above the process's size before it ([`IngestMemory`]).
pub(crate) struct HugeCloud {
    resident: GpuPointCloud,
    view: View,
    in_view: usize,
    settings: FrameSettings,
    memory: IngestMemory,
}

impl HugeCloud {
    pub(crate) fn ingest(
        methods: &Methods,
        options: &BenchOptions,
        points: usize,
        progress: &mut dyn FnMut(&str),
    ) -> Result<Self, BenchError> {
        let name = uniform_workload(points);
        progress(&format!(
            "{name}: generating and uploading segment by segment"
        ));
        let aspect = options.rounds.width as f64 / options.rounds.height as f64;
        let (origin, bounds) = cube_bounds();
        let camera = Camera::auto(&bounds, aspect);
        let settings = FrameSettings::new(options.rounds.width, options.rounds.height, camera);
        let transform = camera.transform(origin, options.rounds.width, options.rounds.height);
        let (w, h) = (options.rounds.width as f64, options.rounds.height as f64);

        let _measuring = memory::measuring();
        let before_host_bytes = memory::resident_bytes();
        memory::reset_peak();
        let mut generator = CellCubeGenerator::new(points, 7);
        let mut in_view = 0usize;
        let resident = methods.compute[0].upload_segments(origin, &mut |n| {
            let segment = generator.next_segment(n)?;
            in_view += segment
                .0
                .iter()
                .filter(|p| {
                    transform
                        .project(p.as_dvec3())
                        .is_some_and(|(x, y, _)| x >= 0.0 && y >= 0.0 && x < w && y < h)
                })
                .count();
            Some(segment)
        })?;
        let peak_host_bytes = memory::peak_resident_bytes();
        let gpu_bytes = resident.gpu_bytes();
        let view = View {
            workload: name,
            description: format!(
                "{points} uniform random points in a cube, all in view, generated and uploaded \
                 segment by segment"
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
    pub(crate) fn measure(
        self,
        methods: &mut Methods,
        options: &BenchOptions,
        progress: &mut dyn FnMut(&str),
    ) -> Result<WorkloadResult, BenchError> {
        progress(&format!("{}: measuring", self.view.workload));
        let huge_options = BenchOptions {
            rounds: FrameRounds {
                warmup_frames: 0,
                frames: 3,
                ..options.rounds
            },
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
        progress(&result.summary_line());
        Ok(result)
    }
}

#[cfg(test)]
mod tests {
    use std::path::PathBuf;

    use pointfarm_render::raster::BATCH_POINTS;

    use super::*;
    use crate::ComputeMode;
    use pointfarm_render::testing::gpu;

    #[test]
    fn huge_workload_streams_many_segments_and_reports_its_memory_peak() {
        let gpu = gpu();
        let options = BenchOptions {
            modes: vec![ComputeMode::HighQuality],
            ..BenchOptions::quick(96, 54, PathBuf::new())
        };
        let mut methods = Methods::new(&gpu, options.modes.len(), false);
        // Segments of 8 batches, so that 300,000 points arrive in ten segments.
        methods.compute[0].set_max_segment_points(8 * BATCH_POINTS);
        let result = HugeCloud::ingest(&methods, &options, 300_000, &mut |_| {})
            .and_then(|huge| huge.measure(&mut methods, &options, &mut |_| {}))
            .expect("measure");
        assert_eq!(result.workload, "uniform-300000");
        assert_eq!(result.points, 300_000);
        assert!(result.points_in_view > 290_000, "{}", result.points_in_view);
        let memory = result.ingest_memory.expect("memory peak");
        // Other tests free memory on their threads meanwhile, so the peak since the reset
        // may be below the size measured before it: only its presence is certain here.
        assert!(memory.peak_host_bytes > 0 && memory.before_host_bytes > 0);
        assert!(memory.gpu_bytes as f64 >= 300_000.0 * 11.0);
        assert!(result.compute.frame_ms > 0.0 && result.modes[0].result.frame_ms > 0.0);
        assert!(result.image_agreement > 0.95, "{}", result.image_agreement);
    }
}
