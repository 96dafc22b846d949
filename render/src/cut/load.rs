//! Loading a cut's nodes onto the host: which detail each is read at, and a wave at a time
//! from the host cache or the store, in two halves (reading the records, then decoding them
//! into the host cache) so a frame's next read overlaps this one's decoding.

use std::sync::{Arc, Mutex};

use super::host_cache::HostNodeCache;
use super::options::CutOptions;
use super::select::CutNode;
use super::CutError;
use crate::color::Coloring;
use crate::filter::PointFilter;
use crate::lod::codec::{Detail, COARSE_MAX_PIXELS};
use crate::lod::{
    fetch_nodes_at, FetchedNodes, LodDataset, LodError, LodHierarchy, NodeKey, NodePoints,
    NodeRecords,
};

/// Which detail a frame reads each node of its cut at (`lod::codec::Detail`): coarse where
/// the node spans at most [`COARSE_MAX_PIXELS`] and the frame draws nothing the coarse section
/// lacks (colors from RGB or heights, no attribute filter, a pixel error above 0), so a cold
/// frame reads about half the bytes (docs/perf/coarse-reads.md).
#[derive(Debug, Clone, Copy)]
pub(super) struct FrameDetails {
    coarse: bool,
}

impl FrameDetails {
    /// Every node read whole.
    pub(super) const FULL: Self = Self { coarse: false };

    pub(super) fn new(
        options: &CutOptions,
        dataset: &LodDataset,
        coloring: Coloring,
        filter: &PointFilter,
    ) -> Self {
        Self {
            coarse: options.lod_error > 0.0
                && dataset.coloring.needs_only_coarse(coloring.mode)
                && !filter.reads_attributes(),
        }
    }

    pub(super) fn of(&self, node: &CutNode) -> Detail {
        if self.coarse && node.priority <= COARSE_MAX_PIXELS {
            Detail::Coarse
        } else {
            Detail::Full
        }
    }
}

/// The records of some nodes read at their details, not yet decoded.
pub(super) struct FetchedAtDetails {
    /// How many nodes were asked for.
    len: usize,
    /// Per detail read, the places among them of the nodes read at it, and their records.
    parts: Vec<(Vec<usize>, FetchedNodes)>,
    bytes_read: u64,
}

/// Reads the records of `nodes` at their details, the coarse ones in one request and the
/// whole ones in another.
pub(super) fn fetch_at_details(
    records: &dyn NodeRecords,
    hierarchy: &LodHierarchy,
    details: &FrameDetails,
    nodes: &[&CutNode],
) -> Result<FetchedAtDetails, LodError> {
    let mut parts = Vec::new();
    let mut bytes_read = 0;
    for detail in [Detail::Coarse, Detail::Full] {
        let at: Vec<usize> = (0..nodes.len())
            .filter(|&i| details.of(nodes[i]) == detail)
            .collect();
        if at.is_empty() {
            continue;
        }
        let keys: Vec<NodeKey> = at.iter().map(|&i| nodes[i].key).collect();
        let fetched = fetch_nodes_at(records, hierarchy, &keys, detail)?;
        bytes_read += fetched.bytes_read();
        parts.push((at, fetched));
    }
    Ok(FetchedAtDetails {
        len: nodes.len(),
        parts,
        bytes_read,
    })
}

impl FetchedAtDetails {
    /// The nodes' points, in the order they were asked for.
    pub(super) fn decode(
        self,
        records: &dyn NodeRecords,
        hierarchy: &LodHierarchy,
    ) -> Result<Vec<NodePoints>, LodError> {
        let mut read: Vec<Option<NodePoints>> = (0..self.len).map(|_| None).collect();
        for (at, fetched) in self.parts {
            for (i, node) in at.into_iter().zip(fetched.decode(records, hierarchy)?) {
                read[i] = Some(node);
            }
        }
        Ok(read
            .into_iter()
            .map(|n| n.expect("every node read"))
            .collect())
    }

    /// The bytes of the records read.
    pub(super) fn bytes_read(&self) -> u64 {
        self.bytes_read
    }
}

/// A wave of a cut's nodes made resident on the host, in the wave's order, with what it
/// took for the frame's report.
pub(super) struct LoadedWave {
    pub(super) nodes: Vec<Arc<NodePoints>>,
    /// The detail the frame draws each at.
    pub(super) details: Vec<Detail>,
    pub(super) host_hits: u64,
    pub(super) nodes_read: u64,
    pub(super) bytes_read: u64,
}

/// A wave of a cut's nodes half loaded: those the host cache held, and the records of the
/// rest read but not decoded.
pub(super) struct FetchedWave {
    cached: Vec<Option<Arc<NodePoints>>>,
    details: Vec<Detail>,
    read: FetchedAtDetails,
}

fn poisoned() -> CutError {
    CutError::Cache("the host node cache is poisoned".into())
}

/// The wave's nodes from the host cache, and the records of the others read from the store
/// (several reads in flight).
pub(super) fn fetch_wave(
    host: &Mutex<HostNodeCache>,
    dataset: &LodDataset,
    hierarchy: &LodHierarchy,
    details: &FrameDetails,
    wave: &[&CutNode],
) -> Result<FetchedWave, CutError> {
    let cached: Vec<Option<Arc<NodePoints>>> = {
        let mut host = host.lock().map_err(|_| poisoned())?;
        wave.iter()
            .map(|n| host.get(n.key, details.of(n)))
            .collect()
    };
    let to_read: Vec<&CutNode> = wave
        .iter()
        .zip(&cached)
        .filter(|(_, c)| c.is_none())
        .map(|(n, _)| *n)
        .collect();
    let read = fetch_at_details(dataset.records.as_ref(), hierarchy, details, &to_read)?;
    Ok(FetchedWave {
        cached,
        details: wave.iter().map(|n| details.of(n)).collect(),
        read,
    })
}

impl FetchedWave {
    /// The wave resident: the records read decoded on all cores and put in the host cache.
    pub(super) fn decode(
        self,
        host: &Mutex<HostNodeCache>,
        dataset: &LodDataset,
        hierarchy: &LodHierarchy,
    ) -> Result<LoadedWave, CutError> {
        let bytes_read = self.read.bytes_read();
        let read: Vec<Arc<NodePoints>> = self
            .read
            .decode(dataset.records.as_ref(), hierarchy)?
            .into_iter()
            .map(Arc::new)
            .collect();
        let mut host = host.lock().map_err(|_| poisoned())?;
        for node in &read {
            host.insert(Arc::clone(node));
        }
        let nodes_read = read.len() as u64;
        let host_hits = self.cached.len() as u64 - nodes_read;
        let mut read = read.into_iter();
        Ok(LoadedWave {
            nodes: self
                .cached
                .into_iter()
                .map(|c| c.or_else(|| read.next()).expect("one read per miss"))
                .collect(),
            details: self.details,
            host_hits,
            nodes_read,
            bytes_read,
        })
    }
}
