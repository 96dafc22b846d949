//! `RawPoint`: one original point as the builder carries it, with its weight, and its fixed
//! 38-byte spill record.

use std::cmp::Ordering;

use glam::DVec3;

use super::source::PointBatch;

/// Bytes of one point in a spill file: position (3 x f64), RGB (3 x u16), intensity (u16),
/// classification, return number, weight (u32).
pub const SPILL_RECORD_BYTES: usize = 38;

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RawPoint {
    pub position: DVec3,
    pub rgb: [u16; 3],
    pub intensity: u16,
    pub classification: u8,
    pub return_number: u8,
    /// The original points this one stands for where its node is drawn without the child
    /// below it (`sampling.rs`): 1 from the source, more once an inner node samples it.
    pub weight: u32,
}

impl RawPoint {
    pub fn from_batch(batch: &PointBatch<'_>, i: usize) -> Self {
        Self {
            position: batch.positions[i],
            rgb: batch.rgb.map_or([0; 3], |rgb| rgb[i]),
            intensity: batch.intensity[i],
            classification: batch.classification[i],
            return_number: batch.return_number[i],
            weight: 1,
        }
    }

    pub fn write_to(&self, out: &mut Vec<u8>) {
        out.extend_from_slice(&self.record());
    }

    /// The point as one spill record.
    pub fn record(&self) -> [u8; SPILL_RECORD_BYTES] {
        let mut record = [0u8; SPILL_RECORD_BYTES];
        for (i, c) in self.position.to_array().into_iter().enumerate() {
            record[8 * i..8 * i + 8].copy_from_slice(&c.to_le_bytes());
        }
        for (i, c) in self.rgb.into_iter().enumerate() {
            record[24 + 2 * i..26 + 2 * i].copy_from_slice(&c.to_le_bytes());
        }
        record[30..32].copy_from_slice(&self.intensity.to_le_bytes());
        record[32] = self.classification;
        record[33] = self.return_number;
        record[34..38].copy_from_slice(&self.weight.to_le_bytes());
        record
    }

    /// Reads one record; `bytes` is exactly [`SPILL_RECORD_BYTES`] long.
    pub fn read_from(bytes: &[u8]) -> Self {
        let f = |i: usize| {
            let mut b = [0; 8];
            b.copy_from_slice(&bytes[i..i + 8]);
            f64::from_le_bytes(b)
        };
        let h = |i: usize| u16::from_le_bytes([bytes[i], bytes[i + 1]]);
        Self {
            position: DVec3::new(f(0), f(8), f(16)),
            rgb: [h(24), h(26), h(28)],
            intensity: h(30),
            classification: bytes[32],
            return_number: bytes[33],
            weight: u32::from_le_bytes([bytes[34], bytes[35], bytes[36], bytes[37]]),
        }
    }

    /// A total order on everything a point holds, so that choices between points at the same
    /// distance never depend on the order they arrived in.
    pub fn content_cmp(&self, other: &Self) -> Ordering {
        let a = self.position;
        let b = other.position;
        a.x.total_cmp(&b.x)
            .then(a.y.total_cmp(&b.y))
            .then(a.z.total_cmp(&b.z))
            .then(self.rgb.cmp(&other.rgb))
            .then(self.intensity.cmp(&other.intensity))
            .then(self.classification.cmp(&other.classification))
            .then(self.return_number.cmp(&other.return_number))
            .then(self.weight.cmp(&other.weight))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spill_records_round_trip() {
        let p = RawPoint {
            position: DVec3::new(515_000.125, -4.5e6, 1e-300),
            rgb: [1, 65_535, 300],
            intensity: 4242,
            classification: 7,
            return_number: 3,
            weight: 70_000,
        };
        let mut out = Vec::new();
        p.write_to(&mut out);
        assert_eq!(out.len(), SPILL_RECORD_BYTES);
        assert_eq!(RawPoint::read_from(&out), p);
        assert_eq!(p.content_cmp(&p), Ordering::Equal);
    }
}
