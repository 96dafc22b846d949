//! The cut of one frame: the nodes in view whose parents' point spacing, projected, exceeds the
//! pixel error, found largest on screen first.
//!
//! A best-first walk as Potree's and Kanzok et al.'s: the root, if in view, goes into a queue
//! ordered by how large the node's cube is on screen (nearest and largest first); the walk takes
//! the first node, adds it to the cut, and queues the children in view when the node's spacing
//! projected at its nearest depth is more than `lod_error` pixels. The cut stops growing when the
//! next node would take it past the GPU node cache's batches or past the points its pixels
//! warrant, so a view too dense for either loses detail far away, never near. The order of the
//! cut is the order its nodes are loaded in.
//!
//! A hierarchy read lazily has nodes whose page is not read yet: the walk stops at the first it
//! takes from the queue and names every such node it queued (`Walk::unread_pages`), so
//! that their pages are read and the walk run again; a walk that takes none from the queue is
//! the walk over the whole hierarchy, since what it visits does not depend on nodes it never
//! takes.

use std::cmp::Ordering;
use std::collections::BinaryHeap;

use glam::DVec3;

use crate::camera::{Camera, CameraTransform, Projection};
use crate::filter::ClipBox;
use crate::lod::{LodHierarchy, NodeKey};
use crate::raster::culling::Frustum;
use crate::raster::gpu_data::GpuBatch;
use crate::raster::BATCH_POINTS;

/// One node of a cut.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CutNode {
    pub key: NodeKey,
    pub points: u32,
    /// The node's cube side in pixels at its nearest depth: the load queue's priority.
    pub priority: f64,
}

impl CutNode {
    /// Batches the node takes in the GPU node cache.
    pub fn batches(&self) -> usize {
        (self.points as usize).div_ceil(BATCH_POINTS)
    }
}

/// The nodes a frame draws, in load order.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Cut {
    pub nodes: Vec<CutNode>,
    /// Whether the GPU node cache's size stopped the cut before the pixel error did.
    pub limited_by_budget: bool,
}

impl Cut {
    pub fn points(&self) -> u64 {
        self.nodes.iter().map(|n| u64::from(n.points)).sum()
    }

    pub fn batches(&self) -> usize {
        self.nodes.iter().map(CutNode::batches).sum()
    }
}

/// What the selection needs of a frame.
#[derive(Debug, Clone, Copy)]
pub struct CutView<'a> {
    pub camera: &'a Camera,
    /// The dataset's rendering origin: node cubes are tested relative to it, as the batches.
    pub origin: DVec3,
    pub width: u32,
    pub height: u32,
    pub point_size: u32,
    /// The largest projected spacing a drawn node may leave unrefined, in pixels; 0 draws
    /// every node in view.
    pub lod_error: f64,
    /// The most batches the cut may take.
    pub max_batches: usize,
    /// The most points the cut may draw (beyond its first node); `None`: as many as the
    /// pixel error selects.
    pub max_points: Option<u64>,
    /// Only nodes that meet this box (world coordinates) are drawn: a filter's clip box.
    pub clip: Option<ClipBox>,
}

struct Queued {
    priority: f64,
    key: NodeKey,
}

impl PartialEq for Queued {
    fn eq(&self, other: &Self) -> bool {
        self.cmp(other) == Ordering::Equal
    }
}
impl Eq for Queued {}
impl PartialOrd for Queued {
    fn partial_cmp(&self, other: &Self) -> Option<Ordering> {
        Some(self.cmp(other))
    }
}
impl Ord for Queued {
    /// Larger on screen first; equal sizes by key, so the walk never depends on the heap.
    fn cmp(&self, other: &Self) -> Ordering {
        self.priority
            .total_cmp(&other.priority)
            .then_with(|| other.key.cmp(&self.key))
    }
}

/// Pixels per world unit at linear depth `depth` (an orthographic camera: at any depth).
fn pixels_per_unit(camera: &Camera, height: u32, depth: f64) -> f64 {
    match camera.projection {
        Projection::Perspective { fov_y_deg } => {
            let half = (fov_y_deg.to_radians() * 0.5).tan();
            f64::from(height) / (2.0 * half * depth.max(camera.near))
        }
        Projection::Orthographic {
            height: view_height,
        } => f64::from(height) / view_height,
    }
}

/// The nearest linear depth of a cube's corners (relative to the origin).
fn nearest_depth(transform: &CameraTransform, min: DVec3, side: f64) -> f64 {
    (0..8)
        .map(|corner| {
            let offset = DVec3::new(
                f64::from(corner & 1),
                f64::from((corner >> 1) & 1),
                f64::from((corner >> 2) & 1),
            ) * side;
            transform.depth_row.dot((min + offset).extend(1.0))
        })
        .fold(f64::INFINITY, f64::min)
}

/// Whether the camera's position lies inside the cube, where every corner's depth can be far
/// while the points are near.
fn contains(min: DVec3, side: f64, p: DVec3) -> bool {
    p.cmpge(min).all() && p.cmple(min + side).all()
}

/// Which nodes of a hierarchy can show in a frame: their cube meets the frustum (widened for
/// the point size) and the clip box. The cut's walk and its point sizes ask the same.
pub(crate) struct NodesInView<'a> {
    hierarchy: &'a LodHierarchy,
    origin: DVec3,
    frustum: Frustum,
    clip: Option<ClipBox>,
}

impl<'a> NodesInView<'a> {
    pub(crate) fn new(
        hierarchy: &'a LodHierarchy,
        view: &CutView<'_>,
        transform: &CameraTransform,
    ) -> Self {
        Self {
            hierarchy,
            origin: view.origin,
            frustum: Frustum::new(transform, view.point_size),
            clip: view.clip,
        }
    }

    pub(crate) fn contains(&self, key: NodeKey) -> bool {
        let (min, side) = self.hierarchy.node_cube(key);
        if let Some(clip) = &self.clip {
            if !clip.meets_cube(min, side) {
                return false;
            }
        }
        // Relative to the origin, widened by a hair for the f32 of the test.
        let min = min - self.origin;
        let pad = side * 1e-6 + 1e-6;
        let lo = (min - pad).as_vec3();
        let hi = (min + side + pad).as_vec3();
        !self.frustum.excludes(&GpuBatch {
            min: lo.to_array(),
            first: 0,
            max: hi.to_array(),
            count: 0,
        })
    }
}

/// A walk over a hierarchy: the cut, unless it reached a page not read yet.
#[derive(Debug, Clone, Default, PartialEq)]
pub(crate) struct Walk {
    /// The cut; only part of it where `unread_pages` is not empty.
    pub(crate) cut: Cut,
    /// The nodes whose pages are not read yet that the walk queued (in view, under a node it
    /// refined), by key; empty when the walk never took one from its queue.
    pub(crate) unread_pages: Vec<NodeKey>,
}

/// The cut of `hierarchy` for `view`; of a hierarchy with pages not read yet, the cut up to
/// the first of them the walk takes (`walk_cut` says which they are).
pub fn select_cut(hierarchy: &LodHierarchy, view: &CutView<'_>) -> Cut {
    walk_cut(hierarchy, view).cut
}

/// The walk of `hierarchy` for `view`: its cut, or the unread pages it needs first.
pub(crate) fn walk_cut(hierarchy: &LodHierarchy, view: &CutView<'_>) -> Walk {
    let transform = view.camera.transform(view.origin, view.width, view.height);
    let nodes_in_view = NodesInView::new(hierarchy, view, &transform);
    let in_view = |key: NodeKey| nodes_in_view.contains(key);
    let eye = view.camera.position - view.origin;
    let cube = |key: NodeKey| {
        let (min, side) = hierarchy.node_cube(key);
        (min - view.origin, side)
    };
    let on_screen = |key: NodeKey| {
        let (min, side) = cube(key);
        if contains(min, side, eye) {
            return f64::INFINITY;
        }
        let depth = nearest_depth(&transform, min, side);
        side * pixels_per_unit(view.camera, view.height, depth)
    };

    let mut cut = Cut::default();
    let mut queue = BinaryHeap::new();
    // Unread pages queued so far: all are read together if the walk takes one.
    let mut unread = Vec::new();
    let enqueue = |queue: &mut BinaryHeap<Queued>, unread: &mut Vec<NodeKey>, key: NodeKey| {
        if hierarchy.is_unread_page(key) {
            unread.push(key);
        }
        queue.push(Queued {
            priority: on_screen(key),
            key,
        });
    };
    if let Some(root) = hierarchy.root() {
        if in_view(root.key) {
            enqueue(&mut queue, &mut unread, root.key);
        }
    }
    let (mut batches, mut points) = (0, 0u64);
    while let Some(Queued { priority, key }) = queue.pop() {
        let Some(node) = hierarchy.node(key) else {
            continue;
        };
        if hierarchy.is_unread_page(key) {
            // Its points and children are unknown: the rest of the walk depends on them.
            unread.sort_unstable();
            unread.dedup();
            return Walk {
                cut,
                unread_pages: unread,
            };
        }
        let node_batches = (node.point_count as usize).div_ceil(BATCH_POINTS);
        let over_points = view
            .max_points
            .is_some_and(|max| points + u64::from(node.point_count) > max);
        if batches + node_batches > view.max_batches || (over_points && !cut.nodes.is_empty()) {
            cut.limited_by_budget = true;
            break;
        }
        batches += node_batches;
        points += u64::from(node.point_count);
        if node.point_count > 0 {
            cut.nodes.push(CutNode {
                key,
                points: node.point_count,
                priority,
            });
        }
        // A node's spacing on screen: its side in pixels over its sampling grid.
        let refine = match hierarchy.spacing(key) {
            Some(spacing) => {
                let side = hierarchy.cube.side_at(key.level);
                priority * spacing / side > view.lod_error
            }
            None => false,
        };
        if refine || node.point_count == 0 {
            for child in hierarchy.children(key) {
                if in_view(child.key) {
                    enqueue(&mut queue, &mut unread, child.key);
                }
            }
        }
    }
    Walk {
        cut,
        unread_pages: Vec::new(),
    }
}
