//! A partition's local octree, built in memory: a node above the leaf bound splits its points into
//! its children, the children are built, then the node samples its own points from theirs
//! (bottom-up, as PotreeConverter 2 does) and every child is finished, into the nodes of the
//! partition's region, stored together once the partition is built (`sink.rs`). The partition's
//! root is returned unfinished: the levels above the partitions still sample from it.

use super::attributes::AttributeRows;
use super::error::LodError;
use super::key::{NodeKey, RootCube, MAX_LEVEL};
use super::point::RawPoint;
use super::sampling::sample;
use super::sink::{EncodedNode, NodeSink};

/// A built subtree's root: its own points and its sampling grid (0 for a leaf).
pub struct SubtreeRoot {
    pub points: Vec<RawPoint>,
    pub sample_grid: u32,
}

pub struct LocalBuilder<'a> {
    pub cube: RootCube,
    pub max_leaf_points: usize,
    pub sample_grid: u32,
    pub sink: &'a NodeSink<'a>,
    /// The attribute rows of the points built.
    pub rows: &'a AttributeRows,
}

/// A subtree whose root's points are kept as they were before its parent sampled from them,
/// so that a store update builds it again alone (`update.rs`): a region of the store.
pub struct KeptRoot {
    pub key: NodeKey,
    /// Points in the subtree, its root's included.
    pub points: u64,
    pub root: EncodedNode,
}

impl LocalBuilder<'_> {
    /// Builds `key`'s subtree of `points`; with `kept`, each child subtree's root is kept
    /// there as it was before `key` sampled from it (a partition's children are the store's
    /// regions: a quarter of a partition on a surface is what an update builds again).
    pub fn build(
        &self,
        key: NodeKey,
        points: Vec<RawPoint>,
        region: &mut Vec<EncodedNode>,
        mut kept: Option<&mut Vec<KeptRoot>>,
    ) -> Result<SubtreeRoot, LodError> {
        if points.len() <= self.max_leaf_points || key.level >= MAX_LEVEL {
            return Ok(SubtreeRoot {
                points,
                sample_grid: 0,
            });
        }
        let children = split(&self.cube, key, points);
        let mut own: [Vec<RawPoint>; 8] = Default::default();
        let mut grids = [0u32; 8];
        let mut present = [false; 8];
        for (i, child_points) in children.into_iter().enumerate() {
            if child_points.is_empty() {
                continue;
            }
            let count = child_points.len() as u64;
            let child = self.build(key.child(i), child_points, region, None)?;
            if let Some(kept) = kept.as_deref_mut() {
                kept.push(KeptRoot {
                    key: key.child(i),
                    points: count,
                    root: self.sink.encode(
                        key.child(i),
                        &child.points,
                        child.sample_grid,
                        self.rows,
                    )?,
                });
            }
            own[i] = child.points;
            grids[i] = child.sample_grid;
            present[i] = true;
        }
        let sampled = sample(&self.cube, key, own, self.sample_grid, self.max_leaf_points);
        for (i, kept) in sampled.kept.iter().enumerate() {
            if present[i] {
                region.push(self.sink.encode(key.child(i), kept, grids[i], self.rows)?);
            }
        }
        Ok(SubtreeRoot {
            points: sampled.parent,
            sample_grid: sampled.grid,
        })
    }
}

/// `points` of `key` by child, each child's vector allocated at its exact size; each point's
/// child is computed once.
pub(crate) fn split(cube: &RootCube, key: NodeKey, points: Vec<RawPoint>) -> [Vec<RawPoint>; 8] {
    let child_level = u32::from(key.level) + 1;
    let base = key.cell() * 2;
    let which: Vec<u8> = points
        .iter()
        .map(|p| {
            let c = cube.cell_at(p.position, child_level) - base;
            (c.x | (c.y << 1) | (c.z << 2)) as u8
        })
        .collect();
    let mut counts = [0usize; 8];
    for &i in &which {
        counts[usize::from(i)] += 1;
    }
    let mut children: [Vec<RawPoint>; 8] = std::array::from_fn(|i| Vec::with_capacity(counts[i]));
    for (p, &i) in points.into_iter().zip(&which) {
        children[usize::from(i)].push(p);
    }
    children
}
