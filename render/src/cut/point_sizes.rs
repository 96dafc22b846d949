//! The adaptive point sizes of a cut: each batch's points sized by the spacing of the deepest
//! nodes of the cut where they lie, as Potree sizes a point by the level of detail drawn
//! around it.
//!
//! A node's points lie among those of its descendants in the cut, so where the cut goes deeper
//! they are drawn as small as the deeper nodes' points; where it stops at the node (its
//! children not refined, or left out by the budgets) they take the node's own spacing. A batch
//! whose box reaches regions of both takes the larger, so that neither is left with holes.
//! Octants of a node that hold no child are not asked: a box that only grazes one would
//! otherwise coarsen a whole batch.

use std::collections::HashSet;

use glam::{DVec3, Vec3};

use super::select::{Cut, NodesInView};
use crate::camera::CameraTransform;
use crate::lod::{LodHierarchy, NodeKey};
use crate::raster::gpu_data::GpuBatch;
use crate::raster::MAX_ADAPTIVE_POINT_SIZE;

/// A frame's point-size factors of the batches of its cut.
pub(crate) struct CutPointSizes<'a> {
    hierarchy: &'a LodHierarchy,
    in_view: NodesInView<'a>,
    transform: CameraTransform,
    origin: DVec3,
    /// The cut's nodes and every ancestor the walk passed through to reach them.
    reached: HashSet<NodeKey>,
    /// The spacing the frame's adaptive size was made for (`LodHierarchy::point_spacing`).
    reference_spacing: f64,
    /// The frame's adaptive size: a point's side in pixels times its linear depth, at factor 1.
    scale: f32,
    /// The largest side of any batch's points so far, in pixels.
    largest_side: u32,
}

impl<'a> CutPointSizes<'a> {
    pub(crate) fn new(
        hierarchy: &'a LodHierarchy,
        cut: &Cut,
        in_view: NodesInView<'a>,
        transform: &CameraTransform,
        origin: DVec3,
        reference_spacing: f64,
        scale: f32,
    ) -> Self {
        let mut reached = HashSet::new();
        for node in &cut.nodes {
            let mut key = Some(node.key);
            while let Some(k) = key.filter(|&k| reached.insert(k)) {
                key = k.parent();
            }
        }
        Self {
            hierarchy,
            in_view,
            transform: *transform,
            origin,
            reached,
            reference_spacing,
            scale,
            largest_side: 1,
        }
    }

    /// What the adaptive size of the points of `batch` (a batch of node `key`, its box
    /// relative to the origin) is multiplied by: their spacing over the reference's.
    pub(crate) fn factor(&mut self, key: NodeKey, batch: &GpuBatch) -> f32 {
        let (lo, hi) = (
            Vec3::from_array(batch.min).as_dvec3(),
            Vec3::from_array(batch.max).as_dvec3(),
        );
        let spacing = self
            .spacing_in(key, lo, hi)
            .unwrap_or(self.reference_spacing);
        let factor = (spacing / self.reference_spacing) as f32;
        let depth = self.nearest_depth(lo, hi).max(self.transform.near) as f32;
        let side = (self.scale * factor / depth + 0.5)
            .floor()
            .clamp(1.0, MAX_ADAPTIVE_POINT_SIZE as f32) as u32;
        self.largest_side = self.largest_side.max(side);
        factor
    }

    /// The largest side any batch's points take, in pixels: the frame's `point_size`.
    pub(crate) fn largest_side(&self) -> u32 {
        self.largest_side
    }

    /// The spacing of the points drawn in the box `lo..hi` of node `key`'s cube (relative to
    /// the origin): the largest of its reached children's, where the box meets them, and the
    /// node's own where it meets a child in view that the cut did not reach.
    fn spacing_in(&self, key: NodeKey, lo: DVec3, hi: DVec3) -> Option<f64> {
        let own = self.hierarchy.points_spacing(key);
        let mut spacing: Option<f64> = None;
        let mut coarsest = |s: Option<f64>| {
            if let Some(s) = s {
                spacing = Some(spacing.map_or(s, |current| current.max(s)));
            }
        };
        for child in self.hierarchy.children(key) {
            let (min, side) = self.hierarchy.node_cube(child.key);
            let min = min - self.origin;
            let max = min + DVec3::splat(side);
            if !(lo.cmple(max).all() && hi.cmpge(min).all()) {
                continue;
            }
            if self.reached.contains(&child.key) {
                coarsest(self.spacing_in(child.key, lo.max(min), hi.min(max)));
            } else if self.in_view.contains(child.key) {
                coarsest(own);
            }
        }
        spacing.or(own)
    }

    /// The least linear depth of the box `lo..hi`: depth is linear, so at one of its corners.
    fn nearest_depth(&self, lo: DVec3, hi: DVec3) -> f64 {
        (0..8)
            .map(|corner| {
                let pick = |bit: usize, lo: f64, hi: f64| if corner & bit == 0 { lo } else { hi };
                DVec3::new(
                    pick(1, lo.x, hi.x),
                    pick(2, lo.y, hi.y),
                    pick(4, lo.z, hi.z),
                )
            })
            .map(|p| self.transform.depth_row.dot(p.extend(1.0)))
            .fold(f64::INFINITY, f64::min)
    }
}
