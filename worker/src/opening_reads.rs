//! The node records a daemon's store's opening fetches, kept for the reads that follow it.
//! Opening reads the coarsest nodes for the framing extent (and, from a daemon that does not
//! send the elevation range, for that range's sample first), and the first frame's cut reads
//! them again: without this, each is a fetch from the daemon, while its cores may be busy
//! building or growing a store. The
//! bytes are the daemon's either way, each checked as it is decoded, so the images do not
//! change. Records are kept only while the store opens, so what is kept is bounded by the
//! opening's sample; the first frame takes them, and what it did not take is dropped after it.
//! They are a store's records, decoded as a store's (a COPC file's chunks are not kept).

use std::collections::HashMap;
use std::sync::{Arc, Mutex};

use pointfarm_render::lod::{LodError, NodeInfo, NodeKey, NodeRecords};

/// Node records read through `inner`, those fetched while the store opens kept for the
/// first frame.
pub struct OpeningReads {
    inner: Arc<dyn NodeRecords>,
    kept: Mutex<Kept>,
}

#[derive(Default)]
struct Kept {
    /// Whether records fetched now are kept (while the store opens).
    keeping: bool,
    /// Whole records by node.
    records: HashMap<NodeKey, Vec<u8>>,
    /// Reads answered from what was kept, for the log.
    served: usize,
}

impl OpeningReads {
    /// Records read through `inner`, kept from now until [`Self::opened`].
    pub fn new(inner: Arc<dyn NodeRecords>) -> Self {
        Self {
            inner,
            kept: Mutex::new(Kept {
                keeping: true,
                ..Kept::default()
            }),
        }
    }

    /// The store is open: records fetched from now on are not kept; a kept one goes to the
    /// first read of it.
    pub fn opened(&self) {
        self.lock().keeping = false;
    }

    /// The first frame is drawn: what it did not take is dropped.
    pub fn forget(&self) {
        let mut kept = self.lock();
        let (left, served) = (kept.records.len(), kept.served);
        kept.records = HashMap::new();
        tracing::debug!(served, left, "node records kept from the store's opening");
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Kept> {
        self.kept.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// `nodes`' records (`coarse`: their coarse sections, the first `head_len` bytes of the
    /// whole ones): the kept ones from memory, the others in one read through `fetch`, in
    /// order. Only whole records read while the store opens are kept.
    fn read(
        &self,
        nodes: &[NodeInfo],
        coarse: bool,
        fetch: impl FnOnce(&[NodeInfo]) -> Result<Vec<Vec<u8>>, LodError>,
    ) -> Result<Vec<Vec<u8>>, LodError> {
        let mut found: Vec<Option<Vec<u8>>> = {
            let mut kept = self.lock();
            let keeping = kept.keeping;
            let found: Vec<Option<Vec<u8>>> = nodes
                .iter()
                .map(|node| {
                    let record = match keeping {
                        true => kept.records.get(&node.key).cloned(),
                        false => kept.records.remove(&node.key),
                    }?;
                    match coarse {
                        true => record.get(..node.head_len as usize).map(<[u8]>::to_vec),
                        false => Some(record),
                    }
                })
                .collect();
            kept.served += found.iter().filter(|record| record.is_some()).count();
            found
        };
        let missing: Vec<NodeInfo> = nodes
            .iter()
            .zip(&found)
            .filter(|(_, record)| record.is_none())
            .map(|(node, _)| *node)
            .collect();
        if missing.is_empty() {
            return Ok(found.into_iter().map(Option::unwrap_or_default).collect());
        }
        let fetched = fetch(&missing)?;
        if fetched.len() != missing.len() {
            return Err(LodError::Records(format!(
                "{} records read for {} nodes",
                fetched.len(),
                missing.len()
            )));
        }
        let mut kept = self.lock();
        let keep = kept.keeping && !coarse;
        let mut fetched = fetched.into_iter();
        for (node, record) in nodes.iter().zip(found.iter_mut()) {
            if record.is_none() {
                let bytes = fetched.next().unwrap_or_default();
                if keep {
                    kept.records.insert(node.key, bytes.clone());
                }
                *record = Some(bytes);
            }
        }
        Ok(found.into_iter().map(Option::unwrap_or_default).collect())
    }
}

impl NodeRecords for OpeningReads {
    fn read_records(&self, nodes: &[NodeInfo]) -> Result<Vec<Vec<u8>>, LodError> {
        self.read(nodes, false, |missing| self.inner.read_records(missing))
    }

    /// Where `inner` reads coarse sections alone; a kept whole record gives its own.
    fn read_coarse_records(&self, nodes: &[NodeInfo]) -> Option<Result<Vec<Vec<u8>>, LodError>> {
        // Asked with no nodes (no fetch) whether the source reads coarse sections at all.
        self.inner.read_coarse_records(&[])?.ok()?;
        Some(self.read(nodes, true, |missing| {
            self.inner
                .read_coarse_records(missing)
                .unwrap_or_else(|| Err(LodError::Records("no coarse sections".into())))
        }))
    }
}

#[cfg(test)]
mod tests {
    use std::sync::atomic::{AtomicUsize, Ordering};

    use pointfarm_render::cut::{LodDataset, StoreBuild, StoredLod};
    use pointfarm_render::ingest::{write_las, LasWriteOptions};
    use pointfarm_render::lod::BuildProgress;

    use super::*;

    /// A store's own records, counting the nodes read through it.
    struct Counted {
        inner: Arc<dyn NodeRecords>,
        read: AtomicUsize,
    }

    impl Counted {
        fn read(&self) -> usize {
            self.read.load(Ordering::SeqCst)
        }
    }

    impl NodeRecords for Counted {
        fn read_records(&self, nodes: &[NodeInfo]) -> Result<Vec<Vec<u8>>, LodError> {
            self.read.fetch_add(nodes.len(), Ordering::SeqCst);
            self.inner.read_records(nodes)
        }

        fn read_coarse_records(
            &self,
            nodes: &[NodeInfo],
        ) -> Option<Result<Vec<Vec<u8>>, LodError>> {
            self.read.fetch_add(nodes.len(), Ordering::SeqCst);
            self.inner.read_coarse_records(nodes)
        }
    }

    /// A store of the sample scene built in `dir`.
    fn store(dir: &std::path::Path) -> StoredLod {
        let path = dir.join("scene.las");
        let scene = pointfarm_render::sample::sample_scene(400_000, 3);
        write_las(&path, &scene, &LasWriteOptions::default()).expect("write");
        let build = StoreBuild {
            folder: &dir.join("lod"),
            memory_budget: 64 << 20,
            disk_budget: None,
            on_build: &mut |_| {},
            progress: &BuildProgress::new(),
        };
        StoredLod::open_or_build_watched(&[path], build).expect("build")
    }

    #[test]
    fn what_the_opening_read_goes_once_to_the_first_frame_and_is_then_forgotten() {
        let dir = tempfile::tempdir().expect("tempdir");
        let lod = store(dir.path());
        let records = Arc::clone(lod.dataset.records());
        let counted = Arc::new(Counted {
            inner: Arc::clone(&records),
            read: AtomicUsize::new(0),
        });
        let opening = Arc::new(OpeningReads::new(counted.clone()));
        let hierarchy = lod.dataset.hierarchy().clone();
        let opened =
            LodDataset::with_records(opening.clone(), hierarchy.clone(), lod.dataset.bounds())
                .expect("opened");
        let at_open = counted.read();
        let nodes: Vec<NodeInfo> = hierarchy.stored_nodes().copied().collect();
        assert!(
            at_open > 1 && at_open == nodes.len(),
            "the opening reads every node of a small store ({at_open} of {})",
            nodes.len()
        );
        // Read again while opening (the framing sample): from memory.
        let again = opening.read_records(&nodes[..1]).expect("read");
        assert_eq!(counted.read(), at_open);
        assert_eq!(again, records.read_records(&nodes[..1]).expect("read"));
        opening.opened();

        // The first frame takes each kept record once, whole or its coarse section, as read.
        let whole = opening.read_records(&nodes[1..]).expect("whole");
        assert_eq!(whole, records.read_records(&nodes[1..]).expect("direct"));
        let coarse = opening
            .read_coarse_records(&nodes[..1])
            .expect("coarse sections");
        assert_eq!(
            coarse.expect("coarse"),
            records
                .read_coarse_records(&nodes[..1])
                .expect("a store reads coarse sections")
                .expect("direct")
        );
        assert_eq!(counted.read(), at_open, "no node fetched again");
        let taken_again = opening.read_records(&nodes[1..2]).expect("again");
        assert_eq!(counted.read(), at_open + 1, "a record is handed out once");
        assert_eq!(taken_again, whole[..1]);
        assert_eq!(opened.point_count(), lod.dataset.point_count());

        // Records fetched after the opening are not kept, and what is left goes with `forget`.
        opening.forget();
        opening.read_records(&nodes[..1]).expect("read");
        opening.read_records(&nodes[..1]).expect("read");
        assert_eq!(counted.read(), at_open + 3);
    }
}
