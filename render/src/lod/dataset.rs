//! `LodDataset`: a store opened for rendering (its hierarchy, where its node records are read
//! from, origin, bounds and color ranges), and the coarse sample its color ranges come from.

use std::sync::Arc;

use glam::DVec3;

use super::colors::DatasetColoring;
use super::pages::{HierarchyPages, LazyLevels, PagesRead};
use super::{read_nodes, LodError, LodHierarchy, LodStore, NodePoints, NodeRecords};
use crate::cloud::WorldBounds;
use crate::color::Coloring;

/// Nodes read, prepared and written to the GPU together: bounds the transient memory of a
/// frame's loads to this many nodes' decoded and prepared points.
pub(crate) const LOAD_WAVE_NODES: usize = 32;

/// Points of the coarsest nodes the elevation range is taken from, at least.
pub const ELEVATION_SAMPLE_POINTS: u64 = 1 << 20;

/// A built store opened for rendering: its hierarchy (always resident), where its node
/// records are read from (the store's payload file, or a daemon that keeps it), rendering
/// origin, bounds and color ranges.
pub struct LodDataset {
    pub(crate) records: Arc<dyn NodeRecords>,
    /// The hierarchy as opened.
    pub(crate) hierarchy: Arc<LodHierarchy>,
    /// Where a hierarchy opened with unread pages reads them, and what it has read since
    /// (boxed: most datasets have none).
    pub(crate) lazy: Option<Box<LazyLevels>>,
    pub(crate) origin: DVec3,
    bounds: WorldBounds,
    pub(crate) coloring: DatasetColoring,
    /// The spacing of the original points, which a frame's adaptive size is made for: a
    /// store's from its leaves (`LodHierarchy::point_spacing`), a COPC file's from its
    /// coarsest nodes, so that it stays the same whatever pages frames read later.
    pub(crate) point_spacing: Option<f64>,
}

impl LodDataset {
    /// Opens a built store whose points lie in `bounds` (the dataset's, as the camera frames
    /// them); the origin is their centre.
    pub fn open(store: LodStore, bounds: WorldBounds) -> Result<Self, LodError> {
        let hierarchy = store.read_hierarchy()?;
        Self::with_records(Arc::new(store), hierarchy, bounds)
    }

    /// A store whose hierarchy is `hierarchy` and whose records come from `records`.
    pub fn with_records(
        records: Arc<dyn NodeRecords>,
        hierarchy: LodHierarchy,
        bounds: WorldBounds,
    ) -> Result<Self, LodError> {
        let origin = bounds.center();
        let mut heights = Vec::new();
        for_each_coarse_node(records.as_ref(), &hierarchy, |points| {
            heights.extend(node_heights(points, origin));
        })?;
        Ok(Self::with_heights(records, hierarchy, bounds, heights))
    }

    /// A store whose elevation range comes from `heights` (of its coarsest nodes, relative to
    /// the centre of `bounds`, [`for_each_coarse_node`]) and whose other color ranges come
    /// from its hierarchy's statistics.
    pub fn with_heights(
        records: Arc<dyn NodeRecords>,
        hierarchy: LodHierarchy,
        bounds: WorldBounds,
        mut heights: Vec<f32>,
    ) -> Self {
        let elevation = crate::color::Stretch::percentiles(&mut heights);
        Self::with_elevation(records, hierarchy, bounds, elevation)
    }

    /// A store whose elevation range is `elevation` (relative to the centre of `bounds`),
    /// taken from a sample where the hierarchy was opened, so no node is read here.
    pub fn with_elevation(
        records: Arc<dyn NodeRecords>,
        hierarchy: LodHierarchy,
        bounds: WorldBounds,
        elevation: Option<crate::color::Stretch>,
    ) -> Self {
        let origin = bounds.center();
        let coloring = DatasetColoring::with_elevation(&hierarchy.stats, elevation, origin.z);
        Self {
            records,
            point_spacing: hierarchy.point_spacing(),
            hierarchy: Arc::new(hierarchy),
            lazy: None,
            origin,
            bounds,
            coloring,
        }
    }

    /// This dataset with its adaptive points made for `spacing` instead of its leaves' (a
    /// hierarchy read a page at a time does not know its leaves when it is opened).
    pub fn with_point_spacing(mut self, spacing: Option<f64>) -> Self {
        self.point_spacing = spacing;
        self
    }

    /// This dataset with its unread hierarchy pages read from `pages` as frames reach them
    /// (`pages.rs`).
    pub fn with_pages(mut self, pages: Arc<dyn HierarchyPages>) -> Self {
        self.lazy = Some(Box::new(LazyLevels::new(
            Arc::clone(&self.hierarchy),
            pages,
        )));
        self
    }

    /// The elevation range of its coarsest nodes, relative to the origin.
    pub fn elevation(&self) -> Option<crate::color::Stretch> {
        self.coloring.elevation()
    }

    /// Where the node records are read from.
    pub fn records(&self) -> &Arc<dyn NodeRecords> {
        &self.records
    }

    /// The hierarchy as opened: of a dataset whose pages are read lazily, without the pages
    /// frames have read since ([`LodDataset::current_hierarchy`] has them).
    pub fn hierarchy(&self) -> &LodHierarchy {
        &self.hierarchy
    }

    /// The hierarchy with every page read so far.
    pub fn current_hierarchy(&self) -> Arc<LodHierarchy> {
        self.lazy
            .as_ref()
            .map_or_else(|| Arc::clone(&self.hierarchy), |lazy| lazy.current())
    }

    /// Hierarchy pages frames have read since the dataset was opened.
    pub fn pages_read(&self) -> PagesRead {
        self.lazy
            .as_ref()
            .map_or_else(PagesRead::default, |lazy| lazy.pages_read())
    }

    pub fn origin(&self) -> DVec3 {
        self.origin
    }

    pub fn bounds(&self) -> WorldBounds {
        self.bounds
    }

    /// The range elevation or intensity is drawn over in `coloring`, in the mode's units
    /// (world Z, raw intensity): what a legend shows.
    pub fn ramp_range(&self, coloring: Coloring) -> Option<crate::color::ColorRange> {
        self.coloring.ramp_range(coloring)
    }

    pub fn point_count(&self) -> u64 {
        self.hierarchy.point_count
    }

    /// The spacing of the original points, from the leaves: what a frame's adaptive point
    /// size is made for, and what a cut's batches are sized against.
    pub fn point_spacing(&self) -> Option<f64> {
        self.point_spacing
    }
}

/// Reads the coarsest nodes of `hierarchy`, level by level, up to
/// [`ELEVATION_SAMPLE_POINTS`] (an even sample of the whole dataset, which color ranges are
/// taken from), a wave at a time, handing each to `visit`; returns their record bytes.
pub fn for_each_coarse_node(
    records: &dyn NodeRecords,
    hierarchy: &LodHierarchy,
    visit: impl FnMut(&NodePoints),
) -> Result<u64, LodError> {
    for_each_coarse_node_up_to(records, hierarchy, ELEVATION_SAMPLE_POINTS, visit)
}

/// [`for_each_coarse_node`] up to `sample_points` points.
pub(crate) fn for_each_coarse_node_up_to(
    records: &dyn NodeRecords,
    hierarchy: &LodHierarchy,
    sample_points: u64,
    mut visit: impl FnMut(&NodePoints),
) -> Result<u64, LodError> {
    let mut levels: Vec<_> = hierarchy.stored_nodes().collect();
    levels.sort_by_key(|n| n.key);
    let mut keys = Vec::new();
    let mut sampled = 0;
    let mut bytes = 0;
    for node in levels {
        if sampled >= sample_points {
            break;
        }
        sampled += u64::from(node.point_count);
        bytes += u64::from(node.byte_len);
        keys.push(node.key);
    }
    for wave in keys.chunks(LOAD_WAVE_NODES) {
        for points in read_nodes(records, hierarchy, wave)? {
            visit(&points);
        }
    }
    Ok(bytes)
}

/// Heights of a node's points relative to `origin` (f64, then f32, as positions are).
pub fn node_heights(node: &NodePoints, origin: DVec3) -> Vec<f32> {
    let base = node.cube_min.z - origin.z;
    node.quantised
        .iter()
        .map(|q| (base + (f64::from(q[2]) + 0.5) * node.step) as f32)
        .collect()
}
