//! A node's points as LAS 1.4 point records: PDRF 6 (30 bytes), or 7 (36 bytes) with RGB,
//! and each point's weight after them as an extra bytes attribute (4 bytes,
//! [`WEIGHT_ATTRIBUTE`]), in the store's order.
//!
//! The weight is how many original points the point stands for where its node is drawn
//! without the child below it (`lod/weights.rs`), so that high quality on a cut of the file
//! averages what full detail would; other readers ignore it. A node without weights (one
//! read from a COPC file without them) writes 1.
//!
//! The order matters for size, not for COPC. The store keeps a node's points in the order its
//! build met them, which keeps runs of the files' scan order; LAZ predicts each point from
//! the one before, and on the real scans that order compresses better than a Morton order of
//! the node's points (autzen: 1.40x the plain LAZ against 1.48x).
//!
//! The store keeps position, RGB, intensity, classification and return number; the other
//! fields are written as LAS's "unknown": number of returns equal to the return number (the
//! store does not keep it, and LAS wants it no smaller), scan angle, user data, point source
//! and GPS time 0.

use glam::DVec3;

use super::transform::ExportTransform;
use crate::lod::weights::{decode_weight, WEIGHT_ATTRIBUTE};
use crate::lod::NodePoints;

/// Bytes of a PDRF 6 record.
pub const PDRF6_BYTES: usize = 30;
/// Bytes of a PDRF 7 record (PDRF 6 and three 16-bit colour channels).
pub const PDRF7_BYTES: usize = 36;
/// Bytes of the weight after a record's fields.
pub const WEIGHT_BYTES: usize = 4;
/// What the extra bytes VLR says of the weight.
pub const WEIGHT_DESCRIPTION: &str = "original points it stands for";

/// The point data record format of an export with or without colour.
pub fn point_format(has_rgb: bool) -> u8 {
    if has_rgb {
        7
    } else {
        6
    }
}

/// Bytes of a record: the point format's fields, then the weight.
pub fn record_len(has_rgb: bool) -> usize {
    fields_len(has_rgb) + WEIGHT_BYTES
}

fn fields_len(has_rgb: bool) -> usize {
    if has_rgb {
        PDRF7_BYTES
    } else {
        PDRF6_BYTES
    }
}

/// The extra bytes VLR's data: the weight's descriptor.
pub fn extra_bytes_vlr() -> Vec<u8> {
    crate::extra_bytes::descriptor(
        WEIGHT_ATTRIBUTE,
        crate::extra_bytes::DATA_TYPE_U32,
        WEIGHT_DESCRIPTION,
    )
    .to_vec()
}

/// A node's records and what the header needs of them.
pub struct NodeRecordBytes {
    pub bytes: Vec<u8>,
    pub count: u64,
    /// Lowest and highest written position (after rounding to the scale).
    pub min: DVec3,
    pub max: DVec3,
    /// Points by return number 1 to 15 (index 0 is return 1).
    pub by_return: [u64; 15],
}

/// The records of `node`'s points under `transform`, coloured when `has_rgb` (a node without
/// stored colour is written black).
pub fn node_records(
    node: &NodePoints,
    transform: &ExportTransform,
    has_rgb: bool,
) -> NodeRecordBytes {
    let n = node.len();
    let len = record_len(has_rgb);
    let weight_at = fields_len(has_rgb);
    let mut bytes = vec![0u8; n * len];
    let mut low = [i32::MAX; 3];
    let mut high = [i32::MIN; 3];
    let mut by_return = [0u64; 15];
    for (i, (record, q)) in bytes.chunks_exact_mut(len).zip(&node.quantised).enumerate() {
        let world = node.cube_min + (DVec3::from(q.map(f64::from)) + 0.5) * node.step;
        let xyz = transform.to_integer(world);
        for axis in 0..3 {
            low[axis] = low[axis].min(xyz[axis]);
            high[axis] = high[axis].max(xyz[axis]);
            record[axis * 4..axis * 4 + 4].copy_from_slice(&xyz[axis].to_le_bytes());
        }
        record[12..14].copy_from_slice(&node.intensity[i].to_le_bytes());
        let returns = node.return_number[i] & 15;
        record[14] = returns | (returns << 4);
        if (1..=15).contains(&returns) {
            by_return[usize::from(returns) - 1] += 1;
        }
        record[16] = node.classification[i];
        if has_rgb {
            let rgb = node.rgb.as_ref().map_or([0; 3], |c| c[i]);
            for (c, value) in rgb.iter().enumerate() {
                record[30 + 2 * c..32 + 2 * c].copy_from_slice(&value.to_le_bytes());
            }
        }
        let weight = node.weights.get(i).map_or(1, |&code| decode_weight(code));
        record[weight_at..weight_at + WEIGHT_BYTES].copy_from_slice(&weight.to_le_bytes());
    }
    NodeRecordBytes {
        bytes,
        count: n as u64,
        min: transform.to_world(low),
        max: transform.to_world(high),
        by_return,
    }
}
