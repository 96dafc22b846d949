//! The node grids a pointfarm export records in an EVLR of its own
//! (`lod::copc_export::node_grids`): each inner node's sampling grid, read and checked when
//! the file is opened, so that a cut of an exported file refines as the store's did. Files
//! without the record refine by the info VLR's spacing.

use std::collections::HashMap;

use super::bytes::RangeReader;
use super::error::CopcError;
use crate::lod::copc_export::node_grids::{self, ENTRY_BYTES, RECORD_ID, USER_ID};
use crate::lod::NodeKey;

/// Cells along each axis of an inner node's sampling grid, by node.
pub(crate) type NodeGrids = HashMap<NodeKey, u32>;

/// Bytes of an EVLR's header; its user id, record id and data length lie at these offsets.
const EVLR_HEADER_BYTES: u64 = 60;
const USER_ID_AT: usize = 2;
const RECORD_ID_AT: usize = 18;
const LENGTH_AT: usize = 20;
/// The most entries read (84 MB of them): a store's node per 20,000 points of 80 billion.
const MAX_ENTRIES: u64 = 1 << 22;
/// The largest grid a node record keeps (`LodHierarchy::encode` stores it in 16 bits).
const MAX_GRID: u32 = u16::MAX as u32;

/// The grids of the node grids EVLR of the file `reader` reads, if it has one; `evlrs` is
/// where its EVLRs start and how many there are, whose extents `ingest::check_file` checked
/// against the file.
pub(crate) fn read_node_grids(
    reader: &mut RangeReader<'_>,
    evlrs: Option<(u64, u32)>,
) -> Result<NodeGrids, CopcError> {
    let path = reader.name();
    let Some((mut offset, count)) = evlrs else {
        return Ok(NodeGrids::new());
    };
    let bad = |reason: String| {
        CopcError::hierarchy(
            &path,
            format!("its node grids (EVLR \"{USER_ID}\" {RECORD_ID}): {reason}"),
        )
    };
    for _ in 0..count {
        let header = reader.read_at(offset, EVLR_HEADER_BYTES)?;
        let mut len = [0u8; 8];
        len.copy_from_slice(&header[LENGTH_AT..LENGTH_AT + 8]);
        let len = u64::from_le_bytes(len);
        let data_at = offset + EVLR_HEADER_BYTES;
        if is_node_grids(&header) {
            if len / ENTRY_BYTES as u64 > MAX_ENTRIES {
                return Err(bad(format!("{len} bytes, more than {MAX_ENTRIES} entries")));
            }
            // Inside the file, as checked (and as the read checks again).
            let data = reader.read_at(data_at, len)?;
            return grids(&data).map_err(bad);
        }
        offset = data_at + len;
    }
    Ok(NodeGrids::new())
}

fn is_node_grids(header: &[u8]) -> bool {
    let user_id = &header[USER_ID_AT..USER_ID_AT + 16];
    let end = user_id.iter().position(|&b| b == 0).unwrap_or(16);
    &user_id[..end] == USER_ID.as_bytes()
        && u16::from_le_bytes([header[RECORD_ID_AT], header[RECORD_ID_AT + 1]]) == RECORD_ID
}

/// The entries of `data`, each key a cell of its level listed once, each grid 1 to
/// [`MAX_GRID`] cells.
fn grids(data: &[u8]) -> Result<NodeGrids, String> {
    let mut grids = NodeGrids::with_capacity(data.len() / ENTRY_BYTES);
    for entry in node_grids::decode(data)? {
        let key = NodeKey::from_voxel_key(entry.key)
            .ok_or_else(|| format!("voxel key {:?} is not a cell of its level", entry.key))?;
        if !(1..=MAX_GRID).contains(&entry.grid) {
            return Err(format!(
                "node {key}'s grid of {} cells is not 1 to {MAX_GRID}",
                entry.grid
            ));
        }
        if grids.insert(key, entry.grid).is_some() {
            return Err(format!("node {key} is listed twice"));
        }
    }
    Ok(grids)
}
