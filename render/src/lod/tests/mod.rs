//! The builder end to end: real sources, real spill files, real sled trees.

mod digest;
mod layers;
mod refusals;
mod removal;
mod store;
mod throughput;
mod update;
mod weights;

use std::collections::HashMap;

use glam::DVec3;

use super::*;
use crate::cloud::PointCloud;

struct Built {
    _dir: tempfile::TempDir,
    store: LodStore,
    report: LodBuildReport,
}

/// A store in `dir`: its sled index (kept open by the returned database) and payload file.
pub(crate) fn temp_store(dir: &std::path::Path) -> (sled::Db, LodStore) {
    let db = sled::open(dir.join("db")).expect("sled");
    let tree = db.open_tree("lod").expect("tree");
    let store = LodStore::open(tree, dir.join("lod.bin")).expect("store");
    (db, store)
}

fn options(dir: &std::path::Path, max_leaf_points: usize) -> LodBuildOptions {
    let mut options = LodBuildOptions::new(dir.join("spill"));
    options.max_leaf_points = max_leaf_points;
    options.memory_budget_bytes = options.min_memory_budget_bytes();
    options
}

fn build_with(source: &dyn PointSource, tweak: impl FnOnce(&mut LodBuildOptions)) -> Built {
    build_watched_with(source, &BuildProgress::new(), tweak)
}

/// [`build_with`], the build listing its stored nodes in `progress` as the daemon's builds do.
fn build_watched_with(
    source: &dyn PointSource,
    progress: &BuildProgress,
    tweak: impl FnOnce(&mut LodBuildOptions),
) -> Built {
    let dir = tempfile::tempdir().expect("tempdir");
    let (_db, store) = temp_store(dir.path());
    let mut options = options(dir.path(), 500);
    tweak(&mut options);
    // The smallest budget the options allow, so every test also checks the meter's bound.
    options.memory_budget_bytes = options
        .memory_budget_bytes
        .max(options.min_memory_budget_bytes());
    let report = build_lod_watched(source, &store, &options, progress).expect("build");
    Built {
        _dir: dir,
        store,
        report,
    }
}

fn read_all_nodes(built: &Built) -> Vec<NodePoints> {
    let hierarchy = built.store.read_hierarchy().expect("hierarchy");
    assert_eq!(hierarchy, built.report.hierarchy);
    hierarchy
        .nodes()
        .iter()
        .map(|n| built.store.read_node(&hierarchy, n.key).expect("node"))
        .collect()
}

/// RGB, intensity, classification and return number of a point.
type Attributes = ([u16; 3], u16, u8, u8);

/// Every input point with its attributes, read through the source.
fn input_points(source: &dyn PointSource) -> Vec<(DVec3, [u16; 3], u16, u8, u8)> {
    let mut out = Vec::new();
    source
        .for_each_batch(&mut |b| {
            for i in 0..b.len() {
                let rgb = b.rgb.map_or([0; 3], |c| c[i]);
                out.push((
                    b.positions[i],
                    rgb,
                    b.intensity[i],
                    b.classification[i],
                    b.return_number[i],
                ));
            }
            Ok(())
        })
        .expect("read");
    out
}

#[test]
fn every_point_is_in_exactly_one_node_within_the_quantisation_step() {
    let source = GeneratedSource::terrain(40_000, 7);
    let built = build_with(&source, |_| {});
    let hierarchy = &built.report.hierarchy;
    assert!(
        hierarchy.nodes().len() > 20,
        "a real tree: {} nodes",
        hierarchy.nodes().len()
    );
    let nodes = read_all_nodes(&built);
    let stored: usize = nodes.iter().map(NodePoints::len).sum();
    assert_eq!(stored as u64, source.point_count());
    assert_eq!(hierarchy.point_count, source.point_count());

    // Attributes (random intensity, height-derived RGB) nearly identify a point; the position
    // must then be within half a step of the node's quantisation.
    let mut decoded: HashMap<Attributes, Vec<(DVec3, f64)>> = HashMap::new();
    for node in &nodes {
        let (min, side) = hierarchy.node_cube(node.key);
        let rgb = node.rgb.as_ref().expect("the terrain has RGB");
        for (i, p) in node.world_positions().into_iter().enumerate() {
            assert!(
                p.cmpge(min).all() && p.cmple(min + side).all(),
                "{p} outside node {}",
                node.key
            );
            let attributes = (
                rgb[i],
                node.intensity[i],
                node.classification[i],
                node.return_number[i],
            );
            decoded.entry(attributes).or_default().push((p, node.step));
        }
    }
    for (position, rgb, intensity, class, ret) in input_points(&source) {
        let candidates = decoded
            .get_mut(&(rgb, intensity, class, ret))
            .expect("attributes stored");
        let found = candidates
            .iter()
            .position(|(p, step)| (*p - position).abs().max_element() <= step * 0.5 + 1e-9)
            .expect("a stored point within half a step of the input point");
        candidates.swap_remove(found);
    }
    assert!(
        decoded.values().all(Vec::is_empty),
        "no stored point without an input point"
    );
}

/// The sampling cell of every point of an inner node, from its 30-bit coordinates (the
/// sampling grid's boundaries fall on the quantisation grid exactly).
fn sampling_cells(node: &NodePoints, grid: u32) -> Vec<[u32; 3]> {
    let shift = codec::POSITION_BITS - grid.trailing_zeros();
    node.quantised
        .iter()
        .map(|q| q.map(|c| c >> shift))
        .collect()
}

fn assert_bounded_and_even(built: &Built, max_leaf: usize) -> (usize, u32) {
    let hierarchy = &built.report.hierarchy;
    let mut inner = 0;
    let mut finest_grid = 0;
    for node in read_all_nodes(built) {
        let info = *hierarchy.node(node.key).expect("listed");
        assert!(
            node.len() <= max_leaf,
            "node {} holds {}",
            node.key,
            node.len()
        );
        assert_eq!(info.is_leaf(), info.sample_grid == 0, "node {}", node.key);
        if info.is_leaf() {
            assert!(!node.is_empty(), "empty leaf {}", node.key);
            continue;
        }
        inner += 1;
        finest_grid = finest_grid.max(info.sample_grid);
        let cells = sampling_cells(&node, info.sample_grid);
        let mut unique = cells.clone();
        unique.sort_unstable();
        unique.dedup();
        assert_eq!(
            unique.len(),
            cells.len(),
            "two points of inner node {} share a cell",
            node.key
        );
        let spacing = hierarchy.spacing(node.key).expect("inner");
        assert!(spacing > 0.0);
    }
    (inner, finest_grid)
}

#[test]
fn nodes_are_bounded_and_inner_nodes_even_on_surfaces_and_volumes() {
    let terrain = build_with(&GeneratedSource::terrain(60_000, 3), |o| {
        o.max_leaf_points = 2_000
    });
    let (inner, grid) = assert_bounded_and_even(&terrain, 2_000);
    assert!(inner >= 3, "{inner} inner nodes");
    assert!(grid >= 32, "a surface keeps a fine grid ({grid})");
    // A volume fills grid^3 cells: the grid must coarsen to keep the node bound.
    let cube = build_with(&GeneratedSource::cube(60_000, 3), |o| {
        o.max_leaf_points = 2_000
    });
    let (inner, grid) = assert_bounded_and_even(&cube, 2_000);
    assert!(inner >= 3 && grid <= 16, "{inner} inner nodes, grid {grid}");
}

#[test]
fn a_small_memory_budget_is_respected_and_spill_files_removed() {
    let source = GeneratedSource::terrain(200_000, 11);
    let built = build_with(&source, |_| {});
    let report = &built.report;
    assert!(
        report.memory_budget_bytes < 4 << 20,
        "a small budget: {}",
        report.memory_budget_bytes
    );
    assert!(report.peak_memory_bytes <= report.memory_budget_bytes);
    assert!(
        report.peak_memory_bytes > report.memory_budget_bytes / 4,
        "the meter saw the buffers"
    );
    assert!(report.partitions > 4, "{} partitions", report.partitions);
    assert!(
        report.spilled_bytes >= 200_000 * 34,
        "every point spilled: {}",
        report.spilled_bytes
    );
    assert!(!report.spill_path.exists(), "the spill folder is removed");
    let left = std::fs::read_dir(report.spill_path.parent().expect("parent"))
        .expect("read")
        .count();
    assert_eq!(left, 0);
    assert_eq!(
        read_all_nodes(&built)
            .iter()
            .map(NodePoints::len)
            .sum::<usize>(),
        200_000
    );
}

/// Dense points in a 1 m cube with two outliers 10 km away: the counting grid cannot separate
/// them, so the builder must split their partition on disk to stay in the budget.
#[test]
fn a_partition_larger_than_the_budget_is_split_on_disk() {
    let mut points: Vec<DVec3> = (0..60_000u32)
        .map(|i| {
            let f = |k: u32| f64::from((i.wrapping_mul(k) >> 7) % 1000) / 1000.0;
            DVec3::new(600_000.0, 5_000_000.0, 10.0)
                + DVec3::new(f(2_654_435_761), f(40_503), f(1_103_515_245))
        })
        .collect();
    points.push(DVec3::new(610_000.0, 5_010_000.0, 10.0));
    points.push(DVec3::new(590_000.0, 4_990_000.0, 10.0));
    let cloud = PointCloud::from_world_points(&points, vec![0; points.len()]);
    let source = CloudSource::new(&cloud);
    let built = build_with(&source, |_| {});
    let report = &built.report;
    assert!(
        report.partitions_split > 0,
        "split: {}",
        report.partitions_split
    );
    assert!(report.peak_memory_bytes <= report.memory_budget_bytes);
    let nodes = read_all_nodes(&built);
    assert_eq!(
        nodes.iter().map(NodePoints::len).sum::<usize>(),
        points.len()
    );
    assert!(
        nodes.iter().all(|n| n.rgb.is_none()),
        "a PointCloud has no raw RGB"
    );
    assert!(!report.spill_path.exists());
}

/// Points over 2 km with two outliers 10 km away: the buckets (1.25 km at the finest bucket
/// grid) each hold far more than the partition size, so the builder splits them on disk before
/// it builds them, though each would fit the budget.
#[test]
fn a_bucket_far_above_the_partition_size_is_split_though_it_fits() {
    let mut points: Vec<DVec3> = (0..60_000u32)
        .map(|i| {
            let f = |k: u32| f64::from((i.wrapping_mul(k) >> 7) % 2000);
            DVec3::new(600_000.0, 5_000_000.0, 10.0)
                + DVec3::new(f(2_654_435_761), f(40_503), f(1_103_515_245) / 100.0)
        })
        .collect();
    points.push(DVec3::new(610_000.0, 5_010_000.0, 10.0));
    points.push(DVec3::new(590_000.0, 4_990_000.0, 10.0));
    let cloud = PointCloud::from_world_points(&points, vec![0; points.len()]);
    let source = CloudSource::new(&cloud);
    let built = build_with(&source, |o| {
        o.memory_budget_bytes = 256 << 20;
        o.max_partition_points = 2_000;
    });
    let report = &built.report;
    assert!(
        report.partitions_split > 0,
        "split: {}",
        report.partitions_split
    );
    assert!(
        report.peak_memory_bytes < report.memory_budget_bytes / 4,
        "split for their size, not for the budget: {} of {}",
        report.peak_memory_bytes,
        report.memory_budget_bytes
    );
    assert_eq!(
        read_all_nodes(&built)
            .iter()
            .map(NodePoints::len)
            .sum::<usize>(),
        points.len()
    );
}

fn stored_nodes(built: &Built) -> Vec<(NodeKey, Vec<u8>)> {
    let hierarchy = &built.report.hierarchy;
    hierarchy
        .stored_nodes()
        .map(|n| {
            let bytes = built
                .store
                .node_bytes(hierarchy, n.key)
                .expect("read")
                .expect("stored");
            (n.key, bytes)
        })
        .collect()
}

/// The hierarchy less where each node lies in the payload file, which depends on the order
/// in which the threads finished their nodes.
fn without_offsets(hierarchy: &LodHierarchy) -> (RootCube, u64, DatasetStats, Vec<NodeInfo>) {
    let nodes = hierarchy
        .nodes()
        .iter()
        .map(|n| NodeInfo {
            offset: 0,
            rest_offset: 0,
            ..*n
        })
        .collect();
    (
        hierarchy.cube,
        hierarchy.point_count,
        hierarchy.stats.clone(),
        nodes,
    )
}

#[test]
fn builds_are_deterministic_whatever_the_thread_count() {
    let source = GeneratedSource::terrain(120_000, 21);
    let one = build_with(&source, |o| o.threads = Some(1));
    let three = build_with(&source, |o| o.threads = Some(3));
    let again = build_with(&source, |o| o.threads = Some(3));
    assert!(one.report.partitions > 2, "several partitions in parallel");
    let shape = without_offsets(&one.report.hierarchy);
    assert_eq!(shape, without_offsets(&three.report.hierarchy));
    assert_eq!(shape, without_offsets(&again.report.hierarchy));
    let bytes = stored_nodes(&one);
    assert_eq!(bytes, stored_nodes(&three));
    assert_eq!(bytes, stored_nodes(&again));
}

#[test]
fn statistics_cover_the_whole_dataset() {
    let source = GeneratedSource::terrain(30_000, 9);
    let built = build_with(&source, |_| {});
    let stats = &built.report.hierarchy.stats;
    let input = input_points(&source);
    assert!(stats.has_rgb);
    let max = input
        .iter()
        .map(|p| p.1.into_iter().max().unwrap_or(0))
        .max()
        .unwrap_or(0);
    assert_eq!(stats.max_rgb_channel(), max);
    let lowest = |c: usize| input.iter().map(|p| p.1[c]).min().unwrap_or(0);
    assert_eq!(stats.min_rgb, [lowest(0), lowest(1), lowest(2)]);
    // The record carries them, as the store reads it back.
    let stored = LodHierarchy::decode(&built.report.hierarchy.encode()).expect("decode");
    assert_eq!(stored.stats, *stats);
    assert_eq!(stats.intensity_histogram.iter().sum::<u64>(), 30_000);
    assert!(stats.intensity_histogram[usize::from(input[0].2)] > 0);
    assert_eq!(stats.class_counts[2] + stats.class_counts[5], 30_000);
    let (low, high) = input.iter().fold((f64::MAX, f64::MIN), |(l, h), p| {
        (l.min(p.0.z), h.max(p.0.z))
    });
    assert_eq!(stats.z_range, [low, high]);
}

#[test]
fn an_empty_source_builds_an_empty_hierarchy() {
    let cloud = PointCloud::from_world_points(&[], vec![]);
    let built = build_with(&CloudSource::new(&cloud), |_| {});
    let hierarchy = built.store.read_hierarchy().expect("hierarchy");
    assert!(hierarchy.nodes().is_empty());
    assert_eq!(hierarchy.point_count, 0);
}

#[test]
fn a_single_partition_dataset_is_one_tree_from_the_root() {
    let scene = crate::sample::sample_scene(3_000, 1);
    let built = build_with(&CloudSource::new(&scene), |o| o.max_leaf_points = 1_000);
    let hierarchy = &built.report.hierarchy;
    let root = hierarchy.root().expect("root");
    assert!(!root.is_leaf());
    assert_eq!(
        hierarchy.children(NodeKey::ROOT).count(),
        root.child_mask.count_ones() as usize
    );
    let nodes = read_all_nodes(&built);
    assert_eq!(nodes.iter().map(NodePoints::len).sum::<usize>(), 3_000);
    // Relative positions are the world positions less the origin, in f64 before f32.
    let node = &nodes[0];
    let relative = node.positions_relative_to(scene.origin);
    for (r, w) in relative.iter().zip(node.world_positions()) {
        assert!((r.as_dvec3() - (w - scene.origin)).abs().max_element() < 1e-3);
    }
}

/// A build lists each node in its progress once the node is stored: whatever a watcher reads
/// during the build decodes whole (checked as a render reads it); at the end the progress holds
/// every stored node and point, and a point budget takes coarse levels first.
#[test]
fn a_build_lists_its_stored_nodes_as_it_goes() {
    let source = GeneratedSource::terrain(200_000, 5);
    let progress = BuildProgress::new();
    let mut partial_reads = 0;
    let built = std::thread::scope(|scope| {
        let build = scope.spawn(|| build_watched_with(&source, &progress, |_| {}));
        while !build.is_finished() {
            let (stored, total) = progress.points();
            let nodes = progress
                .read_points(u64::MAX)
                .expect("stored nodes read whole");
            let read: u64 = nodes.iter().map(|n| n.len() as u64).sum();
            assert!(
                read >= stored && read <= total.max(read),
                "{read} of {stored}"
            );
            if stored > 0 && stored < total {
                partial_reads += 1;
            }
            std::thread::sleep(std::time::Duration::from_millis(2));
        }
        build.join().expect("build thread")
    });
    eprintln!("{partial_reads} reads of a partial build");
    let total = source.point_count();
    assert_eq!(progress.points(), (total, total));

    let by_key = |mut nodes: Vec<NodePoints>| {
        nodes.retain(|n| !n.is_empty());
        nodes.sort_by_key(|n| n.key.to_bytes());
        nodes
    };
    let everything = by_key(progress.read_points(u64::MAX).expect("all nodes"));
    assert_eq!(everything, by_key(read_all_nodes(&built)));

    let budget = total / 10;
    let coarse = progress.read_points(budget).expect("coarse nodes");
    let taken: u64 = coarse.iter().map(|n| n.len() as u64).sum();
    assert!(taken <= budget && taken > 0, "{taken} of {budget}");
    let deepest = coarse.iter().map(|n| n.key.level).max().expect("a node");
    let shallower_left = everything
        .iter()
        .filter(|n| n.key.level < deepest)
        .any(|n| !coarse.iter().any(|c| c.key == n.key));
    assert!(
        !shallower_left,
        "every level above the deepest taken is whole"
    );
}

/// A progress made to notify is told each preview version as the build reaches it, on the
/// build's threads, up to every tenth stored.
#[test]
fn a_watched_build_tells_each_preview_version_as_it_moves() {
    let told = std::sync::Arc::new(std::sync::Mutex::new(Vec::new()));
    let seen = std::sync::Arc::clone(&told);
    let progress = BuildProgress::notifying(move |version| {
        seen.lock().expect("versions").push(version);
    });
    build_watched_with(&GeneratedSource::terrain(200_000, 5), &progress, |_| {});
    let mut told = told.lock().expect("versions").clone();
    assert!(told.contains(&10), "{told:?}");
    assert_eq!(progress.preview_version(), 10);
    // Threads storing at once may tell theirs out of order, never one twice.
    let count = told.len();
    told.sort_unstable();
    told.dedup();
    assert_eq!(told.len(), count, "a version told twice");
    assert!(told.iter().all(|v| (1..=10).contains(v)), "{told:?}");
}
