//! The store on disk: payloads addressed by byte range, damage detected, a store reopened,
//! reads from many threads.

use super::{build_with, options, read_all_nodes, Built};
use crate::lod::*;

/// One leaf of 8,000 points (about 176 KB) and a few small nodes.
fn one_big_leaf() -> Built {
    build_with(&GeneratedSource::terrain(8_000, 5), |o| {
        o.max_leaf_points = 10_000
    })
}

fn largest(hierarchy: &LodHierarchy) -> NodeInfo {
    *hierarchy
        .nodes()
        .iter()
        .max_by_key(|n| n.byte_len)
        .expect("a node")
}

#[test]
fn every_node_has_its_own_byte_range_in_the_payload_file() {
    let built = build_with(&GeneratedSource::terrain(40_000, 2), |_| {});
    let hierarchy = &built.report.hierarchy;
    let payload = built.store.payload_bytes().expect("length");
    assert_eq!(payload, built.report.stored_bytes);
    // The partitions' subtree roots, kept for updates, lie beside the nodes.
    let regions = built.store.read_regions().expect("read").expect("regions");
    let roots: Vec<NodeInfo> = regions.regions.iter().filter_map(|r| r.root).collect();
    assert!(!roots.is_empty());
    let root_bytes: u64 = roots.iter().map(NodeInfo::stored_bytes).sum();
    assert_eq!(payload, hierarchy.payload_bytes() + root_bytes);
    let mut ranges: Vec<_> = hierarchy
        .nodes()
        .iter()
        .chain(&roots)
        .flat_map(|n| n.pieces(n.byte_len).chain(Some(n.attributes_range())))
        .filter(|r| !r.is_empty())
        .collect();
    ranges.sort_by_key(|r| r.start);
    assert_eq!(ranges[0].start, 0);
    for pair in ranges.windows(2) {
        assert_eq!(pair[0].end, pair[1].start, "contiguous, never overlapping");
    }
    assert_eq!(ranges.last().expect("a range").end, payload);
    for node in hierarchy.nodes() {
        let bytes = built.store.node_bytes(hierarchy, node.key).expect("read");
        assert_eq!(
            bytes.map_or(0, |b| b.len()),
            node.byte_len as usize,
            "node {}",
            node.key
        );
    }
    let report = &built.report;
    assert!(report.hierarchy_bytes > 0);
    // 24 B a point, plus each node's header and checksum and its entry in the hierarchy
    // (many of them with leaves of 500 points).
    let per_point = report.disk_bytes_per_point();
    let expected = (payload + report.hierarchy_bytes) as f64 / 40_000.0;
    assert_eq!(per_point, expected);
    let nodes_per_point = per_point - root_bytes as f64 / 40_000.0;
    assert!(
        (24.0..34.0).contains(&nodes_per_point),
        "{nodes_per_point} B/point"
    );
    // The kept roots repeat the points sampled from the partitions' children: in partitions
    // this small, nearly every point (docs/perf/lod-store-update.md has a campaign's share).
    assert!(root_bytes * 2 < payload, "{root_bytes} of {payload} bytes");
}

#[test]
fn a_damaged_node_is_detected_by_its_checksum() {
    let built = one_big_leaf();
    let mut hierarchy = built.store.read_hierarchy().expect("hierarchy");
    let node = largest(&hierarchy);
    assert!(node.byte_len > 128 << 10, "{} bytes", node.byte_len);
    let bytes = built
        .store
        .node_bytes(&hierarchy, node.key)
        .expect("read")
        .expect("stored");
    for at in [0, 13, bytes.len() / 2, bytes.len() - 1] {
        let mut damaged = bytes.clone();
        damaged[at] ^= 0x10;
        built
            .store
            .overwrite_node_bytes(&mut hierarchy, node.key, &damaged)
            .expect("write");
        assert_eq!(hierarchy.node(node.key), Some(&node), "damaged in place");
        let error = built
            .store
            .read_node(&hierarchy, node.key)
            .expect_err("damage detected");
        assert!(
            matches!(error, LodError::CorruptNode { key, .. } if key == node.key),
            "{error}"
        );
        assert!(error.to_string().contains("checksum mismatch"), "{error}");
    }
    built
        .store
        .overwrite_node_bytes(&mut hierarchy, node.key, &bytes[..bytes.len() - 9])
        .expect("write");
    assert!(
        built.store.read_node(&hierarchy, node.key).is_err(),
        "a truncated node"
    );
    built
        .store
        .overwrite_node_bytes(&mut hierarchy, node.key, &bytes)
        .expect("write");
    assert!(
        built.store.read_node(&hierarchy, node.key).is_ok(),
        "restored"
    );
    assert_eq!(
        built.store.read_hierarchy().expect("hierarchy"),
        hierarchy,
        "the stored record follows the node's new copy"
    );

    // A range that is the node's, shifted by a byte: the right length, the wrong bytes.
    let mut shifted = hierarchy.clone();
    let moved = *shifted.node(node.key).expect("listed");
    shifted.set_byte_range(node.key, moved.offset - 1, moved.byte_len);
    let error = built
        .store
        .read_node(&shifted, node.key)
        .expect_err("a shifted range");
    assert!(matches!(error, LodError::CorruptNode { .. }), "{error}");

    edit_hierarchy_record(&built.store, |record| {
        let middle = record.len() / 2;
        record[middle] ^= 1;
    });
    assert!(matches!(
        built.store.read_hierarchy(),
        Err(LodError::CorruptHierarchy(_))
    ));
}

#[test]
fn a_truncated_payload_file_gives_corrupt_nodes_naming_them() {
    let built = build_with(&GeneratedSource::terrain(40_000, 4), |_| {});
    let hierarchy = built.store.read_hierarchy().expect("hierarchy");
    let length = built.store.payload_bytes().expect("length");
    let file = std::fs::OpenOptions::new()
        .write(true)
        .open(built.store.payload_path())
        .expect("open");
    file.set_len(length / 2).expect("truncate");
    let (mut whole, mut cut) = (0, 0);
    for node in hierarchy.stored_nodes() {
        match built.store.read_node(&hierarchy, node.key) {
            Ok(points) => {
                let end = node.pieces(node.byte_len).map(|r| r.end).max();
                assert!(end <= Some(length / 2), "node {}", node.key);
                assert_eq!(points.len(), node.point_count as usize);
                whole += 1;
            }
            Err(error) => {
                assert!(
                    matches!(&error, LodError::CorruptNode { key, .. } if *key == node.key),
                    "{error}"
                );
                assert!(error.to_string().contains("past the end"), "{error}");
                cut += 1;
            }
        }
    }
    assert!(whole > 0 && cut > 0, "{whole} whole, {cut} cut");

    // A hostile range is refused before anything is allocated for it.
    let mut hostile = hierarchy.clone();
    let node = largest(&hierarchy);
    for (offset, len) in [(u64::MAX - 10, 100), (0, u32::MAX)] {
        hostile.set_byte_range(node.key, offset, len);
        let error = built
            .store
            .read_node(&hostile, node.key)
            .expect_err("hostile");
        assert!(
            matches!(&error, LodError::CorruptNode { key, .. } if *key == node.key),
            "{error}"
        );
    }
}

#[test]
fn a_store_reopened_from_disk_reads_every_node_equal() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (db_path, payload) = (dir.path().join("db"), dir.path().join("lod.bin"));
    let source = GeneratedSource::terrain(50_000, 8);
    let (report, nodes) = {
        let db = sled::open(&db_path).expect("sled");
        let store = LodStore::open(db.open_tree("lod").expect("tree"), &payload).expect("store");
        let report = build_lod(&source, &store, &options(dir.path(), 500)).expect("build");
        let nodes: Vec<NodePoints> = report
            .hierarchy
            .nodes()
            .iter()
            .map(|n| store.read_node(&report.hierarchy, n.key).expect("node"))
            .collect();
        (report, nodes)
    };
    let db = sled::open(&db_path).expect("sled again");
    let store = LodStore::open(db.open_tree("lod").expect("tree"), &payload).expect("store");
    let hierarchy = store.read_hierarchy().expect("hierarchy");
    assert_eq!(hierarchy, report.hierarchy);
    assert!(nodes.len() > 20, "{} nodes", nodes.len());
    for (info, expected) in hierarchy.nodes().iter().zip(&nodes) {
        let read = store.read_node(&hierarchy, info.key).expect("node");
        assert_eq!(&read, expected, "node {}", info.key);
    }
}

#[test]
fn a_hierarchy_of_the_earlier_layout_is_refused() {
    let built = one_big_leaf();
    for magic in [b"PFH1", b"PFH5"] {
        edit_hierarchy_record(&built.store, |record| {
            record[..4].copy_from_slice(magic);
            let body = record.len() - 8;
            let sum = super::super::checksum::checksum64(b"hierarchy", &record[..body]);
            record[body..].copy_from_slice(&sum.to_le_bytes());
        });
        let error = built.store.read_hierarchy().expect_err("refused");
        assert!(
            matches!(&error, LodError::CorruptHierarchy(reason) if reason.contains("rebuild")),
            "{error}"
        );
    }
}

/// A partition's nodes are stored together, their coarse sections first, shallow levels first
/// (as are the children of each node above the partitions): the coarse sections of the top levels,
/// as a far view's cut takes them, fill a few stretches of the file, where records stored
/// whole, each coarse section followed by its rest, leave a stretch a node.
#[test]
fn the_top_levels_coarse_sections_are_read_in_few_runs() {
    let built = build_with(&GeneratedSource::terrain(200_000, 7), |o| {
        o.max_partition_points = 25_000;
    });
    let hierarchy = &built.report.hierarchy;
    let top: Vec<NodeInfo> = hierarchy
        .stored_nodes()
        .filter(|n| n.key.level <= 4)
        .copied()
        .collect();
    // Stretches of the file the top levels' coarse sections fill without a byte between.
    let mut heads: Vec<_> = top.iter().flat_map(|n| n.pieces(n.head_len)).collect();
    heads.sort_by_key(|r| r.start);
    let stretches = 1 + heads.windows(2).filter(|w| w[0].end != w[1].start).count();
    assert!(
        top.len() >= 4 * stretches,
        "{} nodes in {stretches} stretches",
        top.len()
    );
    for node in &top {
        assert!(node.head_len < node.byte_len, "node {}", node.key);
    }
    // Read together, the pieces come back as each node's record.
    let keys: Vec<NodeKey> = top.iter().map(|n| n.key).collect();
    let read = read_nodes(&built.store, hierarchy, &keys).expect("read");
    for (node, points) in top.iter().zip(&read) {
        assert_eq!(
            points,
            &built.store.read_node(hierarchy, node.key).expect("node")
        );
    }
}

#[test]
fn concurrent_reads_from_many_threads_agree() {
    let built = build_with(&GeneratedSource::terrain(60_000, 6), |_| {});
    let expected = read_all_nodes(&built);
    let hierarchy = built.store.read_hierarchy().expect("hierarchy");
    let keys: Vec<NodeKey> = hierarchy.nodes().iter().map(|n| n.key).collect();
    std::thread::scope(|scope| {
        for t in 0..8 {
            let (store, hierarchy, keys, expected) =
                (built.store.clone(), &hierarchy, &keys, &expected);
            scope.spawn(move || {
                // Each thread walks the nodes from its own starting point, three times over.
                for round in 0..3 * keys.len() {
                    let i = (round + t * keys.len() / 8) % keys.len();
                    let read = store.read_node(hierarchy, keys[i]).expect("node");
                    assert_eq!(read, expected[i], "node {} on thread {t}", keys[i]);
                }
            });
        }
    });
    use rayon::prelude::*;
    let sum: usize = keys
        .par_iter()
        .map(|&key| built.store.read_node(&hierarchy, key).expect("node").len())
        .sum();
    assert_eq!(sum, 60_000);
}

/// Rewrites the stored hierarchy record through `edit`, as damage or an old layout would.
fn edit_hierarchy_record(store: &LodStore, edit: impl FnOnce(&mut Vec<u8>)) {
    let tree = store.tree();
    let mut record = tree
        .get("hierarchy")
        .expect("get")
        .expect("stored")
        .to_vec();
    edit(&mut record);
    tree.insert("hierarchy", record).expect("insert");
}
