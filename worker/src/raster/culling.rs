//! The frame's batch table: the batches that can be in view.
//!
//! Every frame, on the host, before any GPU work, each chunk's batches are culled against the
//! view frustum (Günther et al.'s frustum culling, per batch): a batch is left out when all
//! eight corners of its box lie beyond the same plane of the frustum, widened by the point
//! size and a pixel of margin for the shaders' f32 arithmetic. The point passes read this
//! table instead of the cloud's own and dispatch one workgroup per entry, so a culled batch
//! costs the GPU nothing (on lavapipe, a view that sees none of a 10M-point cloud went from
//! 3.7 ms to 0.1 ms). Points of listed batches are still culled one by one.
//!
//! The same pass over the boxes bounds the frame's footprint: the pixels any listed point can
//! touch. The resolve skips the rest of the image when it is known to be empty (`targets.rs`).
//!
//! The table is a copy of the entries (32 bytes per 4096 points), in the cloud's Morton order.
//! Sorting it front to back, for the early depth test, made lavapipe's 10M-point frame 20%
//! slower: consecutive workgroups no longer write nearby pixels (BENCHMARKS.md).

use bytemuck::Zeroable;
use glam::{DVec2, DVec3, DVec4, Vec3};

use super::gpu_data::GpuBatch;
use super::pixel_rect::PixelRect;
use crate::camera::CameraTransform;

/// One frame's batch tables of a cloud's chunks, in one GPU buffer.
pub(crate) struct FrameBatches {
    /// Per chunk, its batches that can be in view; each chunk's table starts at a multiple of
    /// the storage-binding offset alignment.
    buffer: Option<wgpu::Buffer>,
    /// Per chunk: byte offset of its table in `buffer` and its number of batches.
    ranges: Vec<(u64, u32)>,
    /// Host copy reused from frame to frame.
    staging: Vec<GpuBatch>,
    /// The pixels that points of the listed batches can touch this frame.
    footprint: PixelRect,
}

impl FrameBatches {
    pub fn new() -> Self {
        Self {
            buffer: None,
            ranges: Vec::new(),
            staging: Vec::new(),
            footprint: PixelRect::EMPTY,
        }
    }

    /// Builds the tables of `chunks` (each its full batch table) for a frame seen through
    /// `transform` with points of `point_size` pixels, and uploads them.
    pub fn update<'a>(
        &mut self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        chunks: impl Iterator<Item = &'a [GpuBatch]>,
        transform: &CameraTransform,
        point_size: u32,
    ) {
        let frustum = Frustum::new(transform, point_size);
        let entry_bytes = std::mem::size_of::<GpuBatch>();
        let alignment =
            (device.limits().min_storage_buffer_offset_alignment as usize).div_ceil(entry_bytes);
        self.staging.clear();
        self.ranges.clear();
        self.footprint = PixelRect::EMPTY;
        for batches in chunks {
            let padding = self.staging.len().next_multiple_of(alignment) - self.staging.len();
            self.staging
                .extend(std::iter::repeat_n(GpuBatch::zeroed(), padding));
            let start = self.staging.len();
            for batch in batches {
                if let Some(footprint) = frustum.footprint(batch) {
                    self.footprint = self.footprint.union(footprint);
                    self.staging.push(*batch);
                }
            }
            self.ranges.push((
                (start * entry_bytes) as u64,
                (self.staging.len() - start) as u32,
            ));
        }
        if self.staging.is_empty() {
            return;
        }
        let bytes = (self.staging.len() * entry_bytes) as u64;
        if self.buffer.as_ref().is_none_or(|b| b.size() < bytes) {
            self.buffer = Some(device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("frame batch table"),
                // Room to grow, so that a moving camera does not reallocate every frame.
                size: bytes.next_power_of_two(),
                usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            }));
        }
        if let Some(buffer) = &self.buffer {
            queue.write_buffer(buffer, 0, bytemuck::cast_slice(&self.staging));
        }
    }

    /// The pixels that points of this frame's listed batches can touch (empty when none is
    /// listed).
    pub fn footprint(&self) -> PixelRect {
        self.footprint
    }

    /// Number of batches of chunk `chunk` in this frame's table.
    pub fn count(&self, chunk: usize) -> u32 {
        self.ranges.get(chunk).map_or(0, |&(_, count)| count)
    }

    /// The table of chunk `chunk` as a storage binding; `None` when no batch is in view.
    pub fn binding(&self, chunk: usize) -> Option<wgpu::BufferBinding<'_>> {
        let (offset, count) = *self.ranges.get(chunk)?;
        let buffer = self.buffer.as_ref()?;
        (count > 0).then(|| wgpu::BufferBinding {
            buffer,
            offset,
            size: wgpu::BufferSize::new(u64::from(count) * std::mem::size_of::<GpuBatch>() as u64),
        })
    }
}

/// The frustum planes of one frame in homogeneous clip space, widened for the point size.
struct Frustum {
    transform: CameraTransform,
    /// Pixels a splat reaches beyond its centre's pixel, plus one for the shaders' f32.
    margin: f64,
    widen_x: f64,
    widen_y: f64,
    near: f64,
    far: f64,
}

impl Frustum {
    fn new(transform: &CameraTransform, point_size: u32) -> Self {
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

    /// `None` when no point in `batch`'s box can show in the image (all its corners lie
    /// beyond one plane); else the pixels its points can touch.
    fn footprint(&self, batch: &GpuBatch) -> Option<PixelRect> {
        let (min, max) = (
            Vec3::from_array(batch.min).as_dvec3(),
            Vec3::from_array(batch.max).as_dvec3(),
        );
        let mut outside = [true; 6];
        let mut all_in_front = true;
        let (mut low, mut high) = (DVec2::splat(f64::INFINITY), DVec2::splat(f64::NEG_INFINITY));
        for corner in 0..8 {
            let p = DVec3::new(
                if corner & 1 == 0 { min.x } else { max.x },
                if corner & 2 == 0 { min.y } else { max.y },
                if corner & 4 == 0 { min.z } else { max.z },
            );
            let clip: DVec4 = self.transform.view_proj * p.extend(1.0);
            let depth = self.transform.depth_row.dot(p.extend(1.0));
            let w = clip.w;
            outside[0] &= clip.x < -w * self.widen_x;
            outside[1] &= clip.x > w * self.widen_x;
            outside[2] &= clip.y < -w * self.widen_y;
            outside[3] &= clip.y > w * self.widen_y;
            outside[4] &= depth < self.near;
            outside[5] &= depth > self.far;
            // Points nearer than `near` are culled, so when every corner is beyond it the box's
            // image is the hull of its corners' images, far from the singular w = 0.
            all_in_front &= depth >= self.near && w > 0.0;
            let pixel = DVec2::new(
                (clip.x / w * 0.5 + 0.5) * f64::from(self.transform.width),
                (0.5 - clip.y / w * 0.5) * f64::from(self.transform.height),
            );
            low = low.min(pixel);
            high = high.max(pixel);
        }
        if outside.iter().any(|&o| o) {
            return None;
        }
        let (width, height) = (self.transform.width, self.transform.height);
        if !all_in_front {
            return Some(PixelRect::full(width, height));
        }
        let clamp = |v: f64, limit: u32| v.clamp(0.0, f64::from(limit)) as u32;
        Some(PixelRect {
            x0: clamp((low.x - self.margin).floor(), width),
            y0: clamp((low.y - self.margin).floor(), height),
            x1: clamp((high.x + self.margin).ceil(), width),
            y1: clamp((high.y + self.margin).ceil(), height),
        })
    }
}

#[cfg(test)]
mod tests {
    use glam::DVec3;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    use super::*;
    use crate::camera::{Camera, Projection};

    fn batch(min: Vec3, max: Vec3) -> GpuBatch {
        GpuBatch {
            min: min.to_array(),
            first: 0,
            max: max.to_array(),
            count: 1,
        }
    }

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

    #[test]
    fn culling_never_drops_a_box_with_a_point_in_view_and_drops_most_outside() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let cameras = [
            Camera {
                position: DVec3::new(0.0, -30.0, 10.0),
                target: DVec3::ZERO,
                up: DVec3::Z,
                projection: Projection::Perspective { fov_y_deg: 50.0 },
                near: 1.0,
                far: 60.0,
            },
            Camera {
                position: DVec3::new(0.0, 0.0, 40.0),
                target: DVec3::ZERO,
                up: DVec3::Y,
                projection: Projection::Orthographic { height: 12.0 },
                near: 20.0,
                far: 50.0,
            },
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
                let footprint = frustum.footprint(&batch(min, max));
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

    #[test]
    fn tables_hold_the_batches_in_view_in_order_at_aligned_offsets() {
        let gpu = crate::testing::gpu();
        // Looking down -z from z = 10: depth is 10 - z.
        let camera = Camera {
            position: DVec3::new(0.0, 0.0, 10.0),
            target: DVec3::ZERO,
            up: DVec3::Y,
            projection: Projection::Orthographic { height: 2.0 },
            near: 1.0,
            far: 20.0,
        };
        let transform = camera.transform(DVec3::ZERO, 64, 64);
        let far = batch(Vec3::splat(-0.1), Vec3::splat(0.1));
        let near = batch(Vec3::new(-0.1, -0.1, 4.9), Vec3::new(0.1, 0.1, 5.1));
        let beside = batch(Vec3::splat(50.0), Vec3::splat(51.0));
        let behind = batch(Vec3::new(-0.1, -0.1, 10.5), Vec3::new(0.1, 0.1, 11.0));
        let chunks: [&[GpuBatch]; 3] = [&[far, beside, near, behind], &[beside], &[beside, far]];
        let mut tables = FrameBatches::new();
        tables.update(&gpu.device, &gpu.queue, chunks.into_iter(), &transform, 1);

        assert_eq!(
            (tables.count(0), tables.count(1), tables.count(2)),
            (2, 0, 1)
        );
        assert!(tables.binding(1).is_none());
        // Both listed boxes project to the middle of the image, 0.2 of its 2 units wide
        // (6.4 pixels), widened by the 1-pixel points and a pixel of margin.
        let footprint = tables.footprint();
        assert!(footprint.contains(32, 32), "{footprint:?}");
        assert!(
            footprint.width() <= 12 && footprint.height() <= 12,
            "{footprint:?}"
        );
        let (offset, _) = tables.ranges[0];
        let first = offset as usize / std::mem::size_of::<GpuBatch>();
        assert_eq!(
            &tables.staging[first..first + 2],
            &[far, near],
            "the cloud's order"
        );
        let alignment = u64::from(gpu.device.limits().min_storage_buffer_offset_alignment);
        for chunk in [0, 2] {
            let binding = tables.binding(chunk).expect("batches in view");
            assert_eq!(binding.offset % alignment, 0);
        }
    }
}
