//! A point cloud resident on the GPU: Morton-ordered batches with bounding boxes, split into
//! chunks whose storage bindings respect the adapter's limit.
//!
//! Points are sorted along a Z-order (Morton) curve so that each batch of consecutive points
//! is spatially compact: its box is small, which makes per-batch frustum culling effective,
//! and nearby threads write nearby pixels. Upload happens once; every frame reuses the buffers.

use std::sync::Mutex;
use std::time::Instant;

use glam::Vec3;
use wgpu::util::DeviceExt;

use super::gpu_data::{GpuBatch, GpuPoint};
use super::RenderError;
use crate::cloud::PointCloud;
use crate::gpu::GpuContext;

/// Points per batch: one workgroup culls and rasterizes one batch.
pub const BATCH_POINTS: usize = 4096;

/// One storage binding's worth of points and the batches that index into it.
pub(crate) struct PointChunk {
    pub points: wgpu::Buffer,
    pub batches: wgpu::Buffer,
    pub batch_count: u32,
}

/// A cloud uploaded for rendering. Create it with [`super::Renderer::upload`].
pub struct GpuPointCloud {
    pub(crate) chunks: Vec<PointChunk>,
    pub(crate) origin: glam::DVec3,
    point_count: usize,
    /// Upload time not yet reported by a frame: the first frame rendered from this cloud
    /// carries it in its "upload" stage.
    unreported_upload_ms: Mutex<Option<f64>>,
}

impl GpuPointCloud {
    pub fn len(&self) -> usize {
        self.point_count
    }

    pub fn is_empty(&self) -> bool {
        self.point_count == 0
    }

    pub fn chunk_count(&self) -> usize {
        self.chunks.len()
    }

    pub fn origin(&self) -> glam::DVec3 {
        self.origin
    }

    pub(crate) fn take_upload_ms(&self) -> f64 {
        self.unreported_upload_ms
            .lock()
            .map(|mut t| t.take().unwrap_or(0.0))
            .unwrap_or(0.0)
    }

    /// Sorts, batches and uploads `cloud`, with at most `max_chunk_points` points per chunk.
    pub(crate) fn upload(
        gpu: &GpuContext,
        cloud: &PointCloud,
        max_chunk_points: usize,
    ) -> Result<Self, RenderError> {
        if cloud.is_empty() {
            return Err(RenderError::EmptyCloud);
        }
        let started = Instant::now();
        let order = morton_order(&cloud.positions);
        let max_chunk_points = (max_chunk_points / BATCH_POINTS).max(1) * BATCH_POINTS;

        let mut chunks = Vec::new();
        for chunk_order in order.chunks(max_chunk_points) {
            let points: Vec<GpuPoint> = chunk_order
                .iter()
                .map(|&i| GpuPoint {
                    position: cloud.positions[i as usize].to_array(),
                    colour: cloud.colors[i as usize],
                })
                .collect();
            let batches: Vec<GpuBatch> = points
                .chunks(BATCH_POINTS)
                .enumerate()
                .map(|(b, batch)| batch_of(b * BATCH_POINTS, batch))
                .collect();
            let label = format!("points chunk {}", chunks.len());
            chunks.push(PointChunk {
                points: gpu
                    .device
                    .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                        label: Some(&label),
                        contents: bytemuck::cast_slice(&points),
                        usage: wgpu::BufferUsages::STORAGE,
                    }),
                batches: gpu
                    .device
                    .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                        label: Some(&format!("{label} batches")),
                        contents: bytemuck::cast_slice(&batches),
                        usage: wgpu::BufferUsages::STORAGE,
                    }),
                batch_count: batches.len() as u32,
            });
        }
        // Make the upload time honest: wait until the copies are done.
        gpu.queue.submit([]);
        gpu.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(|e| RenderError::Gpu(e.to_string()))?;
        let upload_ms = started.elapsed().as_secs_f64() * 1e3;
        tracing::info!(
            points = cloud.len(),
            chunks = chunks.len(),
            upload_ms = format!("{upload_ms:.1}"),
            "points resident on the GPU"
        );
        Ok(Self {
            chunks,
            origin: cloud.origin,
            point_count: cloud.len(),
            unreported_upload_ms: Mutex::new(Some(upload_ms)),
        })
    }
}

fn batch_of(first: usize, points: &[GpuPoint]) -> GpuBatch {
    let mut min = Vec3::splat(f32::INFINITY);
    let mut max = Vec3::splat(f32::NEG_INFINITY);
    for p in points {
        let v = Vec3::from_array(p.position);
        min = min.min(v);
        max = max.max(v);
    }
    GpuBatch {
        min: min.to_array(),
        first: first as u32,
        max: max.to_array(),
        count: points.len() as u32,
    }
}

/// Indices of `positions` in Z-order over their bounding box (21 bits per axis).
fn morton_order(positions: &[Vec3]) -> Vec<u32> {
    let (min, max) = positions.iter().fold(
        (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY)),
        |(lo, hi), p| (lo.min(*p), hi.max(*p)),
    );
    let scale = (max - min).max_element().max(f32::MIN_POSITIVE);
    let cells = ((1u32 << 21) - 1) as f32;
    let mut keyed: Vec<(u64, u32)> = positions
        .iter()
        .enumerate()
        .map(|(i, p)| {
            let q = ((*p - min) / scale * cells).clamp(Vec3::ZERO, Vec3::splat(cells));
            (morton3(q.x as u32, q.y as u32, q.z as u32), i as u32)
        })
        .collect();
    keyed.sort_unstable();
    keyed.into_iter().map(|(_, i)| i).collect()
}

/// Interleaves the low 21 bits of x, y and z.
fn morton3(x: u32, y: u32, z: u32) -> u64 {
    fn spread(v: u32) -> u64 {
        let mut v = v as u64 & 0x1f_ffff;
        v = (v | (v << 32)) & 0x001f_0000_0000_ffff;
        v = (v | (v << 16)) & 0x001f_0000_ff00_00ff;
        v = (v | (v << 8)) & 0x100f_00f0_0f00_f00f;
        v = (v | (v << 4)) & 0x10c3_0c30_c30c_30c3;
        v = (v | (v << 2)) & 0x1249_2492_4924_9249;
        v
    }
    spread(x) | (spread(y) << 1) | (spread(z) << 2)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn morton_code_interleaves_bits() {
        assert_eq!(morton3(1, 0, 0), 0b001);
        assert_eq!(morton3(0, 1, 0), 0b010);
        assert_eq!(morton3(0, 0, 1), 0b100);
        assert_eq!(morton3(3, 0, 0), 0b001_001);
        assert_eq!(morton3(0x1f_ffff, 0x1f_ffff, 0x1f_ffff), (1u64 << 63) - 1);
    }

    #[test]
    fn morton_order_is_a_permutation_that_keeps_neighbours_together() {
        let positions: Vec<Vec3> = (0..64)
            .map(|i| Vec3::new((i % 4) as f32, ((i / 4) % 4) as f32, (i / 16) as f32))
            .collect();
        let order = morton_order(&positions);
        let mut sorted = order.clone();
        sorted.sort_unstable();
        assert_eq!(sorted, (0..64).collect::<Vec<u32>>());
        // The first eight points in Z-order form the 2x2x2 cube at the corner.
        for &i in &order[..8] {
            let p = positions[i as usize];
            assert!(p.max_element() <= 1.0, "{p}");
        }
    }
}
