//! What a level-of-detail store holds, compared between two builds of a campaign: the count
//! and an order-free checksum of every point (its position on the millimetre grid and its
//! attributes), so that a store built another way is checked to hold every point once.

use pointfarm_render::lod::{read_nodes, LodHierarchy, NodeKey, NodeRecords};

/// The count and an order-free checksum of every point the store's nodes hold.
pub fn points_checksum(
    records: &dyn NodeRecords,
    hierarchy: &LodHierarchy,
) -> Result<(u64, u64), String> {
    let keys: Vec<NodeKey> = hierarchy.stored_nodes().map(|n| n.key).collect();
    let (mut count, mut sum) = (0u64, 0u64);
    for chunk in keys.chunks(512) {
        for node in read_nodes(records, hierarchy, chunk).map_err(|e| e.to_string())? {
            let rgb = node.rgb.clone().unwrap_or_else(|| vec![[0; 3]; node.len()]);
            for (i, p) in node.world_positions().into_iter().enumerate() {
                let mm = (p * 1000.0).round();
                let text = format!(
                    "{} {} {} {:?} {} {} {}",
                    mm.x,
                    mm.y,
                    mm.z,
                    rgb[i],
                    node.intensity[i],
                    node.classification[i],
                    node.return_number[i]
                );
                sum = sum.wrapping_add(fnv(text.as_bytes()));
                count += 1;
            }
        }
    }
    Ok((count, sum))
}

fn fnv(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325, |h, &b| {
        (h ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3)
    })
}
