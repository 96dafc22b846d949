//! The view frustum of one frame, widened for the point size: whether a box can be in view
//! (all eight corners beyond one plane, in homogeneous clip space, or not), whether it is
//! wholly in view, and the pixels its points can touch.

use glam::{DVec2, DVec4, Vec3};

use crate::camera::CameraTransform;
use crate::raster::gpu_data::GpuBatch;
use crate::raster::pixel_rect::PixelRect;

/// A box that can be in view.
pub(super) struct InView {
    /// The pixels its points can touch.
    pub footprint: PixelRect,
    /// Every corner lies inside the frustum, so every point of the box does.
    pub whole: bool,
}

/// The frustum planes of one frame in homogeneous clip space, widened for the point size.
pub(crate) struct Frustum {
    transform: CameraTransform,
    /// Pixels a splat reaches beyond its centre's pixel, plus one for the shaders' f32.
    margin: f64,
    widen_x: f64,
    widen_y: f64,
    near: f64,
    far: f64,
}

impl Frustum {
    pub(crate) fn new(transform: &CameraTransform, point_size: u32) -> Self {
        // A splat reaches point_size pixels beyond its centre's pixel; one more pixel covers
        // the shaders' f32 rounding.
        let margin = f64::from(point_size) + 1.0;
        // Depths in f32 may differ from these in the last bits.
        let depth_margin = 1e-5 * transform.far.abs().max(1.0);
        Self {
            transform: *transform,
            margin,
            widen_x: 1.0 + 2.0 * margin / f64::from(transform.width),
            widen_y: 1.0 + 2.0 * margin / f64::from(transform.height),
            near: transform.near - depth_margin,
            far: transform.far + depth_margin,
        }
    }

    /// Whether no point in `batch`'s box can show in the image: all its corners lie beyond
    /// one plane. [`Frustum::view_of`]'s test without the footprint.
    pub(crate) fn excludes(&self, batch: &GpuBatch) -> bool {
        self.beyond_one_plane(&self.corners(batch))
    }

    /// The clip coordinates and depth of each corner of `batch`'s box, from the minimum
    /// corner's plus the transformed edges of the box: one matrix product instead of eight.
    fn corners(&self, batch: &GpuBatch) -> [(DVec4, f64); 8] {
        let (min, max) = (
            Vec3::from_array(batch.min).as_dvec3(),
            Vec3::from_array(batch.max).as_dvec3(),
        );
        let view_proj = &self.transform.view_proj;
        let depth_row = self.transform.depth_row;
        let extent = max - min;
        let clip_min: DVec4 = *view_proj * min.extend(1.0);
        let depth_min = depth_row.dot(min.extend(1.0));
        let clip_edges = [
            view_proj.x_axis * extent.x,
            view_proj.y_axis * extent.y,
            view_proj.z_axis * extent.z,
        ];
        let depth_edges = depth_row.truncate() * extent;
        std::array::from_fn(|corner| {
            let mut clip = clip_min;
            let mut depth = depth_min;
            for axis in 0..3 {
                if corner & (1 << axis) != 0 {
                    clip += clip_edges[axis];
                    depth += depth_edges[axis];
                }
            }
            (clip, depth)
        })
    }

    /// Whether all `corners` lie beyond the same plane.
    fn beyond_one_plane(&self, corners: &[(DVec4, f64); 8]) -> bool {
        let mut outside = [true; 6];
        for &(clip, depth) in corners {
            let w = clip.w;
            outside[0] &= clip.x < -w * self.widen_x;
            outside[1] &= clip.x > w * self.widen_x;
            outside[2] &= clip.y < -w * self.widen_y;
            outside[3] &= clip.y > w * self.widen_y;
            outside[4] &= depth < self.near;
            outside[5] &= depth > self.far;
        }
        outside.iter().any(|&o| o)
    }

    /// `None` when no point in `batch`'s box can show in the image (all its corners lie
    /// beyond one plane); else the pixels its points can touch.
    pub(super) fn view_of(&self, batch: &GpuBatch) -> Option<InView> {
        let corners = self.corners(batch);
        if self.beyond_one_plane(&corners) {
            return None;
        }
        let mut all_inside = true;
        let mut all_in_front = true;
        let (mut low, mut high) = (DVec2::splat(f64::INFINITY), DVec2::splat(f64::NEG_INFINITY));
        let (width, height) = (self.transform.width, self.transform.height);
        let (half_width, half_height) = (0.5 * f64::from(width), 0.5 * f64::from(height));
        for (clip, depth) in corners {
            let w = clip.w;
            all_inside &= clip.x.abs() <= w * self.widen_x
                && clip.y.abs() <= w * self.widen_y
                && depth >= self.near
                && depth <= self.far;
            // Points nearer than `near` are culled, so when every corner is beyond it the box's
            // image is the hull of its corners' images, far from the singular w = 0.
            all_in_front &= depth >= self.near && w > 0.0;
            let inverse_w = 1.0 / w;
            let pixel = DVec2::new(
                (clip.x * inverse_w + 1.0) * half_width,
                (1.0 - clip.y * inverse_w) * half_height,
            );
            low = low.min(pixel);
            high = high.max(pixel);
        }
        let footprint = if all_in_front {
            let clamp = |v: f64, limit: u32| v.clamp(0.0, f64::from(limit)) as u32;
            PixelRect {
                x0: clamp((low.x - self.margin).floor(), width),
                y0: clamp((low.y - self.margin).floor(), height),
                x1: clamp((high.x + self.margin).ceil(), width),
                y1: clamp((high.y + self.margin).ceil(), height),
            }
        } else {
            PixelRect::full(width, height)
        };
        Some(InView {
            footprint,
            whole: all_inside,
        })
    }
}

#[cfg(test)]
mod tests {
    use crate::testing::{perspective_camera, top_down_camera};
    use glam::DVec3;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    use super::*;
    use crate::raster::culling::batch;

    /// The pixels that random points of the box project to, within the image (a culled batch
    /// must have none, and a footprint must hold them all).
    fn pixels_in_view(
        transform: &CameraTransform,
        min: Vec3,
        max: Vec3,
        rng: &mut ChaCha8Rng,
    ) -> Vec<(u32, u32)> {
        (0..400)
            .filter_map(|_| {
                let t = Vec3::new(rng.random(), rng.random(), rng.random());
                let p = (min + (max - min) * t).as_dvec3();
                let (x, y, _) = transform.project(p)?;
                let inside = x >= 0.0
                    && y >= 0.0
                    && x < f64::from(transform.width)
                    && y < f64::from(transform.height);
                inside.then_some((x as u32, y as u32))
            })
            .collect()
    }

    /// Random points of a box said to be wholly in view project into the image, widened by
    /// the frustum's margin.
    fn assert_wholly_in_view(
        transform: &CameraTransform,
        margin: f64,
        min: Vec3,
        max: Vec3,
        rng: &mut ChaCha8Rng,
    ) {
        for _ in 0..100 {
            let t = Vec3::new(rng.random(), rng.random(), rng.random());
            let p = (min + (max - min) * t).as_dvec3();
            let projected = transform.project(p);
            let inside = projected.is_some_and(|(x, y, _)| {
                x >= -margin
                    && y >= -margin
                    && x <= f64::from(transform.width) + margin
                    && y <= f64::from(transform.height) + margin
            });
            assert!(inside, "{p} of {min} {max} is not in view: {projected:?}");
        }
    }

    #[test]
    fn culling_never_drops_a_box_with_a_point_in_view_and_drops_most_outside() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let cameras = [
            perspective_camera(DVec3::new(0.0, -30.0, 10.0), DVec3::ZERO, 50.0, (1.0, 60.0)),
            top_down_camera(DVec3::ZERO, 40.0, 12.0, (20.0, 50.0)),
        ];
        for camera in cameras {
            let transform = camera.transform(DVec3::ZERO, 320, 200);
            let frustum = Frustum::new(&transform, 1);
            let (mut culled, mut outside) = (0, 0);
            let (mut footprints, mut tight) = (0, 0);
            for _ in 0..2000 {
                let centre = Vec3::new(
                    rng.random_range(-40.0..40.0),
                    rng.random_range(-40.0..40.0),
                    rng.random_range(-40.0..40.0),
                );
                let half = Vec3::splat(rng.random_range(0.05..4.0));
                let (min, max) = (centre - half, centre + half);
                let pixels = pixels_in_view(&transform, min, max, &mut rng);
                let shows = !pixels.is_empty();
                let view = frustum.view_of(&batch(min, max));
                // The test of sub-batches, without a footprint, decides the same.
                assert_eq!(frustum.excludes(&batch(min, max)), view.is_none());
                if view.as_ref().is_some_and(|v| v.whole) {
                    assert_wholly_in_view(&transform, frustum.margin, min, max, &mut rng);
                }
                let footprint = view.map(|v| v.footprint);
                let kept = footprint.is_some();
                assert!(
                    kept || !shows,
                    "{camera:?}: culled a box in view: {min} {max}"
                );
                if let Some(footprint) = footprint {
                    for &(x, y) in &pixels {
                        assert!(
                            footprint.contains(x, y),
                            "{camera:?}: pixel {x},{y} of {min} {max} outside {footprint:?}"
                        );
                    }
                    if shows {
                        footprints += 1;
                        tight += usize::from(footprint.pixels() < 320 * 200 / 2);
                    }
                }
                if !shows {
                    outside += 1;
                    culled += usize::from(!kept);
                }
            }
            // Boxes that straddle a plane's extension are kept; most others go.
            assert!(
                culled * 10 >= outside * 7,
                "{camera:?}: culled only {culled} of {outside} boxes out of view"
            );
            // Small boxes get small footprints (those that straddle the near plane get the
            // whole image).
            assert!(
                tight * 10 >= footprints * 7,
                "{camera:?}: only {tight} of {footprints} footprints are tight"
            );
        }
    }
}
