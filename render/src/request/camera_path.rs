//! Where the camera is in each frame of a request: a still camera, a turntable or keyframes,
//! seen through a lens (perspective or orthographic, with optional near and far planes).
//! [`camera_for_frame`] is the one place that turns them into a [`Camera`]: the automatic
//! views (a still without a position, a turntable without a start) frame the robust box of the
//! points ([`Extent`]), cameras placed by hand only take their clip planes from every point's box.

use std::ops::RangeInclusive;

use glam::DVec3;
use serde::{Deserialize, Serialize};

use crate::camera::{
    fitted_orbit, Camera, Projection, AUTO_AZIMUTH_DEG, AUTO_ELEVATION_DEG, DEFAULT_FOV_Y_DEG,
};
use crate::cloud::WorldBounds;
use crate::extent::Extent;

/// A turntable covers a full circle unless asked otherwise.
pub const DEFAULT_TURNTABLE_DEGREES: f64 = 360.0;
/// Elevations a turntable accepts, in degrees above the horizon (not straight up or down,
/// where "around the vertical axis" has no direction).
pub const TURNTABLE_ELEVATION_RANGE: RangeInclusive<f64> = -89.0..=89.0;
/// Elevations of a still's automatic view, in degrees above the horizon (90: from straight
/// above).
pub const VIEW_ELEVATION_RANGE: RangeInclusive<f64> = -90.0..=90.0;
/// Total angles a turntable accepts, in degrees (a hundred turns).
pub const TURNTABLE_DEGREES_RANGE: RangeInclusive<f64> = -36000.0..=36000.0;
/// Vertical fields of view accepted, in degrees (exclusive at both ends).
pub const FOV_Y_DEG_RANGE: RangeInclusive<f64> = 0.0..=180.0;
pub use crate::cloud::MAX_COORDINATE;
/// A keyframe path needs at least this many keyframes.
pub const MIN_KEYFRAMES: usize = 2;
/// The up direction unless asked otherwise: +Z.
pub const DEFAULT_UP: Point3 = Point3 {
    x: 0.0,
    y: 0.0,
    z: 1.0,
};

/// A point or direction in the file's coordinates.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Point3 {
    pub x: f64,
    pub y: f64,
    pub z: f64,
}

impl Point3 {
    pub fn is_finite(&self) -> bool {
        self.x.is_finite() && self.y.is_finite() && self.z.is_finite()
    }
}

impl From<Point3> for DVec3 {
    fn from(p: Point3) -> Self {
        DVec3::new(p.x, p.y, p.z)
    }
}

impl From<DVec3> for Point3 {
    fn from(v: DVec3) -> Self {
        Point3 {
            x: v.x,
            y: v.y,
            z: v.z,
        }
    }
}

/// One camera for one frame: the automatic view of the whole cloud, or parts of it given.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct StillCamera {
    /// Where the camera is; the automatic view's offset from the target when absent.
    pub position: Option<Point3>,
    /// What it looks at; the cloud's centre when absent.
    pub target: Option<Point3>,
    pub up: Point3,
    /// Vertical field of view (perspective lens).
    pub fov_y_deg: f64,
    /// Direction of the automatic view, degrees counter-clockwise from +X (where the camera
    /// is, seen from the target), when the position is absent.
    #[serde(default = "default_azimuth")]
    pub azimuth_deg: f64,
    /// Degrees above the horizon of the automatic view (90: straight down).
    #[serde(default = "default_elevation")]
    pub elevation_deg: f64,
}

impl Default for StillCamera {
    fn default() -> Self {
        Self {
            position: None,
            target: None,
            up: DEFAULT_UP,
            fov_y_deg: DEFAULT_FOV_Y_DEG,
            azimuth_deg: AUTO_AZIMUTH_DEG,
            elevation_deg: AUTO_ELEVATION_DEG,
        }
    }
}

/// Frames orbiting a centre around the vertical axis, evenly spaced over `degrees`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Turntable {
    pub frames: u32,
    /// The cloud's centre when absent.
    pub center: Option<Point3>,
    /// The camera's distance from the centre; fitted so the whole cloud is in view of every
    /// frame when absent.
    pub radius: Option<f64>,
    /// Degrees above the horizon.
    pub elevation_deg: f64,
    /// Total angle covered by the frames.
    pub degrees: f64,
    /// Vertical field of view (perspective lens).
    pub fov_y_deg: f64,
    /// Direction of the first frame, degrees counter-clockwise from +X.
    #[serde(default = "default_azimuth")]
    pub azimuth_deg: f64,
    #[serde(default = "default_up")]
    pub up: Point3,
    /// The camera of the first frame; when given, the radius, elevation and azimuth are its
    /// offset from the centre's.
    #[serde(default)]
    pub start: Option<Point3>,
}

fn default_azimuth() -> f64 {
    AUTO_AZIMUTH_DEG
}

fn default_elevation() -> f64 {
    AUTO_ELEVATION_DEG
}

fn default_up() -> Point3 {
    DEFAULT_UP
}

impl Turntable {
    /// `frames` frames around the cloud from the automatic view's direction.
    pub fn around_the_cloud(frames: u32) -> Self {
        Self {
            frames,
            center: None,
            radius: None,
            elevation_deg: AUTO_ELEVATION_DEG,
            degrees: DEFAULT_TURNTABLE_DEGREES,
            fov_y_deg: DEFAULT_FOV_Y_DEG,
            azimuth_deg: AUTO_AZIMUTH_DEG,
            up: DEFAULT_UP,
            start: None,
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Keyframe {
    pub position: Point3,
    pub target: Point3,
    pub up: Point3,
    /// Vertical field of view (perspective lens).
    pub fov_y_deg: f64,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum Interpolation {
    Linear,
    /// Catmull-Rom through the keyframe positions and targets.
    Spline,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub enum CameraPath {
    Turntable(Turntable),
    /// `frames` frames from the first keyframe to the last.
    Keyframes {
        keyframes: Vec<Keyframe>,
        frames: u32,
        interpolation: Interpolation,
    },
    Still(StillCamera),
}

impl CameraPath {
    pub fn frames(&self) -> u32 {
        match self {
            CameraPath::Turntable(t) => t.frames,
            CameraPath::Keyframes { frames, .. } => *frames,
            CameraPath::Still(_) => 1,
        }
    }
}

/// How the camera projects: a perspective lens (the path's field of view) or an orthographic
/// one, and near and far planes fitted to the cloud unless given.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
#[serde(default)]
pub struct Lens {
    pub orthographic: bool,
    /// Height of the orthographic view in world units; fitted to the cloud when absent.
    pub ortho_height: Option<f64>,
    pub near: Option<f64>,
    pub far: Option<f64>,
}

impl Lens {
    /// The projection for a path whose field of view is `fov_y_deg`.
    fn projection(&self, fov_y_deg: f64, bounds: &WorldBounds, aspect: f64) -> Projection {
        if !self.orthographic {
            return Projection::Perspective { fov_y_deg };
        }
        let height = self.ortho_height.unwrap_or_else(|| {
            // The height that fits the automatic view of the cloud (`framing` fits it).
            let fitted = Camera::framing(
                bounds,
                aspect,
                AUTO_AZIMUTH_DEG,
                AUTO_ELEVATION_DEG,
                Projection::Orthographic { height: 1.0 },
            );
            match fitted.projection {
                Projection::Orthographic { height } => height,
                Projection::Perspective { .. } => 1.0,
            }
        });
        Projection::Orthographic { height }
    }

    /// `camera` with the given near and far planes in place of the fitted ones.
    fn clip(&self, mut camera: Camera) -> Camera {
        if let Some(near) = self.near {
            camera.near = near;
        }
        if let Some(far) = self.far {
            camera.far = far;
        }
        camera
    }
}

/// The camera of frame `index` of `path` through `lens`, for a cloud whose points lie in
/// `extent`, and images of `aspect` (width / height).
pub fn camera_for_frame(
    path: &CameraPath,
    lens: &Lens,
    index: u32,
    extent: &Extent,
    aspect: f64,
) -> Camera {
    let camera = match path {
        CameraPath::Still(still) => still_camera(still, lens, extent, aspect),
        CameraPath::Turntable(turntable) => {
            turntable_camera(turntable, lens, index, extent, aspect)
        }
        CameraPath::Keyframes {
            keyframes,
            frames,
            interpolation,
        } => keyframe_camera(
            keyframes,
            *frames,
            *interpolation,
            lens,
            index,
            &extent.all,
            aspect,
        ),
    };
    lens.clip(camera)
}

fn still_camera(still: &StillCamera, lens: &Lens, extent: &Extent, aspect: f64) -> Camera {
    let bounds = &extent.robust;
    let projection = lens.projection(still.fov_y_deg, bounds, aspect);
    let auto = Camera::fitted_to(
        bounds,
        &extent.outline,
        aspect,
        still.azimuth_deg,
        still.elevation_deg,
        projection,
    );
    // A given orthographic height stays; otherwise the automatic view's fits the cloud.
    let projection = if lens.ortho_height.is_some() {
        projection
    } else {
        auto.projection
    };
    let target = still.target.map_or(auto.target, DVec3::from);
    let position = still
        .position
        .map_or(target + (auto.position - auto.target), DVec3::from);
    let enclosed = if still.position.is_some() {
        &extent.all
    } else {
        bounds
    };
    let mut camera = Camera::looking_at(position, target, enclosed, projection);
    let up = DVec3::from(still.up);
    // Looking along the given up (a view from straight above): the automatic view's up.
    camera.up = if up.cross(target - position).length_squared()
        > 1e-12 * up.length_squared() * (target - position).length_squared()
    {
        up
    } else {
        auto.up
    };
    camera
}

/// Views of an orbit fitted to find its radius: every 5.625 degrees of a full turn, close
/// enough that the box's widest view between two of them is wider by far less than the margin.
const ORBIT_FIT_VIEWS: u32 = 64;

/// The one turntable: the camera of frame `index` on a circle around the vertical axis
/// through the centre.
fn turntable_camera(
    t: &Turntable,
    lens: &Lens,
    index: u32,
    extent: &Extent,
    aspect: f64,
) -> Camera {
    let bounds = &extent.robust;
    let projection = lens.projection(t.fov_y_deg, bounds, aspect);
    let turned = |first: f64| first + t.degrees * index as f64 / t.frames.max(1) as f64;
    let (position, target, enclosed) = match t.start {
        Some(start) => {
            // A start placed by hand orbits the centre of every point, as it always has.
            let center = t.center.map_or(extent.all.center(), DVec3::from);
            let offset = DVec3::from(start) - center;
            let radius = offset.length();
            let elevation = (offset.z / radius.max(f64::MIN_POSITIVE)).asin();
            let azimuth = turned(offset.y.atan2(offset.x).to_degrees()).to_radians();
            let direction = DVec3::new(
                elevation.cos() * azimuth.cos(),
                elevation.cos() * azimuth.sin(),
                elevation.sin(),
            );
            (center + direction * radius, center, &extent.all)
        }
        None => {
            // One orbit for all its views, as close as the widest of them lets the cloud stay
            // in view, so the cloud neither zooms in and out nor leaves the frame.
            let azimuths: Vec<f64> = (0..=ORBIT_FIT_VIEWS)
                .map(|k| t.azimuth_deg + t.degrees * f64::from(k) / f64::from(ORBIT_FIT_VIEWS))
                .collect();
            let mut orbit = fitted_orbit(
                bounds,
                &extent.outline,
                t.center.map(DVec3::from),
                aspect,
                &azimuths,
                t.elevation_deg,
                projection,
            );
            orbit.distance = t.radius.unwrap_or(orbit.distance);
            let (position, target) = orbit.view(
                bounds,
                &extent.outline,
                turned(t.azimuth_deg),
                t.elevation_deg,
            );
            (position, target, bounds)
        }
    };
    let mut camera = Camera::looking_at(position, target, enclosed, projection);
    camera.up = t.up.into();
    camera
}

fn keyframe_camera(
    keys: &[Keyframe],
    frames: u32,
    interpolation: Interpolation,
    lens: &Lens,
    index: u32,
    bounds: &WorldBounds,
    aspect: f64,
) -> Camera {
    // Validation guarantees at least two keyframes and one frame; be total anyway.
    if keys.is_empty() {
        return Camera::auto(bounds, aspect);
    }
    let t = if frames <= 1 || keys.len() < 2 {
        0.0
    } else {
        index as f64 / (frames - 1) as f64 * (keys.len() - 1) as f64
    };
    let segment = (t.floor() as usize).min(keys.len().saturating_sub(2));
    let u = t - segment as f64;
    let at = |i: isize| keys[i.clamp(0, keys.len() as isize - 1) as usize];
    let (k0, k1, k2, k3) = (
        at(segment as isize - 1),
        at(segment as isize),
        at(segment as isize + 1),
        at(segment as isize + 2),
    );
    let blend = |get: fn(&Keyframe) -> DVec3| match interpolation {
        Interpolation::Linear => get(&k1).lerp(get(&k2), u),
        Interpolation::Spline => catmull_rom(get(&k0), get(&k1), get(&k2), get(&k3), u),
    };
    let position = blend(|k| k.position.into());
    let target = blend(|k| k.target.into());
    let up = DVec3::from(k1.up).lerp(k2.up.into(), u);
    let fov = k1.fov_y_deg + (k2.fov_y_deg - k1.fov_y_deg) * u;
    let projection = lens.projection(fov, bounds, aspect);
    let mut camera = Camera::looking_at(position, target, bounds, projection);
    camera.up = up;
    camera
}

/// Uniform Catmull-Rom between p1 (u = 0) and p2 (u = 1).
fn catmull_rom(p0: DVec3, p1: DVec3, p2: DVec3, p3: DVec3, u: f64) -> DVec3 {
    let (u2, u3) = (u * u, u * u * u);
    0.5 * ((2.0 * p1)
        + (p2 - p0) * u
        + (2.0 * p0 - 5.0 * p1 + 4.0 * p2 - p3) * u2
        + (3.0 * p1 - p0 - 3.0 * p2 + p3) * u3)
}
