//! Conversions between the `pointfarm.v1` messages and the daemon's domain types, both ways,
//! as `From`/`TryFrom` where a conversion needs nothing but its input. Requests are validated
//! on the way in, and an invalid field is named in the error. The conversions of frame tasks
//! are public: the remote worker uses them on its side of the wire.
//!
//! The render options and camera paths sit together in the last part of this file.

use pointfarm_proto::v1 as pb;
use pointfarm_render::raster::{
    FillSettings, Shading as RendererShading, MAX_FILL_KERNEL, MAX_PINTUS_LEVELS, MIN_FILL_KERNEL,
};

use crate::error::DaemonError;
use crate::lease::{FrameTask, HeartbeatAnswer, Lease, TaskDataset};
use crate::model::{
    CameraPath, ColorMode, Dataset, Fill, FrameReport, Interpolation, Job, JobSpec, JobState,
    Keyframe, Point3, Quality, RenderOptions, Shading, StageTiming, Turntable,
};

pub(super) fn invalid(field: &str, message: impl Into<String>) -> DaemonError {
    DaemonError::invalid(field, message)
}

/// Validates a submission; limits that depend on the server are checked by the daemon.
impl TryFrom<&pb::SubmitJobRequest> for JobSpec {
    type Error = DaemonError;

    fn try_from(r: &pb::SubmitJobRequest) -> Result<Self, DaemonError> {
        if r.dataset_id.is_empty() {
            return Err(invalid("dataset_id", "is required"));
        }
        if r.width == 0 {
            return Err(invalid("width", "must be at least 1"));
        }
        if r.height == 0 {
            return Err(invalid("height", "must be at least 1"));
        }
        Ok(JobSpec {
            request_id: r.request_id.clone(),
            dataset_id: r.dataset_id.clone(),
            camera_path: camera_path(r.camera_path.as_ref())?,
            width: r.width,
            height: r.height,
            render: render_options(r.render.as_ref())?,
            priority: r.priority,
        })
    }
}

impl From<JobState> for pb::JobState {
    fn from(state: JobState) -> Self {
        match state {
            JobState::Queued => pb::JobState::Queued,
            JobState::Running => pb::JobState::Running,
            JobState::Succeeded => pb::JobState::Succeeded,
            JobState::Failed => pb::JobState::Failed,
            JobState::Cancelled => pb::JobState::Cancelled,
        }
    }
}

/// The state a listing is filtered by; unspecified lists every state.
pub(super) fn state_filter(state: i32) -> Result<Option<JobState>, DaemonError> {
    Ok(match pb::JobState::try_from(state) {
        Ok(pb::JobState::Unspecified) => None,
        Ok(pb::JobState::Queued) => Some(JobState::Queued),
        Ok(pb::JobState::Running) => Some(JobState::Running),
        Ok(pb::JobState::Succeeded) => Some(JobState::Succeeded),
        Ok(pb::JobState::Failed) => Some(JobState::Failed),
        Ok(pb::JobState::Cancelled) => Some(JobState::Cancelled),
        Err(_) => return Err(invalid("state", format!("unknown value {state}"))),
    })
}

/// A job without its original request and frames; the services add those where they answer
/// with them.
impl From<&Job> for pb::Job {
    fn from(job: &Job) -> Self {
        pb::Job {
            id: job.id.clone(),
            request_id: job.spec.request_id.clone(),
            dataset_id: job.spec.dataset_id.clone(),
            state: pb::JobState::from(job.state) as i32,
            frames_total: job.frames_total,
            frames_done: job.frames_done,
            error: job.error.clone().unwrap_or_default(),
            priority: job.spec.priority,
            created_unix_ms: job.created_unix_ms,
            updated_unix_ms: job.updated_unix_ms,
            spec: None,
            frames: Vec::new(),
        }
    }
}

impl From<&Dataset> for pb::Dataset {
    fn from(d: &Dataset) -> Self {
        pb::Dataset {
            id: d.id.clone(),
            name: d.name.clone(),
            size_bytes: d.size_bytes,
            sha256: d.sha256.clone(),
            path: d.path.display().to_string(),
            created_unix_ms: d.created_unix_ms,
        }
    }
}

impl From<&StageTiming> for pb::StageTiming {
    fn from(t: &StageTiming) -> Self {
        pb::StageTiming {
            stage: t.stage.clone(),
            ms: t.ms,
            gpu_clock: t.gpu_clock,
        }
    }
}

impl From<&pb::StageTiming> for StageTiming {
    fn from(t: &pb::StageTiming) -> Self {
        StageTiming {
            stage: t.stage.clone(),
            ms: t.ms,
            gpu_clock: t.gpu_clock,
        }
    }
}

pub fn timings_message(timings: &[StageTiming]) -> Vec<pb::StageTiming> {
    timings.iter().map(pb::StageTiming::from).collect()
}

pub fn stage_timings(timings: &[pb::StageTiming]) -> Vec<StageTiming> {
    timings.iter().map(StageTiming::from).collect()
}

impl From<&FrameReport> for pb::FrameFinished {
    fn from(report: &FrameReport) -> Self {
        pb::FrameFinished {
            index: report.index,
            timings: timings_message(&report.timings),
            dataset_cache_hit: report.dataset_cache_hit,
            failed_attempts: report.failed_attempts,
        }
    }
}

impl From<&Lease> for pb::Lease {
    fn from(lease: &Lease) -> Self {
        pb::Lease {
            lease_id: lease.id.clone(),
            job_id: lease.job_id.clone(),
            frame_index: lease.index,
            worker_name: lease.worker.clone(),
            expires_unix_ms: lease.expires_unix_ms,
            embedded: lease.embedded,
        }
    }
}

impl From<HeartbeatAnswer> for pb::HeartbeatResponse {
    fn from(answer: HeartbeatAnswer) -> Self {
        match answer {
            HeartbeatAnswer::Continue { expires_unix_ms } => pb::HeartbeatResponse {
                action: pb::LeaseAction::Continue as i32,
                reason: String::new(),
                lease_expires_unix_ms: expires_unix_ms,
            },
            HeartbeatAnswer::Stop(reason) => pb::HeartbeatResponse {
                action: pb::LeaseAction::Stop as i32,
                reason,
                lease_expires_unix_ms: 0,
            },
        }
    }
}

pub fn frame_task_message(task: &FrameTask) -> pb::FrameTask {
    pb::FrameTask {
        lease_id: task.lease.id.clone(),
        lease_expires_unix_ms: task.lease.expires_unix_ms,
        lease_timeout_ms: task.lease_timeout.as_millis().min(u32::MAX as u128) as u32,
        job_id: task.lease.job_id.clone(),
        frame_index: task.lease.index,
        dataset: Some(pb::TaskDataset {
            id: task.dataset.id.clone(),
            sha256: task.dataset.sha256.clone(),
            size_bytes: task.dataset.size_bytes,
        }),
        camera_path: Some(camera_path_message(&task.camera_path)),
        width: task.width,
        height: task.height,
        render: Some(render_options_message(&task.render)),
        failed_attempts: task.failed_attempts,
    }
}

/// A task as the worker `worker` receives it, validated like a submission.
pub fn frame_task(message: &pb::FrameTask, worker: &str) -> Result<FrameTask, DaemonError> {
    let dataset = message
        .dataset
        .as_ref()
        .ok_or_else(|| invalid("dataset", "is required"))?;
    if message.width == 0 || message.height == 0 {
        return Err(invalid("width", "the frame size must be at least 1x1"));
    }
    if message.lease_timeout_ms == 0 {
        return Err(invalid("lease_timeout_ms", "must be positive"));
    }
    Ok(FrameTask {
        lease: Lease {
            id: message.lease_id.clone(),
            job_id: message.job_id.clone(),
            index: message.frame_index,
            worker: worker.to_string(),
            embedded: false,
            expires_unix_ms: message.lease_expires_unix_ms,
        },
        lease_timeout: std::time::Duration::from_millis(message.lease_timeout_ms as u64),
        dataset: TaskDataset {
            id: dataset.id.clone(),
            sha256: dataset.sha256.clone(),
            size_bytes: dataset.size_bytes,
        },
        camera_path: camera_path(message.camera_path.as_ref())?,
        width: message.width,
        height: message.height,
        render: render_options(message.render.as_ref())?,
        failed_attempts: message.failed_attempts,
    })
}

// ------------------------------------------------------------- render options and camera paths

/// Point size limit, as the renderer's.
const MAX_POINT_SIZE: u32 = pointfarm_render::raster::MAX_POINT_SIZE;

fn point(field: &str, v: Option<&pb::Vec3>) -> Result<Point3, DaemonError> {
    let v = v.ok_or_else(|| invalid(field, "is required"))?;
    if !(v.x.is_finite() && v.y.is_finite() && v.z.is_finite()) {
        return Err(invalid(field, "must be finite (no NaN or infinity)"));
    }
    Ok(Point3 {
        x: v.x,
        y: v.y,
        z: v.z,
    })
}

fn finite_in<T: Into<f64> + Copy + std::fmt::Display>(
    field: &str,
    value: T,
    range: std::ops::RangeInclusive<f64>,
    what: &str,
) -> Result<T, DaemonError> {
    let wide: f64 = value.into();
    if wide.is_finite() && range.contains(&wide) {
        Ok(value)
    } else {
        Err(invalid(field, format!("must be {what}, got {value}")))
    }
}

fn fov(field: &str, value: f64) -> Result<f64, DaemonError> {
    if value.is_finite() && value > 0.0 && value < 180.0 {
        Ok(value)
    } else {
        Err(invalid(
            field,
            format!("must lie in (0, 180) degrees, got {value}"),
        ))
    }
}

pub fn camera_path(path: Option<&pb::CameraPath>) -> Result<CameraPath, DaemonError> {
    let path = path
        .and_then(|p| p.path.as_ref())
        .ok_or_else(|| invalid("camera_path", "is required (turntable or keyframes)"))?;
    match path {
        pb::camera_path::Path::Turntable(t) => {
            let f = |name: &str| format!("camera_path.turntable.{name}");
            if t.frames == 0 {
                return Err(invalid(&f("frames"), "must be at least 1"));
            }
            let center = t
                .center
                .as_ref()
                .map(|c| point(&f("center"), Some(c)))
                .transpose()?;
            let radius = t
                .radius
                .map(|r| {
                    if r.is_finite() && r > 0.0 {
                        Ok(r)
                    } else {
                        Err(invalid(&f("radius"), format!("must be positive, got {r}")))
                    }
                })
                .transpose()?;
            Ok(CameraPath::Turntable(Turntable {
                frames: t.frames,
                center,
                radius,
                elevation_deg: finite_in(
                    &f("elevation_deg"),
                    t.elevation_deg.unwrap_or(30.0),
                    -89.0..=89.0,
                    "between -89 and 89 degrees",
                )?,
                degrees: finite_in(
                    &f("degrees"),
                    t.degrees.unwrap_or(360.0),
                    -36000.0..=36000.0,
                    "a finite angle",
                )?,
                fov_y_deg: fov(&f("fov_y_deg"), t.fov_y_deg.unwrap_or(50.0))?,
            }))
        }
        pb::camera_path::Path::Keyframes(k) => {
            if k.frames == 0 {
                return Err(invalid(
                    "camera_path.keyframes.frames",
                    "must be at least 1",
                ));
            }
            if k.keyframes.len() < 2 {
                return Err(invalid(
                    "camera_path.keyframes.keyframes",
                    "needs at least 2 keyframes",
                ));
            }
            let keyframes = k
                .keyframes
                .iter()
                .enumerate()
                .map(|(i, key)| {
                    let f = |name: &str| format!("camera_path.keyframes.keyframes[{i}].{name}");
                    let position = point(&f("position"), key.position.as_ref())?;
                    let target = point(&f("target"), key.target.as_ref())?;
                    if position == target {
                        return Err(invalid(&f("target"), "must differ from the position"));
                    }
                    let up = match key.up.as_ref() {
                        Some(up) => point(&f("up"), Some(up))?,
                        None => Point3 {
                            x: 0.0,
                            y: 0.0,
                            z: 1.0,
                        },
                    };
                    Ok(Keyframe {
                        position,
                        target,
                        up,
                        fov_y_deg: fov(&f("fov_y_deg"), key.fov_y_deg)?,
                    })
                })
                .collect::<Result<Vec<_>, _>>()?;
            let interpolation = match pb::Interpolation::try_from(k.interpolation) {
                Ok(pb::Interpolation::Spline) => Interpolation::Spline,
                Ok(pb::Interpolation::Linear | pb::Interpolation::Unspecified) => {
                    Interpolation::Linear
                }
                Err(_) => {
                    return Err(invalid(
                        "camera_path.keyframes.interpolation",
                        format!("unknown value {}", k.interpolation),
                    ))
                }
            };
            Ok(CameraPath::Keyframes {
                keyframes,
                frames: k.frames,
                interpolation,
            })
        }
    }
}

fn rgba(color: &pb::Color) -> [u8; 4] {
    color.rgba.to_be_bytes()
}

pub fn render_options(options: Option<&pb::RenderOptions>) -> Result<RenderOptions, DaemonError> {
    let default = pb::RenderOptions::default();
    let o = options.unwrap_or(&default);
    let point_size = if o.point_size == 0 { 1 } else { o.point_size };
    if point_size > MAX_POINT_SIZE {
        return Err(invalid(
            "render.point_size",
            format!("must be 1 to {MAX_POINT_SIZE}"),
        ));
    }
    let quality = match pb::Quality::try_from(o.quality) {
        Ok(pb::Quality::High) => {
            let band = finite_in(
                "render.depth_band",
                o.depth_band.unwrap_or(0.01),
                0.0..=1.0,
                "0 to 1",
            )?;
            Quality::High { depth_band: band }
        }
        Ok(_) => Quality::Basic,
        Err(_) => {
            return Err(invalid(
                "render.quality",
                format!("unknown value {}", o.quality),
            ))
        }
    };
    let shading = match pb::Shading::try_from(o.shading) {
        Ok(pb::Shading::Edl) => {
            let strength = o
                .edl_strength
                .unwrap_or(RendererShading::DEFAULT_EDL_STRENGTH);
            let radius = o.edl_radius.unwrap_or(RendererShading::DEFAULT_EDL_RADIUS);
            let strength = finite_in("render.edl_strength", strength, 0.0..=100.0, "0 to 100")?;
            let radius = finite_in("render.edl_radius", radius, 0.5..=16.0, "0.5 to 16 pixels")?;
            Shading::Edl { strength, radius }
        }
        Ok(pb::Shading::Pintus) => {
            let levels = o
                .pintus_levels
                .unwrap_or(RendererShading::DEFAULT_PINTUS_LEVELS);
            let exponent = o
                .pintus_exponent
                .unwrap_or(RendererShading::DEFAULT_PINTUS_EXPONENT);
            if !(1..=MAX_PINTUS_LEVELS).contains(&levels) {
                return Err(invalid(
                    "render.pintus_levels",
                    format!("must be 1 to {MAX_PINTUS_LEVELS}, got {levels}"),
                ));
            }
            let exponent = finite_in("render.pintus_exponent", exponent, 0.0..=4.0, "0 to 4")?;
            Shading::Pintus { levels, exponent }
        }
        Ok(_) => Shading::None,
        Err(_) => {
            return Err(invalid(
                "render.shading",
                format!("unknown value {}", o.shading),
            ))
        }
    };
    let color_mode = match pb::ColorMode::try_from(o.color_mode) {
        Ok(pb::ColorMode::Unspecified | pb::ColorMode::Rgb) => ColorMode::Rgb,
        Ok(pb::ColorMode::Intensity) => ColorMode::Intensity,
        Ok(pb::ColorMode::Elevation) => ColorMode::Elevation,
        Ok(pb::ColorMode::Classification) => ColorMode::Classification,
        Ok(pb::ColorMode::ReturnNumber) => ColorMode::ReturnNumber,
        Ok(pb::ColorMode::Fixed) => {
            let [r, g, b, _] = o.fixed_color.as_ref().map(rgba).ok_or_else(|| {
                invalid("render.fixed_color", "is required with COLOR_MODE_FIXED")
            })?;
            ColorMode::Fixed([r, g, b])
        }
        Err(_) => {
            return Err(invalid(
                "render.color_mode",
                format!("unknown value {}", o.color_mode),
            ))
        }
    };
    let background = o.background.as_ref().map(rgba).unwrap_or([24, 24, 28, 255]);
    let fill = match &o.fill {
        None => None,
        Some(f) => {
            let kernel = if f.kernel == 0 {
                FillSettings::DEFAULT_KERNEL
            } else {
                f.kernel
            };
            if !(MIN_FILL_KERNEL..=MAX_FILL_KERNEL).contains(&kernel) || kernel.is_multiple_of(2) {
                return Err(invalid(
                    "render.fill.kernel",
                    format!(
                        "must be an odd number of pixels from {MIN_FILL_KERNEL} to \
                         {MAX_FILL_KERNEL}, got {kernel}"
                    ),
                ));
            }
            Some(Fill { kernel })
        }
    };
    Ok(RenderOptions {
        point_size,
        quality,
        shading,
        color_mode,
        background,
        fill,
    })
}

fn vec3(p: &Point3) -> pb::Vec3 {
    pb::Vec3 {
        x: p.x,
        y: p.y,
        z: p.z,
    }
}

fn color(rgba: [u8; 4]) -> pb::Color {
    pb::Color {
        rgba: u32::from_be_bytes(rgba),
    }
}

/// The inverse of [`camera_path`].
pub fn camera_path_message(path: &CameraPath) -> pb::CameraPath {
    let path = match path {
        CameraPath::Turntable(t) => pb::camera_path::Path::Turntable(pb::Turntable {
            frames: t.frames,
            center: t.center.as_ref().map(vec3),
            radius: t.radius,
            elevation_deg: Some(t.elevation_deg),
            degrees: Some(t.degrees),
            fov_y_deg: Some(t.fov_y_deg),
        }),
        CameraPath::Keyframes {
            keyframes,
            frames,
            interpolation,
        } => pb::camera_path::Path::Keyframes(pb::KeyframePath {
            keyframes: keyframes
                .iter()
                .map(|k| pb::Keyframe {
                    position: Some(vec3(&k.position)),
                    target: Some(vec3(&k.target)),
                    up: Some(vec3(&k.up)),
                    fov_y_deg: k.fov_y_deg,
                })
                .collect(),
            frames: *frames,
            interpolation: match interpolation {
                Interpolation::Linear => pb::Interpolation::Linear,
                Interpolation::Spline => pb::Interpolation::Spline,
            } as i32,
        }),
    };
    pb::CameraPath { path: Some(path) }
}

/// The inverse of [`render_options`].
pub fn render_options_message(options: &RenderOptions) -> pb::RenderOptions {
    // Destructured so that a new option cannot be forgotten here.
    let RenderOptions {
        point_size,
        quality,
        shading,
        color_mode,
        background,
        fill,
    } = options;
    let mut message = pb::RenderOptions {
        point_size: *point_size,
        background: Some(color(*background)),
        fill: fill.map(|Fill { kernel }| pb::FillOptions { kernel }),
        ..Default::default()
    };
    match *quality {
        Quality::Basic => message.quality = pb::Quality::Basic as i32,
        Quality::High { depth_band } => {
            message.quality = pb::Quality::High as i32;
            message.depth_band = Some(depth_band);
        }
    }
    match *shading {
        Shading::None => message.shading = pb::Shading::None as i32,
        Shading::Edl { strength, radius } => {
            message.shading = pb::Shading::Edl as i32;
            message.edl_strength = Some(strength);
            message.edl_radius = Some(radius);
        }
        Shading::Pintus { levels, exponent } => {
            message.shading = pb::Shading::Pintus as i32;
            message.pintus_levels = Some(levels);
            message.pintus_exponent = Some(exponent);
        }
    }
    message.color_mode = match *color_mode {
        ColorMode::Rgb => pb::ColorMode::Rgb,
        ColorMode::Intensity => pb::ColorMode::Intensity,
        ColorMode::Elevation => pb::ColorMode::Elevation,
        ColorMode::Classification => pb::ColorMode::Classification,
        ColorMode::ReturnNumber => pb::ColorMode::ReturnNumber,
        ColorMode::Fixed([r, g, b]) => {
            message.fixed_color = Some(color([r, g, b, 255]));
            pb::ColorMode::Fixed
        }
    } as i32;
    message
}
// ------------------------------------------------------------ end of render options and camera paths

#[cfg(test)]
mod tests {
    use super::*;

    fn valid() -> pb::SubmitJobRequest {
        pb::SubmitJobRequest {
            request_id: "r1".into(),
            dataset_id: "ds-1".into(),
            camera_path: Some(pb::CameraPath {
                path: Some(pb::camera_path::Path::Turntable(pb::Turntable {
                    frames: 4,
                    ..Default::default()
                })),
            }),
            width: 64,
            height: 48,
            render: None,
            priority: 0,
        }
    }

    fn field_of(r: &pb::SubmitJobRequest) -> String {
        match JobSpec::try_from(r) {
            Err(DaemonError::InvalidArgument { field, .. }) => field,
            other => panic!("expected InvalidArgument, got {other:?}"),
        }
    }

    #[test]
    fn invalid_submissions_name_the_field() {
        assert!(JobSpec::try_from(&valid()).is_ok());
        let mut r = valid();
        r.camera_path = Some(pb::CameraPath {
            path: Some(pb::camera_path::Path::Turntable(pb::Turntable {
                frames: 0,
                ..Default::default()
            })),
        });
        assert_eq!(field_of(&r), "camera_path.turntable.frames");
        let mut r = valid();
        r.camera_path = Some(pb::CameraPath {
            path: Some(pb::camera_path::Path::Turntable(pb::Turntable {
                frames: 2,
                center: Some(pb::Vec3 {
                    x: f64::NAN,
                    y: 0.0,
                    z: 0.0,
                }),
                ..Default::default()
            })),
        });
        assert_eq!(field_of(&r), "camera_path.turntable.center");
        let mut r = valid();
        let key = |x: f64| pb::Keyframe {
            position: Some(pb::Vec3 { x, y: 0.0, z: 10.0 }),
            target: Some(pb::Vec3 {
                x: 0.0,
                y: 0.0,
                z: 0.0,
            }),
            up: None,
            fov_y_deg: 50.0,
        };
        r.camera_path = Some(pb::CameraPath {
            path: Some(pb::camera_path::Path::Keyframes(pb::KeyframePath {
                keyframes: vec![key(1.0), key(f64::NAN)],
                frames: 3,
                interpolation: 0,
            })),
        });
        assert_eq!(field_of(&r), "camera_path.keyframes.keyframes[1].position");
        let mut r = valid();
        r.width = 0;
        assert_eq!(field_of(&r), "width");
        let mut r = valid();
        r.camera_path = None;
        assert_eq!(field_of(&r), "camera_path");
        let mut r = valid();
        r.render = Some(pb::RenderOptions {
            point_size: 1000,
            ..Default::default()
        });
        assert_eq!(field_of(&r), "render.point_size");
        let mut r = valid();
        r.render = Some(pb::RenderOptions {
            quality: pb::Quality::High as i32,
            depth_band: Some(f32::NAN),
            ..Default::default()
        });
        assert_eq!(field_of(&r), "render.depth_band");
        for kernel in [1, 4, 11] {
            let mut r = valid();
            r.render = Some(pb::RenderOptions {
                fill: Some(pb::FillOptions { kernel }),
                ..Default::default()
            });
            assert_eq!(field_of(&r), "render.fill.kernel");
        }
        let mut r = valid();
        r.render = Some(pb::RenderOptions {
            shading: pb::Shading::Pintus as i32,
            pintus_levels: Some(0),
            ..Default::default()
        });
        assert_eq!(field_of(&r), "render.pintus_levels");
        let mut r = valid();
        r.render = Some(pb::RenderOptions {
            shading: pb::Shading::Pintus as i32,
            pintus_exponent: Some(f32::NAN),
            ..Default::default()
        });
        assert_eq!(field_of(&r), "render.pintus_exponent");
    }

    #[test]
    fn fill_and_pintus_shading_convert_with_defaults() {
        let mut r = valid();
        r.render = Some(pb::RenderOptions {
            shading: pb::Shading::Pintus as i32,
            fill: Some(pb::FillOptions { kernel: 0 }),
            ..Default::default()
        });
        let render = JobSpec::try_from(&r).expect("valid").render;
        assert_eq!(render.fill, Some(Fill { kernel: 7 }));
        assert_eq!(
            render.shading,
            Shading::Pintus {
                levels: 8,
                exponent: 1.5
            }
        );
        assert_eq!(
            JobSpec::try_from(&valid()).expect("valid").render.fill,
            None
        );
    }

    #[test]
    fn tasks_carry_the_job_spec_unchanged_across_the_wire() {
        let mut r = valid();
        r.render = Some(pb::RenderOptions {
            point_size: 3,
            quality: pb::Quality::High as i32,
            depth_band: Some(0.02),
            shading: pb::Shading::Edl as i32,
            edl_strength: Some(2.0),
            edl_radius: Some(2.5),
            color_mode: pb::ColorMode::Fixed as i32,
            fixed_color: Some(pb::Color { rgba: 0x10203040 }),
            background: Some(pb::Color { rgba: 0x01020304 }),
            fill: Some(pb::FillOptions { kernel: 5 }),
            ..Default::default()
        });
        let key = |x: f64| pb::Keyframe {
            position: Some(pb::Vec3 { x, y: 0.0, z: 10.0 }),
            target: Some(pb::Vec3 {
                x: 0.0,
                y: 1.0,
                z: 0.0,
            }),
            up: None,
            fov_y_deg: 40.0,
        };
        let keyframes = pb::CameraPath {
            path: Some(pb::camera_path::Path::Keyframes(pb::KeyframePath {
                keyframes: vec![key(1.0), key(5.0), key(9.0)],
                frames: 7,
                interpolation: pb::Interpolation::Spline as i32,
            })),
        };
        let turntable = pb::CameraPath {
            path: Some(pb::camera_path::Path::Turntable(pb::Turntable {
                frames: 5,
                center: Some(pb::Vec3 {
                    x: 1e6,
                    y: 2e6,
                    z: 3.0,
                }),
                radius: Some(12.5),
                ..Default::default()
            })),
        };
        for path in [keyframes, turntable] {
            r.camera_path = Some(path);
            let spec = JobSpec::try_from(&r).expect("valid");
            let task = FrameTask {
                lease: Lease {
                    id: "lease-1".into(),
                    job_id: "job-1".into(),
                    index: 4,
                    worker: "w".into(),
                    embedded: false,
                    expires_unix_ms: 1234,
                },
                lease_timeout: std::time::Duration::from_secs(30),
                dataset: TaskDataset {
                    id: "ds-1".into(),
                    sha256: "ab".repeat(32),
                    size_bytes: 99,
                },
                camera_path: spec.camera_path,
                width: spec.width,
                height: spec.height,
                render: spec.render,
                failed_attempts: 2,
            };
            let received = frame_task(&frame_task_message(&task), "w").expect("valid task");
            assert_eq!(received, task);
        }
    }
}
