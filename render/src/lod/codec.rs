//! A node's stored bytes: quantised positions, the raw attributes, a checksum per section.
//!
//! Positions are 30 bits per axis relative to the node's cube, stored as three streams of one
//! 4-byte word per point (after Schütz et al. 2022): the first holds the top 10 bits of x, y
//! and z, the second the next 10, the third the last 10. The first two streams, the colors and
//! the weights come first, with a checksum of their own: what a frame draws of a node that
//! spans at most [`COARSE_MAX_PIXELS`], read alone ([`Detail::Coarse`], 16 of the 24 bytes a
//! point with RGB). Layout, little-endian:
//!
//! ```text
//! "PFN3" | count u32 | flags u8 (bit 0: RGB) | 3 zero bytes
//! stream 0, 1 (count x u32 each) | RGB (count x 3 x u16, if flagged)
//! weight codes (count x u16)
//! checksum u64 of the key and everything before it          (the coarse section ends here)
//! stream 2 (count x u32) | intensity (count x u16) | classification (count x u8)
//! return number (count x u8)
//! checksum u64 of the key and everything before it
//! ```

use glam::{DVec3, Vec3};

use super::checksum::checksum64;
use super::error::LodError;
use super::key::{NodeKey, RootCube};
use super::point::RawPoint;
use super::weights::encode_weight;

const MAGIC: &[u8; 4] = b"PFN3";
const HEADER_BYTES: usize = 12;
const FLAG_RGB: u8 = 1;
/// Bits per axis of a stored position, relative to the node's cube.
pub const POSITION_BITS: u32 = 30;
/// Bits per axis in each of the three position streams.
pub const STREAM_BITS: u32 = 10;
/// Bytes of a point in one position stream.
const STREAM_BYTES: usize = 4;

/// How much of a node a read takes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Detail {
    /// Positions to 20 bits a side of the node's cube, colors and weights: a node a frame
    /// draws at most [`COARSE_MAX_PIXELS`] wide, in RGB or elevation colors.
    Coarse,
    /// Everything.
    Full,
}

/// The widest a node may be on screen, in pixels, for its 20-bit positions: a step of its
/// cube's side over 2^20 is then at most a thousandth of a pixel, in depth as across. Ten bits
/// (an eighth of a pixel at 128 pixels) were too few: eye-dome lighting and Pintus shading
/// drew the depth steps (docs/perf/coarse-reads.md).
pub const COARSE_MAX_PIXELS: f64 = 1024.0;

/// Bits below the coarse section's 20 a side.
const FINE_BITS: u32 = STREAM_BITS;

/// The bytes of a node's coarse section, its checksum included.
pub fn coarse_len(count: usize, has_rgb: bool) -> usize {
    HEADER_BYTES + count * (2 * STREAM_BYTES + if has_rgb { 6 } else { 0 } + 2) + 8
}

/// The bytes a node of `count` points takes.
pub fn encoded_len(count: usize, has_rgb: bool) -> usize {
    coarse_len(count, has_rgb) + count * (STREAM_BYTES + 2 + 1 + 1) + 8
}

/// `q` at the coarse section's precision: its top 20 bits a side, at the centre of their
/// step, so that a node drawn coarse is the same whether read whole or not.
pub fn coarse_position(q: [u32; 3]) -> [u32; 3] {
    q.map(|c| (c >> FINE_BITS << FINE_BITS) | (1 << (FINE_BITS - 1)))
}

/// The 30-bit coordinates of `p` in `key`'s cube, from the one cell formula at level + 30.
fn quantise(cube: &RootCube, key: NodeKey, p: DVec3) -> [u32; 3] {
    let scale = (1u64 << (u32::from(key.level) + POSITION_BITS)) as f64 / cube.side;
    // Truncation is the floor here: only values below zero differ, and they clamp to 0.
    let scaled = (p - cube.min) * scale;
    let max = (1i64 << POSITION_BITS) - 1;
    let cell = key.cell().to_array();
    let s = scaled.to_array();
    std::array::from_fn(|a| {
        ((s[a] as i64) - (i64::from(cell[a]) << POSITION_BITS)).clamp(0, max) as u32
    })
}

pub fn encode_node(cube: &RootCube, key: NodeKey, points: &[RawPoint], has_rgb: bool) -> Vec<u8> {
    let n = points.len();
    let mut out = Vec::with_capacity(encoded_len(n, has_rgb));
    out.extend_from_slice(MAGIC);
    out.extend_from_slice(&(n as u32).to_le_bytes());
    out.push(if has_rgb { FLAG_RGB } else { 0 });
    out.extend_from_slice(&[0; 3]);
    let quantised: Vec<[u32; 3]> = points
        .iter()
        .map(|p| quantise(cube, key, p.position))
        .collect();
    let mask = (1u32 << STREAM_BITS) - 1;
    let stream = |out: &mut Vec<u8>, stream: u32| {
        let shift = POSITION_BITS - STREAM_BITS * (stream + 1);
        for q in &quantised {
            let word = ((q[0] >> shift) & mask)
                | (((q[1] >> shift) & mask) << STREAM_BITS)
                | (((q[2] >> shift) & mask) << (2 * STREAM_BITS));
            out.extend_from_slice(&word.to_le_bytes());
        }
    };
    let checksum = |out: &mut Vec<u8>| {
        let sum = checksum64(&key.to_bytes(), out);
        out.extend_from_slice(&sum.to_le_bytes());
    };
    stream(&mut out, 0);
    stream(&mut out, 1);
    if has_rgb {
        for p in points {
            for c in p.rgb {
                out.extend_from_slice(&c.to_le_bytes());
            }
        }
    }
    for p in points {
        out.extend_from_slice(&encode_weight(p.weight).to_le_bytes());
    }
    checksum(&mut out);
    stream(&mut out, 2);
    for p in points {
        out.extend_from_slice(&p.intensity.to_le_bytes());
    }
    out.extend(points.iter().map(|p| p.classification));
    out.extend(points.iter().map(|p| p.return_number));
    checksum(&mut out);
    out
}

/// A node read back: its points' quantised positions and raw attributes.
#[derive(Debug, Clone, PartialEq)]
pub struct NodePoints {
    pub key: NodeKey,
    /// The corner of the node's cube, in world coordinates.
    pub cube_min: DVec3,
    /// World units per step of the 30-bit coordinates.
    pub step: f64,
    /// 30-bit coordinates per axis in the node's cube.
    pub quantised: Vec<[u32; 3]>,
    pub rgb: Option<Vec<[u16; 3]>>,
    pub intensity: Vec<u16>,
    pub classification: Vec<u8>,
    pub return_number: Vec<u8>,
    /// Each point's weight code (`weights.rs`); empty where the points carry none (a COPC
    /// file's), which counts as 1 each.
    pub weights: Vec<u16>,
    /// What was read: coarse positions (their top 20 bits, at the centre of their step) and
    /// no intensity, classification or return number, or everything.
    pub detail: Detail,
}

impl NodePoints {
    pub fn len(&self) -> usize {
        self.quantised.len()
    }

    pub fn is_empty(&self) -> bool {
        self.quantised.is_empty()
    }

    /// The centre of each point's quantisation step, in world coordinates (within half a step,
    /// [`NodePoints::step`], of the original per axis).
    pub fn world_positions(&self) -> Vec<DVec3> {
        self.quantised
            .iter()
            .map(|q| self.cube_min + (DVec3::from(q.map(f64::from)) + 0.5) * self.step)
            .collect()
    }

    /// The node as a coarse read gives it: positions to the coarse section's precision
    /// ([`coarse_position`]), no intensity, classification or return number.
    pub fn coarsened(&self) -> NodePoints {
        NodePoints {
            key: self.key,
            cube_min: self.cube_min,
            step: self.step,
            quantised: self.quantised.iter().map(|&q| coarse_position(q)).collect(),
            rgb: self.rgb.clone(),
            intensity: Vec::new(),
            classification: Vec::new(),
            return_number: Vec::new(),
            weights: self.weights.clone(),
            detail: Detail::Coarse,
        }
    }

    /// Positions relative to `origin`, computed in f64 and only then rounded to f32.
    pub fn positions_relative_to(&self, origin: DVec3) -> Vec<Vec3> {
        self.positions_at(origin, 0..self.len() as u32)
    }

    /// The positions of the points at `indices`, in that order, relative to `origin` (computed
    /// in f64 and only then rounded to f32).
    pub fn positions_at(&self, origin: DVec3, indices: impl Iterator<Item = u32>) -> Vec<Vec3> {
        let corner = self.cube_min - origin;
        indices
            .map(|i| {
                let q = self.quantised[i as usize];
                (corner + (DVec3::from(q.map(f64::from)) + 0.5) * self.step).as_vec3()
            })
            .collect()
    }
}

fn corrupt(key: NodeKey, reason: impl Into<String>) -> LodError {
    LodError::CorruptNode {
        key,
        reason: reason.into(),
    }
}

/// Checks a node's stored bytes, its coarse section (`bytes` of [`coarse_len`]) or all of it,
/// as [`decode_node`] does (each section's checksum, the layout, `expected` points) without
/// decoding them: what a daemon checks of the records it serves.
pub fn check_node(key: NodeKey, expected: u32, bytes: &[u8]) -> Result<(), LodError> {
    checked_layout(key, expected, bytes).map(drop)
}

/// The detail, point count and RGB flag of a node's stored bytes, once each section's
/// checksum, the layout and the `expected` points are checked.
fn checked_layout(
    key: NodeKey,
    expected: u32,
    bytes: &[u8],
) -> Result<(Detail, usize, bool), LodError> {
    if bytes.len() < HEADER_BYTES + 8 {
        return Err(corrupt(
            key,
            format!("{} bytes is shorter than a node's header", bytes.len()),
        ));
    }
    if &bytes[..4] != MAGIC {
        // The checksum below tells damage from another format where the magic is intact.
        check_sum(key, bytes, bytes.len())?;
        return Err(corrupt(key, "not a node record"));
    }
    let count = u32::from_le_bytes([bytes[4], bytes[5], bytes[6], bytes[7]]);
    let has_rgb = bytes[8] & FLAG_RGB != 0;
    let n = count as usize;
    let (coarse, full) = (coarse_len(n, has_rgb), encoded_len(n, has_rgb));
    let detail = match bytes.len() {
        len if len == full => Detail::Full,
        len if len == coarse => Detail::Coarse,
        len => {
            // A damaged count or flag: the checksum names it as damage.
            check_sum(key, bytes, len)?;
            return Err(corrupt(
                key,
                format!("{len} bytes, {full} (or {coarse} read coarse) expected for {n} points"),
            ));
        }
    };
    check_sum(key, bytes, coarse)?;
    if detail == Detail::Full {
        check_sum(key, bytes, full)?;
    }
    if count != expected {
        return Err(corrupt(
            key,
            format!("holds {count} points, the hierarchy says {expected}"),
        ));
    }
    Ok((detail, n, has_rgb))
}

/// Decodes a node, its coarse section (`bytes` of [`coarse_len`]) or all of it, checking each
/// section's checksum, its layout and that it holds `expected` points.
pub fn decode_node(
    cube: &RootCube,
    key: NodeKey,
    expected: u32,
    bytes: &[u8],
) -> Result<NodePoints, LodError> {
    let (detail, n, has_rgb) = checked_layout(key, expected, bytes)?;
    let mut at = HEADER_BYTES;
    let mut take = |len: usize| {
        let slice = &bytes[at..at + len];
        at += len;
        slice
    };
    let words = |slice: &[u8]| -> Vec<u32> {
        slice
            .chunks_exact(4)
            .map(|w| u32::from_le_bytes([w[0], w[1], w[2], w[3]]))
            .collect()
    };
    let halves = |slice: &[u8]| -> Vec<u16> {
        slice
            .chunks_exact(2)
            .map(|h| u16::from_le_bytes([h[0], h[1]]))
            .collect()
    };
    let (first, second) = (words(take(4 * n)), words(take(4 * n)));
    let rgb = has_rgb.then(|| {
        halves(take(6 * n))
            .chunks_exact(3)
            .map(|c| [c[0], c[1], c[2]])
            .collect()
    });
    let weights = halves(take(2 * n));
    take(8);
    let mask = (1u32 << STREAM_BITS) - 1;
    let part =
        |stream: &[u32], i: usize, axis: usize| (stream[i] >> (axis as u32 * STREAM_BITS)) & mask;
    let (quantised, intensity, classification, return_number) = match detail {
        Detail::Coarse => {
            let quantised = (0..n)
                .map(|i| {
                    coarse_position(std::array::from_fn(|axis| {
                        (part(&first, i, axis) << (2 * STREAM_BITS))
                            | (part(&second, i, axis) << STREAM_BITS)
                    }))
                })
                .collect();
            (quantised, Vec::new(), Vec::new(), Vec::new())
        }
        Detail::Full => {
            let third = words(take(4 * n));
            let quantised = (0..n)
                .map(|i| {
                    std::array::from_fn(|axis| {
                        (part(&first, i, axis) << (2 * STREAM_BITS))
                            | (part(&second, i, axis) << STREAM_BITS)
                            | part(&third, i, axis)
                    })
                })
                .collect();
            let intensity = halves(take(2 * n));
            let classification = take(n).to_vec();
            let return_number = take(n).to_vec();
            (quantised, intensity, classification, return_number)
        }
    };
    Ok(NodePoints {
        key,
        cube_min: cube.node_min(key),
        step: cube.side_at(key.level) / f64::from(1u32 << POSITION_BITS),
        quantised,
        rgb,
        intensity,
        classification,
        return_number,
        weights,
        detail,
    })
}

/// Checks the checksum in the 8 bytes before `end` against the key and the bytes before it.
fn check_sum(key: NodeKey, bytes: &[u8], end: usize) -> Result<(), LodError> {
    let (body, sum) = bytes[..end].split_at(end - 8);
    let stored = u64::from_le_bytes(sum.try_into().expect("8 bytes"));
    let computed = checksum64(&key.to_bytes(), body);
    if stored != computed {
        return Err(corrupt(
            key,
            format!("checksum mismatch (stored {stored:016x}, computed {computed:016x})"),
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cube() -> RootCube {
        RootCube {
            min: DVec3::new(515_000.0, 4_918_000.0, 100.0),
            side: 1000.0,
        }
    }

    #[test]
    fn nodes_round_trip_within_half_a_step() {
        let cube = cube();
        let key = NodeKey::new(3, glam::UVec3::new(2, 5, 0));
        let min = cube.node_min(key);
        let side = cube.side_at(3);
        let points: Vec<RawPoint> = (0..500)
            .map(|i| RawPoint {
                position: min
                    + DVec3::new(i as f64 / 500.0, (i * 7 % 500) as f64 / 500.0, 1.0) * side,
                rgb: [i as u16, 2, 3],
                intensity: i as u16 * 3,
                classification: (i % 7) as u8,
                return_number: (i % 3) as u8,
                weight: i as u32 * 40,
                row: 0,
            })
            .collect();
        let bytes = encode_node(&cube, key, &points, true);
        assert_eq!(bytes.len(), encoded_len(points.len(), true));
        let node = decode_node(&cube, key, 500, &bytes).expect("decodes");
        for (p, q) in points.iter().zip(node.world_positions()) {
            assert!((p.position - q).abs().max_element() <= node.step * 0.5 + 1e-9);
        }
        assert_eq!(node.intensity[7], 21);
        assert_eq!(node.rgb.as_ref().map(|c| c[9]), Some([9, 2, 3]));
        assert_eq!(super::super::weights::decode_weight(node.weights[7]), 280);
        assert!(decode_node(&cube, key, 499, &bytes).is_err());
        assert!(
            decode_node(&cube, key.child(0), 500, &bytes).is_err(),
            "another key's node"
        );
        assert_eq!(node.detail, Detail::Full);

        // The coarse section alone: the same colors and weights, positions to 20 bits at the
        // centre of their step, no other attributes.
        let coarse_bytes = &bytes[..coarse_len(points.len(), true)];
        let coarse = decode_node(&cube, key, 500, coarse_bytes).expect("decodes coarse");
        assert_eq!(coarse.detail, Detail::Coarse);
        assert_eq!((&coarse.rgb, &coarse.weights), (&node.rgb, &node.weights));
        assert!(coarse.intensity.is_empty() && coarse.classification.is_empty());
        let whole: Vec<[u32; 3]> = node.quantised.iter().map(|&q| coarse_position(q)).collect();
        assert_eq!(coarse.quantised, whole);
        let step = side / f64::from(1u32 << 20);
        for (p, q) in points.iter().zip(coarse.world_positions()) {
            assert!((p.position - q).abs().max_element() <= step * 0.5 + node.step);
        }
    }

    /// Each section's checksum finds damage in it: the coarse section's when it is read alone,
    /// the record's when the rest is; damage past the coarse section does not fail a coarse read.
    #[test]
    fn each_section_finds_its_damage() {
        let cube = cube();
        let key = NodeKey::new(2, glam::UVec3::new(1, 0, 3));
        let min = cube.node_min(key);
        let points: Vec<RawPoint> = (0..64)
            .map(|i| RawPoint {
                position: min + DVec3::splat(f64::from(i) * 3.0),
                rgb: [1, 2, 3],
                intensity: 9,
                classification: 2,
                return_number: 1,
                weight: 1,
                row: 0,
            })
            .collect();
        let bytes = encode_node(&cube, key, &points, true);
        let coarse = coarse_len(points.len(), true);
        for at in [HEADER_BYTES + 5, coarse - 3, coarse + 7, bytes.len() - 20] {
            let mut damaged = bytes.clone();
            damaged[at] ^= 0x10;
            let whole = decode_node(&cube, key, 64, &damaged).expect_err("damage found");
            assert!(whole.to_string().contains("checksum"), "{whole}");
            let read_coarse = decode_node(&cube, key, 64, &damaged[..coarse]);
            assert_eq!(read_coarse.is_err(), at < coarse, "byte {at}");
            // A check without decoding finds what decoding finds.
            assert!(check_node(key, 64, &damaged).is_err(), "byte {at}");
            let checked_coarse = check_node(key, 64, &damaged[..coarse]);
            assert_eq!(checked_coarse.is_err(), at < coarse, "byte {at}");
        }
        assert!(check_node(key, 64, &bytes).is_ok());
        assert!(check_node(key, 64, &bytes[..coarse]).is_ok());
        assert!(check_node(key, 63, &bytes).is_err(), "another count");
        assert!(
            check_node(key, 64, &bytes[..bytes.len() - 1]).is_err(),
            "cut short"
        );
        let mut count = bytes.clone();
        count[4] ^= 1;
        let error = decode_node(&cube, key, 64, &count).expect_err("a damaged count");
        assert!(error.to_string().contains("checksum"), "{error}");
    }
}
