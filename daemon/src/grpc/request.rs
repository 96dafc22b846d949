//! The render request on the wire: `pointfarm.v1` camera paths, lenses and render options to
//! the render crate's [`RenderRequest`] and back. Absent fields take the render crate's
//! defaults, and the result is checked by the request's one `validate()`, whose field names
//! are these messages' paths. Plain functions rather than `From`/`TryFrom`, because both
//! sides are other crates' types; `JobSpec`'s conversions build on them.

use pointfarm_proto::v1 as pb;
use pointfarm_render::color::{ColorMode, ColorRamp, ColorRange};
use pointfarm_render::filter::{ClipBox, CodeSet, IntensityRange, PointFilter};
use pointfarm_render::raster::{FillSettings, Quality, Shading, DEFAULT_DEPTH_BAND};
use pointfarm_render::request::{
    CameraPath, Interpolation, Keyframe, Lens, Point3, PointSize, RenderOptions, RenderRequest,
    RequestError, StillCamera, Turntable, DEFAULT_UP,
};

use crate::error::DaemonError;
use crate::model::JobSpec;
use pointfarm_render::source::BuildUnseen;

/// The value of a proto enum field, or an error naming `field` for a number this API does not
/// define (a newer client's value, or garbage).
pub(super) fn known_enum<E: TryFrom<i32>>(field: &str, value: i32) -> Result<E, DaemonError> {
    E::try_from(value).map_err(|_| DaemonError::invalid(field, format!("unknown value {value}")))
}

impl From<RequestError> for DaemonError {
    fn from(e: RequestError) -> Self {
        DaemonError::invalid(e.field, e.message)
    }
}

/// The request of a submission or a frame task, validated.
pub fn render_request(
    width: u32,
    height: u32,
    camera_path: Option<&pb::CameraPath>,
    render: Option<&pb::RenderOptions>,
) -> Result<RenderRequest, DaemonError> {
    let (camera_path, lens) = camera_path_and_lens(camera_path)?;
    let request = RenderRequest {
        width,
        height,
        camera_path,
        lens,
        render: render_options(render)?,
    };
    request.validate()?;
    Ok(request)
}

fn point(v: &pb::Vec3) -> Point3 {
    Point3 {
        x: v.x,
        y: v.y,
        z: v.z,
    }
}

fn required_point(field: &str, v: Option<&pb::Vec3>) -> Result<Point3, DaemonError> {
    v.map(point)
        .ok_or_else(|| DaemonError::invalid(field, "is required"))
}

fn camera_path_and_lens(
    message: Option<&pb::CameraPath>,
) -> Result<(CameraPath, Lens), DaemonError> {
    let path = message.and_then(|p| p.path.as_ref()).ok_or_else(|| {
        DaemonError::invalid("camera_path", "is required (turntable, keyframes or still)")
    })?;
    let camera_path = match path {
        pb::camera_path::Path::Turntable(t) => {
            let default = Turntable::around_the_cloud(t.frames);
            CameraPath::Turntable(Turntable {
                center: t.center.as_ref().map(point),
                radius: t.radius,
                elevation_deg: t.elevation_deg.unwrap_or(default.elevation_deg),
                degrees: t.degrees.unwrap_or(default.degrees),
                fov_y_deg: t.fov_y_deg.unwrap_or(default.fov_y_deg),
                azimuth_deg: t.azimuth_deg.unwrap_or(default.azimuth_deg),
                up: t.up.as_ref().map_or(default.up, point),
                start: t.start.as_ref().map(point),
                ..default
            })
        }
        pb::camera_path::Path::Keyframes(k) => {
            let keyframes = k
                .keyframes
                .iter()
                .enumerate()
                .map(|(i, key)| {
                    let f = |name: &str| format!("camera_path.keyframes.keyframes[{i}].{name}");
                    Ok(Keyframe {
                        position: required_point(&f("position"), key.position.as_ref())?,
                        target: required_point(&f("target"), key.target.as_ref())?,
                        up: key.up.as_ref().map_or(DEFAULT_UP, point),
                        fov_y_deg: key.fov_y_deg,
                    })
                })
                .collect::<Result<Vec<_>, DaemonError>>()?;
            let interpolation =
                match known_enum("camera_path.keyframes.interpolation", k.interpolation)? {
                    pb::Interpolation::Spline => Interpolation::Spline,
                    pb::Interpolation::Linear | pb::Interpolation::Unspecified => {
                        Interpolation::Linear
                    }
                };
            CameraPath::Keyframes {
                keyframes,
                frames: k.frames,
                interpolation,
            }
        }
        pb::camera_path::Path::Still(s) => {
            let default = StillCamera::default();
            CameraPath::Still(StillCamera {
                position: s.position.as_ref().map(point),
                target: s.target.as_ref().map(point),
                up: s.up.as_ref().map_or(default.up, point),
                fov_y_deg: s.fov_y_deg.unwrap_or(default.fov_y_deg),
                azimuth_deg: s.azimuth_deg.unwrap_or(default.azimuth_deg),
                elevation_deg: s.elevation_deg.unwrap_or(default.elevation_deg),
            })
        }
    };
    let lens = message
        .and_then(|p| p.lens.as_ref())
        .map_or_else(Lens::default, |l| Lens {
            orthographic: l.orthographic,
            ortho_height: l.ortho_height,
            near: l.near,
            far: l.far,
        });
    Ok((camera_path, lens))
}

fn rgba(color: &pb::Color) -> [u8; 4] {
    color.rgba.to_be_bytes()
}

fn render_options(message: Option<&pb::RenderOptions>) -> Result<RenderOptions, DaemonError> {
    let empty = pb::RenderOptions::default();
    let o = message.unwrap_or(&empty);
    let default = RenderOptions::default();
    let quality = match known_enum("render.quality", o.quality)? {
        pb::Quality::High => Quality::High {
            depth_band: o.depth_band.unwrap_or(DEFAULT_DEPTH_BAND),
        },
        pb::Quality::Basic | pb::Quality::Unspecified => Quality::Basic,
    };
    // Unset: the default's kind, with the parameters the message gives.
    let kind = match known_enum("render.shading", o.shading)? {
        pb::Shading::Unspecified => match default.shading {
            Shading::None => pb::Shading::None,
            Shading::Edl { .. } => pb::Shading::Edl,
            Shading::Pintus { .. } => pb::Shading::Pintus,
        },
        kind => kind,
    };
    let shading = match kind {
        pb::Shading::Edl => Shading::Edl {
            strength: o.edl_strength.unwrap_or(Shading::DEFAULT_EDL_STRENGTH),
            radius: o.edl_radius.unwrap_or(Shading::DEFAULT_EDL_RADIUS),
        },
        pb::Shading::Pintus => Shading::Pintus {
            levels: o.pintus_levels.unwrap_or(Shading::DEFAULT_PINTUS_LEVELS),
            exponent: o
                .pintus_exponent
                .unwrap_or(Shading::DEFAULT_PINTUS_EXPONENT),
        },
        pb::Shading::None | pb::Shading::Unspecified => Shading::None,
    };
    let color_mode = match known_enum("render.color_mode", o.color_mode)? {
        pb::ColorMode::Unspecified | pb::ColorMode::Rgb => ColorMode::Rgb,
        pb::ColorMode::Intensity => ColorMode::Intensity,
        pb::ColorMode::Elevation => ColorMode::Elevation,
        pb::ColorMode::Classification => ColorMode::Classification,
        pb::ColorMode::ReturnNumber => ColorMode::ReturnNumber,
        pb::ColorMode::Fixed => {
            let [r, g, b, _] = o.fixed_color.as_ref().map(rgba).ok_or_else(|| {
                DaemonError::invalid("render.fixed_color", "is required with COLOR_MODE_FIXED")
            })?;
            ColorMode::Fixed([r, g, b])
        }
    };
    let color_ramp = match known_enum("render.color_ramp", o.color_ramp)? {
        pb::ColorRamp::Unspecified => None,
        pb::ColorRamp::Viridis => Some(ColorRamp::Viridis),
        pb::ColorRamp::Inferno => Some(ColorRamp::Inferno),
        pb::ColorRamp::Turbo => Some(ColorRamp::Turbo),
        pb::ColorRamp::Grey => Some(ColorRamp::Grey),
    };
    Ok(RenderOptions {
        point_size: PointSize::from(o.point_size),
        round_points: o.round_points,
        quality,
        shading,
        color_mode,
        color_range: o.color_range.as_ref().map(|r| ColorRange {
            min: r.min,
            max: r.max,
        }),
        color_ramp,
        background: o.background.as_ref().map_or(default.background, rgba),
        fill: o.fill.as_ref().map(|f| FillSettings {
            kernel: if f.kernel == 0 {
                FillSettings::DEFAULT_KERNEL
            } else {
                f.kernel
            },
        }),
        supersample: o.supersample.unwrap_or(default.supersample),
        // The service has no depth output (the proto says so); the CLI refuses it there.
        depth: false,
        lod_error: o.lod_error,
        filter: o
            .filter
            .as_ref()
            .map(point_filter)
            .transpose()?
            .unwrap_or_default(),
    })
}

/// A code list as a set: `None` when empty (every code), an error naming the field when a
/// code does not fit in a byte.
fn code_set(field: &str, codes: &[u32]) -> Result<Option<CodeSet>, DaemonError> {
    if codes.is_empty() {
        return Ok(None);
    }
    let bytes = codes
        .iter()
        .map(|&code| {
            u8::try_from(code).map_err(|_| {
                DaemonError::invalid(
                    field,
                    format!("code {code} is invalid: it must be 0 to 255"),
                )
            })
        })
        .collect::<Result<Vec<u8>, _>>()?;
    Ok(Some(CodeSet::of(bytes)))
}

fn point_filter(f: &pb::PointFilter) -> Result<PointFilter, DaemonError> {
    let intensity = |value: u32| {
        u16::try_from(value).map_err(|_| {
            DaemonError::invalid(
                "render.filter.intensity",
                format!("intensity {value} is invalid: it must be 0 to 65535"),
            )
        })
    };
    Ok(PointFilter {
        classes: code_set("render.filter.classes", &f.classes)?,
        return_numbers: code_set("render.filter.return_numbers", &f.return_numbers)?,
        intensity: match &f.intensity {
            Some(range) => Some(IntensityRange {
                min: intensity(range.min)?,
                max: intensity(range.max)?,
            }),
            None => None,
        },
        clip: match &f.clip {
            Some(clip) => {
                let corner = |name: &str, v: Option<&pb::Vec3>| {
                    required_point(&format!("render.filter.clip.{name}"), v)
                        .map(|p| [p.x, p.y, p.z])
                };
                Some(ClipBox {
                    min: corner("min", clip.min.as_ref())?,
                    max: corner("max", clip.max.as_ref())?,
                })
            }
            None => None,
        },
    })
}

fn point_filter_message(filter: &PointFilter) -> Option<pb::PointFilter> {
    let PointFilter {
        classes,
        return_numbers,
        intensity,
        clip,
    } = *filter;
    if filter.keeps_everything() {
        return None;
    }
    let codes = |set: Option<CodeSet>| {
        set.map(|s| s.codes().into_iter().map(u32::from).collect())
            .unwrap_or_default()
    };
    let corner = |[x, y, z]: [f64; 3]| pb::Vec3 { x, y, z };
    Some(pb::PointFilter {
        classes: codes(classes),
        return_numbers: codes(return_numbers),
        intensity: intensity.map(|r| pb::IntensityRange {
            min: r.min.into(),
            max: r.max.into(),
        }),
        clip: clip.map(|c| pb::ClipBox {
            min: Some(corner(c.min)),
            max: Some(corner(c.max)),
        }),
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

/// The message of a camera path and its lens, the inverse of [`render_request`]'s reading.
pub fn camera_path_message(path: &CameraPath, lens: &Lens) -> pb::CameraPath {
    let path = match path {
        CameraPath::Turntable(t) => pb::camera_path::Path::Turntable(pb::Turntable {
            frames: t.frames,
            center: t.center.as_ref().map(vec3),
            radius: t.radius,
            elevation_deg: Some(t.elevation_deg),
            degrees: Some(t.degrees),
            fov_y_deg: Some(t.fov_y_deg),
            azimuth_deg: Some(t.azimuth_deg),
            up: Some(vec3(&t.up)),
            start: t.start.as_ref().map(vec3),
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
        CameraPath::Still(s) => pb::camera_path::Path::Still(pb::StillCamera {
            position: s.position.as_ref().map(vec3),
            target: s.target.as_ref().map(vec3),
            up: Some(vec3(&s.up)),
            fov_y_deg: Some(s.fov_y_deg),
            azimuth_deg: Some(s.azimuth_deg),
            elevation_deg: Some(s.elevation_deg),
        }),
    };
    let Lens {
        orthographic,
        ortho_height,
        near,
        far,
    } = *lens;
    pb::CameraPath {
        path: Some(path),
        lens: Some(pb::Lens {
            orthographic,
            ortho_height,
            near,
            far,
        }),
    }
}

/// The message of render options. `depth` is not carried: the service has no depth output,
/// and the CLI refuses `--depth` with `--server` before it gets here.
pub fn render_options_message(options: &RenderOptions) -> pb::RenderOptions {
    // Destructured so that a new option cannot be forgotten here.
    let RenderOptions {
        point_size,
        round_points,
        quality,
        shading,
        color_mode,
        color_range,
        color_ramp,
        background,
        fill,
        supersample,
        depth: _,
        lod_error,
        filter,
    } = *options;
    let mut message = pb::RenderOptions {
        point_size: point_size.into(),
        round_points,
        lod_error,
        filter: point_filter_message(&filter),
        color_range: color_range.map(|ColorRange { min, max }| pb::ColorRange { min, max }),
        color_ramp: match color_ramp {
            None => pb::ColorRamp::Unspecified,
            Some(ColorRamp::Viridis) => pb::ColorRamp::Viridis,
            Some(ColorRamp::Inferno) => pb::ColorRamp::Inferno,
            Some(ColorRamp::Turbo) => pb::ColorRamp::Turbo,
            Some(ColorRamp::Grey) => pb::ColorRamp::Grey,
        } as i32,
        background: Some(color(background)),
        fill: fill.map(|FillSettings { kernel }| pb::FillOptions { kernel }),
        supersample: Some(supersample),
        ..Default::default()
    };
    match quality {
        Quality::Basic => message.quality = pb::Quality::Basic as i32,
        Quality::High { depth_band } => {
            message.quality = pb::Quality::High as i32;
            message.depth_band = Some(depth_band);
        }
    }
    match shading {
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
    message.color_mode = match color_mode {
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

/// The submission of a job: what `pointfarm render --server` sends, and what a job's message
/// shows of its spec.
impl From<&JobSpec> for pb::SubmitJobRequest {
    fn from(spec: &JobSpec) -> Self {
        let request = &spec.request;
        pb::SubmitJobRequest {
            request_id: spec.request_id.clone(),
            dataset_id: spec.dataset_id.clone(),
            camera_path: Some(camera_path_message(&request.camera_path, &request.lens)),
            width: request.width,
            height: request.height,
            render: Some(render_options_message(&request.render)),
            priority: spec.priority,
            requirements: (!spec.requirements.is_empty())
                .then(|| pb::WorkerRequirements::from(&spec.requirements)),
            preview: spec.preview,
            after_job_ids: spec.after.clone(),
            name: spec.name.clone(),
            labels: spec.labels.clone().into_iter().collect(),
            video: spec.video.as_ref().map(super::video::video_spec_message),
            output_url: spec.output_url.clone().unwrap_or_default(),
            build_unseen: build_unseen_message(spec.build_unseen) as i32,
        }
    }
}

/// The files no frame of a job sees, as the job asks: unset is the option's default.
pub(super) fn build_unseen(value: i32) -> Result<BuildUnseen, DaemonError> {
    Ok(match known_enum("build_unseen", value)? {
        pb::BuildUnseen::Unspecified => BuildUnseen::default(),
        pb::BuildUnseen::After => BuildUnseen::After,
        pb::BuildUnseen::Never => BuildUnseen::Never,
    })
}

/// [`build_unseen`] on the wire, always set, so a job's spec shows the choice.
pub(in crate::grpc) fn build_unseen_message(unseen: BuildUnseen) -> pb::BuildUnseen {
    match unseen {
        BuildUnseen::After => pb::BuildUnseen::After,
        BuildUnseen::Never => pb::BuildUnseen::Never,
    }
}
