//! Camera paths to per-frame cameras. Turntables need the cloud's bounds (centre and fitted
//! radius); keyframe paths interpolate linearly or along a Catmull-Rom spline.

use glam::DVec3;
use pointfarm_render::camera::{Camera, Projection, AUTO_AZIMUTH_DEG};
use pointfarm_render::cloud::WorldBounds;

use crate::model::{CameraPath, Interpolation, Keyframe, Turntable};

/// The camera of frame `index` of `path`, for a cloud with `bounds` and images of `aspect`.
pub fn camera_for_frame(
    path: &CameraPath,
    index: u32,
    bounds: &WorldBounds,
    aspect: f64,
) -> Camera {
    match path {
        CameraPath::Turntable(turntable) => turntable_camera(turntable, index, bounds, aspect),
        CameraPath::Keyframes {
            keyframes,
            frames,
            interpolation,
        } => keyframe_camera(keyframes, *frames, *interpolation, index, bounds),
    }
}

fn turntable_camera(t: &Turntable, index: u32, bounds: &WorldBounds, aspect: f64) -> Camera {
    let projection = Projection::Perspective {
        fov_y_deg: t.fov_y_deg,
    };
    let azimuth = AUTO_AZIMUTH_DEG + t.degrees * index as f64 / t.frames.max(1) as f64;
    let center = t.center.map_or(bounds.center(), DVec3::from);
    // One radius for the whole orbit: the fit of the first frame's view (as the local
    // `pointfarm render --turntable` does), so the cloud does not zoom in and out.
    let radius = t.radius.unwrap_or_else(|| {
        let fitted = Camera::framing(
            bounds,
            aspect,
            AUTO_AZIMUTH_DEG,
            t.elevation_deg,
            projection,
        );
        fitted.position.distance(fitted.target)
    });
    let (az, el) = (azimuth.to_radians(), t.elevation_deg.to_radians());
    let direction = DVec3::new(el.cos() * az.cos(), el.cos() * az.sin(), el.sin());
    Camera::looking_at(center + direction * radius, center, bounds, projection)
}

fn keyframe_camera(
    keys: &[Keyframe],
    frames: u32,
    interpolation: Interpolation,
    index: u32,
    bounds: &WorldBounds,
) -> Camera {
    // Validation guarantees at least two keyframes and one frame; be total anyway.
    if keys.is_empty() {
        return Camera::auto(bounds, 1.0);
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
    let mut camera = Camera::looking_at(
        position,
        target,
        bounds,
        Projection::Perspective { fov_y_deg: fov },
    );
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::Point3;

    fn bounds() -> WorldBounds {
        WorldBounds {
            min: DVec3::new(0.0, 0.0, 0.0),
            max: DVec3::new(100.0, 50.0, 20.0),
        }
    }

    fn key(x: f64) -> Keyframe {
        Keyframe {
            position: Point3 {
                x,
                y: -100.0,
                z: 50.0,
            },
            target: Point3 { x, y: 25.0, z: 0.0 },
            up: Point3 {
                x: 0.0,
                y: 0.0,
                z: 1.0,
            },
            fov_y_deg: 40.0 + x / 10.0,
        }
    }

    #[test]
    fn keyframe_paths_pass_through_their_keyframes() {
        let keys = vec![key(0.0), key(30.0), key(100.0)];
        for interpolation in [Interpolation::Linear, Interpolation::Spline] {
            let path = CameraPath::Keyframes {
                keyframes: keys.clone(),
                frames: 5,
                interpolation,
            };
            let cams: Vec<Camera> = (0..5)
                .map(|i| camera_for_frame(&path, i, &bounds(), 1.5))
                .collect();
            assert!((cams[0].position.x - 0.0).abs() < 1e-9);
            assert!(
                (cams[2].position.x - 30.0).abs() < 1e-9,
                "{interpolation:?}"
            );
            assert!((cams[4].position.x - 100.0).abs() < 1e-9);
            for c in &cams {
                c.validate().expect("valid camera");
            }
        }
        let linear = CameraPath::Keyframes {
            keyframes: keys.clone(),
            frames: 5,
            interpolation: Interpolation::Linear,
        };
        let spline = CameraPath::Keyframes {
            keyframes: keys,
            frames: 5,
            interpolation: Interpolation::Spline,
        };
        let l = camera_for_frame(&linear, 1, &bounds(), 1.5).position.x;
        let s = camera_for_frame(&spline, 1, &bounds(), 1.5).position.x;
        assert!((l - 15.0).abs() < 1e-9);
        assert!((s - l).abs() > 0.1, "the spline bends: {s} vs {l}");
    }

    #[test]
    fn turntables_orbit_the_centre_at_a_constant_distance() {
        let t = Turntable {
            frames: 8,
            center: None,
            radius: None,
            elevation_deg: 30.0,
            degrees: 360.0,
            fov_y_deg: 50.0,
        };
        let path = CameraPath::Turntable(t);
        let d: Vec<f64> = (0..8)
            .map(|i| camera_for_frame(&path, i, &bounds(), 1.5))
            .map(|c| c.position.distance(bounds().center()))
            .collect();
        assert!(d.iter().all(|x| (x - d[0]).abs() < 1e-6 * d[0]), "{d:?}");
        let fixed = Turntable {
            frames: 4,
            center: Some(Point3 {
                x: 1.0,
                y: 2.0,
                z: 3.0,
            }),
            radius: Some(10.0),
            elevation_deg: 0.0,
            degrees: 90.0,
            fov_y_deg: 50.0,
        };
        let cam = camera_for_frame(&CameraPath::Turntable(fixed), 3, &bounds(), 1.0);
        assert!((cam.position.distance(DVec3::new(1.0, 2.0, 3.0)) - 10.0).abs() < 1e-9);
    }
}
