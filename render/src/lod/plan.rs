//! Partition planning: the bucket grid's cells merged into partitions of at most `max_points`
//! points, as PotreeConverter 2 does: a pyramid of counts, and from the root down every cell
//! that holds few enough points (or is a cell of the grid itself) becomes one partition.

use glam::UVec3;

use super::counting::CountGrid;
use super::key::NodeKey;

/// A subtree whose points are spilled into one file and built in memory at once.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Partition {
    pub key: NodeKey,
    pub count: u64,
}

/// The partitions and, for every cell of the counting grid, the index of its partition.
pub struct PartitionPlan {
    pub level: u32,
    pub partitions: Vec<Partition>,
    /// `u32::MAX` for an empty cell.
    pub lookup: Vec<u32>,
}

pub fn plan_partitions(grid: &CountGrid, max_points: u64) -> PartitionPlan {
    let top = grid.level;
    let mut pyramid: Vec<Vec<u64>> = vec![Vec::new(); top as usize + 1];
    pyramid[top as usize] = grid.counts.clone();
    for level in (0..top).rev() {
        let finer = &pyramid[level as usize + 1];
        let n = 1u32 << level;
        let mut counts = vec![0u64; 1 << (3 * level)];
        for z in 0..n {
            for y in 0..n {
                for x in 0..n {
                    let cell = UVec3::new(x, y, z);
                    counts[CountGrid::index(level, cell)] = (0..8)
                        .map(|i| {
                            finer
                                [CountGrid::index(level + 1, NodeKey::new(0, cell).child(i).cell())]
                        })
                        .sum();
                }
            }
        }
        pyramid[level as usize] = counts;
    }
    let mut plan = PartitionPlan {
        level: top,
        partitions: Vec::new(),
        lookup: vec![u32::MAX; 1 << (3 * top)],
    };
    let mut stack = vec![NodeKey::ROOT];
    while let Some(key) = stack.pop() {
        let level = u32::from(key.level);
        let count = pyramid[level as usize][CountGrid::index(level, key.cell())];
        if count == 0 {
            continue;
        }
        if count <= max_points || level == top {
            let index = plan.partitions.len() as u32;
            mark(&mut plan, key, index);
            plan.partitions.push(Partition { key, count });
        } else {
            // Pushed in reverse so partitions come out in child order, the same on every run.
            stack.extend((0..8).rev().map(|i| key.child(i)));
        }
    }
    plan
}

/// Points every grid cell inside `key` at partition `index`.
fn mark(plan: &mut PartitionPlan, key: NodeKey, index: u32) {
    let span = 1u32 << (plan.level - u32::from(key.level));
    let base = key.cell() * span;
    for z in 0..span {
        for y in 0..span {
            for x in 0..span {
                plan.lookup[CountGrid::index(plan.level, base + UVec3::new(x, y, z))] = index;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cells_merge_into_partitions_below_the_limit() {
        let level = 2;
        let mut counts = vec![0u64; 64];
        // One dense cell, and a sparse corner that merges.
        counts[CountGrid::index(level, UVec3::new(3, 3, 3))] = 100;
        counts[CountGrid::index(level, UVec3::new(0, 0, 0))] = 3;
        counts[CountGrid::index(level, UVec3::new(1, 0, 0))] = 4;
        let grid = CountGrid {
            level,
            counts,
            segment_points: 1,
        };
        let plan = plan_partitions(&grid, 10);
        assert_eq!(
            plan.partitions,
            vec![
                Partition {
                    key: NodeKey::new(1, UVec3::ZERO),
                    count: 7
                },
                Partition {
                    key: NodeKey::new(2, UVec3::splat(3)),
                    count: 100
                },
            ]
        );
        assert_eq!(plan.lookup[CountGrid::index(level, UVec3::new(1, 0, 0))], 0);
        assert_eq!(plan.lookup[CountGrid::index(level, UVec3::new(3, 3, 3))], 1);
        assert_eq!(
            plan.lookup[CountGrid::index(level, UVec3::new(2, 2, 2))],
            u32::MAX
        );
    }
}
