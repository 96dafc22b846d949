//! `RawPoint`: one original point as the builder carries it, with its weight, and its spill
//! record in one of two layouts: world positions as f64 (38 B), or, where every point of the
//! source lies on one LAS grid, the grid's integers (26 B), which give the same f64 back bit
//! for bit; then the point's attribute row, where the source has one (`attributes.rs`). Spill
//! is most of a build's disk and much of its time (docs/perf/lod-build.md).

use std::cmp::Ordering;

use glam::DVec3;

use super::error::LodError;
use super::grid::PositionGrid;

/// Bytes of a point in the world layout: position (3 x f64), RGB (3 x u16), intensity (u16),
/// classification, return number, weight (u32).
pub const WORLD_RECORD_BYTES: usize = 38;
/// Bytes of a point in the grid layout: the position's three i32, then as the world layout.
pub const GRID_RECORD_BYTES: usize = 26;
/// The largest record of any layout without attribute rows, for estimates made before the
/// source is open.
pub const MAX_RECORD_BYTES: usize = WORLD_RECORD_BYTES;
/// Bytes of a record after its position.
const ATTRIBUTE_BYTES: usize = 14;

/// How a build's spill records hold positions; one layout for all of a build's files.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum PositionLayout {
    World,
    Grid(PositionGrid),
}

/// A build's spill records: positions in their layout, the attributes after them, then the
/// point's attribute row of `row_bytes`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RecordLayout {
    pub positions: PositionLayout,
    pub row_bytes: usize,
}

impl RecordLayout {
    /// The grid layout where the source has a grid, the world layout otherwise, with rows of
    /// `row_bytes`.
    pub fn for_grid(grid: Option<PositionGrid>, row_bytes: usize) -> Self {
        Self {
            positions: grid.map_or(PositionLayout::World, PositionLayout::Grid),
            row_bytes,
        }
    }

    pub fn record_bytes(&self) -> usize {
        self.row_bytes
            + match self.positions {
                PositionLayout::World => WORLD_RECORD_BYTES,
                PositionLayout::Grid(_) => GRID_RECORD_BYTES,
            }
    }

    /// Writes `p` and its attribute `row` as one record into `out`, exactly
    /// [`Self::record_bytes`] long. A point off the grid is an error: the counting pass checks
    /// every point first, so it means the source changed between reads.
    pub fn write(&self, p: &RawPoint, row: &[u8], out: &mut [u8]) -> Result<(), LodError> {
        debug_assert_eq!(out.len(), self.record_bytes());
        debug_assert_eq!(row.len(), self.row_bytes);
        let attributes = match self.positions {
            PositionLayout::World => {
                for (a, c) in p.position.to_array().into_iter().enumerate() {
                    out[8 * a..8 * a + 8].copy_from_slice(&c.to_le_bytes());
                }
                &mut out[24..]
            }
            PositionLayout::Grid(grid) => {
                let i = grid.index(p.position).ok_or_else(|| off_grid(p.position))?;
                for (a, c) in i.into_iter().enumerate() {
                    out[4 * a..4 * a + 4].copy_from_slice(&c.to_le_bytes());
                }
                &mut out[12..]
            }
        };
        for (i, c) in p.rgb.into_iter().enumerate() {
            attributes[2 * i..2 * i + 2].copy_from_slice(&c.to_le_bytes());
        }
        attributes[6..8].copy_from_slice(&p.intensity.to_le_bytes());
        attributes[8] = p.classification;
        attributes[9] = p.return_number;
        attributes[10..ATTRIBUTE_BYTES].copy_from_slice(&p.weight.to_le_bytes());
        attributes[ATTRIBUTE_BYTES..].copy_from_slice(row);
        Ok(())
    }

    /// Appends `p`'s record, with its attribute `row`, to `out`.
    pub fn append(&self, p: &RawPoint, row: &[u8], out: &mut Vec<u8>) -> Result<(), LodError> {
        let at = out.len();
        out.resize(at + self.record_bytes(), 0);
        self.write(p, row, &mut out[at..])
    }

    /// The attribute row of one record.
    pub fn row<'a>(&self, record: &'a [u8]) -> &'a [u8] {
        &record[record.len() - self.row_bytes..]
    }

    /// Reads one record (its row index 0); `bytes` is exactly [`Self::record_bytes`] long.
    pub fn read(&self, bytes: &[u8]) -> RawPoint {
        let (position, attributes) = match self.positions {
            PositionLayout::World => {
                let f = |a: usize| {
                    let mut b = [0; 8];
                    b.copy_from_slice(&bytes[8 * a..8 * a + 8]);
                    f64::from_le_bytes(b)
                };
                (DVec3::new(f(0), f(1), f(2)), &bytes[24..])
            }
            PositionLayout::Grid(grid) => {
                let i = |a: usize| {
                    let b = &bytes[4 * a..4 * a + 4];
                    i32::from_le_bytes([b[0], b[1], b[2], b[3]])
                };
                (
                    grid.position([i(0), i(1), i(2)].map(i64::from)),
                    &bytes[12..],
                )
            }
        };
        let h = |i: usize| u16::from_le_bytes([attributes[i], attributes[i + 1]]);
        let w = &attributes[10..ATTRIBUTE_BYTES];
        RawPoint {
            position,
            rgb: [h(0), h(2), h(4)],
            intensity: h(6),
            classification: attributes[8],
            return_number: attributes[9],
            weight: u32::from_le_bytes([w[0], w[1], w[2], w[3]]),
            row: 0,
        }
    }
}

fn off_grid(p: DVec3) -> LodError {
    LodError::PointOffGrid {
        position: p.to_array(),
    }
}

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
    /// The point's attribute row among those of the points built with it (`attributes.rs`).
    pub row: u32,
}

impl RawPoint {
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

    fn point(position: DVec3) -> RawPoint {
        RawPoint {
            position,
            rgb: [1, 65_535, 300],
            intensity: 4242,
            classification: 7,
            return_number: 3,
            weight: 70_000,
            row: 0,
        }
    }

    fn round_trip(layout: RecordLayout, p: &RawPoint) -> RawPoint {
        let mut out = Vec::new();
        let row: Vec<u8> = (0..layout.row_bytes as u8).collect();
        layout.append(p, &row, &mut out).expect("written");
        assert_eq!(out.len(), layout.record_bytes());
        assert_eq!(layout.row(&out), row);
        layout.read(&out)
    }

    #[test]
    fn world_records_round_trip() {
        let p = point(DVec3::new(515_000.125, -4.5e6, 1e-300));
        assert_eq!(round_trip(RecordLayout::for_grid(None, 0), &p), p);
        assert_eq!(round_trip(RecordLayout::for_grid(None, 23), &p), p);
        assert_eq!(p.content_cmp(&p), Ordering::Equal);
    }

    #[test]
    fn grid_records_give_back_every_position_of_the_grid_bit_for_bit() {
        let scales = [0.01, 0.001, 0.000_25, 1e-7];
        let offsets = [0.0, 515_000.0, -4_500_000.37, 6.1e6];
        let mut state = 0x9e37_79b9_7f4a_7c15u64;
        let mut next = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state as i32
        };
        for scale in scales {
            for offset in offsets {
                let Some(grid) = PositionGrid::new(DVec3::splat(scale), DVec3::splat(offset))
                else {
                    assert!(offset.abs() + scale * 2f64.powi(31) >= scale * 2f64.powi(50));
                    continue;
                };
                let layout = RecordLayout::for_grid(Some(grid), 5);
                for k in 0..2_000 {
                    let i = match k {
                        0 => [i32::MIN, i32::MAX, 0],
                        1 => [-1, 1, i32::MAX - 1],
                        _ => [next(), next() >> 8, next() >> 20],
                    };
                    let p = point(grid.position(i.map(i64::from)));
                    assert_eq!(grid.index(p.position), Some(i));
                    let back = round_trip(layout, &p);
                    assert_eq!(
                        back.position.to_array().map(f64::to_bits),
                        p.position.to_array().map(f64::to_bits)
                    );
                    assert_eq!(back, p);
                }
            }
        }
    }

    #[test]
    fn a_point_off_the_grid_is_an_error_not_a_moved_point() {
        let grid = PositionGrid::new(DVec3::splat(0.01), DVec3::splat(500_000.0)).expect("grid");
        let layout = RecordLayout::for_grid(Some(grid), 0);
        let mut out = vec![0; GRID_RECORD_BYTES];
        for p in [
            DVec3::new(500_000.005, 500_000.0, 500_000.0),
            DVec3::new(500_000.0, 500_000.0, 1e12),
            DVec3::new(f64::NAN, 500_000.0, 500_000.0),
        ] {
            assert!(matches!(
                layout.write(&point(p), &[], &mut out),
                Err(LodError::PointOffGrid { .. })
            ));
        }
    }
}
