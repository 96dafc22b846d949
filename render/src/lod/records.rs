//! `NodeRecords`: where a store's node records are read from — its payload file here, or a
//! daemon that keeps the store — and the one way records become checked [`NodePoints`].

use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};

use rayon::prelude::*;

use super::codec::{decode_node, Detail, NodePoints, POSITION_BITS};
use super::error::LodError;
use super::hierarchy::{LodHierarchy, NodeInfo};
use super::key::{NodeKey, RootCube};

/// A source of stored node records, as the hierarchy lists them (byte ranges of one payload).
/// A record is checked when decoded, wherever it came from.
pub trait NodeRecords: Send + Sync {
    /// The stored bytes of each of `nodes`, in order; each listed with points.
    fn read_records(&self, nodes: &[NodeInfo]) -> Result<Vec<Vec<u8>>, LodError>;

    /// The coarse sections of `nodes`' records (their heads), in order, where this source
    /// reads parts of records; `None` where it reads them whole.
    fn read_coarse_records(&self, _nodes: &[NodeInfo]) -> Option<Result<Vec<Vec<u8>>, LodError>> {
        None
    }

    /// The attributes sections of `nodes` (`attributes.rs`), in order, checked, as rows;
    /// `None` where this source does not keep them (a COPC file, the daemon's records).
    fn read_attribute_rows(
        &self,
        _hierarchy: &LodHierarchy,
        _nodes: &[NodeInfo],
    ) -> Option<Result<Vec<Vec<u8>>, LodError>> {
        None
    }

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
    read_nodes_at(records, hierarchy, keys, Detail::Full)
}

/// [`read_nodes`] at `detail`: the coarse sections alone where `detail` is coarse and the
/// source reads parts of records, else whole records (their nodes then at [`Detail::Full`]).
pub fn read_nodes_at(
    records: &dyn NodeRecords,
    hierarchy: &LodHierarchy,
    keys: &[NodeKey],
    detail: Detail,
) -> Result<Vec<NodePoints>, LodError> {
    fetch_nodes_at(records, hierarchy, keys, detail)?.decode(records, hierarchy)
}

/// The records of some nodes as read, not yet decoded: what a reader hands to the thread that
/// decodes them, so the next read overlaps this decoding.
pub struct FetchedNodes {
    /// Every node asked for, in order.
    infos: Vec<NodeInfo>,
    /// The bytes of each node with points, in order.
    bytes: Vec<Vec<u8>>,
}

/// The first half of [`read_nodes_at`]: reads the records of `keys` (one request for all of
/// them), leaving the decoding to [`FetchedNodes::decode`].
pub fn fetch_nodes_at(
    records: &dyn NodeRecords,
    hierarchy: &LodHierarchy,
    keys: &[NodeKey],
    detail: Detail,
) -> Result<FetchedNodes, LodError> {
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
    let coarse = match detail {
        Detail::Coarse if !stored.is_empty() => records.read_coarse_records(&stored),
        _ => None,
    };
    let bytes = match coarse {
        Some(read) => read?,
        None if stored.is_empty() => Vec::new(),
        None => records.read_records(&stored)?,
    };
    if bytes.len() != stored.len() {
        return Err(LodError::Records(format!(
            "{} records for {} nodes",
            bytes.len(),
            stored.len()
        )));
    }
    Ok(FetchedNodes { infos, bytes })
}

impl FetchedNodes {
    /// The bytes of the records read.
    pub fn bytes_read(&self) -> u64 {
        self.bytes.iter().map(|b| b.len() as u64).sum()
    }

    /// The nodes' points, checked, decoded on all cores, in the order they were asked for.
    pub fn decode(
        self,
        records: &dyn NodeRecords,
        hierarchy: &LodHierarchy,
    ) -> Result<Vec<NodePoints>, LodError> {
        let stored: Vec<&NodeInfo> = self.infos.iter().filter(|i| i.point_count > 0).collect();
        let decoded: Vec<NodePoints> = stored
            .par_iter()
            .zip(self.bytes.par_iter())
            .map(|(info, bytes)| records.decode(&hierarchy.cube, info, bytes))
            .collect::<Result<_, _>>()?;
        let mut decoded = decoded.into_iter();
        Ok(self
            .infos
            .iter()
            .map(|info| match info.point_count {
                0 => empty_node(hierarchy, info.key),
                _ => decoded.next().expect("one record per stored node"),
            })
            .collect())
    }
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
        detail: Detail::Full,
    }
}

/// Positioned reads in flight at once. A read waits on the disk, not on a core, and a disk
/// answers several requests at once, so a cold cut reads with more threads than cores
/// (docs/perf/cold-first-frame.md).
pub const READS_IN_FLIGHT: usize = 8;

/// `read` of each of `items`, in order, with up to [`READS_IN_FLIGHT`] reads at once; the
/// first failure (in `items`' order among those read) stops the others taking more.
pub fn read_concurrently<T: Sync, R: Send, E: Send>(
    items: &[T],
    read: impl Fn(&T) -> Result<R, E> + Sync,
) -> Result<Vec<R>, E> {
    let threads = items.len().min(READS_IN_FLIGHT);
    if threads <= 1 {
        return items.iter().map(read).collect();
    }
    let next = AtomicUsize::new(0);
    let failed = AtomicBool::new(false);
    let mut done: Vec<(usize, Result<R, E>)> = std::thread::scope(|scope| {
        let workers: Vec<_> = (0..threads)
            .map(|_| {
                scope.spawn(|| {
                    let mut done = Vec::new();
                    while !failed.load(Ordering::Relaxed) {
                        let i = next.fetch_add(1, Ordering::Relaxed);
                        let Some(item) = items.get(i) else { break };
                        let result = read(item);
                        if result.is_err() {
                            failed.store(true, Ordering::Relaxed);
                        }
                        done.push((i, result));
                    }
                    done
                })
            })
            .collect();
        workers
            .into_iter()
            .flat_map(|worker| match worker.join() {
                Ok(done) => done,
                Err(panic) => std::panic::resume_unwind(panic),
            })
            .collect()
    });
    done.sort_unstable_by_key(|(i, _)| *i);
    done.into_iter().map(|(_, result)| result).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Many more items than reads in flight come back in order, and a failure is the first
    /// failing item's, however the threads interleave.
    #[test]
    fn concurrent_reads_keep_the_order_and_report_the_first_failure() {
        let items: Vec<u32> = (0..1_000).collect();
        let read = |&i: &u32| -> Result<Vec<u8>, String> { Ok(i.to_le_bytes().to_vec()) };
        let bytes = read_concurrently(&items, read).expect("read");
        let back: Vec<u32> = bytes
            .iter()
            .map(|b| u32::from_le_bytes(b[..4].try_into().expect("4 bytes")))
            .collect();
        assert_eq!(back, items);

        let failing = |&i: &u32| -> Result<Vec<u8>, String> {
            if i % 100 == 37 {
                Err(format!("item {i}"))
            } else {
                Ok(vec![0; 16])
            }
        };
        for _ in 0..20 {
            assert_eq!(read_concurrently(&items, failing), Err("item 37".into()));
        }
        assert_eq!(read_concurrently(&items[..1], read), Ok(vec![vec![0; 4]]));
        assert_eq!(read_concurrently(&items[..0], read), Ok(Vec::new()));
    }
}
