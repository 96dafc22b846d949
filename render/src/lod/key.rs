//! Node keys and the root cube: which cell of which level a point falls in.
//!
//! Keys are COPC's voxel keys (level, x, y, z), so a COPC export needs no renumbering. Every
//! cell index at every level comes from one formula, [`RootCube::cell_at`], which scales the
//! offset from the cube's corner by an exact power of two: a point's cell at level `l + 1`
//! halved is always its cell at level `l`, so the counting grid, the partitions, the local octrees
//! and the sampling grids agree on where a point lies whatever the rounding.

use std::fmt;

use glam::{DVec3, UVec3};

use crate::cloud::{WorldBounds, MAX_COORDINATE};

/// The deepest level a node may have. A node splits only above it, so points closer together
/// than the root's side / 2^24 stay in one leaf whatever their number; with the sampling
/// grid's 7 levels below it, every cell index fits a `u32`.
pub const MAX_LEVEL: u8 = 24;

/// A node: its level (0 = root) and its cell at that level.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct NodeKey {
    pub level: u8,
    pub x: u32,
    pub y: u32,
    pub z: u32,
}

impl fmt::Display for NodeKey {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}-{}-{}-{}", self.level, self.x, self.y, self.z)
    }
}

impl NodeKey {
    pub const ROOT: NodeKey = NodeKey {
        level: 0,
        x: 0,
        y: 0,
        z: 0,
    };

    pub fn new(level: u8, cell: UVec3) -> Self {
        Self {
            level,
            x: cell.x,
            y: cell.y,
            z: cell.z,
        }
    }

    pub fn cell(&self) -> UVec3 {
        UVec3::new(self.x, self.y, self.z)
    }

    /// The node's place along a Z curve through its level: nodes near in it are near in space,
    /// and siblings are next to each other.
    pub fn morton(&self) -> u128 {
        (0..u32::from(MAX_LEVEL)).fold(0, |code, bit| {
            let at = |v: u32, axis: u32| u128::from((v >> bit) & 1) << (3 * bit + axis);
            code | at(self.x, 0) | at(self.y, 1) | at(self.z, 2)
        })
    }

    /// A COPC voxel key (level, x, y, z) as a node key: a level the octree may have and a
    /// cell inside it, else `None`.
    pub fn from_voxel_key([level, x, y, z]: [i32; 4]) -> Option<NodeKey> {
        let level = u8::try_from(level).ok().filter(|&l| l <= MAX_LEVEL)?;
        let cells = 1i64 << level;
        let cell = |v: i32| (0..cells).contains(&i64::from(v)).then_some(v as u32);
        Some(NodeKey {
            level,
            x: cell(x)?,
            y: cell(y)?,
            z: cell(z)?,
        })
    }

    /// The parent, or `None` for the root.
    pub fn parent(&self) -> Option<NodeKey> {
        (self.level > 0).then(|| NodeKey::new(self.level - 1, self.cell() / 2))
    }

    /// Child `index` (bit 0: x, bit 1: y, bit 2: z).
    pub fn child(&self, index: usize) -> NodeKey {
        let offset = UVec3::new(
            index as u32 & 1,
            (index as u32 >> 1) & 1,
            (index as u32 >> 2) & 1,
        );
        NodeKey::new(self.level + 1, self.cell() * 2 + offset)
    }

    /// Which child of its parent this node is.
    pub fn child_index(&self) -> usize {
        ((self.x & 1) | ((self.y & 1) << 1) | ((self.z & 1) << 2)) as usize
    }

    /// 13 bytes, big-endian, so sled orders nodes by level, then x, y, z.
    pub fn to_bytes(&self) -> [u8; 13] {
        let mut out = [0; 13];
        out[0] = self.level;
        out[1..5].copy_from_slice(&self.x.to_be_bytes());
        out[5..9].copy_from_slice(&self.y.to_be_bytes());
        out[9..13].copy_from_slice(&self.z.to_be_bytes());
        out
    }
}

/// The cubic box of the whole octree: the root node's cube.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RootCube {
    pub min: DVec3,
    pub side: f64,
}

impl RootCube {
    /// The smallest cube at `bounds.min` holding `bounds`; a flat or single-point cloud still
    /// gets a cube of positive side. None for bounds that are not finite, inverted or beyond
    /// [`MAX_COORDINATE`].
    pub fn around(bounds: &WorldBounds) -> Option<Self> {
        let finite = bounds.min.is_finite() && bounds.max.is_finite();
        if !finite
            || bounds.min.cmpgt(bounds.max).any()
            || bounds.min.abs().max_element() > MAX_COORDINATE
            || bounds.max.abs().max_element() > MAX_COORDINATE
        {
            return None;
        }
        let extent = bounds.size().max_element();
        // A zero extent would make every cell index undefined; any positive side holds one spot.
        let side = if extent > 0.0 { extent } else { 1.0 };
        Some(Self {
            min: bounds.min,
            side,
        })
    }

    /// The cell of `p` at `level` (at most 31), clamped into the cube.
    pub fn cell_at(&self, p: DVec3, level: u32) -> UVec3 {
        let cells = (1u64 << level) as f64;
        let scaled = (p - self.min) * (cells / self.side);
        let max = (1u64 << level) - 1;
        // A cast truncates, which is the floor of the non-negative values and 0 (the clamp) for
        // the negative ones: cheaper than `floor`, a library call on baseline x86-64.
        let cell = |v: f64| (v as u64).min(max) as u32;
        UVec3::new(cell(scaled.x), cell(scaled.y), cell(scaled.z))
    }

    /// The side of a node at `level`.
    pub fn side_at(&self, level: u8) -> f64 {
        self.side / (1u64 << level) as f64
    }

    /// The corner of `key`'s cube.
    pub fn node_min(&self, key: NodeKey) -> DVec3 {
        self.min + key.cell().as_dvec3() * self.side_at(key.level)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cells_nest_exactly_across_levels() {
        let cube = RootCube {
            min: DVec3::new(515_000.123, 4_918_000.5, -3.0),
            side: 777.77,
        };
        for i in 0..10_000u32 {
            let t = DVec3::new(
                f64::from(i) / 10_000.0,
                f64::from(i * 7 % 10_000) / 10_000.0,
                f64::from(i * 13 % 10_000) / 10_000.0,
            );
            let p = cube.min + t * cube.side;
            for level in 0..31 {
                assert_eq!(cube.cell_at(p, level + 1) / 2, cube.cell_at(p, level));
            }
        }
    }

    #[test]
    fn keys_know_their_family() {
        let key = NodeKey::new(3, UVec3::new(5, 2, 7));
        for i in 0..8 {
            let child = key.child(i);
            assert_eq!(child.parent(), Some(key));
            assert_eq!(child.child_index(), i);
        }
        assert_eq!(NodeKey::ROOT.parent(), None);
    }

    #[test]
    fn bad_bounds_are_refused() {
        let nan = WorldBounds {
            min: DVec3::splat(f64::NAN),
            max: DVec3::ONE,
        };
        assert!(RootCube::around(&nan).is_none());
        let inverted = WorldBounds {
            min: DVec3::ONE,
            max: DVec3::ZERO,
        };
        assert!(RootCube::around(&inverted).is_none());
        let point = WorldBounds {
            min: DVec3::ONE,
            max: DVec3::ONE,
        };
        assert_eq!(RootCube::around(&point).map(|c| c.side), Some(1.0));
    }
}
