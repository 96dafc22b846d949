//! The sampling rule of inner nodes: a node takes, from its children's own points, the one
//! point closest to the centre of each cell of a grid over its cube (Scheiblauer's choice of
//! representative); the children keep the rest. The grid starts at the configured cells per
//! axis and is halved while the sample would hold more than the node bound, so inner nodes are
//! even and bounded on surfaces and volumes alike.
//!
//! Ties in distance are broken by the points' content, so the choice never depends on the
//! order points arrived in.

use std::collections::HashMap;
use std::hash::{BuildHasherDefault, Hasher};

use glam::DVec3;

use super::key::{NodeKey, RootCube};
use super::point::RawPoint;

/// A node's sample and what its children keep.
pub struct Sampled {
    pub parent: Vec<RawPoint>,
    pub kept: [Vec<RawPoint>; 8],
    /// Cells per axis of the grid that was used.
    pub grid: u32,
}

/// The sampling cell of `p` in `key`'s grid of `2^grid_bits` cells per axis.
pub fn sampling_cell(cube: &RootCube, key: NodeKey, grid_bits: u32, p: DVec3) -> glam::UVec3 {
    cube.cell_at(p, u32::from(key.level) + grid_bits) - (key.cell() << grid_bits)
}

/// Cell indices are below 2^21 and already spread: a multiply mixes them enough.
#[derive(Default)]
struct CellHasher(u64);

impl Hasher for CellHasher {
    fn finish(&self) -> u64 {
        self.0
    }

    fn write(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.0 = (self.0 << 8 | u64::from(b)).wrapping_mul(0x9E37_79B9_7F4A_7C15);
        }
    }

    fn write_u32(&mut self, n: u32) {
        self.0 = u64::from(n).wrapping_mul(0x9E37_79B9_7F4A_7C15);
    }
}

type CellMap = HashMap<u32, (f64, u8, u32), BuildHasherDefault<CellHasher>>;

/// Samples `key` from its children's own points with at most `max_points` points.
pub fn sample(
    cube: &RootCube,
    key: NodeKey,
    children: [Vec<RawPoint>; 8],
    grid: u32,
    max_points: usize,
) -> Sampled {
    let candidates: usize = children.iter().map(Vec::len).sum();
    let mut bits = grid.trailing_zeros();
    let mut best = CellMap::with_capacity_and_hasher(candidates.min(1 << 21), Default::default());
    loop {
        best.clear();
        let cell_side = cube.side_at(key.level) / f64::from(1u32 << bits);
        let corner = cube.node_min(key);
        for (c, points) in children.iter().enumerate() {
            for (i, p) in points.iter().enumerate() {
                let cell = sampling_cell(cube, key, bits, p.position);
                let centre = corner + (cell.as_dvec3() + 0.5) * cell_side;
                let d = p.position.distance_squared(centre);
                let index = cell.x | (cell.y << bits) | (cell.z << (2 * bits));
                let entry = best.entry(index).or_insert((d, c as u8, i as u32));
                let (bd, bc, bi) = *entry;
                let better = d < bd
                    || (d == bd
                        && p.content_cmp(&children[usize::from(bc)][bi as usize])
                            .is_lt());
                if better {
                    *entry = (d, c as u8, i as u32);
                }
            }
        }
        if best.len() <= max_points || bits == 0 {
            break;
        }
        bits -= 1;
    }
    let mut chosen: [Vec<bool>; 8] = std::array::from_fn(|c| vec![false; children[c].len()]);
    for &(_, c, i) in best.values() {
        chosen[usize::from(c)][i as usize] = true;
    }
    drop(best);
    let mut parent = Vec::new();
    let kept = std::array::from_fn(|c| {
        let mut kept = Vec::with_capacity(children[c].len());
        for (p, &take) in children[c].iter().zip(&chosen[c]) {
            if take {
                parent.push(*p);
            } else {
                kept.push(*p);
            }
        }
        kept
    });
    Sampled {
        parent,
        kept,
        grid: 1 << bits,
    }
}
