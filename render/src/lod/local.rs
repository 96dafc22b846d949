//! A partition's local octree, built in memory: the partition's points are ordered once along
//! the Z curve of the finest cells below its key (`morton.rs`), so that every node's points are
//! one run of that order and a node's children are cut from its run by the code's next three
//! bits, without moving a point. A node above the leaf bound has its children built, then
//! samples its own points from theirs (bottom-up, as PotreeConverter 2 does) and every child is
//! finished, into the nodes of the partition's region, stored together once the partition is
//! built (`sink.rs`). The leaves' runs are found first, and one pass over the partition's
//! points in the order they came appends each to its leaf: the only copy a point takes before
//! the sampling, with sequential reads, and each leaf's points in the order they came. The
//! partition's root is returned unfinished: the levels above the partitions still sample from
//! it.

use super::attributes::AttributeRows;
use super::error::LodError;
use super::key::{NodeKey, RootCube, MAX_LEVEL};
use super::morton::MortonOrder;
use super::point::RawPoint;
use super::sampling::sample;
use super::sink::{EncodedNode, NodeSink};

/// Levels below a partition its order spans: three digits of the radix sort, deeper than a
/// partition's octree goes but on a dense spot, whose node is then ordered again from its cube.
const ORDER_LEVELS: u8 = 8;

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

/// The partition being built: its points' Z-curve order of the cells `bits` levels below
/// `origin`, and the points of each run the recursion does not split (a leaf, or a node the
/// codes end above), in the order the recursion meets them, each run's points in the order
/// they came.
struct Ordered<'p> {
    order: &'p MortonOrder,
    /// The level the codes start below.
    origin: u8,
    runs: std::vec::IntoIter<Vec<RawPoint>>,
}

impl Ordered<'_> {
    /// The points of the next run the recursion does not split.
    fn next_run(&mut self, key: NodeKey) -> Result<Vec<RawPoint>, LodError> {
        self.runs.next().ok_or_else(|| LodError::CorruptNode {
            key,
            reason: "the partition's order has fewer runs than its octree".into(),
        })
    }
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
        kept: Option<&mut Vec<KeptRoot>>,
    ) -> Result<SubtreeRoot, LodError> {
        if self.is_leaf(key, points.len()) {
            return Ok(SubtreeRoot {
                points,
                sample_grid: 0,
            });
        }
        let levels = ORDER_LEVELS.min(MAX_LEVEL - key.level);
        let order = MortonOrder::below(&self.cube, key, &points, levels);
        let runs = self.unsplit_runs(&order, key, points);
        let mut ordered = Ordered {
            order: &order,
            origin: key.level,
            runs: runs.into_iter(),
        };
        self.build_run(&mut ordered, key, order.entries(), region, kept)
    }

    fn is_leaf(&self, key: NodeKey, points: usize) -> bool {
        points <= self.max_leaf_points || key.level >= MAX_LEVEL
    }

    /// Whether the recursion stops at `key`'s run of `points` at `depth` below the order's
    /// node: a leaf, or a node the codes end above (a dense spot, ordered again from its cube).
    fn is_unsplit(&self, order: &MortonOrder, key: NodeKey, points: usize, depth: u32) -> bool {
        self.is_leaf(key, points) || depth == order.bits()
    }

    /// The points of every run of `order` (below `key`) that the recursion does not split, in
    /// the order it meets them, each with its points in the order they came: one pass over
    /// `points` in that order appending each to its run, instead of a sort of each run's
    /// indices and a copy in scattered order.
    fn unsplit_runs(
        &self,
        order: &MortonOrder,
        key: NodeKey,
        points: Vec<RawPoint>,
    ) -> Vec<Vec<RawPoint>> {
        let mut runs: Vec<&[(u64, u32)]> = Vec::new();
        self.find_unsplit(order, key, order.entries(), 0, &mut runs);
        let mut run_of = vec![0u32; points.len()];
        for (r, run) in runs.iter().enumerate() {
            for &(_, i) in *run {
                run_of[i as usize] = r as u32;
            }
        }
        let mut out: Vec<Vec<RawPoint>> =
            runs.iter().map(|r| Vec::with_capacity(r.len())).collect();
        for (p, &r) in points.iter().zip(&run_of) {
            out[r as usize].push(*p);
        }
        out
    }

    /// Walks `key`'s `run` as [`Self::build_run`] does, noting each run it does not split.
    fn find_unsplit<'r>(
        &self,
        order: &MortonOrder,
        key: NodeKey,
        run: &'r [(u64, u32)],
        depth: u32,
        runs: &mut Vec<&'r [(u64, u32)]>,
    ) {
        if self.is_unsplit(order, key, run.len(), depth) {
            runs.push(run);
            return;
        }
        for (i, child_run) in order.children(run, depth).into_iter().enumerate() {
            if !child_run.is_empty() {
                self.find_unsplit(order, key.child(i), child_run, depth + 1, runs);
            }
        }
    }

    /// Builds `key`'s subtree of the points of `run`, the part of `ordered` in `key`'s cube.
    fn build_run(
        &self,
        ordered: &mut Ordered<'_>,
        key: NodeKey,
        run: &[(u64, u32)],
        region: &mut Vec<EncodedNode>,
        mut kept: Option<&mut Vec<KeptRoot>>,
    ) -> Result<SubtreeRoot, LodError> {
        let depth = u32::from(key.level - ordered.origin);
        if self.is_leaf(key, run.len()) {
            return Ok(SubtreeRoot {
                points: ordered.next_run(key)?,
                sample_grid: 0,
            });
        }
        if self.is_unsplit(ordered.order, key, run.len(), depth) {
            // The codes end above this node (a dense spot): its points are ordered again from
            // its cube.
            let points = ordered.next_run(key)?;
            return self.build(key, points, region, kept);
        }
        let children = ordered.order.children(run, depth);
        let mut own: [Vec<RawPoint>; 8] = Default::default();
        let mut grids = [0u32; 8];
        let mut present = [false; 8];
        for (i, child_run) in children.into_iter().enumerate() {
            if child_run.is_empty() {
                continue;
            }
            let child = self.build_run(ordered, key.child(i), child_run, region, None)?;
            if let Some(kept) = kept.as_deref_mut() {
                kept.push(KeptRoot {
                    key: key.child(i),
                    points: child_run.len() as u64,
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
