//! The frame's batch tables: every segment's listed entries (`listing.rs`) back to back in one
//! GPU buffer, each segment's from a multiple of the storage-binding offset alignment; a cloud
//! of many segments culled on all cores, a segment per task; the segments ordered near to far; each
//! segment's entries split in the phases of the depth-writing pass; the frame's footprint.

use rayon::prelude::*;

use super::frustum::Frustum;
use super::listing::{list_in_view, Listing};
use crate::camera::CameraTransform;
use crate::raster::draw_order::sort_near_to_far;
use crate::raster::gpu_data::GpuBatch;
use crate::raster::occlusion::phase_cuts;
use crate::raster::phases::{split_by_depth, SegmentEntries};
use crate::raster::pixel_rect::{PixelCoverage, PixelRect};
use crate::raster::points::BatchTables;

/// One frame's batch tables of a cloud's segments, in one GPU buffer.
pub(crate) struct FrameBatches {
    /// Per segment, its batches that can be in view; each segment's table starts at a multiple of
    /// the storage-binding offset alignment.
    buffer: Option<wgpu::Buffer>,
    /// Per segment: byte offset of its table in `buffer` and its number of batches.
    ranges: Vec<(u64, u32)>,
    /// The segments with batches in view, near to far (by their listed batches' boxes).
    segment_order: Vec<usize>,
    /// Host copy reused from frame to frame: [`ListedEntry`] words.
    staging: Vec<u32>,
    /// Per segment (as `ranges`): what its listed entries hold.
    listings: Vec<Listing>,
    /// Per segment (as `ranges`): the end of each phase's entries in its table, the nearest
    /// phase first (`phases.rs`).
    phase_ends: Vec<Vec<u32>>,
    /// The pixels that points of the listed batches can touch this frame.
    footprint: PixelRect,
    /// Pixels of the cells of the image those points can touch (`PixelCoverage`).
    covered_pixels: u64,
    /// The storage-binding offset alignment, in entries.
    alignment_entries: u32,
    /// Whether batches that straddle the view's edge are culled again run by run.
    refine_straddlers: bool,
    /// Batches from which a cloud of several segments is culled in parallel: always
    /// [`PARALLEL_CULL_BATCHES`], except in the test that compares both paths.
    parallel_from_batches: usize,
}

/// Batches from which a cloud of several segments is culled on all cores: one segment per task.
const PARALLEL_CULL_BATCHES: usize = 16_384;

impl FrameBatches {
    /// `refine_straddlers`: cull batches that straddle the view's edge again in runs of 256
    /// points. That pays where a point costs far more than a box test on the host, as on a
    /// CPU adapter; on a GPU, which draws a whole batch in less time than the host takes to
    /// test its runs, it does not (docs/perf/batch-culling.md).
    pub fn new(refine_straddlers: bool) -> Self {
        Self {
            buffer: None,
            ranges: Vec::new(),
            segment_order: Vec::new(),
            staging: Vec::new(),
            listings: Vec::new(),
            phase_ends: Vec::new(),
            footprint: PixelRect::EMPTY,
            covered_pixels: 0,
            alignment_entries: 1,
            refine_straddlers,
            parallel_from_batches: PARALLEL_CULL_BATCHES,
        }
    }

    /// Builds the tables of `segments` (each its full batch table) for a frame seen through
    /// `transform` with points of `point_size` pixels, and uploads them.
    pub fn update<'a>(
        &mut self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        segments: impl Iterator<Item = BatchTables<'a>>,
        transform: &CameraTransform,
        point_size: u32,
    ) {
        let frustum = Frustum::new(transform, point_size);
        let entry_bytes = std::mem::size_of::<u32>();
        let alignment =
            (device.limits().min_storage_buffer_offset_alignment as usize).div_ceil(entry_bytes);
        self.alignment_entries = alignment as u32;
        self.staging.clear();
        self.ranges.clear();
        self.listings.clear();
        let mut coverage = PixelCoverage::new(transform.width, transform.height);
        let refine = self.refine_straddlers;
        let segments: Vec<BatchTables<'a>> = segments
            .map(|tables| BatchTables {
                sub_batches: if refine { tables.sub_batches } else { &[] },
                ..tables
            })
            .collect();
        let depth_gradient = transform.depth_row.truncate();
        let batches: usize = segments.iter().map(|tables| tables.batches.len()).sum();
        if segments.len() > 1 && batches >= self.parallel_from_batches {
            // Every segment on its own core, then their tables back to back.
            let culled: Vec<(Vec<u32>, Listing, PixelCoverage)> = segments
                .par_iter()
                .map(|&tables| {
                    let mut entries = Vec::new();
                    let mut segment_coverage =
                        PixelCoverage::new(transform.width, transform.height);
                    let listing = list_in_view(
                        &frustum,
                        tables,
                        depth_gradient,
                        &mut entries,
                        &mut segment_coverage,
                    );
                    (entries, listing, segment_coverage)
                })
                .collect();
            for (entries, listing, segment_coverage) in culled {
                let start = self.pad_to_alignment(alignment);
                self.staging.extend_from_slice(&entries);
                self.ranges
                    .push(((start * entry_bytes) as u64, entries.len() as u32));
                self.listings.push(listing);
                coverage.merge(&segment_coverage);
            }
        } else {
            for &tables in &segments {
                let start = self.pad_to_alignment(alignment);
                let listing = list_in_view(
                    &frustum,
                    tables,
                    depth_gradient,
                    &mut self.staging,
                    &mut coverage,
                );
                self.ranges.push((
                    (start * entry_bytes) as u64,
                    (self.staging.len() - start) as u32,
                ));
                self.listings.push(listing);
            }
        }
        self.order_segments(transform);
        self.footprint = coverage.union();
        self.covered_pixels = coverage.pixels();
        self.split_in_phases(&segments, transform);
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

    /// Pads the staged tables to a multiple of `alignment` entries, where the next segment's
    /// table starts; returns that start.
    fn pad_to_alignment(&mut self, alignment: usize) -> usize {
        let padding = self.staging.len().next_multiple_of(alignment) - self.staging.len();
        self.staging.extend(std::iter::repeat_n(0, padding));
        self.staging.len()
    }

    /// Splits each segment's entries in the phases of the depth-writing pass, where its points
    /// lie deep enough for occlusion culling to pay (`occlusion::phase_cuts`).
    fn split_in_phases(&mut self, segments: &[BatchTables<'_>], transform: &CameraTransform) {
        let cuts = phase_cuts(self.total(), self.points_per_pixel());
        let mut rest = self.staging.as_mut_slice();
        let mut taken = 0;
        let mut entries = Vec::with_capacity(segments.len());
        for (tables, &(offset, count)) in segments.iter().zip(&self.ranges) {
            let start = offset as usize / std::mem::size_of::<u32>();
            let (_, tail) = std::mem::take(&mut rest).split_at_mut(start - taken);
            let (table, tail) = tail.split_at_mut(count as usize);
            rest = tail;
            taken = start + count as usize;
            entries.push(SegmentEntries {
                entries: table,
                batches: tables.batches,
            });
        }
        self.phase_ends = split_by_depth(
            &mut entries,
            &cuts,
            transform.depth_row,
            self.alignment_entries,
        );
    }

    /// Orders the segments that have batches in view near to far, as their batches are: a
    /// cloud larger than one binding comes in segments of neighbouring points (Morton order or
    /// a streaming reader's), so this draws the near segments' points first.
    fn order_segments(&mut self, transform: &CameraTransform) {
        self.segment_order.clear();
        let listed = self.ranges.iter().filter(|&&(_, count)| count > 0).count();
        if listed < 2 {
            // Nothing to order (most clouds are one segment).
            self.segment_order
                .extend(self.ranges.iter().position(|&(_, count)| count > 0));
            return;
        }
        let mut boxes: Vec<GpuBatch> = self
            .ranges
            .iter()
            .zip(&self.listings)
            .enumerate()
            .filter(|(_, (&(_, count), _))| count > 0)
            .map(|(segment, (&(_, count), listing))| GpuBatch {
                min: listing.min.to_array(),
                first: segment as u32,
                max: listing.max.to_array(),
                count,
            })
            .collect();
        sort_near_to_far(&mut boxes, transform.depth_row.truncate());
        self.segment_order
            .extend(boxes.iter().map(|segment_box| segment_box.first as usize));
    }

    /// Phases of the depth-writing pass: at least one.
    pub fn phase_count(&self) -> usize {
        self.phase_ends.iter().map(Vec::len).max().unwrap_or(1)
    }

    /// The pixels that points of this frame's listed batches can touch (empty when none is
    /// listed).
    pub fn footprint(&self) -> PixelRect {
        self.footprint
    }

    /// Points of this frame's listed entries.
    pub fn listed_points(&self) -> u64 {
        self.listings.iter().map(|listing| listing.points).sum()
    }

    /// Number of batches of all segments in this frame's tables.
    pub fn total(&self) -> u32 {
        self.ranges.iter().map(|&(_, count)| count).sum()
    }

    /// Points of the listed batches per pixel they can reach (counted in cells of 64 x 64
    /// pixels): how deep the points that can be in view lie.
    pub fn points_per_pixel(&self) -> f64 {
        self.listed_points() as f64 / self.covered_pixels.max(1) as f64
    }

    /// Phase `phase`'s entries of every segment that has some, segment after segment near to far:
    /// the segment, its entries as a storage binding and their number.
    pub fn phase_parts(
        &self,
        phase: usize,
    ) -> impl Iterator<Item = (usize, (wgpu::BufferBinding<'_>, u32))> + '_ {
        self.segment_order
            .iter()
            .filter_map(move |&segment| Some((segment, self.phase_part(segment, phase)?)))
    }

    /// The entries of segment `segment`'s table in phase `phase` as a storage binding and their
    /// number; `None` when there are none.
    fn phase_part(&self, segment: usize, phase: usize) -> Option<(wgpu::BufferBinding<'_>, u32)> {
        let entries = self.phase_entries(segment, phase);
        self.entries_binding(segment, entries)
    }

    /// The entries of segment `segment`'s table in phase `phase`: consecutive phases hold the
    /// table in order, each from a multiple of the binding alignment.
    fn phase_entries(&self, segment: usize, phase: usize) -> std::ops::Range<u32> {
        let Some(ends) = self.phase_ends.get(segment) else {
            return 0..0;
        };
        let start = if phase == 0 {
            0
        } else {
            ends.get(phase - 1).copied().unwrap_or(0)
        };
        start..ends.get(phase).copied().unwrap_or(start).max(start)
    }

    /// `entries` of segment `segment`'s table as a storage binding and their number.
    fn entries_binding(
        &self,
        segment: usize,
        entries: std::ops::Range<u32>,
    ) -> Option<(wgpu::BufferBinding<'_>, u32)> {
        let (offset, _) = *self.ranges.get(segment)?;
        let buffer = self.buffer.as_ref()?;
        let entry = std::mem::size_of::<u32>() as u64;
        (!entries.is_empty()).then(|| {
            (
                wgpu::BufferBinding {
                    buffer,
                    offset: offset + u64::from(entries.start) * entry,
                    size: wgpu::BufferSize::new(u64::from(entries.len() as u32) * entry),
                },
                entries.len() as u32,
            )
        })
    }

    /// Number of batches of segment `segment` in this frame's table.
    #[cfg(test)]
    fn count(&self, segment: usize) -> u32 {
        self.ranges.get(segment).map_or(0, |&(_, count)| count)
    }

    /// The table of segment `segment` as a storage binding; `None` when no batch is in view.
    #[cfg(test)]
    fn binding(&self, segment: usize) -> Option<wgpu::BufferBinding<'_>> {
        self.entries_binding(segment, 0..self.count(segment))
            .map(|(binding, _)| binding)
    }
}

#[cfg(test)]
mod tests {
    use crate::testing::{perspective_camera, top_down_camera};
    use glam::{DVec3, Vec3};
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    use super::*;
    use crate::gpu::GpuContext;
    use crate::raster::culling::{batch, decoded};
    use crate::raster::draw_order::DrawOrders;
    use crate::raster::occlusion::MIN_PHASES;
    use crate::raster::points::{BATCH_POINTS, SUB_BATCH_POINTS};

    /// A segment's tables with batches only: no sub-batches or groups to refine them.
    fn whole_batches<'a>(batches: &'a [GpuBatch], draw_orders: &'a DrawOrders) -> BatchTables<'a> {
        BatchTables {
            batches,
            sub_batches: &[],
            groups: &[],
            draw_orders,
        }
    }

    /// The frame's tables for `segments` of whole batches, straddlers refined.
    fn tables_of_whole_batches(
        gpu: &GpuContext,
        segments: &[impl AsRef<[GpuBatch]>],
        transform: &CameraTransform,
    ) -> FrameBatches {
        // One cache of draw orders per segment: a cache serves one batch table only.
        let orders: Vec<DrawOrders> = segments.iter().map(|_| DrawOrders::default()).collect();
        let mut tables = FrameBatches::new(true);
        let tables_of = segments
            .iter()
            .zip(&orders)
            .map(|(batches, draw_orders)| whole_batches(batches.as_ref(), draw_orders));
        tables.update(&gpu.device, &gpu.queue, tables_of, transform, 1);
        tables
    }

    /// A 64 x 64 orthographic view down -z from z = 10, 2 units high: depth is 10 - z.
    fn looking_down_from_z_10() -> CameraTransform {
        top_down_camera(DVec3::ZERO, 10.0, 2.0, (1.0, 20.0)).transform(DVec3::ZERO, 64, 64)
    }

    #[test]
    fn tables_hold_the_batches_in_view_in_order_at_aligned_offsets() {
        let gpu = crate::testing::gpu();
        let transform = looking_down_from_z_10();
        let far = batch(Vec3::splat(-0.1), Vec3::splat(0.1));
        let near = batch(Vec3::new(-0.1, -0.1, 4.9), Vec3::new(0.1, 0.1, 5.1));
        let beside = batch(Vec3::splat(50.0), Vec3::splat(51.0));
        let behind = batch(Vec3::new(-0.1, -0.1, 10.5), Vec3::new(0.1, 0.1, 11.0));
        let segments: [&[GpuBatch]; 3] = [&[far, beside, near, behind], &[beside], &[beside, far]];
        let tables = tables_of_whole_batches(&gpu, &segments, &transform);

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
            decoded(&tables.staging[first..first + 2], segments[0]),
            [near, far],
            "near to far"
        );
        let alignment = u64::from(gpu.device.limits().min_storage_buffer_offset_alignment);
        for segment in [0, 2] {
            let binding = tables.binding(segment).expect("batches in view");
            assert_eq!(binding.offset % alignment, 0);
        }
    }

    /// The depth pass's phases split the listed batches by depth across the segments: the first
    /// holds the nearest batches, and together they hold every listed batch once, each segment's
    /// phases one after the other in its table.
    #[test]
    fn phases_split_the_segments_by_depth_and_hold_every_batch_once() {
        let gpu = crate::testing::gpu();
        let transform = looking_down_from_z_10();
        // Batch b of a segment at `depth` lies 0.01 b deeper.
        let at_depth = |depth: f32, n: usize| -> Vec<GpuBatch> {
            (0..n)
                .map(|b| {
                    let z = 10.0 - depth - 0.01 * b as f32;
                    GpuBatch {
                        count: BATCH_POINTS as u32,
                        ..batch(
                            Vec3::new(-0.5, -0.5, z - 0.005),
                            Vec3::new(0.5, 0.5, z + 0.005),
                        )
                    }
                })
                .collect()
        };
        // Segment 0 far, segment 1 near, segment 2 between; 200 full batches each, deep enough on
        // the 64 x 64 image for phases.
        let segments = [at_depth(8.0, 200), at_depth(2.0, 200), at_depth(5.0, 200)];
        let tables = tables_of_whole_batches(&gpu, &segments, &transform);
        assert_eq!(tables.segment_order, [1, 2, 0]);
        let phase_count = tables.phase_count();
        assert!(phase_count >= MIN_PHASES, "{phase_count}");
        let phases: Vec<Vec<(usize, std::ops::Range<u32>)>> = (0..tables.phase_count())
            .map(|phase| {
                tables
                    .segment_order
                    .iter()
                    .map(|&segment| (segment, tables.phase_entries(segment, phase)))
                    .filter(|(_, entries)| !entries.is_empty())
                    .collect()
            })
            .collect();
        // Equal shares of 600 batches: the first from the nearest segment, the last from the
        // farthest (alignment moves a few batches to the phase before theirs, in their own
        // segment).
        assert!(
            phases[0].iter().all(|(segment, _)| *segment == 1),
            "{phases:?}"
        );
        assert!(
            phases[phase_count - 1]
                .iter()
                .all(|(segment, _)| *segment == 0),
            "{phases:?}"
        );
        let mut seen = [0u32; 3];
        for (segment, entries) in phases.iter().flatten() {
            assert_eq!(entries.start, seen[*segment], "{phases:?}");
            assert_eq!(entries.start % tables.alignment_entries, 0, "{phases:?}");
            seen[*segment] = entries.end;
        }
        assert_eq!(seen, [200, 200, 200]);
        // Each segment's table holds its batches once.
        for segment in 0..3 {
            let (offset, count) = tables.ranges[segment];
            let start = offset as usize / 4;
            let mut batches: Vec<u32> = tables.staging[start..start + count as usize]
                .iter()
                .map(|e| e >> 8)
                .collect();
            batches.sort_unstable();
            assert_eq!(batches, (0..200).collect::<Vec<u32>>());
        }
    }

    /// Synthetic segments of `batches` boxes each, scattered in a 20-unit cube, each batch with
    /// its 16 runs as slabs along x.
    fn scattered_segments(segments: usize, batches: usize) -> Vec<(Vec<GpuBatch>, Vec<GpuBatch>)> {
        let mut rng = ChaCha8Rng::seed_from_u64(21);
        let runs = (BATCH_POINTS / SUB_BATCH_POINTS) as u32;
        (0..segments)
            .map(|_| {
                let mut table = Vec::new();
                let mut subs = Vec::new();
                for b in 0..batches as u32 {
                    let min =
                        Vec3::from_array(std::array::from_fn(|_| rng.random_range(-10.0..9.0)));
                    let max = min + Vec3::splat(rng.random_range(0.1..1.0));
                    let whole = GpuBatch {
                        min: min.to_array(),
                        first: b * BATCH_POINTS as u32,
                        max: max.to_array(),
                        count: BATCH_POINTS as u32,
                    };
                    for s in 0..runs {
                        let x = |k: u32| min.x + (max.x - min.x) * k as f32 / runs as f32;
                        subs.push(GpuBatch {
                            min: [x(s), min.y, min.z],
                            first: whole.first + s * SUB_BATCH_POINTS as u32,
                            max: [x(s + 1), max.y, max.z],
                            count: SUB_BATCH_POINTS as u32,
                        });
                    }
                    table.push(whole);
                }
                (table, subs)
            })
            .collect()
    }

    /// A cloud of many segments is culled on all cores into the very tables one core builds;
    /// on a GPU adapter, batches at the view's edge are listed whole.
    #[test]
    fn parallel_culling_builds_the_same_tables_and_gpus_list_straddlers_whole() {
        let gpu = crate::testing::gpu();
        let camera = perspective_camera(
            DVec3::new(6.0, -25.0, 8.0),
            DVec3::new(4.0, 0.0, 3.0),
            35.0,
            (1.0, 100.0),
        );
        let transform = camera.transform(DVec3::ZERO, 320, 200);
        let segments = scattered_segments(5, 1000);
        let orders: Vec<DrawOrders> = segments.iter().map(|_| DrawOrders::default()).collect();
        let build = |refine: bool, parallel_from: usize| {
            let mut tables = FrameBatches::new(refine);
            tables.parallel_from_batches = parallel_from;
            let tables_of =
                segments
                    .iter()
                    .zip(&orders)
                    .map(|((batches, sub_batches), draw_orders)| BatchTables {
                        sub_batches,
                        ..whole_batches(batches, draw_orders)
                    });
            tables.update(&gpu.device, &gpu.queue, tables_of, &transform, 1);
            tables
        };
        let (parallel, serial) = (build(true, 0), build(true, usize::MAX));
        assert_eq!(parallel.staging, serial.staging);
        assert_eq!(parallel.ranges, serial.ranges);
        assert_eq!(parallel.segment_order, serial.segment_order);
        assert_eq!(parallel.footprint, serial.footprint);
        assert_eq!(parallel.covered_pixels, serial.covered_pixels);
        let narrowed = |t: &FrameBatches| {
            let mut narrowed = 0;
            for (&(offset, count), (batches, _)) in t.ranges.iter().zip(&segments) {
                let start = offset as usize / std::mem::size_of::<u32>();
                let entries = decoded(&t.staging[start..][..count as usize], batches);
                narrowed += entries
                    .iter()
                    .filter(|e| e.count % BATCH_POINTS as u32 != 0)
                    .count();
            }
            narrowed
        };
        assert!(narrowed(&serial) > 0, "no batch straddles the view's edge");
        let whole = build(false, usize::MAX);
        assert_eq!(narrowed(&whole), 0);
        assert!(whole.listed_points() > serial.listed_points());
    }
}
