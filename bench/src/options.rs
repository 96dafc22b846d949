//! What a run measures: [`BenchOptions`] (image size, rounds, workloads, the ingest figures)
//! and the compute modes measured besides the basic mode ([`ComputeMode`]).

use std::path::PathBuf;

use serde::Serialize;

use pointfarm_render::raster::{AtomicsMode, FillSettings, FrameSettings, Quality, Shading};

use crate::workloads::UNIFORM_POINTS;

/// The frames rendered per method and workload: their size and how many. The report holds
/// the ones it measured.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct FrameRounds {
    pub width: u32,
    pub height: u32,
    /// Frames rendered and discarded before measuring.
    pub warmup_frames: usize,
    /// Frames measured.
    pub frames: usize,
}

/// What to run.
#[derive(Debug, Clone)]
pub struct BenchOptions {
    pub rounds: FrameRounds,
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
    /// Also render a cube of this many points ([`HUGE_POINTS`](crate::HUGE_POINTS) by
    /// default), generated and uploaded segment by segment, with its host memory peak.
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
    /// The basic mode on the 32-bit atomics path (depth pass, then color pass), the fallback
    /// for adapters without 64-bit atomics: the same image by another route.
    BasicAtomic32,
    /// The basic mode, then Eye-Dome Lighting (default strength and radius): what the
    /// default shading costs.
    Edl,
    /// The basic mode, then Pintus et al.'s visibility and filling (default kernel) and
    /// Eye-Dome Lighting (default strength and radius).
    FillEdl,
    /// The basic mode, then visibility, filling and Pintus et al.'s multi-level shading.
    FillPintus,
}

impl ComputeMode {
    pub const ALL: [ComputeMode; 5] = [
        ComputeMode::HighQuality,
        ComputeMode::BasicAtomic32,
        ComputeMode::Edl,
        ComputeMode::FillEdl,
        ComputeMode::FillPintus,
    ];

    pub fn name(self) -> &'static str {
        match self {
            ComputeMode::HighQuality => "compute-hq",
            ComputeMode::BasicAtomic32 => "compute-basic-32",
            ComputeMode::Edl => "compute-edl",
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
            ComputeMode::Edl => FrameSettings {
                shading: Shading::EDL,
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
            rounds: FrameRounds {
                width,
                height,
                warmup_frames: 1,
                frames: 15,
            },
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
        let full = Self::full(width, height, data_dir);
        Self {
            rounds: FrameRounds {
                frames: 7,
                ..full.rounds
            },
            cuboid_side: 512,
            ingest_points: Some(2_000_000),
            ingest_repeats: 3,
            ..full
        }
    }
}
