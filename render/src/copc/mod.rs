//! COPC files rendered node by node, without a store of their own: a COPC file (LAZ 1.4 with
//! an octree's hierarchy in an EVLR) already is a level-of-detail structure, so its
//! hierarchy becomes a [`LodHierarchy`] (voxel keys are node keys, each inner node's spacing
//! the root's halved per level, or its own grid's where a pointfarm export records it) and its
//! LAZ chunks the node records ([`CopcNodes`]), which
//! a [`LodDataset`] renders cut by cut through the same caches as a built store.
//!
//! - `bytes.rs`: where the bytes come from, a file here or an object by URL
//!   ([`crate::remote`]), read by range through one face, so both are read and checked by the
//!   same code;
//! - `header.rs`: detection (the info VLR first, where the specification puts it) and the
//!   header, LASzip and info VLRs, after the checks every LAS/LAZ file passes;
//! - `hierarchy.rs`: the hierarchy pages walked into nodes, every entry checked against the
//!   file and the header;
//! - `lazy.rs`: child pages read as they are needed, by a frame's cut or the color ranges;
//! - `nodes.rs`: a node's chunk read by byte range and decoded into `NodePoints`;
//! - `node_grids.rs`: the inner nodes' sampling grids a pointfarm export records, which a cut
//!   refines by where the file has them;
//! - `error.rs`: [`CopcError`].
//!
//! A file opened by URL ([`open_copc_url`], [`describe_url`]) is read as a file here is, every
//! read a range of the version its HEAD saw: a wave's chunks, and the child pages a cut reaches,
//! as one read of many ranges, near ones fetched as one request; errors name the URL.
//!
//! For rendering ([`open_copc`]) only the root hierarchy page is read when the file is opened
//! (and the child pages the color sample reaches); a frame's cut reads the pages it reaches,
//! so a large file's first frame reads a few pages, not the whole hierarchy. A daemon, which
//! sends its workers the whole hierarchy, opens the file with every page read
//! ([`open_copc_whole`]); so does [`describe`].
//!
//! The root's spacing is measured, from the area the coarsest nodes cover by box counting, as a
//! resident cloud's spacing is measured ([`crate::spacing::of_sample`]), and the info VLR's is
//! taken only where it is larger: writers declare it differently, and adaptive points sized by
//! a declared spacing smaller than the points' own leave a cut's surfaces open where the same
//! points read whole are closed.
//!
//! Color ranges come from the coarsest nodes, the same even sample the elevation range of a
//! store comes from: the RGB decision, the intensity percentiles and the class counts of up
//! to [`crate::lod::ELEVATION_SAMPLE_POINTS`] points (1M), not of every point.

mod bytes;
mod error;
mod header;
mod hierarchy;
mod lazy;
mod node_grids;
mod nodes;

#[cfg(test)]
mod lazy_tests;
#[cfg(test)]
mod tests;
#[cfg(test)]
mod weights_tests;

use std::path::Path;
use std::sync::Arc;

use glam::DVec3;

pub use error::CopcError;
pub use header::{is_copc, CopcInfo};
pub use nodes::{CopcDecoder, CopcNodes};

use crate::cloud::WorldBounds;
use crate::ingest::Attributes;
use crate::lod::{
    for_each_coarse_node_up_to, node_heights, DatasetStats, LodDataset, LodError, LodHierarchy,
    ELEVATION_SAMPLE_POINTS,
};
use crate::remote::{ObjectUrl, RemoteClient, RemoteObject};
pub(crate) use bytes::CopcBytes;
pub use bytes::RangeCache;
use lazy::CopcPageReader;

/// A COPC file opened for rendering, and what opening it read.
pub struct CopcDataset {
    pub dataset: LodDataset,
    pub info: CopcInfo,
    /// The root's spacing, which its hierarchy halves per level: as measured, or the info VLR's
    /// where that is larger (a declared spacing can only make points larger, never leave holes).
    pub root_spacing: f64,
    /// How its chunks decode, for a reader that is sent them instead of opening the file.
    pub decoder: CopcDecoder,
    /// Hierarchy pages read at open, and their bytes (frames read others:
    /// [`LodDataset::pages_read`]).
    pub pages: usize,
    pub page_bytes: u64,
    /// Child pages left for frames to read.
    pub unread_pages: usize,
    /// Nodes of the hierarchy read at open (with points or children).
    pub nodes: usize,
    /// Nodes and bytes of chunks read for the color ranges.
    pub sample_nodes: usize,
    pub sample_bytes: u64,
}

/// Opens the COPC file `path` for rendering: its header and root hierarchy page, checked, the
/// coarsest nodes for the color ranges (and the child pages they lie in); the other pages
/// are read as frames reach them.
pub fn open_copc(path: &Path) -> Result<CopcDataset, CopcError> {
    open(
        CopcBytes::file(path)?,
        PageReads::AsNeeded,
        ELEVATION_SAMPLE_POINTS,
    )
}

/// Opens the COPC object at `url` for rendering as [`open_copc`] opens a file: a HEAD for its
/// size and version (every later read is pinned to it), then its header, root page and
/// coarsest nodes by range. Frames read the other pages and the nodes they need through
/// `client`, whose counters tell what was fetched.
pub fn open_copc_url(client: &RemoteClient, url: &ObjectUrl) -> Result<CopcDataset, CopcError> {
    open_copc_object(client.open(url)?)
}

/// Opens an object already opened (its version read and perhaps checked by the caller, as a
/// worker checks it against the version its dataset was registered at) for rendering as
/// [`open_copc_url`] does: every read is pinned to that version, so the check and the reads
/// see one object.
pub fn open_copc_object(object: RemoteObject) -> Result<CopcDataset, CopcError> {
    open(
        CopcBytes::remote(object),
        PageReads::AsNeeded,
        ELEVATION_SAMPLE_POINTS,
    )
}

/// Opens an object as [`open_copc_object`] does, its ranges read from `cache` where it holds
/// them for the object's version, and kept there once fetched.
pub fn open_copc_object_cached(
    object: RemoteObject,
    cache: Arc<dyn RangeCache>,
) -> Result<CopcDataset, CopcError> {
    open(
        CopcBytes::remote(object).with_cache(cache),
        PageReads::AsNeeded,
        ELEVATION_SAMPLE_POINTS,
    )
}

/// Opens the COPC file `path` as [`open_copc`] does, with every hierarchy page read and the
/// entries' points checked against the header's count: for a reader that needs the whole
/// hierarchy (a daemon sends it to its workers).
pub fn open_copc_whole(path: &Path) -> Result<CopcDataset, CopcError> {
    open(
        CopcBytes::file(path)?,
        PageReads::All,
        ELEVATION_SAMPLE_POINTS,
    )
}

/// The object at `url`, opened: a HEAD for its size and the version every read is pinned to.
fn open_object(client: &RemoteClient, url: &ObjectUrl) -> Result<CopcBytes, CopcError> {
    Ok(CopcBytes::remote(client.open(url)?))
}

/// Which hierarchy pages opening a file reads.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum PageReads {
    /// The root page and those the color sample needs.
    AsNeeded,
    All,
}

/// Opens `bytes` reading the pages `reads` says, its color ranges from its coarsest
/// `sample_points` points.
fn open(bytes: CopcBytes, reads: PageReads, sample_points: u64) -> Result<CopcDataset, CopcError> {
    let bytes = Arc::new(bytes);
    let path = bytes.name();
    let header = header::read_header(&bytes)?;
    let mut pages = match reads {
        PageReads::AsNeeded => hierarchy::read_root_page(&bytes, &header)?,
        PageReads::All => hierarchy::read_all_pages(&bytes, &header)?,
    };
    let has_rgb = header.format.has_color;
    let (cube, spacing) = (header.info.cube(), header.info.spacing);
    let mut hierarchy = pages.hierarchy(cube, DatasetStats::new(has_rgb), spacing);
    loop {
        let needed = lazy::coarse_pages(&hierarchy, sample_points);
        if needed.is_empty() {
            break;
        }
        pages.read(&bytes, &needed)?;
        hierarchy = pages.hierarchy(cube, DatasetStats::new(has_rgb), spacing);
    }
    let nodes = Arc::new(CopcNodes::new(Arc::clone(&bytes), &header));
    // The color ranges from the coarsest nodes, their heights for the elevation range, and
    // their positions for the points' spacing: the leaves that would give it may lie in pages
    // not read yet, and the sample is the same whichever pages are read.
    let origin = header.bounds.center();
    let mut stats = DatasetStats::new(has_rgb);
    let mut heights = Vec::new();
    let mut positions = Vec::new();
    let mut sample_nodes = 0;
    bytes.keep_reads(true);
    let sample_bytes =
        for_each_coarse_node_up_to(nodes.as_ref(), &hierarchy, sample_points, |points| {
            stats.add_node(points);
            heights.extend(node_heights(points, origin));
            positions.extend(points.positions_relative_to(origin));
            sample_nodes += 1;
        });
    bytes.keep_reads(false);
    let sample_bytes = sample_bytes.map_err(|error| copc_error(path, error))?;
    let point_spacing = crate::spacing::of_sample(&positions, hierarchy.point_count);
    drop(positions);
    let root_spacing =
        measured_root_spacing(&hierarchy, point_spacing).map_or(spacing, |m| m.max(spacing));
    hierarchy = hierarchy.with_root_spacing(root_spacing);
    hierarchy.stats = stats;
    let node_count = hierarchy.nodes().len();
    let unread_pages = hierarchy.unread_pages().len();
    let decoder = nodes.decoder().clone();
    let mut dataset = LodDataset::with_heights(nodes, hierarchy, header.bounds, heights)
        .with_point_spacing(point_spacing);
    let (read, read_bytes) = (pages.pages, pages.page_bytes);
    if !pages.all_read() {
        dataset = dataset.with_pages(Arc::new(CopcPageReader::new(
            Arc::clone(&bytes),
            root_spacing,
            pages,
        )));
    }
    Ok(CopcDataset {
        dataset,
        info: header.info,
        root_spacing,
        decoder,
        pages: read,
        page_bytes: read_bytes,
        unread_pages,
        nodes: node_count,
        sample_nodes,
        sample_bytes,
    })
}

/// The spacing of the root's points, from the area the coarse sample measured
/// (`point_spacing`, of all the hierarchy's points, squared times their count) shared among the
/// root's points; `None` without a spacing or a root with points.
fn measured_root_spacing(hierarchy: &LodHierarchy, point_spacing: Option<f64>) -> Option<f64> {
    let root_points = hierarchy
        .root()
        .map(|root| root.point_count)
        .filter(|&n| n > 0)?;
    let spacing = point_spacing?;
    Some(spacing * (hierarchy.point_count as f64 / f64::from(root_points)).sqrt())
}

/// What a COPC file's header and hierarchy say, without reading a point.
#[derive(Debug, Clone, PartialEq)]
pub struct CopcSummary {
    pub info: CopcInfo,
    /// The header's facts, for a file described without the LAS reader (by URL).
    pub header: CopcHeaderFacts,
    /// Hierarchy pages, and their bytes.
    pub pages: usize,
    pub page_bytes: u64,
    /// Nodes with points, and the levels below the root they reach (0: the root alone).
    pub nodes: usize,
    pub depth: u8,
}

/// What a COPC file's header says of its points, its records and where they lie.
#[derive(Debug, Clone, PartialEq)]
pub struct CopcHeaderFacts {
    /// Bytes of the file or object.
    pub file_bytes: u64,
    /// The points the header declares.
    pub points: u64,
    pub point_format: u8,
    /// Bytes of a point record, extra bytes included.
    pub record_len: u16,
    pub vlrs: u32,
    pub evlrs: u32,
    /// The header's bounds.
    pub bounds: WorldBounds,
    pub scale: DVec3,
    pub offset: DVec3,
    /// The attributes its point format and extra bytes carry.
    pub attributes: Attributes,
}

/// Reads `path`'s header and every hierarchy page, checked as rendering checks them.
pub fn describe(path: &Path) -> Result<CopcSummary, CopcError> {
    summarize(&CopcBytes::file(path)?)
}

/// Reads the header and every hierarchy page of the COPC object at `url`, by range, checked
/// as [`describe`] checks a file's.
pub fn describe_url(client: &RemoteClient, url: &ObjectUrl) -> Result<CopcSummary, CopcError> {
    summarize(&open_object(client, url)?)
}

/// Reads the header and every hierarchy page of an object already opened (its version
/// checked by the caller, as a daemon checks the version its dataset was registered at), as
/// [`describe_url`] does: every read is pinned to that version.
pub fn describe_object(object: RemoteObject) -> Result<CopcSummary, CopcError> {
    summarize(&CopcBytes::remote(object))
}

fn summarize(bytes: &CopcBytes) -> Result<CopcSummary, CopcError> {
    let header = header::read_header(bytes)?;
    let pages = hierarchy::read_all_pages(bytes, &header)?;
    let with_points = || pages.nodes_with_points();
    let (format, t) = (&header.format, &header.transforms);
    let facts = CopcHeaderFacts {
        file_bytes: header.file_len,
        points: header.point_count,
        point_format: format.to_u8().unwrap_or(0),
        record_len: format.len(),
        vlrs: header.vlrs,
        evlrs: header.evlrs,
        bounds: header.bounds,
        scale: DVec3::new(t.x.scale, t.y.scale, t.z.scale),
        offset: DVec3::new(t.x.offset, t.y.offset, t.z.offset),
        attributes: Attributes::of_format(format, header.extra_names.clone()),
    };
    Ok(CopcSummary {
        info: header.info,
        header: facts,
        pages: pages.pages,
        page_bytes: pages.page_bytes,
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
