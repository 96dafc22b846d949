//! Cameras in world coordinates, turned into f64 transforms relative to a dataset origin.
//!
//! Convention (shared by the GPU passes and the CPU reference): right-handed, Z up, the camera
//! looks from `position` towards `target`; pixel (0, 0) is the top-left corner; a point covers
//! the pixel that contains its projection, pixel centres at half-integers. Depth is the linear
//! distance along the viewing direction, and a point is drawn when `near <= depth <= far`.

use glam::dcamera::rh::{proj::directx, view};
use glam::{DMat4, DVec3, DVec4};
use thiserror::Error;

use crate::cloud::WorldBounds;

#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Projection {
    /// Vertical field of view in degrees.
    Perspective { fov_y_deg: f64 },
    /// Height of the view volume in world units.
    Orthographic { height: f64 },
}

/// A camera in world coordinates (the same coordinates as the LAS file).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Camera {
    pub position: DVec3,
    pub target: DVec3,
    pub up: DVec3,
    pub projection: Projection,
    pub near: f64,
    pub far: f64,
}

#[derive(Debug, Error, PartialEq)]
pub enum CameraError {
    #[error("camera {field} is not finite")]
    NotFinite { field: &'static str },
    #[error("camera position and target are the same point")]
    NoViewDirection,
    #[error("camera up vector is zero or parallel to the view direction")]
    DegenerateUp,
    #[error("camera needs 0 < near < far (near {near}, far {far})")]
    DepthRange { near: f64, far: f64 },
    #[error("perspective field of view must lie in (0, 180) degrees, got {0}")]
    FieldOfView(f64),
    #[error("orthographic view height must be positive, got {0}")]
    OrthographicHeight(f64),
}

/// Default viewing direction of the automatic camera: from the south-east, looking down.
pub const AUTO_AZIMUTH_DEG: f64 = -60.0;
pub const AUTO_ELEVATION_DEG: f64 = 30.0;
pub const DEFAULT_FOV_Y_DEG: f64 = 50.0;
/// Room left around the framed box: 5% of its extent.
const FRAMING_MARGIN: f64 = 1.05;

/// The clip planes of a camera `distance` in front of the box it frames, of bounding radius
/// `radius`: the whole box with the framing margin, the near plane kept in front of the camera.
fn framed_clip(distance: f64, radius: f64) -> (f64, f64) {
    let reach = radius * FRAMING_MARGIN;
    ((distance - reach).max(distance * 1e-3), distance + reach)
}

impl Camera {
    /// Checks the camera for values that would give a meaningless or undefined transform.
    pub fn validate(&self) -> Result<(), CameraError> {
        let vectors = [
            ("position", self.position),
            ("target", self.target),
            ("up", self.up),
        ];
        for (field, v) in vectors {
            if !v.is_finite() {
                return Err(CameraError::NotFinite { field });
            }
        }
        for (field, v) in [("near", self.near), ("far", self.far)] {
            if !v.is_finite() {
                return Err(CameraError::NotFinite { field });
            }
        }
        let forward = self.target - self.position;
        if forward.length_squared() == 0.0 {
            return Err(CameraError::NoViewDirection);
        }
        if forward.normalize().cross(self.up).length_squared() < 1e-12 {
            return Err(CameraError::DegenerateUp);
        }
        if !(self.near > 0.0 && self.far > self.near) {
            return Err(CameraError::DepthRange {
                near: self.near,
                far: self.far,
            });
        }
        match self.projection {
            Projection::Perspective { fov_y_deg } => {
                if !(fov_y_deg.is_finite() && fov_y_deg > 0.0 && fov_y_deg < 180.0) {
                    return Err(CameraError::FieldOfView(fov_y_deg));
                }
            }
            Projection::Orthographic { height } => {
                if !(height.is_finite() && height > 0.0) {
                    return Err(CameraError::OrthographicHeight(height));
                }
            }
        }
        Ok(())
    }

    /// A camera that sees all of `bounds`, looking at its centre from the given azimuth
    /// (degrees counter-clockwise from +X) and elevation (degrees above the horizon), as close
    /// as it can while every corner of the box stays in the image, with a 5% margin.
    pub fn framing(
        bounds: &WorldBounds,
        aspect: f64,
        azimuth_deg: f64,
        elevation_deg: f64,
        projection: Projection,
    ) -> Camera {
        let view = BoxView::new(bounds, &box_corners(bounds), azimuth_deg, elevation_deg);
        let (center, radius, corners) = (view.center, view.radius, view.corners);
        let (forward, right, up) = (view.forward, view.right, view.up);
        let corners = corners.into_iter();
        let (distance, projection) = match projection {
            Projection::Perspective { fov_y_deg } => {
                let tan_y = (fov_y_deg.to_radians() * 0.5).tan();
                let tan_x = tan_y * aspect;
                // A corner c is in view when its lateral offsets fit the field of view at
                // its depth, distance + c·forward.
                let distance = corners
                    .map(|c| {
                        let fit_x = c.dot(right).abs() * FRAMING_MARGIN / tan_x;
                        let fit_y = c.dot(up).abs() * FRAMING_MARGIN / tan_y;
                        fit_x.max(fit_y) - c.dot(forward)
                    })
                    .fold(radius * 0.01, f64::max);
                (distance, projection)
            }
            Projection::Orthographic { .. } => {
                let half_height = corners
                    .map(|c| c.dot(up).abs().max(c.dot(right).abs() / aspect))
                    .fold(radius * 0.01, f64::max);
                (
                    radius * 2.0,
                    Projection::Orthographic {
                        height: 2.0 * half_height * FRAMING_MARGIN,
                    },
                )
            }
        };
        let (near, far) = framed_clip(distance, radius);
        Camera {
            position: center - forward * distance,
            target: center,
            up: DVec3::Z,
            projection,
            near,
            far,
        }
    }

    /// The automatic view: the box `bounds` seen from the given azimuth (degrees
    /// counter-clockwise from +X) and elevation (degrees above the horizon, 90 straight down
    /// with +Y, or the azimuth's far side, up the image), framed tightly: the camera looks
    /// past the box's centre so that the box's projection is centred in the image, and comes
    /// as close as the 5% margin lets every corner stay in view. [`Camera::framing`] looks
    /// at the centre instead; a turntable's views are centred the same way (`fitted_orbit`).
    pub fn fitted(
        bounds: &WorldBounds,
        aspect: f64,
        azimuth_deg: f64,
        elevation_deg: f64,
        projection: Projection,
    ) -> Camera {
        Camera::fitted_to(
            bounds,
            &box_corners(bounds),
            aspect,
            azimuth_deg,
            elevation_deg,
            projection,
        )
    }

    /// [`Camera::fitted`] to the points `outline` (world coordinates) of a cloud in `bounds`
    /// instead of the box's corners: the points that lie outermost in any direction frame the
    /// cloud itself, whose box's corners may be empty.
    pub fn fitted_to(
        bounds: &WorldBounds,
        outline: &[DVec3],
        aspect: f64,
        azimuth_deg: f64,
        elevation_deg: f64,
        projection: Projection,
    ) -> Camera {
        let view = BoxView::new(bounds, outline, azimuth_deg, elevation_deg);
        let (center, radius) = (view.center, view.radius);
        let (forward, right, up) = (view.forward, view.right, view.up);
        let max_of = |f: &dyn Fn(DVec3) -> f64| view.max_of(f);
        // The camera's offsets from the centre along right, up and forward.
        let (sideways, upwards, along, projection) = match projection {
            Projection::Perspective { fov_y_deg } => {
                let tan_y = (fov_y_deg.to_radians() * 0.5).tan() / FRAMING_MARGIN;
                let along = view.fitted_depth(tan_y * aspect, tan_y);
                let (sideways, upwards) = view.centring(along);
                (sideways, upwards, along, projection)
            }
            Projection::Orthographic { .. } => {
                let span = |axis: DVec3| {
                    let high = max_of(&|c| c.dot(axis));
                    let low = -max_of(&|c| -c.dot(axis));
                    ((high + low) * 0.5, (high - low) * 0.5)
                };
                let (a, half_width) = span(right);
                let (v, half_height) = span(up);
                let height =
                    2.0 * half_height.max(half_width / aspect).max(radius * 0.01) * FRAMING_MARGIN;
                (a, v, -radius * 2.0, Projection::Orthographic { height })
            }
        };
        let target = center + right * sideways + up * upwards;
        let (near, far) = framed_clip(-along, radius);
        Camera {
            position: target + forward * along,
            target,
            // Z is the world's up; only a view along it needs another.
            up: if elevation_deg.abs() < 89.0 {
                DVec3::Z
            } else {
                up
            },
            projection,
            near,
            far,
        }
    }

    /// A camera at `position` looking at `target`, with near and far planes that enclose
    /// `bounds` as seen from there.
    pub fn looking_at(
        position: DVec3,
        target: DVec3,
        bounds: &WorldBounds,
        projection: Projection,
    ) -> Camera {
        let radius = bounds.radius().max(1e-3);
        let distance = position.distance(bounds.center());
        Camera {
            position,
            target,
            up: DVec3::Z,
            projection,
            // Inside the cloud the near plane must still be positive: keep it small.
            near: (distance - radius * 1.05).max(radius * 1e-4),
            far: distance + radius * 1.05,
        }
    }

    /// The automatic camera: frames the whole cloud from a pleasant oblique view.
    pub fn auto(bounds: &WorldBounds, aspect: f64) -> Camera {
        Camera::framing(
            bounds,
            aspect,
            AUTO_AZIMUTH_DEG,
            AUTO_ELEVATION_DEG,
            Projection::Perspective {
                fov_y_deg: DEFAULT_FOV_Y_DEG,
            },
        )
    }

    /// This camera moved `degrees` around the vertical axis through its target: distance,
    /// height and target stay as they are (a test's view from another side; turntables are
    /// camera paths, `request::camera_for_frame`).
    pub fn orbit(&self, degrees: f64) -> Camera {
        let (sin, cos) = degrees.to_radians().sin_cos();
        let offset = self.position - self.target;
        let rotated = DVec3::new(
            offset.x * cos - offset.y * sin,
            offset.x * sin + offset.y * cos,
            offset.z,
        );
        Camera {
            position: self.target + rotated,
            ..*self
        }
    }

    /// This camera moved without turning, `right` and `up` world units along the image's
    /// horizontal and vertical axes (a pan of the whole view).
    pub fn moved_sideways(&self, right: f64, up: f64) -> Camera {
        let forward = (self.target - self.position).normalize();
        let image_right = forward.cross(self.up).normalize();
        let image_up = image_right.cross(forward);
        let offset = image_right * right + image_up * up;
        Camera {
            position: self.position + offset,
            target: self.target + offset,
            ..*self
        }
    }

    /// The camera's transform for points stored relative to `origin`. Built entirely in f64:
    /// the camera position is recentred before the view matrix exists, so nothing large ever
    /// meets an f32.
    pub fn transform(&self, origin: DVec3, width: u32, height: u32) -> CameraTransform {
        let aspect = width as f64 / height as f64;
        let eye = self.position - origin;
        let view_matrix = view::look_at_mat4(eye, self.target - origin, self.up);
        let projection = match self.projection {
            Projection::Perspective { fov_y_deg } => {
                directx::perspective(fov_y_deg.to_radians(), aspect, self.near, self.far)
            }
            Projection::Orthographic { height } => {
                let half_h = height * 0.5;
                let half_w = half_h * aspect;
                directx::orthographic(-half_w, half_w, -half_h, half_h, self.near, self.far)
            }
        };
        // View space looks down -Z, so the linear depth is minus the view-space z.
        let depth_row = -view_matrix.row(2);
        CameraTransform {
            view_proj: projection * view_matrix,
            depth_row,
            near: self.near,
            far: self.far,
            width,
            height,
        }
    }

    /// The transform of the `window` of the `frame_width` x `frame_height` image this camera
    /// sees: the same frustum cut to that rectangle of pixels (an off-axis projection,
    /// perspective or orthographic), so that a point lands in the window at its pixel in the
    /// whole image less the window's corner. Tiled rendering draws a large image window by
    /// window with it.
    pub fn window_transform(
        &self,
        origin: DVec3,
        frame_width: u32,
        frame_height: u32,
        window: ImageWindow,
    ) -> CameraTransform {
        let whole = self.transform(origin, frame_width, frame_height);
        let (fw, fh) = (f64::from(frame_width), f64::from(frame_height));
        let (x0, y0) = (f64::from(window.x0), f64::from(window.y0));
        let (w, h) = (f64::from(window.width), f64::from(window.height));
        // The window's NDC as an affine map of the whole image's, applied to clip space (x and
        // y scale, w carries the shift): pixel x = (ndc + 1) / 2 * width in both, less x0 in
        // the window; pixel y runs down, ndc y up.
        let (scale_x, shift_x) = (fw / w, (fw - 2.0 * x0) / w - 1.0);
        let (scale_y, shift_y) = (fh / h, 1.0 - (fh - 2.0 * y0) / h);
        let crop = DMat4::from_cols(
            DVec4::new(scale_x, 0.0, 0.0, 0.0),
            DVec4::new(0.0, scale_y, 0.0, 0.0),
            DVec4::new(0.0, 0.0, 1.0, 0.0),
            DVec4::new(shift_x, shift_y, 0.0, 1.0),
        );
        CameraTransform {
            view_proj: crop * whole.view_proj,
            width: window.width,
            height: window.height,
            ..whole
        }
    }
}

/// A rectangle of an image's pixels: columns `x0..x0 + width`, rows `y0..y0 + height`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ImageWindow {
    pub x0: u32,
    pub y0: u32,
    pub width: u32,
    pub height: u32,
}

impl ImageWindow {
    /// All of a `width` x `height` image.
    pub fn whole(width: u32, height: u32) -> Self {
        Self {
            x0: 0,
            y0: 0,
            width,
            height,
        }
    }
}

/// A box seen from an azimuth and elevation (degrees, as [`Camera::fitted`] takes them): its
/// centre, its radius, the points framed (its corners, or a cloud's outermost points) around
/// the centre, and the camera's axes.
struct BoxView {
    center: DVec3,
    radius: f64,
    forward: DVec3,
    right: DVec3,
    up: DVec3,
    corners: Vec<DVec3>,
}

impl BoxView {
    fn new(bounds: &WorldBounds, outline: &[DVec3], azimuth_deg: f64, elevation_deg: f64) -> Self {
        let center = bounds.center();
        let forward = -view_direction(azimuth_deg, elevation_deg.clamp(-90.0, 90.0));
        // From the horizontal direction the camera faces, so that a view straight down (or
        // up) still has a right and an up.
        let facing = -view_direction(azimuth_deg, 0.0);
        let right = facing.cross(DVec3::Z);
        Self {
            center,
            // Never zero, so a single point or a flat cloud still gives a valid camera.
            radius: bounds.radius().max(1e-3),
            forward,
            right,
            up: right.cross(forward).normalize(),
            corners: if outline.is_empty() {
                box_corners(bounds).iter().map(|&c| c - center).collect()
            } else {
                outline.iter().map(|&c| c - center).collect()
            },
        }
    }

    /// The largest value of `f` over the points framed.
    fn max_of(&self, f: &dyn Fn(DVec3) -> f64) -> f64 {
        self.corners.iter().map(|&c| f(c)).fold(f64::MIN, f64::max)
    }

    /// The camera's offset along `forward` from the centre (negative: behind it) at which
    /// every point fits a field of view of half-angle tangents `tan_x` by `tan_y`, the camera
    /// panned to centre them: as close as the tighter image axis lets it come.
    fn fitted_depth(&self, tan_x: f64, tan_y: f64) -> f64 {
        let forward = self.forward;
        // A point c is in view when |(c - e)·axis| <= tan (c - e)·forward. With e's offsets a
        // (along the axis) and b (along forward) that is two half-planes per axis, which meet
        // at the b that just fits that axis; the camera goes back to the tighter axis's.
        let fit = |axis: DVec3, tan: f64| {
            let high = self.max_of(&|c| c.dot(axis) - tan * c.dot(forward));
            let low = self.max_of(&|c| -c.dot(axis) - tan * c.dot(forward));
            -(high + low) / (2.0 * tan)
        };
        fit(self.right, tan_x)
            .min(fit(self.up, tan_y))
            .min(-self.radius * 0.01)
    }

    /// The camera's offsets from the centre along `right` and `up` that centre the points'
    /// projection in the image of a perspective camera `along` the forward axis from the
    /// centre: the widest tangent on one side falls as the offset grows and on the other
    /// rises, so halving the interval finds where they are equal.
    fn centring(&self, along: f64) -> (f64, f64) {
        let centred = |axis: DVec3| {
            let widest = |a: f64, side: f64| {
                self.max_of(&|c| side * (c.dot(axis) - a) / (c.dot(self.forward) - along))
            };
            let (mut lo, mut hi) = (-self.radius, self.radius);
            for _ in 0..64 {
                let mid = 0.5 * (lo + hi);
                if widest(mid, 1.0) > widest(mid, -1.0) {
                    lo = mid;
                } else {
                    hi = mid;
                }
            }
            0.5 * (lo + hi)
        };
        (centred(self.right), centred(self.up))
    }
}

/// The unit vector from a target towards a camera at `azimuth_deg` (counter-clockwise from
/// +X) and `elevation_deg` (above the horizon).
fn view_direction(azimuth_deg: f64, elevation_deg: f64) -> DVec3 {
    let (az, el) = (azimuth_deg.to_radians(), elevation_deg.to_radians());
    DVec3::new(el.cos() * az.cos(), el.cos() * az.sin(), el.sin())
}

/// The corners of `bounds`.
pub fn box_corners(bounds: &WorldBounds) -> [DVec3; 8] {
    std::array::from_fn(|i| {
        let pick = |bit: usize, lo: f64, hi: f64| if i & bit == 0 { lo } else { hi };
        DVec3::new(
            pick(1, bounds.min.x, bounds.max.x),
            pick(2, bounds.min.y, bounds.max.y),
            pick(4, bounds.min.z, bounds.max.z),
        )
    })
}

/// What a rasterizer needs of a camera, relative to the dataset origin, in f64.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CameraTransform {
    pub view_proj: DMat4,
    /// Linear depth of a point p is `depth_row · (p, 1)`.
    pub depth_row: DVec4,
    pub near: f64,
    pub far: f64,
    pub width: u32,
    pub height: u32,
}

impl CameraTransform {
    /// Projects a point (relative to the origin) to continuous pixel coordinates and depth.
    /// `None` when the point is outside `near..=far`.
    pub fn project(&self, p: DVec3) -> Option<(f64, f64, f64)> {
        let depth = self.depth_row.dot(p.extend(1.0));
        if !(depth >= self.near && depth <= self.far) {
            return None;
        }
        let clip = self.view_proj * p.extend(1.0);
        let (ndc_x, ndc_y) = (clip.x / clip.w, clip.y / clip.w);
        let px = (ndc_x * 0.5 + 0.5) * self.width as f64;
        let py = (0.5 - ndc_y * 0.5) * self.height as f64;
        Some((px, py, depth))
    }
}

mod orbit;

pub use orbit::{fitted_orbit, Orbit};

#[cfg(test)]
mod tests;
