//! The one validation of a render request: every range it checks is a named constant of the
//! renderer's settings or of the camera path, and every error names the field at fault with
//! the path the service's messages use (`render.edl_strength`, `camera_path.turntable.frames`).

use std::fmt::Display;
use std::ops::RangeInclusive;

use super::camera_path::{
    CameraPath, Keyframe, Lens, Point3, StillCamera, Turntable, FOV_Y_DEG_RANGE, MAX_COORDINATE,
    MIN_KEYFRAMES, TURNTABLE_DEGREES_RANGE, TURNTABLE_ELEVATION_RANGE, VIEW_ELEVATION_RANGE,
};
use super::{PointSize, RenderOptions, RenderRequest};
use crate::color::ColorRange;
use crate::cut::MAX_LOD_ERROR_PX;
use crate::filter::{IntensityRange, PointFilter, MAX_RETURN_NUMBER};
use crate::raster::{
    FillSettings, Quality, Shading, DEPTH_BAND_RANGE, EDL_RADIUS_RANGE, EDL_STRENGTH_RANGE,
    MAX_FILL_KERNEL, MAX_PINTUS_LEVELS, MAX_POINT_SIZE, MAX_SUPERSAMPLE, MIN_FILL_KERNEL,
    PINTUS_EXPONENT_RANGE,
};

/// A field of a render request is invalid.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{field}: {message}")]
pub struct RequestError {
    /// Where the field sits, e.g. `render.fill.kernel` or `camera_path.keyframes.keyframes[1].up`.
    pub field: String,
    pub message: String,
}

fn invalid(field: impl Into<String>, message: impl Into<String>) -> RequestError {
    RequestError {
        field: field.into(),
        message: message.into(),
    }
}

type Checked = Result<(), RequestError>;

impl RenderRequest {
    /// Checks every field; the first invalid one is the error.
    pub fn validate(&self) -> Checked {
        // The largest size depends on the adapter (and on a server's limits): the renderer
        // and the daemon check it.
        for (field, side) in [("width", self.width), ("height", self.height)] {
            if side == 0 {
                return Err(invalid(field, "must be at least 1 pixel"));
            }
        }
        self.camera_path.validate()?;
        self.lens.validate()?;
        self.render.validate()
    }
}

/// `value` lies in `range` (and is finite).
fn within<T: Into<f64> + Copy + Display>(
    field: &str,
    what: &str,
    value: T,
    range: &RangeInclusive<T>,
    unit: &str,
) -> Checked {
    let (wide, low, high) = (value.into(), (*range.start()).into(), (*range.end()).into());
    if wide.is_finite() && (low..=high).contains(&wide) {
        Ok(())
    } else {
        Err(invalid(
            field,
            format!(
                "{what} {value} is invalid: it must be a finite number from {} to {}{unit}",
                range.start(),
                range.end()
            ),
        ))
    }
}

/// The whole number `value` lies in `range`.
fn counted(
    field: &str,
    what: &str,
    (value, range): (u32, RangeInclusive<u32>),
    unit: &str,
) -> Checked {
    if range.contains(&value) {
        return Ok(());
    }
    let (low, high) = (range.start(), range.end());
    let message = format!("{what} {value} is invalid: it must be {low} to {high}{unit}");
    Err(invalid(field, message))
}

/// A point of a camera path: finite, and no coordinate beyond [`MAX_COORDINATE`].
fn finite_point(field: &str, p: &Point3) -> Checked {
    if !p.is_finite() {
        return Err(invalid(field, "must be finite (no NaN or infinity)"));
    }
    if [p.x, p.y, p.z].iter().any(|c| c.abs() > MAX_COORDINATE) {
        return Err(invalid(
            field,
            format!("has a coordinate beyond ±{MAX_COORDINATE:e}"),
        ));
    }
    Ok(())
}

/// A camera looking from `position` at `target` has an `up` that is not along its view: the
/// picture would have no vertical direction.
fn up_across_the_view(field: &str, up: &Point3, position: &Point3, target: &Point3) -> Checked {
    let view = glam::DVec3::from(*target) - glam::DVec3::from(*position);
    let up = glam::DVec3::from(*up);
    if view.cross(up).length() <= 1e-9 * view.length() * up.length() {
        return Err(invalid(field, "is parallel to the view direction"));
    }
    Ok(())
}

fn direction(field: &str, p: &Point3) -> Checked {
    finite_point(field, p)?;
    if glam::DVec3::from(*p).length_squared() == 0.0 {
        return Err(invalid(field, "must not be the zero vector"));
    }
    Ok(())
}

fn field_of_view(field: &str, fov_y_deg: f64) -> Checked {
    let (low, high) = (*FOV_Y_DEG_RANGE.start(), *FOV_Y_DEG_RANGE.end());
    if fov_y_deg.is_finite() && fov_y_deg > low && fov_y_deg < high {
        Ok(())
    } else {
        Err(invalid(
            field,
            format!("field of view {fov_y_deg} must lie in ({low}, {high}) degrees"),
        ))
    }
}

/// A length of a camera path: positive and at most [`MAX_COORDINATE`].
fn positive(field: &str, what: &str, value: f64) -> Checked {
    if value.is_finite() && value > 0.0 && value <= MAX_COORDINATE {
        Ok(())
    } else {
        Err(invalid(
            field,
            format!("{what} {value} is invalid: it must be positive, at most {MAX_COORDINATE:e}"),
        ))
    }
}

fn at_least_one_frame(field: &str, frames: u32) -> Checked {
    if frames == 0 {
        return Err(invalid(field, "must be at least 1 frame"));
    }
    Ok(())
}

impl CameraPath {
    fn validate(&self) -> Checked {
        match self {
            CameraPath::Still(still) => still.validate(),
            CameraPath::Turntable(turntable) => turntable.validate(),
            CameraPath::Keyframes {
                keyframes, frames, ..
            } => {
                at_least_one_frame("camera_path.keyframes.frames", *frames)?;
                if keyframes.len() < MIN_KEYFRAMES {
                    return Err(invalid(
                        "camera_path.keyframes.keyframes",
                        format!("needs at least {MIN_KEYFRAMES} keyframes"),
                    ));
                }
                for (i, key) in keyframes.iter().enumerate() {
                    key.validate(&format!("camera_path.keyframes.keyframes[{i}]"))?;
                }
                Ok(())
            }
        }
    }
}

impl StillCamera {
    fn validate(&self) -> Checked {
        let f = |name: &str| format!("camera_path.still.{name}");
        for (name, point) in [("position", self.position), ("target", self.target)] {
            if let Some(p) = point {
                finite_point(&f(name), &p)?;
            }
        }
        if self.position.is_some() && self.position == self.target {
            return Err(invalid(
                f("target"),
                "camera position and target are the same point",
            ));
        }
        direction(&f("up"), &self.up)?;
        if let (Some(position), Some(target)) = (&self.position, &self.target) {
            up_across_the_view(&f("up"), &self.up, position, target)?;
        }
        view_angles(
            &f,
            self.azimuth_deg,
            self.elevation_deg,
            &VIEW_ELEVATION_RANGE,
        )?;
        field_of_view(&f("fov_y_deg"), self.fov_y_deg)
    }
}

/// A view's azimuth (any finite angle) and its elevation (within `elevations`), named by `f`.
fn view_angles(
    f: &dyn Fn(&str) -> String,
    azimuth_deg: f64,
    elevation_deg: f64,
    elevations: &std::ops::RangeInclusive<f64>,
) -> Checked {
    within(
        &f("elevation_deg"),
        "elevation",
        elevation_deg,
        elevations,
        " degrees",
    )?;
    if !azimuth_deg.is_finite() {
        return Err(invalid(f("azimuth_deg"), "must be finite"));
    }
    Ok(())
}

impl Turntable {
    fn validate(&self) -> Checked {
        let f = |name: &str| format!("camera_path.turntable.{name}");
        at_least_one_frame(&f("frames"), self.frames)?;
        if let Some(center) = &self.center {
            finite_point(&f("center"), center)?;
        }
        if let Some(radius) = self.radius {
            positive(&f("radius"), "radius", radius)?;
        }
        if let Some(start) = &self.start {
            finite_point(&f("start"), start)?;
            if self.radius.is_some() {
                return Err(invalid(
                    f("radius"),
                    "cannot be given with a start position",
                ));
            }
            if self.center == Some(*start) {
                return Err(invalid(f("start"), "is the centre of the orbit"));
            }
        }
        view_angles(
            &f,
            self.azimuth_deg,
            self.elevation_deg,
            &TURNTABLE_ELEVATION_RANGE,
        )?;
        within(
            &f("degrees"),
            "angle",
            self.degrees,
            &TURNTABLE_DEGREES_RANGE,
            " degrees",
        )?;
        direction(&f("up"), &self.up)?;
        field_of_view(&f("fov_y_deg"), self.fov_y_deg)
    }
}

impl Keyframe {
    fn validate(&self, at: &str) -> Checked {
        let f = |name: &str| format!("{at}.{name}");
        finite_point(&f("position"), &self.position)?;
        finite_point(&f("target"), &self.target)?;
        if self.position == self.target {
            return Err(invalid(f("target"), "must differ from the position"));
        }
        direction(&f("up"), &self.up)?;
        up_across_the_view(&f("up"), &self.up, &self.position, &self.target)?;
        field_of_view(&f("fov_y_deg"), self.fov_y_deg)
    }
}

impl Lens {
    fn validate(&self) -> Checked {
        let f = |name: &str| format!("camera_path.lens.{name}");
        if let Some(height) = self.ortho_height {
            if !self.orthographic {
                return Err(invalid(
                    f("ortho_height"),
                    "needs the orthographic projection",
                ));
            }
            positive(&f("ortho_height"), "orthographic view height", height)?;
        }
        if let Some(near) = self.near {
            positive(&f("near"), "near distance", near)?;
        }
        if let Some(far) = self.far {
            positive(&f("far"), "far distance", far)?;
        }
        if let (Some(near), Some(far)) = (self.near, self.far) {
            if far <= near {
                return Err(invalid(
                    f("far"),
                    format!("far distance {far} must be beyond the near distance {near}"),
                ));
            }
        }
        Ok(())
    }
}

impl RenderOptions {
    /// A color range (finite, min below max) and ramp only with a mode drawn through them.
    fn validate_color_ramp(&self) -> Checked {
        let mode = self.color_mode;
        let applies = |field: &str| {
            if mode.is_ramped() {
                Ok(())
            } else {
                Err(invalid(
                    field,
                    format!(
                        "applies only to the elevation and intensity color modes, not {}",
                        mode.name()
                    ),
                ))
            }
        };
        if let Some(ColorRange { min, max }) = self.color_range {
            applies("render.color_range")?;
            if !(min.is_finite() && max.is_finite()) {
                return Err(invalid(
                    "render.color_range",
                    format!("color range {min}..{max} is invalid: both ends must be finite"),
                ));
            }
            if min >= max {
                return Err(invalid(
                    "render.color_range",
                    format!("color range {min}..{max} is invalid: min must be below max"),
                ));
            }
        }
        if self.color_ramp.is_some() {
            applies("render.color_ramp")?;
        }
        Ok(())
    }

    fn validate(&self) -> Checked {
        if let PointSize::Fixed(side) = self.point_size {
            counted(
                "render.point_size",
                "point size",
                (side, 1..=MAX_POINT_SIZE),
                " pixels",
            )?;
        }
        self.validate_color_ramp()?;
        if let Quality::High { depth_band } = self.quality {
            within(
                "render.depth_band",
                "depth band",
                depth_band,
                &DEPTH_BAND_RANGE,
                "",
            )?;
        }
        match self.shading {
            Shading::None => {}
            Shading::Edl { strength, radius } => {
                let what = "Eye-Dome Lighting strength";
                within(
                    "render.edl_strength",
                    what,
                    strength,
                    &EDL_STRENGTH_RANGE,
                    "",
                )?;
                let what = "Eye-Dome Lighting radius";
                within(
                    "render.edl_radius",
                    what,
                    radius,
                    &EDL_RADIUS_RANGE,
                    " pixels",
                )?;
            }
            Shading::Pintus { levels, exponent } => {
                let what = "number of Pintus shading levels";
                counted(
                    "render.pintus_levels",
                    what,
                    (levels, 1..=MAX_PINTUS_LEVELS),
                    "",
                )?;
                let what = "Pintus shading exponent";
                within(
                    "render.pintus_exponent",
                    what,
                    exponent,
                    &PINTUS_EXPONENT_RANGE,
                    "",
                )?;
            }
        }
        if let Some(FillSettings { kernel }) = self.fill {
            if !(MIN_FILL_KERNEL..=MAX_FILL_KERNEL).contains(&kernel) || kernel.is_multiple_of(2) {
                return Err(invalid(
                    "render.fill.kernel",
                    format!(
                        "fill kernel {kernel} is invalid: it must be an odd number of pixels \
                         from {MIN_FILL_KERNEL} to {MAX_FILL_KERNEL}"
                    ),
                ));
            }
        }
        if let Some(lod_error) = self.lod_error {
            if !(lod_error.is_finite() && (0.0..=MAX_LOD_ERROR_PX).contains(&lod_error)) {
                return Err(invalid(
                    "render.lod_error",
                    format!(
                        "level-of-detail pixel error {lod_error} is invalid: it must be 0 to \
                         {MAX_LOD_ERROR_PX} pixels"
                    ),
                ));
            }
        }
        let supersample = (self.supersample, 1..=MAX_SUPERSAMPLE);
        counted(
            "render.supersample",
            "supersampling factor",
            supersample,
            "",
        )?;
        self.filter.validate()
    }
}

impl PointFilter {
    fn validate(&self) -> Checked {
        let sets = [
            ("render.filter.classes", "class", self.classes, u8::MAX),
            (
                "render.filter.return_numbers",
                "return number",
                self.return_numbers,
                MAX_RETURN_NUMBER,
            ),
        ];
        for (field, what, set, max) in sets {
            let Some(set) = set else { continue };
            if set.is_empty() {
                return Err(invalid(
                    field,
                    format!("lists no {what}: nothing would be drawn"),
                ));
            }
            if let Some(highest) = set.max().filter(|&highest| highest > max) {
                return Err(invalid(
                    field,
                    format!("{what} {highest} is invalid: it must be 0 to {max}"),
                ));
            }
        }
        if let Some(IntensityRange { min, max }) = self.intensity {
            if min > max {
                return Err(invalid(
                    "render.filter.intensity",
                    format!(
                        "intensity range {min}..{max} is empty: its minimum is above its maximum"
                    ),
                ));
            }
        }
        if let Some(clip) = self.clip {
            let field = "render.filter.clip";
            for (axis, (min, max)) in ["x", "y", "z"]
                .iter()
                .zip(clip.min.into_iter().zip(clip.max))
            {
                for value in [min, max] {
                    if !value.is_finite() || value.abs() > MAX_COORDINATE {
                        return Err(invalid(
                            field,
                            format!(
                                "{axis} {value} is invalid: coordinates must be finite and at \
                                 most {MAX_COORDINATE:e} in magnitude"
                            ),
                        ));
                    }
                }
                if min >= max {
                    return Err(invalid(
                        field,
                        format!("the box is empty along {axis}: {min} is not below {max}"),
                    ));
                }
            }
        }
        Ok(())
    }
}
