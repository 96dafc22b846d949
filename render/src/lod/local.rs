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
//!
//! A node's children hold disjoint points, so the subtrees of a node of a few leaves' worth are
//! built on the pool's threads at once, and its finished children encoded at once: one
//! partition keeps many cores busy where the budget holds few partitions at a time. Their
//! nodes come back in child order, so the store is the same whatever the threads.

use rayon::prelude::*;

use super::attributes::AttributeRows;
use super::error::LodError;
use super::key::{NodeKey, RootCube, MAX_LEVEL};
use super::morton::{MortonOrder, OrderBuffers};
use super::point::RawPoint;
use super::sampling::sample;
use super::sink::{EncodedNode, NodeSink};

/// Levels below a partition its order spans: three digits of the radix sort, deeper than a
/// partition's octree goes but on a dense spot, whose node is then ordered again from its cube.
const ORDER_LEVELS: u8 = 8;

/// Leaves' worth of points from which a node's children are built on several threads.
const PARALLEL_LEAVES: usize = 4;

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

/// A subtree's points made ready to build: a leaf's, or their order and unsplit runs.
pub enum Prepared {
    Leaf(Vec<RawPoint>),
    Ordered {
        key: NodeKey,
        order: MortonOrder,
        runs: Vec<Vec<RawPoint>>,
        starts: Vec<usize>,
    },
}

/// The partition being built: its points' Z-curve order of the cells `bits` levels below
/// `origin`.
struct Ordered<'p> {
    order: &'p MortonOrder,
    /// The level the codes start below.
    origin: u8,
}

/// The points of the runs the recursion does not split (a leaf, or a node the codes end
/// above) within one node's run, in the order the recursion meets them, each run's points in
/// the order they came, with where each run starts among the order's entries: a node's
/// children each take the runs that start within theirs.
struct Runs<'r> {
    points: &'r mut [Vec<RawPoint>],
    starts: &'r [usize],
}

impl<'r> Runs<'r> {
    /// The points of the one run of a node the recursion does not split.
    fn only(self, key: NodeKey) -> Result<Vec<RawPoint>, LodError> {
        match self.points {
            [run] => Ok(std::mem::take(run)),
            _ => Err(LodError::CorruptNode {
                key,
                reason: "the partition's order does not match its octree".into(),
            }),
        }
    }

    /// The runs that start before `end`, and the rest.
    fn split_before(self, end: usize) -> (Runs<'r>, Runs<'r>) {
        let n = self.starts.partition_point(|&s| s < end);
        let (points, rest_points) = self.points.split_at_mut(n);
        let (starts, rest_starts) = self.starts.split_at(n);
        (
            Runs { points, starts },
            Runs {
                points: rest_points,
                starts: rest_starts,
            },
        )
    }
}

/// A built subtree: its root, the nodes finished below it and, where asked, its children's
/// roots as they were before it sampled from them.
struct Built {
    root: SubtreeRoot,
    region: Vec<EncodedNode>,
    kept: Vec<KeptRoot>,
}

/// A child built: its index, its subtree and, where asked, its root as it was.
type BuiltChild = (usize, Built, Option<KeptRoot>);

/// A child of a node being built: its index, its run of the order and where that starts, and
/// the points of the runs in it.
type ChildWork<'e, 'r> = (usize, &'e [(u64, u32)], usize, Runs<'r>);

impl LocalBuilder<'_> {
    /// The first step of building `key`'s subtree of `points`, on one thread: the points in
    /// their order below `key`, cut into the runs the recursion does not split.
    pub fn prepare(&self, key: NodeKey, points: Vec<RawPoint>) -> Prepared {
        if self.is_leaf(key, points.len()) {
            return Prepared::Leaf(points);
        }
        // The sort's second buffer is freed before the runs take their copies.
        let buffers = OrderBuffers::default();
        self.ordered_runs(key, &points, buffers, &mut Vec::new(), drop)
    }

    /// [`Self::prepare`] of `points` the caller keeps (a buffer it reuses: a leaf's points are
    /// taken out of it, another's copied to their runs), the order built in `order` and each
    /// point's run noted in `run_of`, buffers whose room is reused too.
    pub fn prepare_in(
        &self,
        key: NodeKey,
        points: &mut Vec<RawPoint>,
        order: &mut OrderBuffers,
        run_of: &mut Vec<u32>,
    ) -> Prepared {
        if self.is_leaf(key, points.len()) {
            return Prepared::Leaf(std::mem::take(points));
        }
        let buffers = std::mem::take(order);
        self.ordered_runs(key, points, buffers, run_of, |sorted| order.sorted = sorted)
    }

    /// `points` ordered below `key` in `buffers`, the sort's second buffer handed to `sorted`,
    /// then cut into their runs.
    fn ordered_runs(
        &self,
        key: NodeKey,
        points: &[RawPoint],
        buffers: OrderBuffers,
        run_of: &mut Vec<u32>,
        sorted: impl FnOnce(Vec<(u64, u32)>),
    ) -> Prepared {
        let levels = ORDER_LEVELS.min(MAX_LEVEL - key.level);
        let (order, second) = MortonOrder::below_in(&self.cube, key, points, levels, buffers);
        sorted(second);
        let (runs, starts) = self.unsplit_runs(&order, key, points, run_of);
        Prepared::Ordered {
            key,
            order,
            runs,
            starts,
        }
    }

    /// Builds the subtree [`Self::prepare`] made ready; with `kept`, each child subtree's root
    /// is kept there as it was before the subtree's root sampled from it (a partition's
    /// children are the store's regions: a quarter of a partition on a surface is what an
    /// update builds again).
    /// Also returns the order, where there was one, for its buffer to be reused.
    pub fn build_prepared(
        &self,
        prepared: Prepared,
        region: &mut Vec<EncodedNode>,
        kept: Option<&mut Vec<KeptRoot>>,
    ) -> Result<(SubtreeRoot, Option<MortonOrder>), LodError> {
        let (built, order) = self.build_ordered(prepared, kept.is_some())?;
        region.extend(built.region);
        if let Some(kept) = kept {
            kept.extend(built.kept);
        }
        Ok((built.root, order))
    }

    fn build_subtree(
        &self,
        key: NodeKey,
        points: Vec<RawPoint>,
        keep: bool,
    ) -> Result<Built, LodError> {
        self.build_ordered(self.prepare(key, points), keep)
            .map(|(built, _)| built)
    }

    /// The subtree built, and its order where it had one.
    fn build_ordered(
        &self,
        prepared: Prepared,
        keep: bool,
    ) -> Result<(Built, Option<MortonOrder>), LodError> {
        let (key, order, mut runs, starts) = match prepared {
            Prepared::Leaf(points) => {
                let built = Built {
                    root: SubtreeRoot {
                        points,
                        sample_grid: 0,
                    },
                    region: Vec::new(),
                    kept: Vec::new(),
                };
                return Ok((built, None));
            }
            Prepared::Ordered {
                key,
                order,
                runs,
                starts,
            } => (key, order, runs, starts),
        };
        let ordered = Ordered {
            order: &order,
            origin: key.level,
        };
        let runs = Runs {
            points: &mut runs,
            starts: &starts,
        };
        let built = self.build_run(&ordered, runs, key, order.entries(), 0, keep)?;
        Ok((built, Some(order)))
    }

    fn is_leaf(&self, key: NodeKey, points: usize) -> bool {
        points <= self.max_leaf_points || key.level >= MAX_LEVEL
    }

    /// Whether the recursion stops at `key`'s run of `points` at `depth` below the order's
    /// node: a leaf, or a node the codes end above (a dense spot, ordered again from its cube).
    fn is_unsplit(&self, order: &MortonOrder, key: NodeKey, points: usize, depth: u32) -> bool {
        self.is_leaf(key, points) || depth == order.bits()
    }

    /// Whether `points` are enough to build a node's children on several threads: a few
    /// leaves' worth, so that a task is far more work than its handing over.
    fn in_parallel(&self, points: usize) -> bool {
        points >= PARALLEL_LEAVES * self.max_leaf_points
    }

    /// The points of every run of `order` (below `key`) that the recursion does not split, in
    /// the order it meets them, each with its points in the order they came, and where each
    /// starts among the order's entries: one pass over `points` in that order appending each
    /// to its run, instead of a sort of each run's indices and a copy in scattered order.
    /// `run_of` holds each point's run meanwhile: a buffer reused, every point's entry written
    /// before it is read, so it is not zeroed first.
    fn unsplit_runs(
        &self,
        order: &MortonOrder,
        key: NodeKey,
        points: &[RawPoint],
        run_of: &mut Vec<u32>,
    ) -> (Vec<Vec<RawPoint>>, Vec<usize>) {
        let mut runs: Vec<(usize, &[(u64, u32)])> = Vec::new();
        self.find_unsplit(order, key, order.entries(), 0, 0, &mut runs);
        let n = points.len();
        if run_of.len() < n {
            run_of.reserve_exact(n - run_of.len());
            run_of.resize(n, 0);
        }
        let run_of = &mut run_of[..n];
        // The runs cover the order, whose entries are every point once.
        debug_assert_eq!(runs.iter().map(|(_, r)| r.len()).sum::<usize>(), n);
        for (r, (_, run)) in runs.iter().enumerate() {
            for &(_, i) in *run {
                run_of[i as usize] = r as u32;
            }
        }
        let mut out: Vec<Vec<RawPoint>> = runs
            .iter()
            .map(|(_, r)| Vec::with_capacity(r.len()))
            .collect();
        for (p, &r) in points.iter().zip(run_of.iter()) {
            out[r as usize].push(*p);
        }
        (out, runs.iter().map(|&(start, _)| start).collect())
    }

    /// Walks `key`'s `run` (starting at `start` among the order's entries) as
    /// [`Self::build_run`] does, noting each run it does not split.
    fn find_unsplit<'r>(
        &self,
        order: &MortonOrder,
        key: NodeKey,
        run: &'r [(u64, u32)],
        start: usize,
        depth: u32,
        runs: &mut Vec<(usize, &'r [(u64, u32)])>,
    ) {
        if self.is_unsplit(order, key, run.len(), depth) {
            runs.push((start, run));
            return;
        }
        let mut child_start = start;
        for (i, child_run) in order.children(run, depth).into_iter().enumerate() {
            if !child_run.is_empty() {
                self.find_unsplit(order, key.child(i), child_run, child_start, depth + 1, runs);
            }
            child_start += child_run.len();
        }
    }

    /// Builds `key`'s subtree of the points of `run`, the part of the order in `key`'s cube
    /// starting at `start` among its entries, whose unsplit runs are `runs`; with `keep`, its
    /// children's roots are kept as they were before it sampled from them.
    fn build_run(
        &self,
        ordered: &Ordered<'_>,
        runs: Runs<'_>,
        key: NodeKey,
        run: &[(u64, u32)],
        start: usize,
        keep: bool,
    ) -> Result<Built, LodError> {
        let depth = u32::from(key.level - ordered.origin);
        if self.is_leaf(key, run.len()) {
            return Ok(Built {
                root: SubtreeRoot {
                    points: runs.only(key)?,
                    sample_grid: 0,
                },
                region: Vec::new(),
                kept: Vec::new(),
            });
        }
        if self.is_unsplit(ordered.order, key, run.len(), depth) {
            // The codes end above this node (a dense spot): its points are ordered again from
            // its cube.
            return self.build_subtree(key, runs.only(key)?, keep);
        }
        let mut work: Vec<ChildWork<'_, '_>> = Vec::with_capacity(8);
        let mut rest = runs;
        let mut child_start = start;
        for (i, child_run) in ordered.order.children(run, depth).into_iter().enumerate() {
            let end = child_start + child_run.len();
            let (mine, after) = rest.split_before(end);
            rest = after;
            if !child_run.is_empty() {
                work.push((i, child_run, child_start, mine));
            }
            child_start = end;
        }
        // Each child's subtree is its own points: they are built at once where there are
        // enough, and their nodes come back in child order, as one after another would.
        let build_child = |(i, child_run, child_start, child_runs): ChildWork<'_, '_>| {
            let child = self.build_run(
                ordered,
                child_runs,
                key.child(i),
                child_run,
                child_start,
                false,
            )?;
            let kept = match keep {
                true => Some(KeptRoot {
                    key: key.child(i),
                    points: child_run.len() as u64,
                    root: self.sink.encode(
                        key.child(i),
                        &child.root.points,
                        child.root.sample_grid,
                        self.rows,
                    )?,
                }),
                false => None,
            };
            Ok((i, child, kept))
        };
        let parallel = self.in_parallel(run.len());
        let children: Vec<Result<BuiltChild, LodError>> = match parallel {
            true => work.into_par_iter().map(build_child).collect(),
            false => work.into_iter().map(build_child).collect(),
        };
        let mut own: [Vec<RawPoint>; 8] = Default::default();
        let mut grids = [0u32; 8];
        let mut present = [false; 8];
        let mut region = Vec::new();
        let mut kept = Vec::new();
        for child in children {
            let (i, child, child_kept) = child?;
            region.extend(child.region);
            kept.extend(child_kept);
            own[i] = child.root.points;
            grids[i] = child.root.sample_grid;
            present[i] = true;
        }
        let sampled = sample(&self.cube, key, own, self.sample_grid, self.max_leaf_points);
        let encode = |(i, kept): (usize, &Vec<RawPoint>)| {
            self.sink.encode(key.child(i), kept, grids[i], self.rows)
        };
        let finished = sampled.kept.iter().enumerate().filter(|&(i, _)| present[i]);
        let encoded: Result<Vec<EncodedNode>, LodError> = match parallel {
            true => finished
                .collect::<Vec<_>>()
                .into_par_iter()
                .map(encode)
                .collect(),
            false => finished.map(encode).collect(),
        };
        region.extend(encoded?);
        Ok(Built {
            root: SubtreeRoot {
                points: sampled.parent,
                sample_grid: sampled.grid,
            },
            region,
            kept,
        })
    }
}
