//! `LodStore`: a built dataset in a `sled::Tree` the caller owns (so it can live in the dataset
//! cache): one record per node and one for the hierarchy, written last, so a build that did not
//! finish leaves no hierarchy and is never read as complete.

use super::codec::{decode_node, NodePoints};
use super::error::LodError;
use super::hierarchy::LodHierarchy;
use super::key::NodeKey;

const HIERARCHY_KEY: &[u8] = b"hierarchy";
const NODE_PREFIX: u8 = b'n';

#[derive(Debug, Clone)]
pub struct LodStore {
    tree: sled::Tree,
}

fn node_key(key: NodeKey) -> [u8; 14] {
    let mut out = [0; 14];
    out[0] = NODE_PREFIX;
    out[1..].copy_from_slice(&key.to_bytes());
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

    pub(crate) fn write_node(&self, key: NodeKey, bytes: Vec<u8>) -> Result<(), LodError> {
        self.tree.insert(node_key(key), bytes)?;
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

    /// The raw stored bytes of a node (tests and tools that check the store).
    pub fn node_bytes(&self, key: NodeKey) -> Result<Option<sled::IVec>, LodError> {
        Ok(self.tree.get(node_key(key))?)
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
        let bytes = self
            .tree
            .get(node_key(key))?
            .ok_or_else(|| LodError::CorruptNode {
                key,
                reason: "its record is missing".into(),
            })?;
        decode_node(&hierarchy.cube, key, info.point_count, &bytes)
    }

    /// Overwrites a node's stored bytes, to test that damage is detected.
    #[cfg(test)]
    pub(crate) fn overwrite_node_bytes(
        &self,
        key: NodeKey,
        bytes: Vec<u8>,
    ) -> Result<(), LodError> {
        self.write_node(key, bytes)
    }
}
