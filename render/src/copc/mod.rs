//! COPC files rendered node by node, without a store of their own: a COPC file (LAZ 1.4 with
//! an octree's hierarchy in an EVLR) already is a level-of-detail structure, so its
//! hierarchy becomes a [`LodHierarchy`] (voxel keys are node keys, each inner node's spacing
//! the info VLR's halved per level) and its LAZ chunks the node records ([`CopcNodes`]), which
//! a [`LodDataset`] renders cut by cut through the same caches as a built store.
//!
//! - `header.rs`: detection (the info VLR first, where the specification puts it) and the
//!   header, LASzip and info VLRs, after the checks every LAS/LAZ file passes;
//! - `hierarchy.rs`: the hierarchy pages walked into nodes, every entry checked against the
//!   file and the header;
//! - `nodes.rs`: a node's chunk read by byte range and decoded into `NodePoints`;
//! - `error.rs`: [`CopcError`].
//!
//! Colour ranges come from the coarsest nodes, the same even sample the elevation range of a
//! store comes from: the RGB decision, the intensity percentiles and the class counts of up
//! to [`crate::cut::ELEVATION_SAMPLE_POINTS`] points (1M), not of every point.

mod error;
mod header;
mod hierarchy;
mod nodes;

#[cfg(test)]
mod tests;

use std::fs::File;
use std::path::Path;
use std::sync::Arc;

pub use error::CopcError;
pub use header::{is_copc, CopcInfo};
pub use nodes::{CopcDecoder, CopcNodes};

use crate::cut::{for_each_coarse_node, node_heights, LodDataset};
use crate::lod::{DatasetStats, LodError, LodHierarchy};

/// A COPC file opened for rendering, and what opening it read.
pub struct CopcDataset {
    pub dataset: LodDataset,
    pub info: CopcInfo,
    /// How its chunks decode, for a reader that is sent them instead of opening the file.
    pub decoder: CopcDecoder,
    /// Hierarchy pages read, and their bytes.
    pub pages: usize,
    pub page_bytes: u64,
    /// Nodes of the hierarchy (with points or children).
    pub nodes: usize,
    /// Nodes and bytes of chunks read for the colour ranges.
    pub sample_nodes: usize,
    pub sample_bytes: u64,
}

/// Opens the COPC file `path`: its header and every hierarchy page, checked, then the
/// coarsest nodes for the colour ranges.
pub fn open_copc(path: &Path) -> Result<CopcDataset, CopcError> {
    let mut file = File::open(path).map_err(|e| CopcError::io(path, e))?;
    let header = header::read_header(path, &mut file)?;
    let list = hierarchy::read_pages(path, &file, &header)?;
    let has_rgb = header.format.has_color;
    let hierarchy = LodHierarchy::with_level_spacing(
        header.info.cube(),
        header.point_count,
        DatasetStats::new(has_rgb),
        header.info.spacing,
        list.nodes,
    );
    let nodes = Arc::new(CopcNodes::new(path, file, &header));
    // The colour ranges from the coarsest nodes, and their heights for the elevation range.
    let origin = header.bounds.center();
    let mut stats = DatasetStats::new(has_rgb);
    let mut heights = Vec::new();
    let mut sample_nodes = 0;
    let sample_bytes = for_each_coarse_node(nodes.as_ref(), &hierarchy, |points| {
        stats.add_node(points);
        heights.extend(node_heights(points, origin));
        sample_nodes += 1;
    })
    .map_err(|error| copc_error(path, error))?;
    let mut hierarchy = hierarchy;
    hierarchy.stats = stats;
    let node_count = hierarchy.nodes().len();
    let decoder = nodes.decoder().clone();
    let dataset = LodDataset::with_heights(nodes, hierarchy, header.bounds, heights);
    Ok(CopcDataset {
        dataset,
        info: header.info,
        decoder,
        pages: list.pages,
        page_bytes: list.page_bytes,
        nodes: node_count,
        sample_nodes,
        sample_bytes,
    })
}

/// What a COPC file's header and hierarchy say, without reading a point.
#[derive(Debug, Clone, PartialEq)]
pub struct CopcSummary {
    pub info: CopcInfo,
    /// Hierarchy pages, and their bytes.
    pub pages: usize,
    pub page_bytes: u64,
    /// Nodes with points, and the levels below the root they reach (0: the root alone).
    pub nodes: usize,
    pub depth: u8,
}

/// Reads `path`'s header and every hierarchy page, checked as rendering checks them.
pub fn describe(path: &Path) -> Result<CopcSummary, CopcError> {
    let mut file = File::open(path).map_err(|e| CopcError::io(path, e))?;
    let header = header::read_header(path, &mut file)?;
    let list = hierarchy::read_pages(path, &file, &header)?;
    let with_points = || list.nodes.iter().filter(|node| node.point_count > 0);
    Ok(CopcSummary {
        info: header.info,
        pages: list.pages,
        page_bytes: list.page_bytes,
        nodes: with_points().count(),
        depth: with_points().map(|node| node.key.level).max().unwrap_or(0),
    })
}

/// A failure reading nodes through the store's interface, as the COPC error it came from.
fn copc_error(path: &Path, error: LodError) -> CopcError {
    match error {
        LodError::RecordSource(source) => match source.downcast::<CopcError>() {
            Ok(error) => *error,
            Err(other) => CopcError::hierarchy(path, other.to_string()),
        },
        other => CopcError::hierarchy(path, other.to_string()),
    }
}
