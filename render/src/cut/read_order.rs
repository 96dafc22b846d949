//! The order a frame reads the nodes it lacks: the load queue's (the cut's, by priority) a
//! window of records at a time, and within a window by where the records lie, so that nodes
//! stored together (a partition's top levels, `lod/sink.rs`) are read together, in long runs, and
//! not one read a node (docs/perf/payload-layout.md). A frame waits for its whole cut either
//! way; the windows keep the nearest, largest nodes read first.

use std::borrow::Borrow;

use crate::lod::LodHierarchy;

use super::select::CutNode;

/// Bytes of records a window of the load queue holds.
pub(super) const READ_WINDOW_BYTES: u64 = 256 << 20;

/// `nodes` (in the load queue's order) in the order to read them.
pub(super) fn in_read_order<N: Borrow<CutNode>>(
    nodes: impl IntoIterator<Item = N>,
    hierarchy: &LodHierarchy,
) -> Vec<N> {
    let mut window = (0u64, 0u64);
    let mut ordered: Vec<((u64, u64), N)> = nodes
        .into_iter()
        .map(|node| {
            let (offset, len) = hierarchy
                .node(node.borrow().key)
                .map_or((0, 0), |info| (info.offset, u64::from(info.byte_len)));
            let place = (window.0, offset);
            window.1 += len;
            if window.1 >= READ_WINDOW_BYTES {
                window = (window.0 + 1, 0);
            }
            (place, node)
        })
        .collect();
    ordered.sort_by_key(|(place, _)| *place);
    ordered.into_iter().map(|(_, node)| node).collect()
}

#[cfg(test)]
mod tests {
    use glam::DVec3;

    use super::*;
    use crate::lod::{DatasetStats, NodeInfo, NodeKey, RootCube};

    /// The queue is cut into windows of [`READ_WINDOW_BYTES`] in its own order; each window is
    /// read by offset, and no node of a later window comes before one of an earlier window.
    #[test]
    fn each_window_of_the_queue_is_read_in_file_order() {
        let len = 100 << 20;
        let children: Vec<NodeKey> = (0..6).map(|i| NodeKey::ROOT.child(i)).collect();
        let nodes: Vec<NodeInfo> = children
            .iter()
            .enumerate()
            .map(|(i, &key)| {
                let node = NodeInfo {
                    point_count: 1,
                    ..NodeInfo::empty(key)
                };
                node.in_one_piece((5 - i as u64) * u64::from(len), len)
            })
            .collect();
        let cube = RootCube {
            min: DVec3::ZERO,
            side: 1.0,
        };
        let hierarchy = LodHierarchy::assemble(cube, 6, 1, DatasetStats::new(false), nodes.clone());
        let queue: Vec<CutNode> = children
            .iter()
            .map(|&key| CutNode {
                key,
                points: 1,
                priority: 1.0,
            })
            .collect();
        let order: Vec<usize> = in_read_order(&queue, &hierarchy)
            .iter()
            .map(|n| n.key.child_index())
            .collect();
        assert_eq!(order, [2, 1, 0, 5, 4, 3]);
        assert!(in_read_order(Vec::<CutNode>::new(), &hierarchy).is_empty());
    }
}
