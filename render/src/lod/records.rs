//! `NodeRecords`: where a store's node records are read from — its payload file here, or a
//! daemon that keeps the store — and the one way records become checked [`NodePoints`].

use rayon::prelude::*;

use super::codec::{decode_node, NodePoints, POSITION_BITS};
use super::error::LodError;
use super::hierarchy::{LodHierarchy, NodeInfo};
use super::key::{NodeKey, RootCube};

/// A source of stored node records, as the hierarchy lists them (byte ranges of one payload).
/// A record is checked when decoded, wherever it came from.
pub trait NodeRecords: Send + Sync {
    /// The stored bytes of each of `nodes`, in order; each listed with points.
    fn read_records(&self, nodes: &[NodeInfo]) -> Result<Vec<Vec<u8>>, LodError>;

    /// A record's points, checked against what the hierarchy says of its node. A store's
    /// records are its own format ([`decode_node`]); a source whose records are another
    /// format (a COPC file's LAZ chunks) decodes them itself.
    fn decode(
        &self,
        cube: &RootCube,
        info: &NodeInfo,
        bytes: &[u8],
    ) -> Result<NodePoints, LodError> {
        decode_node(cube, info.key, info.point_count, bytes)
    }
}

/// Reads and checks the nodes `keys` of `hierarchy` from `records` (one request for all of
/// them), decoding on all cores; a node without points needs no read.
pub fn read_nodes(
    records: &dyn NodeRecords,
    hierarchy: &LodHierarchy,
    keys: &[NodeKey],
) -> Result<Vec<NodePoints>, LodError> {
    let infos: Vec<NodeInfo> = keys
        .iter()
        .map(|&key| {
            hierarchy
                .node(key)
                .copied()
                .ok_or(LodError::UnknownNode { key })
        })
        .collect::<Result<_, _>>()?;
    let stored: Vec<NodeInfo> = infos
        .iter()
        .filter(|i| i.point_count > 0)
        .copied()
        .collect();
    let bytes = if stored.is_empty() {
        Vec::new()
    } else {
        records.read_records(&stored)?
    };
    if bytes.len() != stored.len() {
        return Err(LodError::Records(format!(
            "{} records for {} nodes",
            bytes.len(),
            stored.len()
        )));
    }
    let decoded: Vec<NodePoints> = stored
        .par_iter()
        .zip(bytes.par_iter())
        .map(|(info, bytes)| records.decode(&hierarchy.cube, info, bytes))
        .collect::<Result<_, _>>()?;
    let mut decoded = decoded.into_iter();
    Ok(infos
        .iter()
        .map(|info| match info.point_count {
            0 => empty_node(hierarchy, info.key),
            _ => decoded.next().expect("one record per stored node"),
        })
        .collect())
}

/// A node the hierarchy lists without points.
fn empty_node(hierarchy: &LodHierarchy, key: NodeKey) -> NodePoints {
    NodePoints {
        key,
        cube_min: hierarchy.cube.node_min(key),
        step: hierarchy.cube.side_at(key.level) / f64::from(1u32 << POSITION_BITS),
        quantised: Vec::new(),
        rgb: hierarchy.stats.has_rgb.then(Vec::new),
        intensity: Vec::new(),
        classification: Vec::new(),
        return_number: Vec::new(),
        weights: Vec::new(),
    }
}
