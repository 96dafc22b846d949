//! The node grids a pointfarm export records in an EVLR of its own
//! (`lod::copc_export::node_grids`): each inner node's sampling grid, read and checked when
//! the file is opened, so that a cut of an exported file refines as the store's did. Files
//! without the record refine by the info VLR's spacing.

use std::collections::HashMap;
use std::fs::File;
use std::os::unix::fs::FileExt;
use std::path::Path;

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

/// The grids of `file`'s node grids EVLR, if it has one; `evlrs` is where its EVLRs start and
/// how many there are, whose extents `ingest::check_file` checked against the file.
pub(crate) fn read_node_grids(
    path: &Path,
    file: &File,
    evlrs: Option<(u64, u32)>,
) -> Result<NodeGrids, CopcError> {
    let Some((mut offset, count)) = evlrs else {
        return Ok(NodeGrids::new());
    };
    let bad = |reason: String| {
        CopcError::hierarchy(
            path,
            format!("its node grids (EVLR \"{USER_ID}\" {RECORD_ID}): {reason}"),
        )
    };
    for _ in 0..count {
        let mut header = [0u8; EVLR_HEADER_BYTES as usize];
        file.read_exact_at(&mut header, offset)
            .map_err(|e| CopcError::io(path, e))?;
        let mut len = [0u8; 8];
        len.copy_from_slice(&header[LENGTH_AT..LENGTH_AT + 8]);
        let len = u64::from_le_bytes(len);
        let data_at = offset + EVLR_HEADER_BYTES;
        if is_node_grids(&header) {
            if len / ENTRY_BYTES as u64 > MAX_ENTRIES {
                return Err(bad(format!("{len} bytes, more than {MAX_ENTRIES} entries")));
            }
            // Inside the file, as checked.
            let mut data = vec![0u8; len as usize];
            file.read_exact_at(&mut data, data_at)
                .map_err(|e| CopcError::io(path, e))?;
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
