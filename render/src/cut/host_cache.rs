//! `HostNodeCache`: decoded nodes in host memory, least recently used first out, within a
//! byte bound.
//!
//! A node is held as its decoded columns (`NodePoints`: 12 B of quantised position and the
//! raw attributes a point), shared with whoever is preparing it for the GPU, so an eviction
//! never frees a node in use: it only drops the cache's reference.

use std::collections::{BTreeMap, HashMap};
use std::sync::Arc;

use crate::lod::codec::Detail;
use crate::lod::{NodeKey, NodePoints};

/// The bytes a decoded node holds on the host.
pub fn node_heap_bytes(node: &NodePoints) -> u64 {
    let per_point = 12 + if node.rgb.is_some() { 6 } else { 0 };
    let attributes =
        2 * node.intensity.len() + node.classification.len() + node.return_number.len();
    (node.len() * per_point + attributes + node.weights.len() * 2) as u64 + 128
}

pub struct HostNodeCache {
    capacity_bytes: u64,
    bytes: u64,
    tick: u64,
    nodes: HashMap<NodeKey, (Arc<NodePoints>, u64)>,
    /// Last use → key: the oldest first.
    by_use: BTreeMap<u64, NodeKey>,
}

impl HostNodeCache {
    pub fn new(capacity_bytes: u64) -> Self {
        Self {
            capacity_bytes,
            bytes: 0,
            tick: 0,
            nodes: HashMap::new(),
            by_use: BTreeMap::new(),
        }
    }

    pub fn capacity_bytes(&self) -> u64 {
        self.capacity_bytes
    }

    /// Bytes of the nodes held.
    pub fn bytes(&self) -> u64 {
        self.bytes
    }

    #[cfg(test)]
    pub fn len(&self) -> usize {
        self.nodes.len()
    }

    #[cfg(test)]
    pub fn is_empty(&self) -> bool {
        self.nodes.is_empty()
    }

    /// Whether it holds the node read at `detail` at least.
    pub fn contains(&self, key: NodeKey, detail: Detail) -> bool {
        self.nodes
            .get(&key)
            .is_some_and(|(n, _)| n.detail >= detail)
    }

    /// The node read at `detail` at least, marked as just used.
    pub fn get(&mut self, key: NodeKey, detail: Detail) -> Option<Arc<NodePoints>> {
        let (node, used) = self.nodes.get_mut(&key)?;
        if node.detail < detail {
            return None;
        }
        self.by_use.remove(used);
        self.tick += 1;
        *used = self.tick;
        self.by_use.insert(self.tick, key);
        Some(Arc::clone(node))
    }

    /// Holds `node`, evicting the least recently used ones until it fits. A node larger than
    /// the whole cache is not held.
    pub fn insert(&mut self, node: Arc<NodePoints>) {
        let key = node.key;
        let size = node_heap_bytes(&node);
        self.remove(key);
        if size > self.capacity_bytes {
            return;
        }
        while self.bytes + size > self.capacity_bytes {
            let Some((_, oldest)) = self.by_use.pop_first() else {
                break;
            };
            if let Some((evicted, _)) = self.nodes.remove(&oldest) {
                self.bytes -= node_heap_bytes(&evicted);
            }
        }
        self.tick += 1;
        self.by_use.insert(self.tick, key);
        self.nodes.insert(key, (node, self.tick));
        self.bytes += size;
    }

    fn remove(&mut self, key: NodeKey) {
        if let Some((node, used)) = self.nodes.remove(&key) {
            self.by_use.remove(&used);
            self.bytes -= node_heap_bytes(&node);
        }
    }
}

#[cfg(test)]
mod tests {
    use glam::{DVec3, UVec3};

    use super::*;

    fn node(level: u8, x: u32, points: usize) -> Arc<NodePoints> {
        Arc::new(NodePoints {
            key: NodeKey::new(level, UVec3::new(x, 0, 0)),
            cube_min: DVec3::ZERO,
            step: 1.0,
            quantised: vec![[0; 3]; points],
            rgb: None,
            intensity: vec![0; points],
            classification: vec![0; points],
            return_number: vec![0; points],
            weights: vec![0; points],
            detail: Detail::Full,
        })
    }

    #[test]
    fn the_least_recently_used_node_goes_first_and_the_bound_holds() {
        let one = node_heap_bytes(&node(3, 0, 100));
        let mut cache = HostNodeCache::new(3 * one);
        for x in 0..3 {
            cache.insert(node(3, x, 100));
        }
        assert_eq!(cache.len(), 3);
        // Node 0 used again: node 1 is now the oldest.
        assert!(cache
            .get(NodeKey::new(3, UVec3::new(0, 0, 0)), Detail::Full)
            .is_some());
        cache.insert(node(3, 3, 100));
        assert!(cache.contains(NodeKey::new(3, UVec3::new(0, 0, 0)), Detail::Full));
        assert!(!cache.contains(NodeKey::new(3, UVec3::new(1, 0, 0)), Detail::Coarse));
        assert!(cache.bytes() <= cache.capacity_bytes());
        for x in 4..40 {
            cache.insert(node(3, x, 100));
            assert!(cache.bytes() <= cache.capacity_bytes());
        }
        assert_eq!(cache.len(), 3);
    }

    #[test]
    fn a_node_larger_than_the_cache_is_not_held() {
        let mut cache = HostNodeCache::new(100);
        cache.insert(node(1, 0, 1000));
        assert!(cache.is_empty());
        assert_eq!(cache.bytes(), 0);
    }
}
