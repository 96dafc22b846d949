//! The level-of-detail store: an octree of a dataset's original points, built by streaming
//! from any [`PointSource`] within a memory budget, its nodes appended to one payload file.
//!
//! How it works: every point lies in exactly one node. A leaf holds at most
//! [`LodBuildOptions::max_leaf_points`] points; an inner node holds a spatially even subset,
//! one point per cell of a grid over its cube (the point closest to the cell's centre), chosen
//! from its children's points, which keep the rest ([`sampling`]). Keys are COPC's voxel keys
//! (level, x, y, z) in a cube around the bounds ([`key`]). The build follows PotreeConverter 2
//! ([`build`]): a counting pass, partitions of bounded size spilled to disk, each partition's
//! octree built in memory in parallel, then the levels above. Nodes are stored quantised to 30 bits
//! per axis in their cube, 12 bytes a position in three coarse-to-fine streams, with the raw
//! attributes and a checksum ([`codec`]). Each node's record lies in one append-only payload
//! file at the byte range its [`NodeInfo`] records, read with positioned reads from any number
//! of threads; the hierarchy, small and always resident, is one sled record written last,
//! after the payload file is synced ([`hierarchy`], [`store`]). Payloads are not sled values:
//! sled holds memory in proportion to what it stores.
//!
//! A build resumes where it stopped (killed, power lost) when it runs again on the same inputs
//! and options (`journal.rs`, `resume.rs`). Its units: the counting pass (one unit: a build
//! stopped in it counts again), each partition's octree, each split of a partition on disk,
//! and each node above the partitions with its children. A unit's output (its nodes in the
//! payload file, its subtree root in a spill file, a split's child files) is synced, then the
//! unit is recorded in the journal, then its inputs are removed; units are recorded one at a
//! time, so the payload file holds the recorded units in order and at most one unit more,
//! cut off on resume. What the journal lists is checked (checksums, lengths) before it is
//! used, and a journal of other inputs (the source's [`PointSource::fingerprint`]: its
//! files' paths, lengths and modification times) or options starts the build over. A source
//! without a fingerprint builds in a fresh folder and does not resume. The resumed store is
//! the uninterrupted build's node for node: the same nodes of the same points; where their
//! records lie follows the order units finished, which parallel builds do not fix. The test
//! hook `POINTFARM_TEST_PAUSE_AT` (`pause.rs`) stops a build at a chosen point of each stage,
//! for tests/build_resume.rs to kill it there.
//!
//! A built store is updated in place when files are added to its dataset (`update.rs`): it
//! keeps its regions, the subtrees of each partition's children, with each subtree root's points
//! as they were before the levels above sampled from them (`regions.rs`, written with the
//! hierarchy in one sled batch). Each added point goes to the region whose cube holds it (or
//! starts one where no region is); only the regions that received points are built again,
//! from their points decoded from the store and the added ones, then every level above the
//! regions is sampled again from the regions' roots. New nodes are appended and the new
//! hierarchy and regions switch in one batch, so an update killed part way leaves the old
//! store whole. Added points outside the store's cube, or files of other attributes, are
//! refused, and the store is built again.
//!
//! Opened for rendering, a store or a COPC file is a [`LodDataset`] (`dataset.rs`: its
//! hierarchy, with pages read as frames reach them, `pages.rs`, and its color ranges,
//! `colors.rs`), what both the COPC reader and the cut renderer build on.

pub mod attributes;
pub mod build;
mod checksum;
pub mod codec;
mod colors;
pub mod compact;
mod context;
pub mod copc_export;
mod counting;
mod dataset;
pub mod digest;
pub mod disk;
pub mod disk_usage;
pub mod error;
mod fields;
pub mod file_facts;
pub mod generated;
mod grid;
pub mod hierarchy;
mod journal;
pub mod key;
pub mod layers;
mod local;
pub mod memory;
mod morton;
pub mod options;
mod pages;
pub mod partition_figures;
mod partitions;
mod pause;
mod plan;
mod point;
pub mod progress;
pub mod published;
pub mod records;
pub mod regions;
mod removal;
mod resume;
pub mod sampling;
mod scratch;
mod sink;
pub mod source;
mod spill;
pub mod stats;
pub mod store;
pub mod thread_cpu;
pub mod update;
mod upper;
pub mod weights;

#[cfg(test)]
mod tests;

pub use attributes::AttributeSchema;
pub use build::{build_lod, build_lod_watched, BuildTimings, LodBuildReport};
pub use codec::NodePoints;
pub use colors::DatasetColoring;
pub use dataset::{for_each_coarse_node, node_heights, LodDataset, ELEVATION_SAMPLE_POINTS};
pub(crate) use dataset::{for_each_coarse_node_up_to, LOAD_WAVE_NODES};
pub use error::LodError;
pub use generated::{GeneratedShape, GeneratedSource};
pub use grid::PositionGrid;
pub use hierarchy::{LodHierarchy, NodeInfo};
pub use key::{NodeKey, RootCube, MAX_LEVEL};
pub use options::LodBuildOptions;
pub use pages::{HierarchyPages, PagesRead};
pub use progress::{preview_version, BuildProgress, PREVIEW_REDRAW_SHARE, PREVIEW_STORED_POINTS};
pub use records::{
    fetch_nodes_at, read_concurrently, read_nodes, read_nodes_at, FetchedNodes, NodeRecords,
};
pub use source::{BatchColumns, BatchVisitor, CloudSource, PointBatch, PointSource};
pub use stats::DatasetStats;
pub use store::LodStore;
pub use update::{update_lod, update_store, LodUpdateReport, ReopenFiles, StoreChange};
