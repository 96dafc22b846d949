//! The frame's batch table: the batches that can be in view.
//!
//! Every frame, on the host, before any GPU work, each chunk's batches are culled against the
//! view frustum (Günther et al.'s frustum culling, per batch): a batch is left out when all
//! eight corners of its box lie beyond the same plane of the frustum, widened by the point
//! size and a pixel of margin for the shaders' f32 arithmetic. The point passes read this
//! table instead of the cloud's own and dispatch one workgroup per entry, so a culled batch
//! costs the GPU nothing (on lavapipe, a view that sees none of a 10M-point cloud went from
//! 3.7 ms to 0.1 ms). Points of listed entries are still culled one by one.
//!
//! - Runs of 32 batches (groups) are tested first: a group wholly in view is listed without
//!   testing its batches, a group wholly outside is dropped with them.
//! - On a CPU adapter, a batch that straddles the edge of the view is culled again in runs of
//!   256 points (sub-batches, whose boxes only the host keeps), and only its runs that can be
//!   in view are listed: on lavapipe this took a view of a cube's corner from 9.9 to 8.4 ms of
//!   point pass (BENCHMARKS.md). A GPU draws the whole batch faster than the host tests them.
//! - A cloud of many chunks is culled on all cores, a chunk per task.
//!
//! The same pass over the boxes bounds the frame's footprint: the pixels any listed point can
//! touch. The resolve skips the rest of the image when it is known to be empty (`targets.rs`).
//!
//! The table holds a word per listed batch (`ListedEntry`: the batch's index in its chunk's
//! resident table and the run of its sub-batches to draw), not a copy of its 32-byte entry.
//! Each chunk's entries are listed near to far along a mirrored Z-order curve
//! (`draw_order.rs`: the order is kept per chunk and octant of view directions, so a frame
//! walks it instead of sorting), and the chunks themselves are ordered near to far. This is
//! the stage "cull" of a frame's timings, part of its frame time.

use glam::{DVec2, DVec3, DVec4, Vec3};
use rayon::prelude::*;

use super::draw_order::sort_near_to_far;
use super::gpu_data::GpuBatch;
use super::occlusion::phase_cuts;
use super::phases::{split_by_depth, ChunkEntries};
use super::pixel_rect::{PixelCoverage, PixelRect};
use super::points::{BatchTables, BATCH_POINTS, GROUP_BATCHES, SUB_BATCH_POINTS};
use crate::camera::CameraTransform;

/// One frame's batch tables of a cloud's chunks, in one GPU buffer.
pub(crate) struct FrameBatches {
    /// Per chunk, its batches that can be in view; each chunk's table starts at a multiple of
    /// the storage-binding offset alignment.
    buffer: Option<wgpu::Buffer>,
    /// Per chunk: byte offset of its table in `buffer` and its number of batches.
    ranges: Vec<(u64, u32)>,
    /// The chunks with batches in view, near to far (by their listed batches' boxes).
    chunk_order: Vec<usize>,
    /// Host copy reused from frame to frame: [`ListedEntry`] words.
    staging: Vec<u32>,
    /// Per chunk (as `ranges`): what its listed entries hold.
    listings: Vec<Listing>,
    /// Per chunk (as `ranges`): the end of each phase's entries in its table, the nearest
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
    /// Batches from which a cloud of several chunks is culled in parallel: always
    /// [`PARALLEL_CULL_BATCHES`], except in the test that compares both paths.
    parallel_from_batches: usize,
}

/// Batches from which a cloud of several chunks is culled on all cores: one chunk per task.
const PARALLEL_CULL_BATCHES: usize = 16_384;

impl FrameBatches {
    /// `refine_straddlers`: cull batches that straddle the view's edge again in runs of 256
    /// points. That pays where a point costs far more than a box test on the host, as on a
    /// CPU adapter (on lavapipe a view of a cube's corner went from 9.9 to 8.4 ms); on a GPU,
    /// which draws a whole batch in less time than the host takes to test its runs, it does
    /// not (an H200's corner view spent 0.7 ms on the host to save microseconds).
    pub fn new(refine_straddlers: bool) -> Self {
        Self {
            buffer: None,
            ranges: Vec::new(),
            chunk_order: Vec::new(),
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

    /// Builds the tables of `chunks` (each its full batch table) for a frame seen through
    /// `transform` with points of `point_size` pixels, and uploads them.
    pub fn update<'a>(
        &mut self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        chunks: impl Iterator<Item = BatchTables<'a>>,
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
        let chunks: Vec<BatchTables<'a>> = chunks
            .map(|tables| BatchTables {
                sub_batches: if refine { tables.sub_batches } else { &[] },
                ..tables
            })
            .collect();
        let depth_gradient = transform.depth_row.truncate();
        let batches: usize = chunks.iter().map(|tables| tables.batches.len()).sum();
        if chunks.len() > 1 && batches >= self.parallel_from_batches {
            // Every chunk on its own core, then their tables back to back.
            let culled: Vec<(Vec<u32>, Listing, PixelCoverage)> = chunks
                .par_iter()
                .map(|&tables| {
                    let mut entries = Vec::new();
                    let mut chunk_coverage = PixelCoverage::new(transform.width, transform.height);
                    let listing = list_in_view(
                        &frustum,
                        tables,
                        depth_gradient,
                        &mut entries,
                        &mut chunk_coverage,
                    );
                    (entries, listing, chunk_coverage)
                })
                .collect();
            for (entries, listing, chunk_coverage) in culled {
                let start = self.pad_to_alignment(alignment);
                self.staging.extend_from_slice(&entries);
                self.ranges
                    .push(((start * entry_bytes) as u64, entries.len() as u32));
                self.listings.push(listing);
                coverage.merge(&chunk_coverage);
            }
        } else {
            for &tables in &chunks {
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
        self.order_chunks(transform);
        self.footprint = coverage.union();
        self.covered_pixels = coverage.pixels();
        self.split_in_phases(&chunks, transform);
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

    /// Pads the staged tables to a multiple of `alignment` entries, where the next chunk's
    /// table starts; returns that start.
    fn pad_to_alignment(&mut self, alignment: usize) -> usize {
        let padding = self.staging.len().next_multiple_of(alignment) - self.staging.len();
        self.staging.extend(std::iter::repeat_n(0, padding));
        self.staging.len()
    }

    /// Splits each chunk's entries in the phases of the depth-writing pass, where its points
    /// lie deep enough for occlusion culling to pay (`occlusion::phase_cuts`).
    fn split_in_phases(&mut self, chunks: &[BatchTables<'_>], transform: &CameraTransform) {
        let cuts = phase_cuts(self.total(), self.points_per_pixel());
        let mut rest = self.staging.as_mut_slice();
        let mut taken = 0;
        let mut entries = Vec::with_capacity(chunks.len());
        for (tables, &(offset, count)) in chunks.iter().zip(&self.ranges) {
            let start = offset as usize / std::mem::size_of::<u32>();
            let (_, tail) = std::mem::take(&mut rest).split_at_mut(start - taken);
            let (table, tail) = tail.split_at_mut(count as usize);
            rest = tail;
            taken = start + count as usize;
            entries.push(ChunkEntries {
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

    /// Orders the chunks that have batches in view near to far, as their batches are: a
    /// cloud larger than one binding comes in chunks of neighbouring points (Morton order or
    /// a streaming reader's), so this draws the near chunks' points first.
    fn order_chunks(&mut self, transform: &CameraTransform) {
        self.chunk_order.clear();
        let listed = self.ranges.iter().filter(|&&(_, count)| count > 0).count();
        if listed < 2 {
            // Nothing to order (most clouds are one chunk).
            self.chunk_order
                .extend(self.ranges.iter().position(|&(_, count)| count > 0));
            return;
        }
        let mut boxes: Vec<GpuBatch> = self
            .ranges
            .iter()
            .zip(&self.listings)
            .enumerate()
            .filter(|(_, (&(_, count), _))| count > 0)
            .map(|(chunk, (&(_, count), listing))| GpuBatch {
                min: listing.min.to_array(),
                first: chunk as u32,
                max: listing.max.to_array(),
                count,
            })
            .collect();
        sort_near_to_far(&mut boxes, transform.depth_row.truncate());
        self.chunk_order
            .extend(boxes.iter().map(|chunk_box| chunk_box.first as usize));
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

    /// Number of batches of all chunks in this frame's tables.
    pub fn total(&self) -> u32 {
        self.ranges.iter().map(|&(_, count)| count).sum()
    }

    /// Points of the listed batches per pixel they can reach (counted in cells of 64 x 64
    /// pixels): how deep the points that can be in view lie.
    pub fn points_per_pixel(&self) -> f64 {
        self.listed_points() as f64 / self.covered_pixels.max(1) as f64
    }

    /// Phase `phase`'s entries of every chunk that has some, chunk after chunk near to far:
    /// the chunk, its entries as a storage binding and their number.
    pub fn phase_parts(
        &self,
        phase: usize,
    ) -> impl Iterator<Item = (usize, (wgpu::BufferBinding<'_>, u32))> + '_ {
        self.chunk_order
            .iter()
            .filter_map(move |&chunk| Some((chunk, self.phase_part(chunk, phase)?)))
    }

    /// The entries of chunk `chunk`'s table in phase `phase` as a storage binding and their
    /// number; `None` when there are none.
    fn phase_part(&self, chunk: usize, phase: usize) -> Option<(wgpu::BufferBinding<'_>, u32)> {
        let entries = self.phase_entries(chunk, phase);
        self.entries_binding(chunk, entries)
    }

    /// The entries of chunk `chunk`'s table in phase `phase`: consecutive phases hold the
    /// table in order, each from a multiple of the binding alignment.
    fn phase_entries(&self, chunk: usize, phase: usize) -> std::ops::Range<u32> {
        let Some(ends) = self.phase_ends.get(chunk) else {
            return 0..0;
        };
        let start = if phase == 0 {
            0
        } else {
            ends.get(phase - 1).copied().unwrap_or(0)
        };
        start..ends.get(phase).copied().unwrap_or(start).max(start)
    }

    /// `entries` of chunk `chunk`'s table as a storage binding and their number.
    fn entries_binding(
        &self,
        chunk: usize,
        entries: std::ops::Range<u32>,
    ) -> Option<(wgpu::BufferBinding<'_>, u32)> {
        let (offset, _) = *self.ranges.get(chunk)?;
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

    /// Number of batches of chunk `chunk` in this frame's table.
    #[cfg(test)]
    fn count(&self, chunk: usize) -> u32 {
        self.ranges.get(chunk).map_or(0, |&(_, count)| count)
    }

    /// The table of chunk `chunk` as a storage binding; `None` when no batch is in view.
    #[cfg(test)]
    fn binding(&self, chunk: usize) -> Option<wgpu::BufferBinding<'_>> {
        self.entries_binding(chunk, 0..self.count(chunk))
            .map(|(binding, _)| binding)
    }
}

/// A frame table's entry: batch `index` of its chunk's resident table and the run of that
/// batch's sub-batches to draw, in one word (the shaders' `listed_batch` in common.wgsl):
/// the index in the upper 24 bits (a chunk's point indices are u32, so it holds at most
/// 2^20 batches), then the run's first sub-batch and its length - 1, 4 bits each. A frame
/// uploads 4 bytes per listed batch instead of a copy of its 32-byte entry.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct ListedEntry(pub u32);

/// Sub-batches per batch: a run's first and length each fit in 4 bits.
const SUBS_PER_BATCH: usize = BATCH_POINTS / SUB_BATCH_POINTS;
const _: () = assert!(SUBS_PER_BATCH <= 16);
const _: () = assert!((u32::MAX as usize / BATCH_POINTS) < 1 << 24);

impl ListedEntry {
    fn whole(batch: usize) -> Self {
        Self::run(batch, 0, SUBS_PER_BATCH)
    }

    fn run(batch: usize, first_sub: usize, subs: usize) -> Self {
        debug_assert!(first_sub + subs <= SUBS_PER_BATCH && subs > 0);
        Self(((batch as u32) << 8) | ((first_sub as u32) << 4) | (subs as u32 - 1))
    }

    /// The entry as the shaders see it: its batch's box, with the run's points.
    #[cfg(test)]
    pub fn batch(self, batches: &[GpuBatch]) -> GpuBatch {
        let batch = batches[(self.0 >> 8) as usize];
        let first = batch.first + ((self.0 >> 4) & 15) * SUB_BATCH_POINTS as u32;
        let end =
            (first + ((self.0 & 15) + 1) * SUB_BATCH_POINTS as u32).min(batch.first + batch.count);
        GpuBatch {
            first,
            count: end - first,
            ..batch
        }
    }
}

/// What one chunk's listed entries hold.
#[derive(Clone, Copy, Debug)]
struct Listing {
    points: u64,
    /// The box of the listed batches.
    min: Vec3,
    max: Vec3,
}

impl Listing {
    const EMPTY: Self = Self {
        points: 0,
        min: Vec3::INFINITY,
        max: Vec3::NEG_INFINITY,
    };

    fn add(&mut self, batch: &GpuBatch, points: u32) {
        self.points += u64::from(points);
        self.min = self.min.min(Vec3::from_array(batch.min));
        self.max = self.max.max(Vec3::from_array(batch.max));
    }
}

/// Appends to `out` the entries of `tables` that can be in view, near to far for a view
/// whose depth grows along `depth_gradient`, and adds the pixels their points can touch to
/// `coverage`. A group of batches wholly inside the frustum is listed without testing its
/// batches; of the other groups, each batch is tested: a batch wholly inside is listed whole;
/// of a batch that straddles the edge, only the runs of sub-batches that can be in view. The
/// entries follow the table's near-to-far order (`DrawOrders`), so no frame sorts.
fn list_in_view(
    frustum: &Frustum,
    tables: BatchTables<'_>,
    depth_gradient: DVec3,
    out: &mut Vec<u32>,
    coverage: &mut PixelCoverage,
) -> Listing {
    let visibility = batch_visibility(frustum, tables, coverage);
    let mut listing = Listing::EMPTY;
    for &b in tables.draw_orders.get(tables.batches, depth_gradient) {
        let b = b as usize;
        match visibility[b] {
            Visibility::Hidden => {}
            Visibility::Whole => {
                let batch = &tables.batches[b];
                out.push(ListedEntry::whole(b).0);
                listing.add(batch, batch.count);
            }
            Visibility::Straddling(footprint) => {
                if list_runs_in_view(frustum, tables, b, out, &mut listing) {
                    coverage.add(footprint);
                }
            }
        }
    }
    listing
}

/// Whether a batch is listed, and how.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Visibility {
    Hidden,
    /// Listed as it is (its footprint already added to the coverage).
    Whole,
    /// At the view's edge: its runs are tested when it is listed, and its footprint (the
    /// batch's, which holds its runs') added to the coverage if any is.
    Straddling(PixelRect),
}

/// Each batch's [`Visibility`], testing groups first; adds the footprints of the batches
/// listed whole to `coverage`.
fn batch_visibility(
    frustum: &Frustum,
    tables: BatchTables<'_>,
    coverage: &mut PixelCoverage,
) -> Vec<Visibility> {
    let mut visibility = vec![Visibility::Hidden; tables.batches.len()];
    if tables.groups.is_empty() {
        test_batches(
            frustum,
            tables,
            0..tables.batches.len(),
            &mut visibility,
            coverage,
        );
        return visibility;
    }
    for (g, group) in tables.groups.iter().enumerate() {
        let Some(view) = frustum.view_of(group) else {
            continue;
        };
        let batches = g * GROUP_BATCHES..((g + 1) * GROUP_BATCHES).min(tables.batches.len());
        if view.whole {
            coverage.add(view.footprint);
            visibility[batches].fill(Visibility::Whole);
        } else {
            test_batches(frustum, tables, batches, &mut visibility, coverage);
        }
    }
    visibility
}

/// [`batch_visibility`] for the batches `range`, one by one.
fn test_batches(
    frustum: &Frustum,
    tables: BatchTables<'_>,
    range: std::ops::Range<usize>,
    visibility: &mut [Visibility],
    coverage: &mut PixelCoverage,
) {
    for b in range {
        let Some(view) = frustum.view_of(&tables.batches[b]) else {
            continue;
        };
        visibility[b] = if view.whole || tables.sub_batches.is_empty() {
            coverage.add(view.footprint);
            Visibility::Whole
        } else {
            Visibility::Straddling(view.footprint)
        };
    }
}

/// Appends to `out` the runs of consecutive sub-batches of batch `b` that can be in view;
/// whether there was any. Their footprints are not computed: the batch's holds them, and the
/// test without them costs a sub-batch no division (on the 10M cube's corner view, the cull
/// went from 0.6 to 0.3 ms).
fn list_runs_in_view(
    frustum: &Frustum,
    tables: BatchTables<'_>,
    b: usize,
    out: &mut Vec<u32>,
    listing: &mut Listing,
) -> bool {
    let batch = &tables.batches[b];
    let subs = tables
        .sub_batches
        .get(b * SUBS_PER_BATCH..)
        .unwrap_or_default()
        .iter()
        .take(SUBS_PER_BATCH)
        .take_while(|sub| sub.first < batch.first + batch.count);
    // The open run: its first sub-batch, length and points.
    let mut run: Option<(usize, usize, u32)> = None;
    let mut listed = false;
    let mut close = |run: Option<(usize, usize, u32)>, out: &mut Vec<u32>| {
        if let Some((first, length, points)) = run {
            out.push(ListedEntry::run(b, first, length).0);
            listing.add(batch, points);
            listed = true;
        }
    };
    for (s, sub) in subs.enumerate() {
        if frustum.excludes(sub) {
            close(run.take(), out);
            continue;
        }
        match run.as_mut() {
            Some((_, length, points)) => {
                *length += 1;
                *points += sub.count;
            }
            None => run = Some((s, 1, sub.count)),
        }
    }
    close(run, out);
    listed
}

/// A box that can be in view.
struct InView {
    /// The pixels its points can touch.
    footprint: PixelRect,
    /// Every corner lies inside the frustum, so every point of the box does.
    whole: bool,
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

    /// Whether no point in `batch`'s box can show in the image: all its corners lie beyond
    /// one plane. [`Frustum::view_of`]'s test without the footprint.
    fn excludes(&self, batch: &GpuBatch) -> bool {
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
    fn view_of(&self, batch: &GpuBatch) -> Option<InView> {
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
    use glam::DVec3;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    use super::*;
    use crate::camera::{Camera, Projection};
    use crate::raster::draw_order::DrawOrders;
    use crate::raster::occlusion::MIN_PHASES;

    /// An entry names its batch and a run of its sub-batches; the run ends with the batch,
    /// which may hold fewer points than a full one.
    #[test]
    fn entries_hold_their_batch_or_a_run_of_it() {
        let full = GpuBatch {
            first: 0,
            count: BATCH_POINTS as u32,
            ..batch(Vec3::ZERO, Vec3::ONE)
        };
        let short = GpuBatch {
            first: BATCH_POINTS as u32,
            count: 1000,
            ..batch(Vec3::ONE, Vec3::splat(2.0))
        };
        let batches = [full, short];
        let at = |entry: ListedEntry| {
            let b = entry.batch(&batches);
            (b.min, b.max, b.first, b.count)
        };
        let sub = SUB_BATCH_POINTS as u32;
        assert_eq!(at(ListedEntry::whole(0)), (full.min, full.max, 0, 4096));
        assert_eq!(
            at(ListedEntry::whole(1)),
            (short.min, short.max, 4096, 1000)
        );
        assert_eq!(
            at(ListedEntry::run(0, 15, 1)),
            (full.min, full.max, 15 * sub, sub)
        );
        assert_eq!(
            at(ListedEntry::run(1, 1, 2)),
            (short.min, short.max, 4096 + sub, 2 * sub)
        );
        // The last run of the short batch stops at its end.
        assert_eq!(
            at(ListedEntry::run(1, 2, 3)),
            (short.min, short.max, 4096 + 2 * sub, 1000 - 2 * sub)
        );
    }

    /// Entries of a frame table as the shaders see them, from their chunk's `batches`.
    fn decoded(entries: &[u32], batches: &[GpuBatch]) -> Vec<GpuBatch> {
        entries
            .iter()
            .map(|&entry| ListedEntry(entry).batch(batches))
            .collect()
    }

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

    /// A 64 x 64 orthographic view down -z from z = 10, 2 units high: depth is 10 - z.
    fn looking_down_from_z_10() -> CameraTransform {
        let camera = Camera {
            position: DVec3::new(0.0, 0.0, 10.0),
            target: DVec3::ZERO,
            up: DVec3::Y,
            projection: Projection::Orthographic { height: 2.0 },
            near: 1.0,
            far: 20.0,
        };
        camera.transform(DVec3::ZERO, 64, 64)
    }

    #[test]
    fn tables_hold_the_batches_in_view_in_order_at_aligned_offsets() {
        let gpu = crate::testing::gpu();
        let transform = looking_down_from_z_10();
        let far = batch(Vec3::splat(-0.1), Vec3::splat(0.1));
        let near = batch(Vec3::new(-0.1, -0.1, 4.9), Vec3::new(0.1, 0.1, 5.1));
        let beside = batch(Vec3::splat(50.0), Vec3::splat(51.0));
        let behind = batch(Vec3::new(-0.1, -0.1, 10.5), Vec3::new(0.1, 0.1, 11.0));
        let chunks: [&[GpuBatch]; 3] = [&[far, beside, near, behind], &[beside], &[beside, far]];
        let orders: [DrawOrders; 3] = Default::default();
        let mut tables = FrameBatches::new(true);
        let tables_of = chunks
            .into_iter()
            .zip(&orders)
            .map(|(batches, draw_orders)| BatchTables {
                batches,
                sub_batches: &[],
                groups: &[],
                draw_orders,
            });
        tables.update(&gpu.device, &gpu.queue, tables_of, &transform, 1);

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
            decoded(&tables.staging[first..first + 2], chunks[0]),
            [near, far],
            "near to far"
        );
        let alignment = u64::from(gpu.device.limits().min_storage_buffer_offset_alignment);
        for chunk in [0, 2] {
            let binding = tables.binding(chunk).expect("batches in view");
            assert_eq!(binding.offset % alignment, 0);
        }
    }

    /// Views of a cube of side 20 centred on the origin that see part of it.
    fn views_of_the_cube() -> [Camera; 3] {
        [
            // Perspective, seeing a corner of the cube.
            Camera {
                position: DVec3::new(14.0, -30.0, 12.0),
                target: DVec3::new(9.0, 0.0, 8.0),
                up: DVec3::Z,
                projection: Projection::Perspective { fov_y_deg: 30.0 },
                near: 1.0,
                far: 100.0,
            },
            // Orthographic from above, a quarter of the top face.
            Camera {
                position: DVec3::new(5.0, 5.0, 40.0),
                target: DVec3::new(5.0, 5.0, 0.0),
                up: DVec3::Y,
                projection: Projection::Orthographic { height: 8.0 },
                near: 20.0,
                far: 60.0,
            },
            // Perspective, the near plane cutting through the cube.
            Camera {
                position: DVec3::new(0.0, -5.0, 0.0),
                target: DVec3::new(0.0, 10.0, 0.0),
                up: DVec3::Z,
                projection: Projection::Perspective { fov_y_deg: 60.0 },
                near: 2.0,
                far: 100.0,
            },
        ]
    }

    /// Of batches that straddle the edge of the view only the sub-batches that can be in
    /// view are listed: every point in view is in a listed entry, and fewer points are listed
    /// than whole batches would give.
    #[test]
    fn straddling_batches_list_only_their_sub_batches_that_can_be_in_view() {
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        let points: Vec<Vec3> = (0..24 * BATCH_POINTS + 300)
            .map(|_| Vec3::from_array(std::array::from_fn(|_| rng.random_range(-10.0..10.0))))
            .collect();
        let (batches, sub_batches, dequantised) = crate::raster::points::host_tables(&points);
        let orders = DrawOrders::default();
        let (width, height) = (160, 120);
        for camera in views_of_the_cube() {
            let transform = camera.transform(DVec3::ZERO, width, height);
            let frustum = Frustum::new(&transform, 1);
            let gradient = transform.depth_row.truncate();
            let mut listed = Vec::new();
            let mut coverage = PixelCoverage::new(width, height);
            list_in_view(
                &frustum,
                BatchTables {
                    batches: &batches,
                    sub_batches: &sub_batches,
                    groups: &[],
                    draw_orders: &orders,
                },
                gradient,
                &mut listed,
                &mut coverage,
            );
            let footprint = coverage.union();
            let listed = decoded(&listed, &batches);
            let mut whole_batches = Vec::new();
            list_in_view(
                &frustum,
                BatchTables {
                    batches: &batches,
                    sub_batches: &[],
                    groups: &[],
                    draw_orders: &orders,
                },
                gradient,
                &mut whole_batches,
                &mut PixelCoverage::new(width, height),
            );
            let whole_batches = decoded(&whole_batches, &batches);
            let mut is_listed = vec![false; points.len()];
            for entry in &listed {
                // Each entry keeps its batch's box: the shaders dequantise against it.
                let batch = batches[entry.first as usize / BATCH_POINTS];
                assert_eq!((entry.min, entry.max), (batch.min, batch.max));
                assert!(entry.first + entry.count <= batch.first + batch.count);
                for flag in &mut is_listed[entry.first as usize..][..entry.count as usize] {
                    assert!(!*flag, "{camera:?}: a point listed twice");
                    *flag = true;
                }
            }
            let mut in_view = 0;
            for (i, p) in dequantised.iter().enumerate() {
                let Some((x, y, _)) = transform.project(p.as_dvec3()) else {
                    continue;
                };
                if x >= 0.0 && y >= 0.0 && x < f64::from(width) && y < f64::from(height) {
                    in_view += 1;
                    assert!(
                        is_listed[i],
                        "{camera:?}: point {i} at {p} in view, not listed"
                    );
                    assert!(footprint.contains(x as u32, y as u32), "{camera:?}");
                }
            }
            let listed_points: u32 = listed.iter().map(|e| e.count).sum();
            let whole_points: u32 = whole_batches.iter().map(|e| e.count).sum();
            assert!(in_view > 0, "{camera:?}: nothing in view");
            assert!(
                listed_points < whole_points,
                "{camera:?}: {in_view} in view, {listed_points} listed, {whole_points} in \
                 whole batches"
            );
        }
    }

    /// The depth pass's phases split the listed batches by depth across the chunks: the first
    /// holds the nearest batches, and together they hold every listed batch once, each chunk's
    /// phases one after the other in its table.
    #[test]
    fn phases_split_the_chunks_by_depth_and_hold_every_batch_once() {
        let gpu = crate::testing::gpu();
        let transform = looking_down_from_z_10();
        // Batch b of a chunk at `depth` lies 0.01 b deeper.
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
        // Chunk 0 far, chunk 1 near, chunk 2 between; 200 full batches each, deep enough on
        // the 64 x 64 image for phases.
        let chunks = [at_depth(8.0, 200), at_depth(2.0, 200), at_depth(5.0, 200)];
        let orders: [DrawOrders; 3] = Default::default();
        let mut tables = FrameBatches::new(true);
        tables.update(
            &gpu.device,
            &gpu.queue,
            chunks
                .iter()
                .zip(&orders)
                .map(|(batches, draw_orders)| BatchTables {
                    batches,
                    sub_batches: &[],
                    groups: &[],
                    draw_orders,
                }),
            &transform,
            1,
        );
        assert_eq!(tables.chunk_order, [1, 2, 0]);
        let phase_count = tables.phase_count();
        assert!(phase_count >= MIN_PHASES, "{phase_count}");
        let phases: Vec<Vec<(usize, std::ops::Range<u32>)>> = (0..tables.phase_count())
            .map(|phase| {
                tables
                    .chunk_order
                    .iter()
                    .map(|&chunk| (chunk, tables.phase_entries(chunk, phase)))
                    .filter(|(_, entries)| !entries.is_empty())
                    .collect()
            })
            .collect();
        // Equal shares of 600 batches: the first from the nearest chunk, the last from the
        // farthest (alignment moves a few batches to the phase before theirs, in their own
        // chunk).
        assert!(phases[0].iter().all(|(chunk, _)| *chunk == 1), "{phases:?}");
        assert!(
            phases[phase_count - 1].iter().all(|(chunk, _)| *chunk == 0),
            "{phases:?}"
        );
        let mut seen = [0u32; 3];
        for (chunk, entries) in phases.iter().flatten() {
            assert_eq!(entries.start, seen[*chunk], "{phases:?}");
            assert_eq!(entries.start % tables.alignment_entries, 0, "{phases:?}");
            seen[*chunk] = entries.end;
        }
        assert_eq!(seen, [200, 200, 200]);
        // Each chunk's table holds its batches once.
        for chunk in 0..3 {
            let (offset, count) = tables.ranges[chunk];
            let start = offset as usize / 4;
            let mut batches: Vec<u32> = tables.staging[start..start + count as usize]
                .iter()
                .map(|e| e >> 8)
                .collect();
            batches.sort_unstable();
            assert_eq!(batches, (0..200).collect::<Vec<u32>>());
        }
    }

    /// Synthetic chunks of `batches` boxes each, scattered in a 20-unit cube, each batch with
    /// its 16 runs as slabs along x.
    fn scattered_chunks(chunks: usize, batches: usize) -> Vec<(Vec<GpuBatch>, Vec<GpuBatch>)> {
        let mut rng = ChaCha8Rng::seed_from_u64(21);
        let runs = (BATCH_POINTS / SUB_BATCH_POINTS) as u32;
        (0..chunks)
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

    /// A cloud of many chunks is culled on all cores into the very tables one core builds;
    /// on a GPU adapter, batches at the view's edge are listed whole.
    #[test]
    fn parallel_culling_builds_the_same_tables_and_gpus_list_straddlers_whole() {
        let gpu = crate::testing::gpu();
        let camera = Camera {
            position: DVec3::new(6.0, -25.0, 8.0),
            target: DVec3::new(4.0, 0.0, 3.0),
            up: DVec3::Z,
            projection: Projection::Perspective { fov_y_deg: 35.0 },
            near: 1.0,
            far: 100.0,
        };
        let transform = camera.transform(DVec3::ZERO, 320, 200);
        let chunks = scattered_chunks(5, 1000);
        let orders: Vec<DrawOrders> = chunks.iter().map(|_| DrawOrders::default()).collect();
        let build = |refine: bool, parallel_from: usize| {
            let mut tables = FrameBatches::new(refine);
            tables.parallel_from_batches = parallel_from;
            tables.update(
                &gpu.device,
                &gpu.queue,
                chunks
                    .iter()
                    .zip(&orders)
                    .map(|((batches, sub_batches), draw_orders)| BatchTables {
                        batches,
                        sub_batches,
                        groups: &[],
                        draw_orders,
                    }),
                &transform,
                1,
            );
            tables
        };
        let (parallel, serial) = (build(true, 0), build(true, usize::MAX));
        assert_eq!(parallel.staging, serial.staging);
        assert_eq!(parallel.ranges, serial.ranges);
        assert_eq!(parallel.chunk_order, serial.chunk_order);
        assert_eq!(parallel.footprint, serial.footprint);
        assert_eq!(parallel.covered_pixels, serial.covered_pixels);
        let narrowed = |t: &FrameBatches| {
            let mut narrowed = 0;
            for (&(offset, count), (batches, _)) in t.ranges.iter().zip(&chunks) {
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

    /// Listing by groups gives the very entries that testing every batch gives, in the same
    /// order, and a footprint that holds theirs: a group is listed whole only when all its
    /// batches would be.
    #[test]
    fn groups_list_the_same_entries_as_batches_one_by_one() {
        let mut rng = ChaCha8Rng::seed_from_u64(13);
        let points: Vec<Vec3> = (0..10 * GROUP_BATCHES * BATCH_POINTS + 999)
            .map(|_| Vec3::from_array(std::array::from_fn(|_| rng.random_range(-10.0..10.0))))
            .collect();
        let (batches, sub_batches, _) = crate::raster::points::host_tables(&points);
        let groups = crate::raster::points::batch_groups(&batches);
        let orders = DrawOrders::default();
        assert_eq!(groups.len(), 11);
        let (width, height) = (160, 120);
        // The whole cube in view (every group listed whole), then groups in, out, and across
        // the edge of the view.
        let whole = Camera {
            position: DVec3::new(0.0, -60.0, 10.0),
            target: DVec3::ZERO,
            up: DVec3::Z,
            projection: Projection::Perspective { fov_y_deg: 40.0 },
            near: 1.0,
            far: 200.0,
        };
        let mut whole_groups = 0;
        for camera in std::iter::once(whole).chain(views_of_the_cube()) {
            let transform = camera.transform(DVec3::ZERO, width, height);
            let frustum = Frustum::new(&transform, 1);
            let list = |groups: &[GpuBatch]| {
                let (mut listed, mut coverage) = (Vec::new(), PixelCoverage::new(width, height));
                let tables = BatchTables {
                    batches: &batches,
                    sub_batches: &sub_batches,
                    groups,
                    draw_orders: &orders,
                };
                let gradient = transform.depth_row.truncate();
                list_in_view(&frustum, tables, gradient, &mut listed, &mut coverage);
                (listed, coverage.union())
            };
            let (by_group, group_footprint) = list(&groups);
            let (one_by_one, footprint) = list(&[]);
            assert!(!one_by_one.is_empty(), "{camera:?}: nothing listed");
            assert_eq!(by_group, one_by_one, "{camera:?}");
            assert_eq!(
                group_footprint.union(footprint),
                group_footprint,
                "{camera:?}"
            );
            whole_groups += groups
                .iter()
                .filter(|g| frustum.view_of(g).is_some_and(|v| v.whole))
                .count();
        }
        assert!(whole_groups >= groups.len(), "{whole_groups} groups whole");
    }
}
