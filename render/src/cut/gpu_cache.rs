//! `GpuNodeCache`: nodes resident on the GPU, in pages of batch slots, least recently used
//! first out, within a byte bound.
//!
//! A page is one segment of the renderer's cloud (`raster/points.rs`): a positions, a colors
//! and a batch buffer of a fixed number of batch slots. A node takes one slot per batch of its
//! points (a node is at most tens of thousands of points, a batch 4096), anywhere in any page,
//! so the cache never fragments. Each frame every page's batch table is set to the batches of
//! the cut's nodes it holds, in key order, and the renderer draws the pages as it draws any
//! cloud: the batch culling, the draw order, the phases and the occlusion tiles work inside
//! the nodes unchanged.
//!
//! Colors are written with the points, so the cache holds one color mode: a frame in another
//! mode empties it. Each point also has 16 bits of weight for the high-quality mode (its
//! code and child octant), and each slot the children of its node that the frame draws.
//! The resident cloud's segments carry neither.

use std::collections::{BTreeMap, HashMap, HashSet};

use crate::color::Coloring;
use crate::filter::PointFilter;
use crate::gpu::GpuContext;
use crate::lod::codec::Detail;
use crate::lod::NodeKey;
use crate::raster::gpu_data::{GpuBatch, QuantisedPosition, COLOR_BYTES};
use crate::raster::points::{
    GpuPointCloud, PointSegment, SegmentData, SUB_BATCH_POINTS, WEIGHT_BYTES,
};
use crate::raster::BATCH_POINTS;

/// Sub-batches per batch slot: a batch's runs are found at `slot * SUBS_PER_SLOT`.
const SUBS_PER_SLOT: usize = BATCH_POINTS / SUB_BATCH_POINTS;

/// Bytes one batch slot takes on the GPU: its points' positions, colors and weights, its
/// entry and its node's drawn children.
pub const SLOT_BYTES: u64 = BATCH_POINTS as u64
    * (std::mem::size_of::<QuantisedPosition>() as u64 + COLOR_BYTES + WEIGHT_BYTES)
    + std::mem::size_of::<GpuBatch>() as u64
    + 4;

/// Bytes a page has beyond its slots: its colors' spare words (`PointSegment::page`).
const PAGE_SPARE_BYTES: u64 = 8;

#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
struct Slot {
    page: u32,
    index: u32,
}

/// The point-size factor of each batch of a frame, by its node (`point_sizes.rs`).
pub(crate) type SizeFactors<'a> = &'a mut dyn FnMut(NodeKey, &GpuBatch) -> f32;

/// One page's batch tables of a frame: its batches, their runs, and their point-size factors
/// (empty: all 1).
#[derive(Default)]
struct PageTables {
    batches: Vec<GpuBatch>,
    sub_batches: Vec<GpuBatch>,
    sizes: Vec<f32>,
}

struct ResidentNode {
    slots: Vec<Slot>,
    /// Per slot: its batch (`first` at the slot's first point) and its runs, padded to
    /// [`SUBS_PER_SLOT`].
    batches: Vec<GpuBatch>,
    sub_batches: Vec<GpuBatch>,
    points: u32,
    last_used: u64,
    /// The positions it was prepared from: a node drawn coarse is drawn so wherever it was
    /// read from.
    detail: Detail,
}

pub struct GpuNodeCache {
    cloud: GpuPointCloud,
    slots_per_page: usize,
    max_pages: usize,
    /// Free slots, the lowest first, so where a node lands depends only on what came before.
    free: std::collections::BTreeSet<Slot>,
    resident: HashMap<NodeKey, ResidentNode>,
    by_use: BTreeMap<u64, NodeKey>,
    tick: u64,
    /// How the resident nodes were prepared: their colors and the points they kept.
    prepared_for: Option<(Coloring, PointFilter)>,
    /// Bytes written since the uploads were last submitted.
    unsubmitted_bytes: u64,
    /// Whether high quality weighs each point (else every point counts once, as a cut did
    /// before it had weights: the benchmark's comparison).
    pub(crate) weighted: bool,
}

/// Bytes of node uploads staged before they are submitted and waited for, so that the
/// staging memory of a frame's uploads is bounded by this, not by its cut (on a CPU adapter it
/// is host memory beside both caches). Small enough for the staging to fit the one block of
/// host memory the allocator keeps, so it is reused rather than allocated again
/// (docs/perf/cold-first-frame.md).
const UPLOAD_SUBMIT_BYTES: u64 = 16 << 20;

impl GpuNodeCache {
    /// A cache of at most `budget_bytes`, in pages of at most `max_page_points` points.
    pub fn new(origin: glam::DVec3, budget_bytes: u64, max_page_points: usize) -> Self {
        let total_slots = (budget_bytes / SLOT_BYTES).max(1) as usize;
        let mut slots_per_page = (max_page_points / BATCH_POINTS).clamp(1, total_slots);
        let mut max_pages = (total_slots / slots_per_page).max(1);
        // Every page's color buffer has a spare word or two beyond its slots.
        while slots_per_page > 1
            && max_pages as u64 * (slots_per_page as u64 * SLOT_BYTES + PAGE_SPARE_BYTES)
                > budget_bytes
        {
            slots_per_page -= 1;
            max_pages = (total_slots / slots_per_page).max(1);
        }
        Self {
            cloud: GpuPointCloud::of_pages(origin),
            slots_per_page,
            max_pages,
            free: Default::default(),
            resident: HashMap::new(),
            by_use: BTreeMap::new(),
            tick: 0,
            prepared_for: None,
            unsubmitted_bytes: 0,
            weighted: true,
        }
    }

    /// Batch slots the cache can hold: the most a cut may take.
    pub fn capacity_batches(&self) -> usize {
        self.max_pages * self.slots_per_page
    }

    /// Bytes of the pages allocated so far.
    pub fn gpu_bytes(&self) -> u64 {
        self.cloud.gpu_bytes()
    }

    /// Whether it holds the node prepared at `detail`.
    pub fn contains(&self, key: NodeKey, detail: Detail) -> bool {
        self.resident.get(&key).is_some_and(|n| n.detail == detail)
    }

    /// Empties the cache when its nodes were not prepared with these colors and this filter.
    pub fn prepare_for(&mut self, coloring: Coloring, filter: PointFilter) {
        let wanted = Some((coloring, filter));
        if self.prepared_for != wanted {
            let keys: Vec<NodeKey> = self.resident.keys().copied().collect();
            for key in keys {
                self.evict(key);
            }
            self.prepared_for = wanted;
        }
    }

    /// Marks a resident node as used by this frame, if it was prepared at `detail`; else drops
    /// it.
    pub fn touch(&mut self, key: NodeKey, detail: Detail) -> bool {
        let Some(node) = self.resident.get_mut(&key) else {
            return false;
        };
        if node.detail != detail {
            // Prepared at the other detail: it is prepared again.
            self.evict(key);
            return false;
        }
        self.by_use.remove(&node.last_used);
        self.tick += 1;
        node.last_used = self.tick;
        self.by_use.insert(self.tick, key);
        true
    }

    /// Writes a node's prepared points (`data`, batches counted from its first point) into
    /// free slots, evicting the least recently used nodes not in `keep`. The caller has made
    /// sure the frame's cut fits (`capacity_batches`).
    pub fn insert(
        &mut self,
        gpu: &GpuContext,
        key: NodeKey,
        detail: Detail,
        data: &SegmentData,
        keep: &HashSet<NodeKey>,
    ) -> Result<u64, String> {
        let needed = data.batches.len();
        let mut evicted = 0;
        while self.free.len() < needed {
            if self.cloud.segments.len() < self.max_pages {
                let page = self.cloud.segments.len();
                self.cloud.segments.push(PointSegment::page(
                    gpu,
                    page,
                    self.slots_per_page * BATCH_POINTS,
                ));
                self.free.extend((0..self.slots_per_page).map(|index| Slot {
                    page: page as u32,
                    index: index as u32,
                }));
                continue;
            }
            let oldest = self
                .by_use
                .values()
                .copied()
                .find(|k| !keep.contains(k))
                .ok_or_else(|| {
                    format!("the GPU node cache is full: node {key} needs {needed} batch slots")
                })?;
            self.evict(oldest);
            evicted += 1;
        }
        let slots: Vec<Slot> = (0..needed)
            .map(|_| self.free.pop_first().expect("counted above"))
            .collect();
        let mut batches = Vec::with_capacity(needed);
        let mut sub_batches = Vec::with_capacity(needed * SUBS_PER_SLOT);
        let position_bytes = std::mem::size_of::<QuantisedPosition>();
        for (b, (slot, batch)) in slots.iter().zip(&data.batches).enumerate() {
            let page = &self.cloud.segments[slot.page as usize];
            let base = slot.index as usize * BATCH_POINTS;
            let (first, count) = (batch.first as usize, batch.count as usize);
            gpu.queue.write_buffer(
                &page.positions,
                (base * position_bytes) as u64,
                bytemuck::cast_slice(&data.positions[first..first + count]),
            );
            // Colors are written in 4-byte words: the slot's bytes are a multiple of 4 from
            // its start, and the last slot of a node has room for the padding.
            let color_start = first * COLOR_BYTES as usize;
            let color_end = ((first + count) * COLOR_BYTES as usize).next_multiple_of(4);
            let color_end = color_end.min(data.colors.len());
            gpu.queue.write_buffer(
                &page.colors,
                (base * COLOR_BYTES as usize) as u64,
                &data.colors[color_start..color_end],
            );
            if let (Some(weights), false) = (&page.weights, data.weights.is_empty()) {
                // Whole words: the slot starts on one and a node's codes are padded to one.
                let end = (first + count).next_multiple_of(2).min(data.weights.len());
                gpu.queue.write_buffer(
                    &weights.codes,
                    base as u64 * WEIGHT_BYTES,
                    bytemuck::cast_slice(&data.weights[first..end]),
                );
            }
            let shift = |mut entry: GpuBatch| {
                entry.first = entry.first - batch.first + base as u32;
                entry
            };
            batches.push(shift(*batch));
            let runs = &data.sub_batches[b * SUBS_PER_SLOT..]
                [..count.div_ceil(SUB_BATCH_POINTS).min(SUBS_PER_SLOT)];
            sub_batches.extend(runs.iter().map(|&run| shift(run)));
            // Padding that the listing's walk stops at: it starts at the batch's end.
            let end = GpuBatch {
                first: (base + count) as u32,
                count: 0,
                ..*batch
            };
            sub_batches.resize(sub_batches.len().next_multiple_of(SUBS_PER_SLOT), end);
        }
        self.tick += 1;
        self.by_use.insert(self.tick, key);
        self.resident.insert(
            key,
            ResidentNode {
                slots,
                batches,
                sub_batches,
                points: data.positions.len() as u32,
                last_used: self.tick,
                detail,
            },
        );
        self.unsubmitted_bytes += (data.positions.len() * position_bytes
            + data.colors.len()
            + data.weights.len() * WEIGHT_BYTES as usize) as u64;
        if self.unsubmitted_bytes >= UPLOAD_SUBMIT_BYTES {
            self.unsubmitted_bytes = 0;
            gpu.queue.submit([]);
            gpu.device
                .poll(wgpu::PollType::wait_indefinitely())
                .map_err(|e| format!("uploading nodes: {e}"))?;
        }
        Ok(evicted)
    }

    fn evict(&mut self, key: NodeKey) {
        if let Some(node) = self.resident.remove(&key) {
            self.by_use.remove(&node.last_used);
            self.free.extend(node.slots);
        }
    }

    /// Sets every page's batch table to the batches of `cut` (resident nodes, in key order),
    /// each with the point-size factor `size_factor` gives it (none: 1), and returns the
    /// cloud to render, with `upload_ms` to report as its transfers.
    pub fn frame_cloud(
        &mut self,
        gpu: &GpuContext,
        cut: &[NodeKey],
        upload_ms: f64,
        mut size_factor: Option<SizeFactors<'_>>,
    ) -> &GpuPointCloud {
        let mut keys: Vec<NodeKey> = cut
            .iter()
            .copied()
            .filter(|k| self.resident.contains_key(k))
            .collect();
        keys.sort_unstable();
        let pages = self.cloud.segments.len();
        let mut tables: Vec<PageTables> = (0..pages).map(|_| PageTables::default()).collect();
        let mut drawn_children = vec![vec![0u32; self.slots_per_page]; pages];
        // A child counts as drawn when it or a node below it is: the selection walks through
        // nodes left without points (their parents took them all) but does not list them.
        let mut in_cut: HashSet<NodeKey> = HashSet::with_capacity(cut.len());
        for &key in cut {
            let mut at = Some(key);
            while let Some(k) = at.filter(|k| in_cut.insert(*k)) {
                at = k.parent();
            }
        }
        let mut points = 0;
        for key in keys {
            let node = &self.resident[&key];
            points += node.points as usize;
            // Every child "drawn" makes every point count once.
            let children = (0..8)
                .filter(|&c| !self.weighted || in_cut.contains(&key.child(c)))
                .fold(0u32, |mask, c| mask | 1 << c);
            for (s, slot) in node.slots.iter().enumerate() {
                drawn_children[slot.page as usize][slot.index as usize] = children;
                let table = &mut tables[slot.page as usize];
                let batch = node.batches[s];
                table.batches.push(batch);
                if let Some(factor) = size_factor.as_mut() {
                    table.sizes.push(factor(key, &batch));
                }
                table.sub_batches.extend_from_slice(
                    &node.sub_batches[s * SUBS_PER_SLOT..(s + 1) * SUBS_PER_SLOT],
                );
            }
        }
        for ((page, table), children) in self
            .cloud
            .segments
            .iter_mut()
            .zip(tables)
            .zip(drawn_children)
        {
            page.set_batches(&gpu.queue, table.batches, table.sub_batches, &table.sizes);
            if let Some(weights) = &page.weights {
                gpu.queue
                    .write_buffer(&weights.drawn_children, 0, bytemuck::cast_slice(&children));
            }
        }
        self.cloud.set_frame_points(points, upload_ms);
        &self.cloud
    }
}
