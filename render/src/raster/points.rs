//! A point cloud resident on the GPU: Morton-ordered batches with bounding boxes, split into
//! segments whose storage bindings respect the adapter's limit.
//!
//! Points are sorted along a Z-order (Morton) curve so that each batch of consecutive points
//! is spatially compact: its box is small, which makes per-batch frustum culling effective,
//! and nearby threads write nearby pixels. Upload happens once; every frame reuses the buffers.
//!
//! 11 bytes per point (Kanzok et al.'s batch-relative quantisation): the position as 64 bits
//! of fixed point within its batch's box (21, 21 and 22 bits for x, y, z) and the RGB color
//! in a separate buffer, so that a pass reads the color only for points that pass the early
//! depth test. The batch table adds 32 bytes per 4096 points. The quantisation error of an
//! axis is at most half a step, `extent / (2 (2^bits - 1))` of the batch's box on that axis
//! (about 1/4,000,000 of it for x and y, 1/8,000,000 for z), plus f32 rounding of a few ulp of
//! the coordinate when the shader dequantises: for a 10 m batch, 2.4 µm.

use std::sync::Mutex;
use std::time::Instant;

use glam::{UVec3, Vec3};
use wgpu::util::DeviceExt;

use super::draw_order::DrawOrders;
use pointfarm_shaders::layout::{self, INV_QUANT_MAX, POSITION_BITS};

use super::gpu_data::{GpuBatch, QuantisedPosition, COLOR_BYTES};
use super::morton::morton_order;
use super::RenderError;
use crate::cloud::PointCloud;
use crate::gpu::GpuContext;

/// Points per batch: one workgroup culls and rasterizes one batch ([`layout::BATCH_POINTS`]).
pub const BATCH_POINTS: usize = layout::BATCH_POINTS as usize;

/// Points per sub-batch: the host also keeps the box of every run of this many points of a
/// batch, and lists only the runs that can be in view of a batch that straddles the edge of
/// the view (`culling/listing.rs`; [`layout::SUB_BATCH_POINTS`]).
pub const SUB_BATCH_POINTS: usize = layout::SUB_BATCH_POINTS as usize;

/// Bytes one point adds to a segment's point buffers (position and color).
pub const POINT_BYTES: u64 = std::mem::size_of::<QuantisedPosition>() as u64 + COLOR_BYTES;

/// Points per segment when a cloud is streamed in. A segment's host copy takes about 27 bytes a
/// point while it is sorted and quantised (measured on an H200, where the 4 GiB binding let
/// a 100M-point cloud come in as one segment: 2.7 GB of host memory for 1.1 GB on the GPU);
/// this keeps it near 430 MiB whatever the adapter's binding limit.
pub const STREAM_SEGMENT_POINTS: usize = 1 << 24;

/// One storage binding's worth of points and the batches that index into it.
pub(crate) struct PointSegment {
    /// `QuantisedPosition` per point.
    pub positions: wgpu::Buffer,
    /// RGB bytes per point, back to back, padded with one spare word so that a shader can
    /// always read the two words that hold a point's color.
    pub colors: wgpu::Buffer,
    pub batches: wgpu::Buffer,
    /// The same batch table on the host, from which each frame's table is built
    /// (`culling/`).
    pub batch_table: Vec<GpuBatch>,
    /// Host only: each batch's points in runs of [`SUB_BATCH_POINTS`], each with the box of
    /// the positions the shaders dequantise; batch `b`'s runs start at `b * BATCH_POINTS /
    /// SUB_BATCH_POINTS`.
    pub sub_batches: Vec<GpuBatch>,
    /// Host only: the boxes of runs of [`GROUP_BATCHES`] consecutive batches, which the
    /// culling tests first (`batch_groups`).
    pub groups: Vec<GpuBatch>,
    /// Host only: the batch table's near-to-far orders, built as views need them.
    pub draw_orders: DrawOrders,
    /// A node-cache page's point weights for the high-quality mode; none for a resident
    /// cloud, whose points each count once.
    pub weights: Option<PageWeights>,
}

/// What a page of the GPU node cache holds beside its points for the weighted high-quality
/// accumulation (`shaders/hq_accumulate_weighted.wgsl`).
pub(crate) struct PageWeights {
    /// 16 bits a point: its weight's code (`lod/weights.rs`) and its child octant above it.
    pub codes: wgpu::Buffer,
    /// Per batch slot: the children of its node that the frame draws, one bit per octant.
    pub drawn_children: wgpu::Buffer,
}

/// Bytes a page's weights take per point.
pub const WEIGHT_BYTES: u64 = 2;

impl PointSegment {
    /// An empty page of the GPU node cache: room for `capacity` points (a multiple of
    /// [`BATCH_POINTS`]), written batch slot by batch slot, its batch table set per frame
    /// (`cut/gpu_cache.rs`).
    pub(crate) fn page(gpu: &GpuContext, index: usize, capacity: usize) -> Self {
        let buffer = |what: &str, size: u64| {
            gpu.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(&format!("node page {index} {what}")),
                size,
                usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            })
        };
        let slots = capacity.div_ceil(BATCH_POINTS) as u64;
        let capacity = capacity as u64;
        Self {
            positions: buffer(
                "positions",
                capacity * std::mem::size_of::<QuantisedPosition>() as u64,
            ),
            colors: buffer("colors", capacity * COLOR_BYTES + 8), // the spare words of `colors`
            batches: buffer("batches", slots * std::mem::size_of::<GpuBatch>() as u64),
            batch_table: Vec::new(),
            sub_batches: Vec::new(),
            groups: Vec::new(),
            draw_orders: DrawOrders::default(),
            weights: Some(PageWeights {
                // Rounded up to whole words, as the shader reads them.
                codes: buffer("weights", (capacity * WEIGHT_BYTES).next_multiple_of(4)),
                drawn_children: buffer("drawn children", slots * 4),
            }),
        }
    }

    /// Sets the batches a frame draws from this segment (their points already written), on the
    /// host and in its GPU table, the latter with each batch's point-size factor from
    /// `size_factors` (empty: all 1).
    pub(crate) fn set_batches(
        &mut self,
        queue: &wgpu::Queue,
        batches: Vec<GpuBatch>,
        sub_batches: Vec<GpuBatch>,
        size_factors: &[f32],
    ) {
        if size_factors.is_empty() {
            if !batches.is_empty() {
                queue.write_buffer(&self.batches, 0, bytemuck::cast_slice(&batches));
            }
        } else {
            let sized: Vec<GpuBatch> = batches
                .iter()
                .zip(size_factors)
                .map(|(batch, &factor)| batch.with_size_factor(factor))
                .collect();
            queue.write_buffer(&self.batches, 0, bytemuck::cast_slice(&sized));
        }
        self.groups = batch_groups(&batches);
        self.draw_orders = DrawOrders::default();
        self.batch_table = batches;
        self.sub_batches = sub_batches;
    }

    pub(crate) fn tables(&self) -> BatchTables<'_> {
        BatchTables {
            batches: &self.batch_table,
            sub_batches: &self.sub_batches,
            groups: &self.groups,
            draw_orders: &self.draw_orders,
        }
    }
}

/// A segment's batches and sub-batches, as the host's culling reads them.
#[derive(Clone, Copy)]
pub(crate) struct BatchTables<'a> {
    pub batches: &'a [GpuBatch],
    pub sub_batches: &'a [GpuBatch],
    /// Group `g` bounds batches `g * GROUP_BATCHES..`; empty when the segment has none.
    pub groups: &'a [GpuBatch],
    /// The batches' near-to-far orders (`draw_order.rs`).
    pub draw_orders: &'a DrawOrders,
}

/// Batches per group: the culling lists a group wholly in view without testing its batches
/// one by one.
pub const GROUP_BATCHES: usize = 32;

/// The box of each run of [`GROUP_BATCHES`] consecutive batches, with the run's points. The
/// batches are in Morton order, so a run is compact in space.
pub(crate) fn batch_groups(batches: &[GpuBatch]) -> Vec<GpuBatch> {
    batches
        .chunks(GROUP_BATCHES)
        .map(|run| {
            let (mut min, mut max) = (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY));
            for batch in run {
                min = min.min(Vec3::from_array(batch.min));
                max = max.max(Vec3::from_array(batch.max));
            }
            GpuBatch {
                min: min.to_array(),
                first: run[0].first,
                max: max.to_array(),
                count: run.iter().map(|b| b.count).sum(),
            }
        })
        .collect()
}

/// A cloud uploaded for rendering. Create it with [`super::Renderer::upload`].
pub struct GpuPointCloud {
    pub(crate) segments: Vec<PointSegment>,
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

    pub fn segment_count(&self) -> usize {
        self.segments.len()
    }

    /// Batches of all segments.
    pub fn batch_count(&self) -> usize {
        self.segments.iter().map(|c| c.batch_table.len()).sum()
    }

    pub fn origin(&self) -> glam::DVec3 {
        self.origin
    }

    /// Bytes of every GPU buffer that holds this cloud: positions, colors and batch tables.
    pub fn gpu_bytes(&self) -> u64 {
        self.segments
            .iter()
            .map(|c| {
                let weights = c
                    .weights
                    .as_ref()
                    .map_or(0, |w| w.codes.size() + w.drawn_children.size());
                c.positions.size() + c.colors.size() + c.batches.size() + weights
            })
            .sum()
    }

    /// [`Self::gpu_bytes`] per point.
    pub fn gpu_bytes_per_point(&self) -> f64 {
        self.gpu_bytes() as f64 / self.point_count.max(1) as f64
    }

    /// A cloud of node-cache pages, filled and given its batches frame by frame.
    pub(crate) fn of_pages(origin: glam::DVec3) -> Self {
        Self {
            segments: Vec::new(),
            origin,
            point_count: 0,
            unreported_upload_ms: Mutex::new(None),
        }
    }

    /// The points a frame of pages draws, and the time their transfers took.
    pub(crate) fn set_frame_points(&mut self, points: usize, upload_ms: f64) {
        self.point_count = points;
        if let Ok(mut pending) = self.unreported_upload_ms.lock() {
            *pending = Some(pending.unwrap_or(0.0) + upload_ms);
        }
    }

    pub(crate) fn take_upload_ms(&self) -> f64 {
        self.unreported_upload_ms
            .lock()
            .map(|mut t| t.take().unwrap_or(0.0))
            .unwrap_or(0.0)
    }

    /// Sorts, batches and uploads `cloud`, with at most `max_segment_points` points per segment.
    pub(crate) fn upload(
        gpu: &GpuContext,
        cloud: &PointCloud,
        max_segment_points: usize,
    ) -> Result<Self, RenderError> {
        if cloud.is_empty() {
            return Err(RenderError::EmptyCloud);
        }
        let started = Instant::now();
        let order = morton_order(&cloud.positions);
        let max_segment_points = (max_segment_points / BATCH_POINTS).max(1) * BATCH_POINTS;

        let mut segments = Vec::new();
        for segment_order in order.chunks(max_segment_points) {
            let positions: Vec<Vec3> = segment_order
                .iter()
                .map(|&i| cloud.positions[i as usize])
                .collect();
            let colors = segment_order.iter().map(|&i| cloud.colors[i as usize]);
            segments.push(SegmentData::new(&positions, colors).upload(gpu, segments.len()));
        }
        Self::finish(gpu, segments, cloud.origin, cloud.len(), started)
    }

    /// Uploads points that are already in their final order, one segment at a time, so that a
    /// caller generating or streaming a huge cloud never holds more than one segment on the host.
    /// `next_segment` returns the positions (relative to `origin`) and RGBA8 colors of up to
    /// `segment_points` points, or `None` when done; `segment_points` is a multiple of
    /// [`BATCH_POINTS`].
    pub(crate) fn upload_segments(
        gpu: &GpuContext,
        origin: glam::DVec3,
        max_segment_points: usize,
        next_segment: &mut dyn FnMut(usize) -> Option<(Vec<Vec3>, Vec<u32>)>,
    ) -> Result<Self, RenderError> {
        let started = Instant::now();
        let segment_points =
            (max_segment_points.min(STREAM_SEGMENT_POINTS) / BATCH_POINTS).max(1) * BATCH_POINTS;
        let mut segments = Vec::new();
        let mut points = 0;
        while let Some((positions, colors)) = next_segment(segment_points) {
            if positions.is_empty() {
                break;
            }
            points += positions.len();
            let data = SegmentData::new(&positions, colors.into_iter());
            drop(positions);
            segments.push(data.upload(gpu, segments.len()));
            // Submit the segment's pending copy and wait for it before the next segment is
            // generated, so that at most one segment's staging memory is alive at a time.
            gpu.queue.submit([]);
            gpu.device
                .poll(wgpu::PollType::wait_indefinitely())
                .map_err(|e| RenderError::Gpu(e.to_string()))?;
        }
        if points == 0 {
            return Err(RenderError::EmptyCloud);
        }
        Self::finish(gpu, segments, origin, points, started)
    }

    fn finish(
        gpu: &GpuContext,
        segments: Vec<PointSegment>,
        origin: glam::DVec3,
        point_count: usize,
        started: Instant,
    ) -> Result<Self, RenderError> {
        // Make the upload time honest: wait until the copies are done.
        gpu.queue.submit([]);
        gpu.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(|e| RenderError::Gpu(e.to_string()))?;
        let upload_ms = started.elapsed().as_secs_f64() * 1e3;
        let cloud = Self {
            segments,
            origin,
            point_count,
            unreported_upload_ms: Mutex::new(Some(upload_ms)),
        };
        tracing::info!(
            points = point_count,
            segments = cloud.segments.len(),
            bytes_per_point = format!("{:.3}", cloud.gpu_bytes_per_point()),
            upload_ms = format!("{upload_ms:.1}"),
            "points resident on the GPU"
        );
        Ok(cloud)
    }
}

/// One segment's buffers, built on the host (also a level-of-detail node's, before it is
/// written into the pages of the GPU node cache, `cut/gpu_cache.rs`).
pub(crate) struct SegmentData {
    pub positions: Vec<QuantisedPosition>,
    /// RGB bytes per point and one spare word (see [`PointSegment::colors`]).
    pub colors: Vec<u8>,
    /// `first` counts from the segment's first point.
    pub batches: Vec<GpuBatch>,
    pub sub_batches: Vec<GpuBatch>,
    /// A level-of-detail node's weight bits per point (`PageWeights::codes`), padded to an
    /// even count; empty for a resident cloud's segment.
    pub weights: Vec<u16>,
}

impl SegmentData {
    /// Batches, bounds and quantises points in their final order.
    pub(crate) fn new(positions: &[Vec3], colors: impl Iterator<Item = u32>) -> Self {
        let mut quantised = Vec::with_capacity(positions.len());
        let mut batches = Vec::with_capacity(positions.len().div_ceil(BATCH_POINTS));
        let mut sub_batches = Vec::with_capacity(positions.len().div_ceil(SUB_BATCH_POINTS));
        for (b, batch) in positions.chunks(BATCH_POINTS).enumerate() {
            let gpu_batch = batch_of(b * BATCH_POINTS, batch);
            let (min, step) = (
                Vec3::from_array(gpu_batch.min),
                quantisation_step(&gpu_batch),
            );
            let first = quantised.len();
            quantised.extend(batch.iter().map(|&p| quantise(p, min, step)));
            for (s, run) in quantised[first..].chunks(SUB_BATCH_POINTS).enumerate() {
                sub_batches.push(sub_batch_of(&gpu_batch, first + s * SUB_BATCH_POINTS, run));
            }
            batches.push(gpu_batch);
        }
        // Three bytes per point and one spare word (see `PointSegment::colors`).
        let mut rgb = Vec::with_capacity(positions.len() * 3 + 8);
        for color in colors.take(positions.len()) {
            rgb.extend_from_slice(&color.to_le_bytes()[..3]);
        }
        rgb.resize(rgb.len().next_multiple_of(4) + 4, 0);
        Self {
            positions: quantised,
            colors: rgb,
            batches,
            sub_batches,
            weights: Vec::new(),
        }
    }

    fn upload(self, gpu: &GpuContext, index: usize) -> PointSegment {
        let label = format!("points segment {index}");
        let buffer = |what: &str, contents: &[u8]| {
            gpu.device
                .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                    label: Some(&format!("{label} {what}")),
                    contents,
                    usage: wgpu::BufferUsages::STORAGE,
                })
        };
        PointSegment {
            positions: buffer("positions", bytemuck::cast_slice(&self.positions)),
            colors: buffer("colors", &self.colors),
            batches: buffer("batches", bytemuck::cast_slice(&self.batches)),
            groups: batch_groups(&self.batches),
            draw_orders: DrawOrders::default(),
            batch_table: self.batches,
            sub_batches: self.sub_batches,
            weights: None,
        }
    }
}

fn batch_of(first: usize, points: &[Vec3]) -> GpuBatch {
    let mut min = Vec3::splat(f32::INFINITY);
    let mut max = Vec3::splat(f32::NEG_INFINITY);
    for &p in points {
        min = min.min(p);
        max = max.max(p);
    }
    GpuBatch {
        min: min.to_array(),
        first: first as u32,
        max: max.to_array(),
        count: points.len() as u32,
    }
}

/// The run of quantised points of `batch` starting at index `first`, with the box of their
/// dequantised positions widened by one step on each side: the shaders' f32 dequantisation
/// lands within a few ulp of the exact value, far inside that step.
fn sub_batch_of(batch: &GpuBatch, first: usize, run: &[QuantisedPosition]) -> GpuBatch {
    let (mut low, mut high) = (UVec3::MAX, UVec3::ZERO);
    for &word in run {
        let q = unpack(word);
        low = low.min(q);
        high = high.max(q);
    }
    let min = Vec3::from_array(batch.min).as_dvec3();
    let step = quantisation_step(batch).as_dvec3();
    let corner = |q: UVec3, side: f64| (min + (q.as_dvec3() + side) * step).as_vec3();
    GpuBatch {
        min: corner(low, -1.0).to_array(),
        first: first as u32,
        max: corner(high, 1.0).to_array(),
        count: run.len() as u32,
    }
}

/// Largest quantised value of each axis.
fn quantisation_max() -> UVec3 {
    UVec3::from_array(POSITION_BITS.map(|bits| (1u32 << bits) - 1))
}

/// The size of one quantisation step on each axis of `batch`'s box, computed as the shaders
/// do (`quantisation_step` in common.wgsl): the extent times the reciprocal of the largest
/// quantised value, in f32.
pub(crate) fn quantisation_step(batch: &GpuBatch) -> Vec3 {
    let extent = Vec3::from_array(batch.max) - Vec3::from_array(batch.min);
    extent * Vec3::from_array(INV_QUANT_MAX)
}

/// Where y's bits split between the two words ([`POSITION_BITS`]): its low bits fill the first
/// word above x's, its high bits start the second, below z's.
const Y_LOW_BITS: u32 = 32 - POSITION_BITS[0];
const Y_HIGH_BITS: u32 = POSITION_BITS[1] - Y_LOW_BITS;

/// The nearest quantised position to `p` in a box starting at `min` with steps `step`.
pub(crate) fn quantise(p: Vec3, min: Vec3, step: Vec3) -> QuantisedPosition {
    let max = quantisation_max();
    let q: [u32; 3] = std::array::from_fn(|axis| {
        if step[axis] > 0.0 {
            let steps = (p[axis] as f64 - min[axis] as f64) / step[axis] as f64;
            steps.round().clamp(0.0, max[axis] as f64) as u32
        } else {
            0
        }
    });
    [
        q[0] | (q[1] << POSITION_BITS[0]),
        (q[1] >> Y_LOW_BITS) | (q[2] << Y_HIGH_BITS),
    ]
}

/// The quantised steps of each axis (the shaders' `dequantise` in common.wgsl).
fn unpack(word: QuantisedPosition) -> UVec3 {
    UVec3::new(
        word[0] & ((1 << POSITION_BITS[0]) - 1),
        (word[0] >> POSITION_BITS[0]) | ((word[1] & ((1 << Y_HIGH_BITS) - 1)) << Y_LOW_BITS),
        word[1] >> Y_HIGH_BITS,
    )
}

/// The position a shader reads back (`dequantise` in common.wgsl).
#[cfg(test)]
fn dequantise(word: QuantisedPosition, min: Vec3, step: Vec3) -> Vec3 {
    min + unpack(word).as_vec3() * step
}

/// Host tables of `positions` sorted in Morton order, as an upload builds them: the batches,
/// the sub-batches and each point's position as the shaders dequantise it.
#[cfg(test)]
pub(crate) fn host_tables(positions: &[Vec3]) -> (Vec<GpuBatch>, Vec<GpuBatch>, Vec<Vec3>) {
    let sorted: Vec<Vec3> = morton_order(positions)
        .into_iter()
        .map(|i| positions[i as usize])
        .collect();
    let data = SegmentData::new(&sorted, std::iter::repeat(0));
    let dequantised = data
        .positions
        .iter()
        .enumerate()
        .map(|(i, &word)| {
            let batch = &data.batches[i / BATCH_POINTS];
            dequantise(word, Vec3::from_array(batch.min), quantisation_step(batch))
        })
        .collect();
    (data.batches, data.sub_batches, dequantised)
}

#[cfg(test)]
mod tests {
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    use super::*;

    /// The documented bound: half a step, plus f32 rounding of a few ulp of the coordinate.
    #[test]
    fn quantised_positions_are_within_half_a_step_of_the_original() {
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        for (offset, size) in [(0.0, 1.0), (-250.0, 40.0), (1200.0, 0.01), (-3.0, 7000.0)] {
            let points: Vec<Vec3> = (0..BATCH_POINTS)
                .map(|_| {
                    Vec3::from_array(std::array::from_fn(|_| offset + rng.random::<f32>() * size))
                })
                .collect();
            let batch = batch_of(0, &points);
            let (min, step) = (Vec3::from_array(batch.min), quantisation_step(&batch));
            for &p in &points {
                let back = dequantise(quantise(p, min, step), min, step);
                let ulp = (p.abs() + Vec3::from_array(batch.max).abs()) * f32::EPSILON;
                let bound = step * 0.5 + 2.0 * ulp;
                let error = (back - p).abs();
                assert!(
                    error.cmple(bound).all(),
                    "{p} came back as {back}: error {error} > bound {bound}"
                );
            }
        }
    }

    #[test]
    fn sub_batches_split_each_batch_in_order_and_bound_its_dequantised_points() {
        let mut rng = ChaCha8Rng::seed_from_u64(12);
        // Two full batches and a partial one, at survey-like offsets.
        let points: Vec<Vec3> = (0..2 * BATCH_POINTS + 700)
            .map(|_| Vec3::from_array(std::array::from_fn(|_| 300.0 + rng.random::<f32>() * 90.0)))
            .collect();
        let (batches, subs, dequantised) = host_tables(&points);
        assert_eq!(batches.len(), 3);
        assert_eq!(subs.len(), 2 * BATCH_POINTS / SUB_BATCH_POINTS + 3);
        let mut next = 0;
        for (s, sub) in subs.iter().enumerate() {
            assert_eq!(
                sub.first as usize, next,
                "sub-batch {s} follows the one before"
            );
            next += sub.count as usize;
            let batch = &batches[sub.first as usize / BATCH_POINTS];
            assert!(sub.first + sub.count <= batch.first + batch.count);
            let (min, max) = (Vec3::from_array(sub.min), Vec3::from_array(sub.max));
            let run = &dequantised[sub.first as usize..(sub.first + sub.count) as usize];
            for p in run {
                assert!(
                    p.cmpge(min).all() && p.cmple(max).all(),
                    "{p} outside {sub:?}"
                );
            }
            // Tight: Morton order makes a run much smaller than its batch.
            let batch_size = Vec3::from_array(batch.max) - Vec3::from_array(batch.min);
            assert!(
                (max - min).length() < batch_size.length(),
                "{sub:?} in {batch:?}"
            );
        }
        assert_eq!(next, points.len());
    }

    #[test]
    fn a_flat_batch_keeps_its_flat_axis_exact() {
        let points = [Vec3::new(1.0, 5.0, -2.0), Vec3::new(3.0, 5.0, 4.0)];
        let batch = batch_of(0, &points);
        let (min, step) = (Vec3::from_array(batch.min), quantisation_step(&batch));
        for p in points {
            let back = dequantise(quantise(p, min, step), min, step);
            assert_eq!(back.y, 5.0);
            assert!((back - p).abs().max_element() < 1e-5, "{p} -> {back}");
        }
    }

    #[test]
    fn segment_data_packs_rgb_bytes_and_a_spare_word() {
        let positions = vec![Vec3::ZERO; 5];
        let colors = (0..5u32).map(|i| u32::from_le_bytes([i as u8, 10 + i as u8, 20, 255]));
        let data = SegmentData::new(&positions, colors);
        assert_eq!(data.colors.len(), 20);
        assert_eq!(&data.colors[3..6], &[1, 11, 20]);
        assert_eq!(data.positions.len(), 5);
        assert_eq!(data.batches.len(), 1);
    }

    /// However large the adapter's binding limit, a streamed cloud is asked for in segments of
    /// at most `STREAM_SEGMENT_POINTS`, which bounds the host's memory during ingest.
    #[test]
    fn streamed_segments_are_capped_whatever_the_binding_limit() {
        let gpu = crate::testing::gpu();
        let mut asked = Vec::new();
        let mut left = 3;
        let cloud = GpuPointCloud::upload_segments(&gpu, glam::DVec3::ZERO, usize::MAX, &mut |n| {
            asked.push(n);
            left -= 1;
            (left >= 0).then(|| {
                (
                    vec![Vec3::new(1.0, 2.0, left as f32); 5],
                    vec![0xff00_00ff; 5],
                )
            })
        })
        .expect("upload");
        assert_eq!(cloud.len(), 15);
        assert_eq!(cloud.segments.len(), 3);
        assert!(
            asked.iter().all(|&n| n == STREAM_SEGMENT_POINTS),
            "asked for {asked:?}"
        );
    }
}
