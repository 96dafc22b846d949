//! Point weights: every cut that is closed upward counts the original points (all but what a
//! child's only point of a grandchild octant stood for when its parent took it), and a coarse
//! cut's weighted share of the terrain's vegetation is far closer to full detail's.

use std::collections::{HashMap, HashSet};

use super::*;
use crate::lod::weights::decode_weight;

/// The built terrain's nodes by key, with each node's count of points in its subtree.
struct Tree {
    nodes: HashMap<NodeKey, NodePoints>,
    subtree: HashMap<NodeKey, u64>,
}

fn tree(built: &Built) -> Tree {
    let nodes: HashMap<NodeKey, NodePoints> = read_all_nodes(built)
        .into_iter()
        .map(|n| (n.key, n))
        .collect();
    let mut subtree: HashMap<NodeKey, u64> = HashMap::new();
    for node in nodes.values() {
        let mut key = Some(node.key);
        while let Some(k) = key {
            *subtree.entry(k).or_default() += node.len() as u64;
            key = k.parent();
        }
    }
    Tree { nodes, subtree }
}

impl Tree {
    /// The nodes of levels 0 to `level`: the cut that stops at one depth everywhere.
    fn levels_to(&self, level: u8) -> HashSet<NodeKey> {
        self.nodes
            .keys()
            .copied()
            .filter(|k| k.level <= level)
            .collect()
    }
}

/// The child octant of a point of a node, from the top bit of its 30-bit coordinates.
fn octant(q: &[u32; 3]) -> usize {
    let bit = |a: usize| ((q[a] >> (codec::POSITION_BITS - 1)) & 1) as usize;
    bit(0) | (bit(1) << 1) | (bit(2) << 2)
}

/// What each point of `node` counts for in a cut of `drawn`: its weight where the child
/// below it is not drawn, else 1.
fn cut_weights<'a>(
    node: &'a NodePoints,
    drawn: &'a HashSet<NodeKey>,
) -> impl Iterator<Item = u64> + 'a {
    node.quantised
        .iter()
        .zip(&node.weights)
        .map(move |(q, &w)| {
            if drawn.contains(&node.key.child(octant(q))) {
                1
            } else {
                u64::from(decode_weight(w))
            }
        })
}

fn cut_total(tree: &Tree, drawn: &HashSet<NodeKey>) -> u64 {
    drawn
        .iter()
        .filter_map(|k| tree.nodes.get(k))
        .flat_map(|n| cut_weights(n, drawn))
        .sum()
}

/// The most a cut may miss of the points: what a taken point stood for in its child where
/// the child kept no other point of its grandchild octant has no heir (`sampling.rs`).
const MISSED_SHARE: f64 = 0.01;

fn assert_counts(counted: u64, expected: u64, what: &str) {
    assert!(
        counted <= expected && counted as f64 >= expected as f64 * (1.0 - MISSED_SHARE),
        "{what}: {counted} of {expected} points counted"
    );
}

/// Cuts by level, and cuts that stop at different levels in different places (closed upward,
/// as `select_cut` makes them), each count the dataset's points, never more and within
/// [`MISSED_SHARE`]; and every node's weights count the points of its subtree the same way
/// (most nodes exactly). Weights of 1 count only the drawn points, and weights without the heirs of
/// taken points lose what those stood for in their child (a quarter of it or more): both fail.
#[test]
fn every_cut_counts_every_point_once() {
    let source = GeneratedSource::terrain(60_000, 11);
    let built = build_with(&source, |_| {});
    let tree = tree(&built);
    let total = source.point_count();
    let deepest = tree.nodes.keys().map(|k| k.level).max().expect("nodes");
    assert!(deepest >= 3, "a real tree: {deepest} levels");
    let heavy = tree
        .nodes
        .values()
        .flat_map(|n| &n.weights)
        .filter(|&&w| decode_weight(w) > 1)
        .count();
    assert!(heavy > 100, "{heavy} points stand for more than themselves");
    for level in 0..=deepest {
        let drawn = tree.levels_to(level);
        assert_counts(
            cut_total(&tree, &drawn),
            total,
            &format!("levels to {level}"),
        );
    }
    // Deeper where x is low: a cut that stops at a different level in every part.
    for split in [1u32, 3, 5] {
        let drawn: HashSet<NodeKey> = tree
            .nodes
            .keys()
            .copied()
            .filter(|k| {
                let x = k.cell().x >> k.level.saturating_sub(3);
                u32::from(k.level) <= split + (7 - x.min(7)) / 2
            })
            .filter(|k| {
                // Closed upward: every ancestor passes the same rule (deeper never helps).
                let mut a = k.parent();
                while let Some(p) = a {
                    let x = p.cell().x >> p.level.saturating_sub(3);
                    if u32::from(p.level) > split + (7 - x.min(7)) / 2 {
                        return false;
                    }
                    a = p.parent();
                }
                true
            })
            .collect();
        assert_counts(
            cut_total(&tree, &drawn),
            total,
            &format!("the mixed cut {split}"),
        );
    }
    let mut exact = 0;
    for (key, node) in &tree.nodes {
        let own: u64 = node
            .weights
            .iter()
            .map(|&w| u64::from(decode_weight(w)))
            .sum();
        assert_counts(own, tree.subtree[key], &format!("node {key}"));
        exact += usize::from(own == tree.subtree[key]);
    }
    assert!(
        exact * 10 >= tree.nodes.len() * 9,
        "{exact} of {} nodes count exactly",
        tree.nodes.len()
    );
}

/// The terrain problem at a small scale: vegetation is 20% of the points but most of the
/// coarse levels' (one point per occupied cell, and the canopy fills cells up its height).
/// Weighted, a coarse cut's vegetation share moves most of the way to full detail's; what
/// is left comes from cells that hold both, whose one point (the nearest the cell's centre,
/// more often in the canopy) stands for all of them (levels to 0, 1, 2, 3: 79%, 90%, 70%, 38%
/// of the points, 53%, 41%, 25%, 20.1% weighted, against 20%).
#[test]
fn a_coarse_cut_weighs_vegetation_nearly_as_full_detail_does() {
    let source = GeneratedSource::terrain(60_000, 5);
    let built = build_with(&source, |_| {});
    let tree = tree(&built);
    let full: usize = tree
        .nodes
        .values()
        .flat_map(|n| &n.classification)
        .filter(|&&c| c == 5)
        .count();
    let full_share = full as f64 / source.point_count() as f64;
    for level in 0..=4 {
        let drawn = tree.levels_to(level);
        let (mut plain, mut plain_vegetation) = (0u64, 0u64);
        let (mut weighted, mut weighted_vegetation) = (0u64, 0u64);
        for key in &drawn {
            let node = &tree.nodes[key];
            for (w, &class) in cut_weights(node, &drawn).zip(&node.classification) {
                let vegetation = u64::from(class == 5);
                plain += 1;
                plain_vegetation += vegetation;
                weighted += w;
                weighted_vegetation += w * vegetation;
            }
        }
        let plain_share = plain_vegetation as f64 / plain as f64;
        let weighted_share = weighted_vegetation as f64 / weighted as f64;
        eprintln!(
            "levels to {level}: vegetation {:.1}% of the points, {:.1}% weighted, {:.1}% at \
             full detail",
            100.0 * plain_share,
            100.0 * weighted_share,
            100.0 * full_share
        );
        let (plain_error, weighted_error) = (
            (plain_share - full_share).abs(),
            (weighted_share - full_share).abs(),
        );
        assert!(
            weighted_error <= 0.6 * plain_error + 0.005,
            "levels to {level}: weighted {weighted_share} against {plain_share} unweighted"
        );
        // Once the cells are about the canopy's height or smaller, what remains is small.
        if level >= 2 {
            assert!(weighted_error < 0.06, "levels to {level}: {weighted_share}");
        }
    }
}
