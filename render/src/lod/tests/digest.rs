//! The store's digest: the same for builds that store the same bytes, another where one
//! node's bytes differ.

use super::*;
use crate::lod::digest::store_digest;
use crate::lod::generated::GeneratedSource;

#[test]
fn the_digest_follows_the_stored_bytes_not_the_order_they_were_written_in() {
    let source = GeneratedSource::terrain(60_000, 5);
    // The thread count sizes the partitions, and with them the regions' kept roots: the
    // same count, the units finished in whatever order.
    let one = build_with(&source, |o| o.threads = Some(3));
    let again = build_with(&source, |o| o.threads = Some(3));
    let digest = store_digest(&one.store).expect("digest");
    assert_eq!(digest, store_digest(&again.store).expect("digest"));
    let mut hierarchy = one.store.read_hierarchy().expect("hierarchy");
    let key = hierarchy.stored_nodes().last().expect("a node").key;
    let mut bytes = one
        .store
        .node_bytes(&hierarchy, key)
        .expect("read")
        .expect("stored");
    let last = bytes.len() - 9;
    bytes[last] ^= 1;
    one.store
        .overwrite_node_bytes(&mut hierarchy, key, &bytes)
        .expect("overwritten");
    assert_ne!(digest, store_digest(&one.store).expect("digest"));
}

/// Prints the digest of each store named in `POINTFARM_STORE_DIGEST` (folders holding
/// `sled/` and `nodes.bin`, as the campaign bench's), to compare the stores that two
/// binaries built.
#[test]
#[ignore = "a tool, not a check: needs stores to read"]
fn print_the_digests_of_stores() {
    let dirs = std::env::var("POINTFARM_STORE_DIGEST").unwrap_or_default();
    for dir in dirs.split(':').filter(|d| !d.is_empty()) {
        let dir = std::path::Path::new(dir);
        let db = sled::open(dir.join("sled")).expect("sled");
        let store = LodStore::open(db.open_tree("lod").expect("tree"), dir.join("nodes.bin"))
            .expect("store");
        let hierarchy = store.read_hierarchy().expect("hierarchy");
        let digest = store_digest(&store).expect("digest");
        println!(
            "{}: {} nodes, {} points, digest {digest:016x}",
            dir.display(),
            hierarchy.nodes().len(),
            hierarchy.point_count
        );
    }
}
