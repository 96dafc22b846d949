//! The adaptive point size of a frame: the cloud's point spacing as the camera projects it.
//!
//! Potree sizes each point by its level of detail's spacing over its depth, so that a scan's
//! surfaces read closed near and far without smearing detail. The renderer does the same per
//! point (`FrameSettings::adaptive_size`); this chooses the scale and the largest side, the
//! size of the nearest part of the cloud's box, which bounds the point passes' work.

use glam::DVec3;

use super::PointSize;
use crate::camera::{Camera, Projection};
use crate::cloud::WorldBounds;
use crate::raster::{FrameSettings, DEFAULT_POINT_SIZE, MAX_ADAPTIVE_POINT_SIZE};

/// The point size settings of a frame of `width` x `height` through `camera`, for a cloud
/// with `bounds` whose points lie `spacing` apart (world units; `None` when unknown, which
/// draws adaptive points at the default size).
pub(crate) fn resolve(
    size: PointSize,
    camera: &Camera,
    height: u32,
    bounds: &WorldBounds,
    spacing: Option<f64>,
) -> (u32, Option<f32>) {
    let spacing = match (size, spacing) {
        (PointSize::Fixed(side), _) => return (side, None),
        (PointSize::Adaptive, Some(spacing)) if spacing.is_finite() && spacing > 0.0 => spacing,
        (PointSize::Adaptive, _) => return (DEFAULT_POINT_SIZE, None),
    };
    let side = |pixels: f64| pixels.round().clamp(1.0, MAX_ADAPTIVE_POINT_SIZE as f64) as u32;
    match camera.projection {
        // Every depth has the same scale: one fixed side.
        Projection::Orthographic {
            height: view_height,
        } => (side(spacing * height as f64 / view_height), None),
        Projection::Perspective { fov_y_deg } => {
            let focal_px = height as f64 / (2.0 * (fov_y_deg.to_radians() / 2.0).tan());
            let scale = spacing * focal_px;
            // Kept when every point is one pixel: a level-of-detail cut sizes coarser nodes
            // from it, and the point passes skip per-point sizes at one pixel anyway
            // (`SplatShape`).
            (
                side(scale / nearest_depth(camera, bounds)),
                Some(scale as f32),
            )
        }
    }
}

/// The smallest linear depth of `bounds` in front of `camera`: depth is linear, so its least
/// value over the box is at a corner; the near plane when that corner is behind it.
fn nearest_depth(camera: &Camera, bounds: &WorldBounds) -> f64 {
    let forward = (camera.target - camera.position).normalize();
    (0..8)
        .map(|i| {
            let pick = |bit: usize, lo: f64, hi: f64| if i & bit == 0 { lo } else { hi };
            DVec3::new(
                pick(1, bounds.min.x, bounds.max.x),
                pick(2, bounds.min.y, bounds.max.y),
                pick(4, bounds.min.z, bounds.max.z),
            )
        })
        .map(|corner| (corner - camera.position).dot(forward))
        .fold(f64::INFINITY, f64::min)
        .max(camera.near)
}

impl FrameSettings {
    /// These settings with the point size `size` resolves to for a cloud with `bounds` and
    /// point `spacing`.
    pub fn with_point_size(
        self,
        size: PointSize,
        bounds: &WorldBounds,
        spacing: Option<f64>,
    ) -> FrameSettings {
        let (point_size, adaptive_size) = resolve(size, &self.camera, self.height, bounds, spacing);
        FrameSettings {
            point_size,
            adaptive_size,
            ..self
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 100 x 100 x 10 box whose nearest corner lies 50 in front of a camera looking down +y.
    fn scene(projection: Projection) -> (Camera, WorldBounds) {
        let bounds = WorldBounds {
            min: DVec3::new(-50.0, 50.0, -5.0),
            max: DVec3::new(50.0, 150.0, 5.0),
        };
        let camera = Camera {
            position: DVec3::ZERO,
            target: DVec3::Y,
            up: DVec3::Z,
            projection,
            near: 1.0,
            far: 1000.0,
        };
        (camera, bounds)
    }

    const PERSPECTIVE: Projection = Projection::Perspective { fov_y_deg: 90.0 };

    #[test]
    fn a_fixed_size_is_kept() {
        let (camera, bounds) = scene(PERSPECTIVE);
        let fixed = PointSize::Fixed(5);
        assert_eq!(resolve(fixed, &camera, 100, &bounds, Some(1.0)), (5, None));
    }

    #[test]
    fn adaptive_points_are_the_spacing_over_the_depth() {
        let (camera, bounds) = scene(PERSPECTIVE);
        // 90 degrees over 400 pixels: 200 pixels at depth 1; 0.8 apart: 160 pixels at depth 1,
        // 3.2 at the nearest corner's depth of 50. Points 0.01 apart stay one pixel and keep
        // their scale, which sizes a cut's coarser nodes.
        for (spacing, side, pixels_at_depth_1) in [(0.8, 3, 160.0), (0.01, 1, 2.0)] {
            let (largest, scale) =
                resolve(PointSize::Adaptive, &camera, 400, &bounds, Some(spacing));
            assert_eq!(largest, side, "{spacing}");
            let scale = scale.expect("adaptive");
            assert!(
                (scale - pixels_at_depth_1).abs() < 1e-3,
                "{spacing}: {scale}"
            );
        }
        let settings = FrameSettings::new(400, 400, camera).with_point_size(
            PointSize::Adaptive,
            &bounds,
            Some(0.8),
        );
        assert_eq!(settings.point_side_at(50.0), 3);
        assert_eq!(settings.point_side_at(100.0), 2);
        assert_eq!(settings.point_side_at(150.0), 1);
    }

    #[test]
    fn sparse_points_near_the_camera_are_capped() {
        let (mut camera, bounds) = scene(PERSPECTIVE);
        camera.position = DVec3::new(0.0, 100.0, 0.0); // inside the box
        let (largest, scale) = resolve(PointSize::Adaptive, &camera, 400, &bounds, Some(0.8));
        assert_eq!((largest, scale.is_some()), (MAX_ADAPTIVE_POINT_SIZE, true));
    }

    #[test]
    fn orthographic_points_have_one_size() {
        let (camera, bounds) = scene(Projection::Orthographic { height: 100.0 });
        // 4 pixels a unit: 0.8 apart is 3.2 pixels.
        let resolved = resolve(PointSize::Adaptive, &camera, 400, &bounds, Some(0.8));
        assert_eq!(resolved, (3, None));
    }

    #[test]
    fn without_a_spacing_adaptive_points_take_the_default_size() {
        let (camera, bounds) = scene(PERSPECTIVE);
        let resolved = resolve(PointSize::Adaptive, &camera, 400, &bounds, None);
        assert_eq!(resolved, (DEFAULT_POINT_SIZE, None));
        let resolved = resolve(PointSize::Adaptive, &camera, 400, &bounds, Some(f64::NAN));
        assert_eq!(resolved, (DEFAULT_POINT_SIZE, None));
    }
}
