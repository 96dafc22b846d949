//! The export's own EVLR: each inner node's sampling grid, so that pointfarm reads an exported
//! file's cuts as it reads the store's.
//!
//! COPC has one spacing, the root's, halved at each level; a store samples each inner node on
//! a grid of its own (`lod/sampling.rs`). The info VLR declares the coarsest grid, which no
//! node is sparser than, for every reader (docs/perf/copc-export-spacing.md); this record says
//! what each node's grid was, and a pointfarm reader refines by it. Other readers skip an
//! EVLR they do not know.
//!
//! ```text
//! EVLR "pointfarm" 1: per inner node, voxel key (level, x, y, z: 4 x i32) and grid (u32,
//! cells along each axis of the node's cube), in the store's key order
//! ```

use super::super::hierarchy::NodeInfo;

/// The record's user id and record id.
pub const USER_ID: &str = "pointfarm";
pub const RECORD_ID: u16 = 1;
pub const DESCRIPTION: &str = "pointfarm node grids";
/// Bytes of one entry.
pub const ENTRY_BYTES: usize = 20;

/// One entry as stored: a voxel key and the grid's cells along each axis.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct GridEntry {
    pub key: [i32; 4],
    pub grid: u32,
}

/// The record's data: an entry for each node of `nodes` sampled on a grid (inner nodes).
pub fn encode(nodes: &[NodeInfo]) -> Vec<u8> {
    let mut data = Vec::new();
    for node in nodes.iter().filter(|n| n.sample_grid > 0) {
        let key = node.key;
        // Cells of a level up to MAX_LEVEL fit an i32, as the hierarchy's entries need too.
        for v in [u32::from(key.level), key.x, key.y, key.z, node.sample_grid] {
            data.extend_from_slice(&v.to_le_bytes());
        }
    }
    data
}

/// The entries of `data`, or why it is not a list of them.
pub fn decode(data: &[u8]) -> Result<impl Iterator<Item = GridEntry> + '_, String> {
    if !data.len().is_multiple_of(ENTRY_BYTES) {
        return Err(format!(
            "{} bytes, not a whole number of {ENTRY_BYTES}-byte entries",
            data.len()
        ));
    }
    Ok(data.chunks_exact(ENTRY_BYTES).map(|entry| {
        let word = |i: usize| {
            let at = 4 * i;
            [entry[at], entry[at + 1], entry[at + 2], entry[at + 3]]
        };
        GridEntry {
            key: [0, 1, 2, 3].map(|i| i32::from_le_bytes(word(i))),
            grid: u32::from_le_bytes(word(4)),
        }
    }))
}
