//! A digest of what a store holds, whatever order its units were written in: each node the
//! hierarchy lists (its key, count and sampling grid, its record and its attributes' rows)
//! and each region's kept subtree root, in key order. Two stores with the same digest hold
//! the same nodes byte for byte (up to a 64-bit checksum's collisions): what a change of the
//! builder's internals that must keep the store is checked against, across binaries.

use super::checksum::checksum64;
use super::error::LodError;
use super::hierarchy::NodeInfo;
use super::store::LodStore;

/// The digest of `store`'s nodes and its regions' kept roots.
pub fn store_digest(store: &LodStore) -> Result<u64, LodError> {
    let hierarchy = store.read_hierarchy()?;
    let row_bytes = hierarchy.attributes().map_or(0, |a| a.row_bytes());
    let mut digest = checksum64(b"store digest", &hierarchy.point_count.to_le_bytes());
    let mut add = |info: &NodeInfo| -> Result<(), LodError> {
        let mut head = info.key.to_bytes().to_vec();
        head.extend_from_slice(&info.point_count.to_le_bytes());
        head.extend_from_slice(&info.sample_grid.to_le_bytes());
        digest = checksum64(&digest.to_le_bytes(), &head);
        if info.point_count == 0 {
            return Ok(());
        }
        digest = checksum64(&digest.to_le_bytes(), &store.read_range(info)?);
        if row_bytes > 0 {
            let rows = store.read_attribute_sections(row_bytes, std::slice::from_ref(info))?;
            digest = checksum64(&digest.to_le_bytes(), &rows[0]);
        }
        Ok(())
    };
    let mut nodes: Vec<NodeInfo> = hierarchy.nodes().to_vec();
    nodes.sort_unstable_by_key(|n| (n.key.level, n.key.morton()));
    nodes.iter().try_for_each(&mut add)?;
    let regions = store.read_regions()?.map(|r| r.regions).unwrap_or_default();
    let mut roots: Vec<NodeInfo> = regions.iter().filter_map(|r| r.root).collect();
    roots.sort_unstable_by_key(|n| (n.key.level, n.key.morton()));
    roots.iter().try_for_each(&mut add)?;
    Ok(digest)
}
