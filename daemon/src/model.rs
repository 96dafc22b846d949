//! The daemon's domain types: what is stored in sled and what the gRPC layer converts to and
//! from. Nothing here knows about protobuf.

use serde::{Deserialize, Serialize};

pub type DatasetId = String;
pub type JobId = String;

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Dataset {
    pub id: DatasetId,
    pub name: String,
    pub size_bytes: u64,
    pub sha256: String,
    pub path: std::path::PathBuf,
    pub created_unix_ms: i64,
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Point3 {
    pub x: f64,
    pub y: f64,
    pub z: f64,
}

impl From<Point3> for glam::DVec3 {
    fn from(p: Point3) -> Self {
        glam::DVec3::new(p.x, p.y, p.z)
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Turntable {
    pub frames: u32,
    pub center: Option<Point3>,
    pub radius: Option<f64>,
    pub elevation_deg: f64,
    pub degrees: f64,
    pub fov_y_deg: f64,
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Keyframe {
    pub position: Point3,
    pub target: Point3,
    pub up: Point3,
    pub fov_y_deg: f64,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum Interpolation {
    Linear,
    Spline,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub enum CameraPath {
    Turntable(Turntable),
    Keyframes {
        keyframes: Vec<Keyframe>,
        frames: u32,
        interpolation: Interpolation,
    },
}

impl CameraPath {
    pub fn frames(&self) -> u32 {
        match self {
            CameraPath::Turntable(t) => t.frames,
            CameraPath::Keyframes { frames, .. } => *frames,
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub enum Quality {
    Basic,
    High { depth_band: f32 },
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub enum Shading {
    None,
    Edl { strength: f32, radius: f32 },
    Pintus { levels: u32, exponent: f32 },
}

/// Pintus et al.'s visibility and hole filling.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Fill {
    /// Visibility kernel side in pixels (odd, 3 to 9).
    pub kernel: u32,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum ColorMode {
    Rgb,
    Intensity,
    Elevation,
    Classification,
    ReturnNumber,
    Fixed([u8; 3]),
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RenderOptions {
    pub point_size: u32,
    pub quality: Quality,
    pub shading: Shading,
    pub color_mode: ColorMode,
    pub background: [u8; 4],
    /// Absent in jobs stored before filling existed.
    #[serde(default)]
    pub fill: Option<Fill>,
}

/// What a client asked for, validated.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct JobSpec {
    pub request_id: String,
    pub dataset_id: DatasetId,
    pub camera_path: CameraPath,
    pub width: u32,
    pub height: u32,
    pub render: RenderOptions,
    pub priority: i32,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum JobState {
    Queued,
    Running,
    Succeeded,
    Failed,
    Cancelled,
}

impl JobState {
    pub fn is_terminal(self) -> bool {
        matches!(
            self,
            JobState::Succeeded | JobState::Failed | JobState::Cancelled
        )
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Job {
    pub id: JobId,
    pub spec: JobSpec,
    pub state: JobState,
    pub frames_total: u32,
    pub frames_done: u32,
    pub error: Option<String>,
    pub created_unix_ms: i64,
    pub updated_unix_ms: i64,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StageTiming {
    pub stage: String,
    pub ms: f64,
    pub gpu_clock: bool,
}

/// What the worker reports of a finished frame.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FrameReport {
    pub index: u32,
    pub timings: Vec<StageTiming>,
    /// Set when the worker loaded the dataset for this frame: from its cache or not.
    pub dataset_cache_hit: Option<bool>,
    /// Attempts that ended without a result before this one (failed, or the worker was lost).
    #[serde(default)]
    pub failed_attempts: u32,
}

/// One frame of a job.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub enum FrameState {
    Pending { attempts: u32 },
    Done(FrameReport),
}

/// Something that happened to a job, for watchers.
#[derive(Debug, Clone, PartialEq)]
pub struct JobEvent {
    pub job: Job,
    /// Set when a frame finished.
    pub frame: Option<FrameReport>,
}

pub fn now_unix_ms() -> i64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_millis() as i64)
        .unwrap_or(0)
}
