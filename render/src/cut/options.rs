//! `CutOptions`: the pixel error of a cut and the two caches' budgets, their defaults and
//! ranges stated once.

use thiserror::Error;

/// The default pixel error: a node is refined while its point spacing covers more than this
/// on screen. A quarter of a pixel keeps about 97% of the covered pixels of a basic-mode frame
/// within 8/255 of full detail on a scene with noisy colors, more in high quality and on
/// smooth colors (docs/perf/lod-fidelity.md).
pub const DEFAULT_LOD_ERROR_PX: f64 = 0.25;
/// The largest pixel error accepted.
pub const MAX_LOD_ERROR_PX: f64 = 256.0;
/// The pixel error of a COPC file's preview frames, drawn before its final ones: on the 100M
/// terrain at 1920x1080 a hundredth of the points, its first frame 20x sooner than decoding
/// the whole file, where the default's is 1.5x (docs/perf/copc-first-frame.md).
pub const PREVIEW_LOD_ERROR_PX: f64 = 4.0;
/// The most points a cut at a pixel error above 0 draws per pixel of the frame. Where the
/// error alone would select more (a far view of a dense campaign, whose leaves hold points
/// far finer than the error), the cut stops refining, far away first, so that a frame's time
/// follows its pixels, not the dataset's points. 32 kept every mode within the fidelity rule
/// where 8 did not (docs/perf/cut-point-cap.md).
pub const MAX_CUT_POINTS_PER_PIXEL: u64 = 32;
/// The default bound of the host node cache.
pub const DEFAULT_MEMORY_BUDGET_BYTES: u64 = 2 << 30;
/// The default bound of the GPU node cache on a GPU with memory of its own.
pub const DEFAULT_GPU_BUDGET_BYTES: u64 = 2 << 30;
/// The most points a dataset may hold to be rendered resident (read whole, uploaded once)
/// unless levels of detail are asked for: below it, a resident frame is faster than a cut and
/// a build is not worth waiting for.
pub const RESIDENT_MAX_POINTS: u64 = 20_000_000;
/// The smallest budget of either cache.
pub const MIN_BUDGET_BYTES: u64 = 16 << 20;

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CutOptions {
    /// Pixels; 0 draws every point in view.
    pub lod_error: f64,
    /// Host memory for nodes: on a CPU adapter (lavapipe), where GPU memory is host memory,
    /// the GPU node cache's share of it too.
    pub memory_budget_bytes: u64,
    /// GPU memory for nodes; `None`: [`DEFAULT_GPU_BUDGET_BYTES`] on a GPU, half the memory
    /// budget on a CPU adapter.
    pub gpu_budget_bytes: Option<u64>,
}

impl Default for CutOptions {
    fn default() -> Self {
        Self {
            lod_error: DEFAULT_LOD_ERROR_PX,
            memory_budget_bytes: DEFAULT_MEMORY_BUDGET_BYTES,
            gpu_budget_bytes: None,
        }
    }
}

#[derive(Debug, Error, PartialEq)]
pub enum CutOptionsError {
    #[error("lod_error is {0}, expected 0 to {MAX_LOD_ERROR_PX} pixels")]
    LodError(f64),
    #[error("{field} is {bytes} bytes, at least {MIN_BUDGET_BYTES} are needed")]
    Budget { field: &'static str, bytes: u64 },
    #[error(
        "gpu_budget ({gpu} bytes) must leave room in memory_budget ({memory} bytes) on a CPU \
         adapter, whose GPU memory is host memory"
    )]
    GpuBudgetOnCpu { gpu: u64, memory: u64 },
}

/// The budgets of the two caches as one adapter has them.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct CacheBudgets {
    pub host_bytes: u64,
    pub gpu_bytes: u64,
}

impl CutOptions {
    pub fn validate(&self) -> Result<(), CutOptionsError> {
        if !(self.lod_error.is_finite() && (0.0..=MAX_LOD_ERROR_PX).contains(&self.lod_error)) {
            return Err(CutOptionsError::LodError(self.lod_error));
        }
        let budgets = [
            ("memory_budget", Some(self.memory_budget_bytes)),
            ("gpu_budget", self.gpu_budget_bytes),
        ];
        for (field, bytes) in budgets {
            if let Some(bytes) = bytes.filter(|&b| b < MIN_BUDGET_BYTES) {
                return Err(CutOptionsError::Budget { field, bytes });
            }
        }
        Ok(())
    }

    /// How the budgets split on an adapter whose GPU memory is host memory (`cpu_adapter`)
    /// or one with memory of its own.
    pub fn budgets(&self, cpu_adapter: bool) -> Result<CacheBudgets, CutOptionsError> {
        self.validate()?;
        let memory = self.memory_budget_bytes;
        if !cpu_adapter {
            return Ok(CacheBudgets {
                host_bytes: memory,
                gpu_bytes: self.gpu_budget_bytes.unwrap_or(DEFAULT_GPU_BUDGET_BYTES),
            });
        }
        let gpu = self.gpu_budget_bytes.unwrap_or(memory / 2);
        if gpu + MIN_BUDGET_BYTES > memory {
            return Err(CutOptionsError::GpuBudgetOnCpu { gpu, memory });
        }
        Ok(CacheBudgets {
            host_bytes: memory - gpu,
            gpu_bytes: gpu,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ranges_are_checked_by_field() {
        let bad = CutOptions {
            lod_error: f64::NAN,
            ..Default::default()
        };
        assert!(matches!(bad.validate(), Err(CutOptionsError::LodError(e)) if e.is_nan()));
        assert!(CutOptions {
            lod_error: -1.0,
            ..Default::default()
        }
        .validate()
        .is_err());
        assert_eq!(
            CutOptions {
                memory_budget_bytes: 1000,
                ..Default::default()
            }
            .validate(),
            Err(CutOptionsError::Budget {
                field: "memory_budget",
                bytes: 1000
            })
        );
    }

    #[test]
    fn a_cpu_adapter_takes_the_gpu_cache_out_of_the_memory_budget() {
        let options = CutOptions {
            memory_budget_bytes: 512 << 20,
            ..Default::default()
        };
        let cpu = options.budgets(true).expect("budgets");
        assert_eq!(cpu.host_bytes + cpu.gpu_bytes, 512 << 20);
        let gpu = options.budgets(false).expect("budgets");
        assert_eq!(gpu.host_bytes, 512 << 20);
        assert_eq!(gpu.gpu_bytes, DEFAULT_GPU_BUDGET_BYTES);
        let too_much = CutOptions {
            gpu_budget_bytes: Some(512 << 20),
            ..options
        };
        assert!(matches!(
            too_much.budgets(true),
            Err(CutOptionsError::GpuBudgetOnCpu { .. })
        ));
    }
}
