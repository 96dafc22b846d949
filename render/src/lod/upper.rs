//! The levels above the partitions: from the deepest waiting subtree roots up, each parent loads
//! its waiting children, samples its own points from them by the same rule as inside a partition,
//! finishes the children and waits in turn, until the root is finished. Parents of one level
//! are built in parallel, each holding its reservation while it works.

use std::collections::BTreeMap;

use rayon::prelude::*;

use super::attributes::AttributeRows;
use super::context::{BuildContext, Pending};
use super::error::LodError;
use super::journal::UnitKind;
use super::key::NodeKey;
use super::local::SubtreeRoot;
use super::partitions::build_bytes_per_point;
use super::point::RawPoint;
use super::sampling::sample;
use super::spill::{self, read_block_bytes};

pub fn build_upper_levels(ctx: &BuildContext<'_>) -> Result<(), LodError> {
    loop {
        let level_nodes = {
            let mut pending = ctx
                .pending
                .lock()
                .unwrap_or_else(|poisoned| poisoned.into_inner());
            let Some(deepest) = pending.keys().map(|k| k.level).max() else {
                return Ok(());
            };
            let keys: Vec<NodeKey> = pending
                .keys()
                .filter(|k| k.level == deepest)
                .copied()
                .collect();
            keys.into_iter()
                .filter_map(|k| pending.remove(&k).map(|p| (k, p)))
                .collect::<Vec<_>>()
        };
        let mut families: BTreeMap<NodeKey, Vec<(NodeKey, Pending)>> = BTreeMap::new();
        for (key, node) in level_nodes {
            // Every waiting node is below the root: only the root is finished without waiting.
            let Some(parent) = key.parent() else {
                return Err(LodError::Source(format!("the root {key} was left waiting")));
            };
            families.entry(parent).or_default().push((key, node));
        }
        let families: Vec<_> = families.into_iter().collect();
        families
            .into_par_iter()
            .with_max_len(1)
            .try_for_each(|(parent, children)| build_parent(ctx, parent, children))?;
    }
}

fn build_parent(
    ctx: &BuildContext<'_>,
    parent: NodeKey,
    children: Vec<(NodeKey, Pending)>,
) -> Result<(), LodError> {
    let total: u64 = children.iter().map(|(_, c)| c.root.count).sum();
    let layout = ctx.spill.layout();
    let _reservation = ctx.meter.reserve(
        total * build_bytes_per_point(layout) + read_block_bytes(layout),
        "a node above the partitions with its children",
    )?;
    let mut own: [Vec<RawPoint>; 8] = Default::default();
    let mut grids = [0u32; 8];
    let mut present = [false; 8];
    let mut rows = AttributeRows::new(layout.row_bytes);
    for (key, child) in &children {
        let i = key.child_index();
        own[i] = spill::read_all(
            std::slice::from_ref(&child.path),
            layout,
            child.root.count,
            &mut rows,
        )?;
        grids[i] = child.root.sample_grid;
        present[i] = true;
    }
    let sampled = sample(
        &ctx.cube,
        parent,
        own,
        ctx.options.sample_grid,
        ctx.options.max_leaf_points,
    );
    let mut region = Vec::new();
    for (i, kept) in sampled.kept.iter().enumerate() {
        if present[i] {
            region.push(ctx.sink.encode(parent.child(i), kept, grids[i], &rows)?);
        }
    }
    let root = SubtreeRoot {
        points: sampled.parent,
        sample_grid: sampled.grid,
    };
    ctx.finish_unit(UnitKind::Parent, region, parent, root, &rows, Vec::new())?;
    // Removed once the parent is recorded: a build stopped before then builds it again.
    for (_, child) in &children {
        spill::remove(&child.path)?;
    }
    Ok(())
}
