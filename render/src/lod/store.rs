//! `LodStore`: a built dataset in a `sled::Tree` the caller owns (so it can live in the dataset
//! cache): one record per node and one for the hierarchy, written last, so a build that did not
//! finish leaves no hierarchy and is never read as complete.

use super::codec::{decode_node, NodePoints};
use super::error::LodError;
use super::hierarchy::LodHierarchy;
use super::key::NodeKey;

const HIERARCHY_KEY: &[u8] = b"hierarchy";
const NODE_PREFIX: u8 = b'n';
/// A node's record is stored in pages of at most this many bytes: sled reads large values
/// through a slow path and rescans them when it opens (docs/perf/dataset-cache.md).
pub const NODE_PAGE_BYTES: usize = 64 << 10;

#[derive(Debug, Clone)]
pub struct LodStore {
    tree: sled::Tree,
}

/// The prefix of a node's pages: the node prefix and its 13-byte key.
fn node_prefix(key: NodeKey) -> [u8; 14] {
    let mut out = [0; 14];
    out[0] = NODE_PREFIX;
    out[1..].copy_from_slice(&key.to_bytes());
    out
}

/// Page `page` of a node: big-endian, so a prefix scan returns the pages in order.
fn page_key(key: NodeKey, page: u16) -> [u8; 16] {
    let mut out = [0; 16];
    out[..14].copy_from_slice(&node_prefix(key));
    out[14..].copy_from_slice(&page.to_be_bytes());
    out
}

impl LodStore {
    /// A store in `tree`, which holds this dataset only.
    pub fn new(tree: sled::Tree) -> Self {
        Self { tree }
    }

    pub fn tree(&self) -> &sled::Tree {
        &self.tree
    }

    /// Removes everything, hierarchy first, so a half-cleared store is never read as built.
    pub(crate) fn clear(&self) -> Result<(), LodError> {
        self.tree.remove(HIERARCHY_KEY)?;
        self.tree.clear()?;
        Ok(())
    }

    /// Writes a node's record in pages; a store is cleared before a build, so no page of an
    /// earlier record is left behind.
    pub(crate) fn write_node(&self, key: NodeKey, bytes: &[u8]) -> Result<(), LodError> {
        for (page, chunk) in bytes.chunks(NODE_PAGE_BYTES).enumerate() {
            let page = u16::try_from(page).map_err(|_| LodError::CorruptNode {
                key,
                reason: format!("{} bytes is more than a node may hold", bytes.len()),
            })?;
            self.tree.insert(page_key(key, page), chunk)?;
        }
        Ok(())
    }

    /// Writes what sled buffers to disk.
    pub(crate) fn flush(&self) -> Result<(), LodError> {
        self.tree.flush()?;
        Ok(())
    }

    pub(crate) fn write_hierarchy(&self, hierarchy: &LodHierarchy) -> Result<(), LodError> {
        self.tree.flush()?;
        self.tree.insert(HIERARCHY_KEY, hierarchy.encode())?;
        self.tree.flush()?;
        Ok(())
    }

    pub fn read_hierarchy(&self) -> Result<LodHierarchy, LodError> {
        let bytes = self
            .tree
            .get(HIERARCHY_KEY)?
            .ok_or(LodError::MissingHierarchy)?;
        LodHierarchy::decode(&bytes)
    }

    /// The raw stored bytes of a node, its pages joined (tests and tools that check the
    /// store); `None` when it has no page.
    pub fn node_bytes(&self, key: NodeKey) -> Result<Option<Vec<u8>>, LodError> {
        let mut bytes = Vec::new();
        let mut pages = 0;
        for page in self.tree.scan_prefix(node_prefix(key)) {
            let (_, value) = page?;
            bytes.extend_from_slice(&value);
            pages += 1;
        }
        Ok((pages > 0).then_some(bytes))
    }

    /// Reads and checks one node of `hierarchy`.
    pub fn read_node(
        &self,
        hierarchy: &LodHierarchy,
        key: NodeKey,
    ) -> Result<NodePoints, LodError> {
        let info = hierarchy.node(key).ok_or(LodError::UnknownNode { key })?;
        if info.point_count == 0 {
            return Ok(NodePoints {
                key,
                cube_min: hierarchy.cube.node_min(key),
                step: hierarchy.cube.side_at(key.level)
                    / f64::from(1u32 << super::codec::POSITION_BITS),
                quantised: Vec::new(),
                rgb: hierarchy.stats.has_rgb.then(Vec::new),
                intensity: Vec::new(),
                classification: Vec::new(),
                return_number: Vec::new(),
            });
        }
        let bytes = self.node_bytes(key)?.ok_or_else(|| LodError::CorruptNode {
            key,
            reason: "its record is missing".into(),
        })?;
        decode_node(&hierarchy.cube, key, info.point_count, &bytes)
    }

    /// Overwrites a node's stored bytes, to test that damage is detected.
    #[cfg(test)]
    pub(crate) fn overwrite_node_bytes(&self, key: NodeKey, bytes: &[u8]) -> Result<(), LodError> {
        for page in self.tree.scan_prefix(node_prefix(key)).keys() {
            self.tree.remove(page?)?;
        }
        self.write_node(key, bytes)
    }
}
